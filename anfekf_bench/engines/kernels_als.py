"""The fast engine's kernel of `als` (filters/als.py): online autocovariance least squares.

The rule is filters/als.py's plain functions, called here as the filterpy engine's `ALSEKF`
calls them from its hooks (numba compiles them with `register_jitable`; their two batched
products, numpy's broadcasting matmul there, are plain loops here); the EKF steps are
kernels.py's primitives. The loop runs over one run's stamps: stamp i predicts with the controls
u[i] over dt[i], then fuses the landmarks lm[i] .. lm[i + 1] - 1 (their map positions xy and
measurements z), then records when record[i].

The motion model is reached only through `_predict` and `_jacobians` (the bicycle today); the
Q basis of the sensitivities is the motion model's own Q of a unit control variance (what
`_predict` returns with Qu = E_V or E_G), as `ALSEKF.predict` takes `model.Q(G, E, dt)`.

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
"""

from __future__ import annotations

import importlib.util
import math
import sys

import numpy as np

from ..filters import als as _als
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
predict, jacobian_arrays = _k.predict, _k.jacobian_arrays
innovation, nis, gain, correct = _k.innovation, _k.nis, _k.gain, _k.correct
healthy, record, as_diag, clip_to_bounds = _k.healthy, _k.record, _k.as_diag, _k.clip_to_bounds

MOTION_BICYCLE = 0
MOTION_UNICYCLE = 1


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    name = __name__ + "_pure"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, __file__)
    mod = importlib.util.module_from_spec(spec)
    mod._PURE = True  # read while the copy executes
    spec.loader.exec_module(mod)
    sys.modules[name] = mod
    return mod


if JIT and not _PURE_COPY:
    from numba.extending import overload, register_jitable

    @overload(_als.batch_left)
    def _batch_left_loop(L, X):
        """Compiled, L X_i over a stack is a plain loop (one allocation, k ascending)."""

        def impl(L, X):
            q, b, c = X.shape
            a = L.shape[0]
            out = np.empty((q, a, c))
            for i in range(q):
                for r in range(a):
                    for s in range(c):
                        t = 0.0
                        for k in range(b):
                            t += L[r, k] * X[i, k, s]
                        out[i, r, s] = t
            return out

        return impl

    @overload(_als.batch_sandwich)
    def _batch_sandwich_loop(L, X, Rm):
        """Compiled, (L X_i) Rm^T over a stack is a plain loop (two allocations)."""

        def impl(L, X, Rm):
            q, b, c = X.shape
            a = L.shape[0]
            d = Rm.shape[0]
            out = np.empty((q, a, d))
            tmp = np.empty((a, c))
            for i in range(q):
                for r in range(a):
                    for s in range(c):
                        t = 0.0
                        for k in range(b):
                            t += L[r, k] * X[i, k, s]
                        tmp[r, s] = t
                for r in range(a):
                    for s in range(d):
                        t = 0.0
                        for k in range(c):
                            t += tmp[r, k] * Rm[s, k]
                        out[i, r, s] = t
            return out

        return impl

    for _rule in (
        _als.predict_sensitivities, _als.update_sensitivities, _als.push_past,
        _als.rows_per_innovation, _als.innovation_rows, _als.ring_slot, _als.stack_rows,
        _als._passive_solution, _als.nnls, _als.solve_variances, _als.r_basis,
    ):  # fmt: skip
        register_jitable(_rule)

predict_sensitivities = _als.predict_sensitivities
update_sensitivities = _als.update_sensitivities
push_past = _als.push_past
rows_per_innovation = _als.rows_per_innovation
innovation_rows = _als.innovation_rows
ring_slot = _als.ring_slot
stack_rows = _als.stack_rows
solve_variances = _als.solve_variances
r_basis = _als.r_basis

