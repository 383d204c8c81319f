"""The fast engine's kernel of `als` (filters/als.py): online autocovariance least squares.

The rule is filters/als.py's plain functions, called here as the filterpy engine's `ALSEKF`
calls them from its hooks (numba compiles them with `register_jitable`; their batched
products and the QR's factor, numpy's there, are plain loops here, each writing one array and
no temporaries: numba's small arrays cost more than their arithmetic); the EKF steps are
kernels.py's primitives. The loop runs over one run's stamps: stamp i predicts with the controls
u[i] over dt[i], then fuses the landmarks lm[i] .. lm[i + 1] - 1 (their map positions xy and
measurements z), then records when record_at[i].

The motion model (bicycle or unicycle, an argument) is reached only through kernels.py's
`predict` and `interval_step` (AdaptiveEKF.predict's interval accumulators, A <- F A F^T +
Q(e) with the model's Q of a unit control noise e, and F_scan <- F F_scan).

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import als as _als
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
jacobians, noise_scale, interval_step = _k.jacobians, _k.noise_scale, _k.interval_step
predict_with = _k.predict_with
innovation, nis, gain, correct = _k.innovation, _k.nis, _k.gain, _k.correct
feeds_adaptation = _k.feeds_adaptation
healthy, record, clip_to_bounds = _k.healthy, _k.record, _k.clip_to_bounds
stamp_input, NO_TALLY = _k.stamp_input, _k.NO_TALLY

MOTION_BICYCLE, MOTION_UNICYCLE = _k.MOTION_BICYCLE, _k.MOTION_UNICYCLE


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


if JIT and not _PURE_COPY:
    from numba.extending import overload, register_jitable

    @register_jitable
    def _left_cols(out, L, X):
        """out[i] = L X_i column by column, each column of X_i read before out's is written
        (so out may be X: in place)."""
        q, b, c = X.shape
        a = L.shape[0]
        if b == 3 and a == 3:  # L in locals too
            l00, l01, l02, l10, l11, l12 = L[0, 0], L[0, 1], L[0, 2], L[1, 0], L[1, 1], L[1, 2]
            l20, l21, l22 = L[2, 0], L[2, 1], L[2, 2]
            for i in range(q):
                for s in range(c):
                    x0, x1, x2 = X[i, 0, s], X[i, 1, s], X[i, 2, s]
                    out[i, 0, s] = l00 * x0 + l01 * x1 + (l02 * x2)
                    out[i, 1, s] = l10 * x0 + l11 * x1 + (l12 * x2)
                    out[i, 2, s] = l20 * x0 + l21 * x1 + (l22 * x2)
        elif b == 3:
            for i in range(q):
                for s in range(c):
                    x0, x1, x2 = X[i, 0, s], X[i, 1, s], X[i, 2, s]
                    for r in range(a):
                        out[i, r, s] = L[r, 0] * x0 + L[r, 1] * x1 + (L[r, 2] * x2)
        elif b == 2:
            for i in range(q):
                for s in range(c):
                    x0, x1 = X[i, 0, s], X[i, 1, s]
                    for r in range(a):
                        out[i, r, s] = L[r, 0] * x0 + L[r, 1] * x1
        else:  # (no such stack here: its temporary column is allocated in this branch)
            col = np.empty(b)
            for i in range(q):
                for s in range(c):
                    for k in range(b):
                        col[k] = X[i, k, s]
                    for r in range(a):
                        out[i, r, s] = _dot(L, r, col)

    @register_jitable
    def _dot(L, r, v):
        """L[r] . v, k ascending."""
        t = 0.0
        for k in range(v.shape[0]):
            t += L[r, k] * v[k]
        return t

    @register_jitable
    def _right_rows(out, X, Rm):
        """out[i] += X_i Rm^T, row by row, k ascending (each row of X_i in locals)."""
        q, a, c = X.shape
        d = Rm.shape[0]
        if c == 3:
            for i in range(q):
                for r in range(a):
                    y0, y1, y2 = X[i, r, 0], X[i, r, 1], X[i, r, 2]
                    for s in range(d):
                        out[i, r, s] += y0 * Rm[s, 0] + y1 * Rm[s, 1] + (y2 * Rm[s, 2])
        else:
            for i in range(q):
                for r in range(a):
                    for s in range(d):
                        t = 0.0
                        for k in range(c):
                            t += X[i, r, k] * Rm[s, k]
                        out[i, r, s] += t

    @overload(_als.batch_left)
    def _batch_left_loop(L, X):
        """Compiled, L X_i over a stack is a plain loop (one allocation)."""

        def impl(L, X):
            out = np.empty((X.shape[0], L.shape[0], X.shape[2]))
            _left_cols(out, L, X)
            return out

        return impl

    @overload(_als.left_in_place)
    def _left_in_place_loop(L, X):
        """Compiled, X_i <- L X_i column by column, each column read before it is written."""

        def impl(L, X):
            _left_cols(X, L, X)

        return impl

    @register_jitable
    def _sandwich_into(L, X, Rm):
        """(L X_i) Rm^T over the stack into a new array, each row of L X_i in locals (summed as
        `_left_cols` then a right product would, without the intermediate stack)."""
        q, b, c = X.shape
        a, d = L.shape[0], Rm.shape[0]
        out = np.empty((q, a, d))
        if b == 3 and c == 3:
            for i in range(q):
                x00, x01, x02 = X[i, 0, 0], X[i, 0, 1], X[i, 0, 2]
                x10, x11, x12 = X[i, 1, 0], X[i, 1, 1], X[i, 1, 2]
                x20, x21, x22 = X[i, 2, 0], X[i, 2, 1], X[i, 2, 2]
                for r in range(a):
                    l0, l1, l2 = L[r, 0], L[r, 1], L[r, 2]
                    t0 = l0 * x00 + l1 * x10 + (l2 * x20)
                    t1 = l0 * x01 + l1 * x11 + (l2 * x21)
                    t2 = l0 * x02 + l1 * x12 + (l2 * x22)
                    for s in range(d):
                        out[i, r, s] = t0 * Rm[s, 0] + t1 * Rm[s, 1] + (t2 * Rm[s, 2])
        elif b == 2 and c == 2:
            for i in range(q):
                x00, x01, x10, x11 = X[i, 0, 0], X[i, 0, 1], X[i, 1, 0], X[i, 1, 1]
                for r in range(a):
                    l0, l1 = L[r, 0], L[r, 1]
                    t0 = l0 * x00 + l1 * x10
                    t1 = l0 * x01 + l1 * x11
                    for s in range(d):
                        out[i, r, s] = t0 * Rm[s, 0] + t1 * Rm[s, 1]
        else:  # (no such stack here: its temporaries are allocated in this branch)
            LX = np.empty((q, a, c))
            _left_cols(LX, L, X)
            for i in range(q):
                for r in range(a):
                    for s in range(d):
                        t = 0.0
                        for k in range(c):
                            t += LX[i, r, k] * Rm[s, k]
                        out[i, r, s] = t
        return out

    @overload(_als.sandwich_plus)
    def _sandwich_plus_loop(L, X, Rm, Y):
        """Compiled, (L X_i) Rm^T + Y_i is one loop into one array."""

        def impl(L, X, Rm, Y):
            out = _sandwich_into(L, X, Rm)
            q, a, d = out.shape
            for i in range(q):
                for r in range(a):
                    for s in range(d):
                        out[i, r, s] += Y[i, r, s]
            return out

        return impl

    @overload(_als.right_plus_sandwich)
    def _right_plus_sandwich_loop(X, Rm, L, Y):
        """Compiled, X_i Rm^T + (L Y_i) L^T is one loop into one array (a + b = b + a)."""

        def impl(X, Rm, L, Y):
            out = _sandwich_into(L, Y, L)
            _right_rows(out, X, Rm)
            return out

        return impl

    @overload(_als.right_minus_left)
    def _right_minus_left_loop(X, Rm, L, Y):
        """Compiled, X_i Rm^T - L Y_i is one loop into one array: -(L Y_i) + X_i Rm^T, the
        same value (negation and a - b = -b + a are exact)."""

        def impl(X, Rm, L, Y):
            out = np.empty((X.shape[0], X.shape[1], Rm.shape[0]))
            _left_cols(out, L, Y)
            q, a, d = out.shape
            for i in range(q):
                for r in range(a):
                    for s in range(d):
                        out[i, r, s] = -out[i, r, s]
            _right_rows(out, X, Rm)
            return out

        return impl

    @overload(_als.dual)
    def _dual_loop(R, c, x):
        """Compiled, R^T (c - R x) is two plain loops (numba's `@` calls BLAS, whose call
        costs more than these 4 x 4 products), sums in index order."""

        def impl(R, c, x):
            n, k = R.shape
            res = np.empty(n)
            for i in range(n):
                t = 0.0
                for j in range(k):
                    t += R[i, j] * x[j]
                res[i] = c[i] - t
            w = np.empty(k)
            for j in range(k):
                t = 0.0
                for i in range(n):
                    t += res[i] * R[i, j]
                w[j] = t
            return w

        return impl

    @overload(_als.closed_loop)
    def _closed_loop_loop(K, H):
        """Compiled, I - K H is one loop into one array (K H summed as `matmul`'s loop)."""

        def impl(K, H):
            n, m = K.shape
            A = np.empty((n, n))
            for r in range(n):
                for c in range(n):
                    t = 0.0
                    for k in range(m):
                        t += K[r, k] * H[k, c]
                    A[r, c] = (1.0 if r == c else 0.0) - t
            return A

        return impl

    @register_jitable
    def _factor_columns(Wt):
        """The upper-triangular factor of W (r x k), given as its columns Wt = W^T (k x r, so
        that every inner loop runs along contiguous memory), overwritten: Householder's QR as
        LAPACK's dgeqr2 runs it (dlarfg's sign convention: T's diagonal is -sign(w_jj) times
        the column's norm)."""
        k, r = Wt.shape
        for j in range(min(r, k)):
            s = 0.0
            for i in range(j + 1, r):
                s += Wt[j, i] * Wt[j, i]
            alpha = Wt[j, j]
            if s == 0.0:  # nothing below the diagonal: H = I
                continue
            norm = math.sqrt(alpha * alpha + s)
            beta = -norm if alpha >= 0.0 else norm
            tau = (beta - alpha) / beta
            scale = 1.0 / (alpha - beta)  # dlarfg scales by the reciprocal too
            for i in range(j + 1, r):
                Wt[j, i] *= scale
            Wt[j, j] = beta
            for c in range(j + 1, k):
                t = Wt[c, j]
                for i in range(j + 1, r):
                    t += Wt[j, i] * Wt[c, i]
                t *= tau
                Wt[c, j] -= t
                for i in range(j + 1, r):
                    Wt[c, i] -= t * Wt[j, i]
        T = np.zeros((k, k))
        for i in range(min(r, k)):
            for c in range(i, k):
                T[i, c] = Wt[c, i]
        return T

    @overload(_als.triangularise)
    def _triangularise_loop(Z):
        """Compiled, the factor is `_factor_columns` on a copy of Z's columns."""

        def impl(Z):
            r, k = Z.shape
            Wt = np.empty((k, r))
            for i in range(r):
                for c in range(k):
                    Wt[c, i] = Z[i, c]
            return _factor_columns(Wt)

        return impl

    @overload(_als.merge_factors)
    def _merge_factors_loop(X, Y):
        """Compiled, the rows of X and Y are stacked straight into the factor's work array."""

        def impl(X, Y):
            rx, k = X.shape
            ry = Y.shape[0]
            Wt = np.empty((k, rx + ry))
            for i in range(rx):
                for c in range(k):
                    Wt[c, i] = X[i, c]
            for i in range(ry):
                for c in range(k):
                    Wt[c, rx + i] = Y[i, c]
            return _factor_columns(Wt)

        return impl

    for _rule in (
        _als.predict_sensitivities, _als.update_sensitivities, _als.push_past,
        _als.rows_per_innovation, _als.innovation_rows, _als.window_push,
        _als.window_factor, _als._passive_solution, _als.nnls, _als.nnls_triangular,
        _als.r_basis,
    ):  # fmt: skip
        register_jitable(_rule)

predict_sensitivities = _als.predict_sensitivities
update_sensitivities = _als.update_sensitivities
push_past = _als.push_past
rows_per_innovation = _als.rows_per_innovation
innovation_rows = _als.innovation_rows
triangularise = _als.triangularise
window_push = _als.window_push
window_factor = _als.window_factor
nnls_triangular = _als.nnls_triangular
r_basis = _als.r_basis

_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_EYE9 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@maybe_njit
def as_diag(v):
    """A length-2 array as the row-major tuple of diag(v)."""
    return (v[0], 0.0, 0.0, v[1])


@maybe_njit
def nnls(A, b):
    """filters.als.nnls as the kernel runs it (compiled when numba is in use): for tests."""
    return _als.nnls(A, b)


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
    u, dt, lm, xy, z, motion, B, T0, x0, P0, Qu0, R0, gate, has_gate,
    adapt_R, adapt_Q, adaptation, from_all, floor, ceiling, lags, window, every, warmup,
    record_at, out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """filterpy_engine.run_filter with filters.als.ALSEKF: per stamp the predict and the
    interval's transition and unit noises; per landmark that feeds adaptation the
    sensitivities brought up to date and the innovation's rows (before its gain), reduced to
    their factor in the window; the gate, the update and the sensitivities through it; per
    scan with a landmark, every `every`-th, the non-negative least squares of the window (from
    min(warmup, window) innovations on) and Qu, R from it within bounds. Returns (diverged,
    records written, nis_sum, n_updates, n_rejected) as the other kernels."""
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
    F_scan_a = np.empty((3, 3))
    past_nu = np.zeros((lags, 2))
    past_D = np.zeros((lags * 4, 3, 2))
    n_past = np.int64(0)  # not the literal 0: numba would compile _finish for it as well
    rows = np.empty((rows_per_innovation(2, lags), 5))
    # The window's factors; no more than the run's measurements can fill it (a smaller ring
    # that never wraps holds the same innovations).
    size = max(1, min(window, z.shape[0]))
    fac = np.empty((size, 5, 5))
    suf = np.empty((size, 5, 5))
    back = np.zeros((5, 5))
    head = 0
    count = 0
    n_front = 0
    min_count = min(warmup, window)
    # the interval since the sensitivities were last brought up to date (AdaptiveEKF's)
    steps = 0
    A_v = _ZERO9
    A_g = _ZERO9
    F_scan = _EYE9
    pending = False
    pend_nu = np.zeros(2)
    pend_H = np.zeros((2, 3))
    no_gain = np.zeros((3, 2))
    K = np.empty((3, 2))
    S = np.empty((2, 2))
    scans = 0
    bad_record, j, nis_sum, n_updates, n_rejected = NO_TALLY
    n_records = out_x.shape[0]
    for i in range(n_stamps):
        u0, u1, h = stamp_input(u, dt, i)
        f02, f12, G = jacobians(x[2], u0, u1, h, motion, B)  # once for both
        c = noise_scale(h, motion, T0)
        A_v, A_g, F_scan = interval_step(A_v, A_g, F_scan, f02, f12, G, c)
        steps += 1
        x, P, _ = predict_with(x, P, f02, f12, G, u0, u1, h, motion, B, T0, Qu)
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
            ok, feeds = feeds_adaptation(HPHt, R, nu, from_all, gate, has_gate)
            if not ok:
                return True, j, nis_sum, n_updates, n_rejected
            if feeds:
                if steps:  # ALSEKF._catch_up
                    _fill(F_scan_a, F_scan)
                    _fill(Q_basis[0], A_v)
                    _fill(Q_basis[1], A_g)
                    M = predict_sensitivities(M, past_D, n_past, F_scan_a, Q_basis)
                    steps = 0
                    A_v = _ZERO9
                    A_g = _ZERO9
                    F_scan = _EYE9
                for a in range(4):
                    S[a // 2, a % 2] = HPHt[a] + R[a]
                # (the buffers of the previous innovation are free: it was finished above)
                pend_nu[0] = nu[0]
                pend_nu[1] = nu[1]
                pend_H[0, 0] = H[0]
                pend_H[0, 1] = H[1]
                pend_H[1, 0] = H[2]
                pend_H[1, 1] = H[3]
                pend_H[1, 2] = -1.0
                n = innovation_rows(
                    pend_nu, pend_H, M, R_basis, past_nu, past_D, n_past, S, rows
                )  # fmt: skip
                head, count, n_front = window_push(
                    fac, suf, back, head, count, n_front, triangularise(rows[:n])
                )
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
                for a in range(6):
                    K[a // 2, a % 2] = Kt[a]
                M, n_past = _finish(M, past_nu, past_D, n_past, pend_nu, pend_H, K, R_basis)
                pending = False
        # end_scan
        if pending:
            M, n_past = _finish(M, past_nu, past_D, n_past, pend_nu, pend_H, no_gain, R_basis)
            pending = False
        scans += 1
        if adaptation and scans % every == 0 and count >= min_count:
            T = window_factor(fac, suf, back, head, count, n_front)
            theta = nnls_triangular(T[:4, :4], T[:4, 4])
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