# a unit variance on V, on gamma, as the Qu of `_predict` (row-major 2 x 2)
_UNIT_V = (1.0, 0.0, 0.0, 0.0)
_UNIT_G = (0.0, 0.0, 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# The motion model (the bicycle's primitives of kernels.py for now)


@maybe_njit
def _predict(x, P, u0, u1, dt, motion, B, T0, Qu):
    """The motion model's EKF predict: (x-, P-, Q) with Q the step's state-space noise."""
    if motion != MOTION_BICYCLE:
        raise ValueError("the als kernel implements the bicycle motion model only")
    return predict(x, P, u0, u1, dt, B, Qu)


@maybe_njit
def _jacobians(x2, u0, u1, dt, motion, B, T0):
    """The motion model's F (3 x 3) and G (3 x 2) at heading x2 and controls (u0, u1)."""
    if motion != MOTION_BICYCLE:
        raise ValueError("the als kernel implements the bicycle motion model only")
    return jacobian_arrays(x2, u0, u1, dt, B)


@maybe_njit
def nnls(A, b):
    """filters.als.nnls as the kernel runs it (compiled when numba is in use): for tests."""
    return solve_variances(A, b)


@maybe_njit
def _fill(out, Q):
    """A row-major 3 x 3 tuple into the 3 x 3 array `out`."""
    for i in range(9):
        out[i // 3, i % 3] = Q[i]


@maybe_njit
def _finish(M, past_nu, past_D, n_past, nu, H, K, R_basis):
    """ALSEKF._finish_pending: the sensitivities through one innovation's update (K zero for a
    rejected one), then (nu, C) kept as the newest past innovation. Returns (M, n_past)."""
    M, C = update_sensitivities(M, past_D, n_past, H, K, R_basis)
    return M, push_past(past_nu, past_D, n_past, nu, C)


# ---------------------------------------------------------------------------------------------
# The loop


@maybe_njit
def run_als_kernel(
    u, dt, lm, xy, z, record_at, motion, B, T0, x0, P0, Qu0, R0, gate, has_gate,
    adapt_R, adapt_Q, adaptation, from_all, floor, ceiling, lags, window, every, warmup,
    out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """filterpy_engine.run_filter with filters.als.ALSEKF: per stamp the predict and the
    sensitivities' prediction; per landmark the rows of an innovation that feeds adaptation
    (before its gain), the gate, the update and the sensitivities through it; per scan with a
    landmark, every `every`-th, the non-negative least squares over the last `window`
    innovations' rows (from min(warmup, window) of them on) and Qu, R from it within bounds.
    Returns (diverged, records written, nis_sum, n_updates, n_rejected) as the other kernels."""
    n_stamps = u.shape[0]
    x = (x0[0], x0[1], x0[2])
    P = (P0[0], P0[1], P0[2], P0[3], P0[4], P0[5], P0[6], P0[7], P0[8])
    Qu = (Qu0[0], Qu0[1], Qu0[2], Qu0[3])
    R = (R0[0], R0[1], R0[2], R0[3])
    R0_diag = np.array([R0[0], R0[3]])
    Qu0_diag = np.array([Qu0[0], Qu0[3]])
    bounds = (floor, ceiling)
    M = np.zeros((4, 3, 3))
    R_basis = r_basis()
    Q_basis = np.zeros((4, 3, 3))
    past_nu = np.zeros((lags, 2))
    past_D = np.zeros((lags * 4, 3, 2))
    n_past = 0
    # A ring of `window` innovations' rows; no more than the run's measurements can fill it
    # (a smaller ring that never wraps holds the same rows).
    size = max(1, min(window, z.shape[0]))
    n_cols = rows_per_innovation(2, lags)
    A_ring = np.empty((size, n_cols, 4))
    b_ring = np.empty((size, n_cols))
    n_rows = np.zeros(size, dtype=np.int64)
    head = 0
    count = 0
    min_rows = min(warmup, window)
    pending = False
    pend_nu = np.zeros(2)
    pend_H = np.zeros((2, 3))
    no_gain = np.zeros((3, 2))
    scans = 0
    nis_sum = 0.0
    n_updates = 0
    n_rejected = 0
    n_records = out_x.shape[0]
    j = 0
    bad_record = False
    for i in range(n_stamps):
        u0 = u[i, 0]
        u1 = u[i, 1]
        h = dt[i]
        # ALSEKF.predict: F, G and the unit noises at the estimate before the step
        F, _ = _jacobians(x[2], u0, u1, h, motion, B, T0)
        _fill(Q_basis[0], _predict(x, P, u0, u1, h, motion, B, T0, _UNIT_V)[2])
        _fill(Q_basis[1], _predict(x, P, u0, u1, h, motion, B, T0, _UNIT_G)[2])
        x, P, _ = _predict(x, P, u0, u1, h, motion, B, T0, Qu)
        M = predict_sensitivities(M, past_D, n_past, F, Q_basis)
        first = lm[i]
        last = lm[i + 1]
        if last == first:
            if record_at[i] and j < n_records:
                j, bad = record(j, x, P, R, Qu, out_x, out_P, out_R, out_Q)
                bad_record = bad_record or bad
            continue
        for m in range(first, last):
            z0 = z[m, 0]
            z1 = z[m, 1]
            H, zh, nu, HPHt = innovation(x, P, xy[m, 0], xy[m, 1], z0, z1)
            # before_gain: the previous landmark of this scan, if the gate refused it
            if pending:
                M, n_past = _finish(M, past_nu, past_D, n_past, pend_nu, pend_H, no_gain, R_basis)
                pending = False
            feeds = True
            if not from_all and has_gate:
                ok, v = nis(HPHt, R, nu[0], nu[1])
                if not ok:
                    return True, j, nis_sum, n_updates, n_rejected
                feeds = v <= gate
            if feeds:
                S = np.empty((2, 2))
                for a in range(4):
                    S[a // 2, a % 2] = HPHt[a] + R[a]
                pend_nu = np.array([nu[0], nu[1]])
                pend_H = np.array([[H[0], H[1], 0.0], [H[2], H[3], -1.0]])
                slot, head, count = ring_slot(head, count, size)
                n_rows[slot] = innovation_rows(
                    pend_nu, pend_H, M, R_basis, past_nu, past_D, n_past, S,
                    A_ring[slot], b_ring[slot],
                )  # fmt: skip
                pending = True
            ok, v = nis(HPHt, R, nu[0], nu[1])
            if not ok or not math.isfinite(v):
                return True, j, nis_sum, n_updates, n_rejected
            if has_gate and not v <= gate:
                n_rejected += 1
                continue
            nis_sum += v
            n_updates += 1
            ok, Kt = gain(P, H, R)
            if not ok:
                return True, j, nis_sum, n_updates, n_rejected
            ok, x, P = correct(x, P, H, zh, z0, z1, R)
            # after_update
            if pending:
                K = np.empty((3, 2))
                for a in range(6):
                    K[a // 2, a % 2] = Kt[a]
                M, n_past = _finish(M, past_nu, past_D, n_past, pend_nu, pend_H, K, R_basis)
                pending = False
        # end_scan
        if pending:
            M, n_past = _finish(M, past_nu, past_D, n_past, pend_nu, pend_H, no_gain, R_basis)
            pending = False
        scans += 1
        if adaptation and scans % every == 0 and count >= min_rows:
            A, b = stack_rows(A_ring, b_ring, n_rows, head, count)
            theta = solve_variances(A, b)
            for a in range(4):
                if not math.isfinite(theta[a]):
                    return True, j, nis_sum, n_updates, n_rejected
            if adapt_Q:
                Qu = as_diag(clip_to_bounds(theta[:2].copy(), Qu0_diag, bounds))
            if adapt_R:
                R = as_diag(clip_to_bounds(theta[2:].copy(), R0_diag, bounds))
        if not healthy(x, P, R, Qu):
            return True, j, nis_sum, n_updates, n_rejected
        if record_at[i] and j < n_records:
            j, bad = record(j, x, P, R, Qu, out_x, out_P, out_R, out_Q)
            bad_record = bad_record or bad
    return bad_record, j, nis_sum, n_updates, n_rejected
