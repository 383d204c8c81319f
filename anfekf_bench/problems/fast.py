"""The fast engine of problem scenarios (SPEC 17, SPEC 11): each generic filter family's loop
compiled once by numba, for every problem.

How a problem's functions reach the loops: numba cannot cache a function that takes another
jitted function as an argument (each function is a type of its own: a new specialisation per
problem, compiled again in every process). Here every model function has one signature,
`(x: float64[::1], k: int64, p: float64[::1]) -> float64[::1]` (f, h) or `-> float64[:, ::1]`
(F, G, H), where `p` is the problem's parameter vector; the loops take them as numba's
first-class function type of that signature, so each loop is compiled once for all problems and
cached on disk, and each problem's five functions are compiled (and cached, beside their source)
on their own. A call through the function pointer costs a few nanoseconds. The small matrix
products are plain loops (`_mm`, `_mmt`, `_mv`, `_outer`): numba's `@` calls BLAS, which costs
more than the product at these sizes (measured: the loops halve the per-run time and compile
faster).

- `linear_model`: the linear problem's functions read F, G, H from `p` (cached like the loops);
- `tracking_model`: the tracking radar's read the radar, its transitions and the turn from `p`;
- `compile_module_model`: a user's module's functions compiled with that signature, or
  `NotCompilable` saying which one does not compile and why;
- `sage_husa_run`, `vbr_run`, `als_run`: the loops of `filters.SageHusaKF`, `VBRKF` and
  `als.ALSKF`, and `ekf_run`, `GenericKF`'s (Sage-Husa's adapting neither Q nor R), the same
  arithmetic in the same order (the engines' equivalence test holds them to 1e-9:
  tests/test_problems_fast.py). Three loops, not one per family: each costs 15-30 s of
  compilation the first time. Each takes the problem's gate (`gate_of`: infinity, none) and
  returns the measurements it dropped, with the Python filters' rule (`kalman.outside_gate`:
  a dropped measurement is neither used nor adapted on).

Importing this module compiles the loops (or loads them from numba's cache): only the fast
engine imports it. Without numba importing it raises ImportError saying so.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..compiled import use_reached_sources_stamp
from .base import NotCompilable

try:
    from numba import njit, types
except ImportError:  # pragma: no cover - numba is installed wherever CI runs the fast engine
    raise ImportError(
        "the fast engine of problems needs numba (pip install -e '.[fast]')"
    ) from None
use_reached_sources_stamp()  # the package's one cache stamp, whichever module comes first

A1, A2, A3 = types.float64[::1], types.float64[:, ::1], types.float64[:, :, ::1]
VECTOR_FN = A1(A1, types.int64, A1)
MATRIX_FN = A2(A1, types.int64, A1)
VectorFn, MatrixFn = types.FunctionType(VECTOR_FN), types.FunctionType(MATRIX_FN)
# f, F, G, h, H, p, angles: the model arguments every loop starts with
MODEL_ARGS = (VectorFn, MatrixFn, MatrixFn, VectorFn, MatrixFn, A1, types.int64[::1])
I64, F64 = types.int64, types.float64


@dataclass(frozen=True)
class CompiledModel:
    """A problem's compiled functions, its parameter vector and angle-valued components."""

    f: object
    F: object
    G: object
    h: object
    H: object
    params: np.ndarray
    angles: np.ndarray
    compile_seconds: float = 0.0

    def args(self) -> tuple:
        return (self.f, self.F, self.G, self.h, self.H, self.params, self.angles)


@njit(cache=True)
def _mm(A, B):  # pragma: no cover - compiled
    """A @ B as a plain loop: numba's `@` on small matrices calls BLAS, costlier than the sum."""
    n, m, q = A.shape[0], A.shape[1], B.shape[1]
    out = np.zeros((n, q))
    for i in range(n):
        for l in range(m):
            a = A[i, l]
            for j in range(q):
                out[i, j] += a * B[l, j]
    return out


@njit(cache=True)
def _mmt(A, B):  # pragma: no cover - compiled
    """A @ B.T as a plain loop."""
    n, m, q = A.shape[0], A.shape[1], B.shape[0]
    out = np.empty((n, q))
    for i in range(n):
        for j in range(q):
            acc = 0.0
            for l in range(m):
                acc += A[i, l] * B[j, l]
            out[i, j] = acc
    return out


@njit(cache=True)
def _mv(A, x):  # pragma: no cover - compiled
    """A @ x as a plain loop."""
    out = np.empty(A.shape[0])
    for i in range(A.shape[0]):
        acc = 0.0
        for j in range(A.shape[1]):
            acc += A[i, j] * x[j]
        out[i] = acc
    return out


@njit(cache=True)
def _outer(a, b):  # pragma: no cover - compiled
    out = np.empty((a.shape[0], b.shape[0]))
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            out[i, j] = a[i] * b[j]
    return out


# --- the linear problem: F, G, H packed in p = (n, nw, nz, F, G, H) ------------------------------


def linear_params(F: np.ndarray, G: np.ndarray, H: np.ndarray) -> np.ndarray:
    n, nw, nz = F.shape[0], G.shape[1], H.shape[0]
    return np.concatenate([[n, nw, nz], F.ravel(), G.ravel(), H.ravel()]).astype(float)


@njit(cache=True)
def _block(p, start, rows, cols):  # pragma: no cover - compiled
    return p[start : start + rows * cols].reshape((rows, cols))


@njit(VECTOR_FN, cache=True)
def _linear_f(x, k, p):  # pragma: no cover - compiled
    n = int(p[0])
    return _mv(_block(p, 3, n, n), x)


@njit(MATRIX_FN, cache=True)
def _linear_F(x, k, p):  # pragma: no cover - compiled
    n = int(p[0])
    return _block(p, 3, n, n).copy()


@njit(MATRIX_FN, cache=True)
def _linear_G(x, k, p):  # pragma: no cover - compiled
    n, nw = int(p[0]), int(p[1])
    return _block(p, 3 + n * n, n, nw).copy()


@njit(VECTOR_FN, cache=True)
def _linear_h(x, k, p):  # pragma: no cover - compiled
    n, nw, nz = int(p[0]), int(p[1]), int(p[2])
    return _mv(_block(p, 3 + n * n + n * nw, nz, n), x)


@njit(MATRIX_FN, cache=True)
def _linear_H(x, k, p):  # pragma: no cover - compiled
    n, nw, nz = int(p[0]), int(p[1]), int(p[2])
    return _block(p, 3 + n * n + n * nw, nz, n).copy()


def linear_model(F, G, H, angles=()) -> CompiledModel:
    """The compiled model of x(k+1) = F x + G w, z = H x + v (the functions are cached)."""
    return CompiledModel(_linear_f, _linear_F, _linear_G, _linear_h, _linear_H,
                         linear_params(F, G, H), np.array(angles, dtype=np.int64))  # fmt: skip


# --- the tracking radar: p = (px, py, start, end, known, A_ncv, A_ct) ----------------------------
# (`tracking.TrackingProblem`: the filters' transition is the coordinated turn A_ct over the
# steps [start, end) when they are told of the turn (known = 1), else A_ncv.)


def tracking_params(radar, ncv: np.ndarray, ct: np.ndarray | None, turn) -> np.ndarray:
    known = turn is not None and turn.known
    start, end = (turn.start, turn.end) if turn is not None else (0, 0)
    ct = ncv if ct is None else ct
    head = [radar[0], radar[1], start, end, 1.0 if known else 0.0]
    return np.concatenate([head, ncv.ravel(), ct.ravel()]).astype(float)


@njit(cache=True)
def _tracking_A(k, p):  # pragma: no cover - compiled
    if p[4] != 0.0 and p[2] <= k < p[3]:
        return _block(p, 21, 4, 4)
    return _block(p, 5, 4, 4)


@njit(VECTOR_FN, cache=True)
def _tracking_f(x, k, p):  # pragma: no cover - compiled
    return _mv(_tracking_A(k, p), x)


@njit(MATRIX_FN, cache=True)
def _tracking_F(x, k, p):  # pragma: no cover - compiled
    return _tracking_A(k, p).copy()


@njit(MATRIX_FN, cache=True)
def _tracking_G(x, k, p):  # pragma: no cover - compiled
    return np.eye(4)


@njit(VECTOR_FN, cache=True)
def _tracking_h(x, k, p):  # pragma: no cover - compiled
    dx, dy = x[0] - p[0], x[2] - p[1]
    out = np.empty(2)
    out[0], out[1] = math.hypot(dx, dy), math.atan2(dy, dx)
    return out


@njit(MATRIX_FN, cache=True)
def _tracking_H(x, k, p):  # pragma: no cover - compiled
    dx, dy = x[0] - p[0], x[2] - p[1]
    r2 = max(dx * dx + dy * dy, 1e-12)  # as TrackingProblem.H: the bearing undefined at 0
    r = math.sqrt(r2)
    out = np.zeros((2, 4))
    out[0, 0], out[0, 2], out[1, 0], out[1, 2] = dx / r, dy / r, -dy / r2, dx / r2
    return out


def tracking_model(radar, ncv, ct, turn, angles) -> CompiledModel:
    """The compiled model of a `tracking.TrackingProblem` (the functions are cached): its
    radar, transitions (nearly constant velocity; the turn's or None) and `Turn` or None."""
    return CompiledModel(_tracking_f, _tracking_F, _tracking_G, _tracking_h, _tracking_H,
                         tracking_params(radar, ncv, ct, turn),
                         np.array(angles, dtype=np.int64))  # fmt: skip


# --- a user's module -----------------------------------------------------------------------------


def _why(exc: BaseException) -> str:
    """numba's error in one line: its first line that says something about the code."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    useful = [ln for ln in lines if not ln.startswith(("Failed in", "During:", "File ", "^"))]
    text = (useful or lines or [type(exc).__name__])[0]
    return text if len(text) <= 240 else text[:237] + "..."


@lru_cache(maxsize=16)
def _compile_functions(path: str, digest: str, module_name: str) -> tuple[tuple, float]:
    import sys

    module = sys.modules[module_name]
    started = time.perf_counter()
    out = []
    for key, sig in (("f", VECTOR_FN), ("F", MATRIX_FN), ("G", MATRIX_FN), ("h", VECTOR_FN),
                     ("H", MATRIX_FN)):  # fmt: skip
        fn = getattr(module, key)
        fn = getattr(fn, "py_func", fn)  # already a numba dispatcher: its Python function
        try:
            out.append(njit(sig, cache=True)(fn))
        except Exception as exc:  # numba's errors have many types; each is the user's code's
            raise NotCompilable(
                f"{Path(path).name}: {key} does not compile with numba ({_why(exc)}); run it"
                " on engine filterpy, or see docs/CUSTOM_PROBLEMS.md"
            ) from None
    return tuple(out), time.perf_counter() - started


def compile_module_model(problem) -> CompiledModel:
    """The compiled model of a `module.ModuleProblem` (compiled once per process and file
    content; numba's cache keeps it on disk between processes)."""
    functions, seconds = _compile_functions(str(problem.path), problem.digest,
                                            problem.module.__name__)  # fmt: skip
    return CompiledModel(*functions, np.ascontiguousarray(problem.params, dtype=float),
                         np.array(problem.angles, dtype=np.int64), seconds)  # fmt: skip


# --- the shared arithmetic (filters.GenericKF, kalman.joseph_update, kalman.nearest_psd) ----


@njit(cache=True)
def _wrap(r, angles):  # pragma: no cover - compiled
    for i in angles:
        r[i] = np.pi - np.mod(np.pi - r[i], 2 * np.pi)
    return r


@njit(cache=True)
def _symmetric(M):  # pragma: no cover - compiled
    return 0.5 * (M + M.T)


@njit(cache=True)
def _nearest_psd(M, floor):  # pragma: no cover - compiled
    w, V = np.linalg.eigh(_symmetric(M))
    return _symmetric(_mmt(V * np.maximum(w, floor), V))


@njit(cache=True)
def _joseph(x, P, nu, H, R):  # pragma: no cover - compiled
    S = _mmt(_mm(H, P), H) + R
    K = np.linalg.solve(S.T, _mmt(P, H).T).T.copy()
    x = x + _mv(K, nu)
    IKH = np.eye(x.shape[0]) - _mm(K, H)
    P = _mmt(_mm(IKH, P), IKH) + _mmt(_mm(K, R), K)
    return x, _symmetric(P)


@njit(cache=True)
def _outside_gate(nu, H, P, R, gate):  # pragma: no cover - compiled
    """kalman.outside_gate: nu^T (H P H^T + R)^-1 nu > gate (gate inf: the problem has none)."""
    if gate == np.inf:
        return False
    v = np.linalg.solve(_mmt(_mm(H, P), H) + R, nu)
    acc = 0.0
    for i in range(nu.shape[0]):
        acc += nu[i] * v[i]
    return acc > gate


@njit(cache=True)
def _predict(f, F, G, p, x, P, Q, k):  # pragma: no cover - compiled
    Fk, Gk = F(x, k, p), G(x, k, p)
    return f(x, k, p), _symmetric(_mmt(_mm(Fk, P), Fk) + _mmt(_mm(Gk, Q), Gk)), Fk, Gk


# --- the loops -----------------------------------------------------------------------------------


@njit((*MODEL_ARGS, A1, A2, A2, A2, A2, F64, F64, I64, I64, I64, A2, A2, F64), cache=True)
def sage_husa_run(f, F, G, h, H, p, angles, x0, P0, Q, R, z, gate, b, adapt_r, adapt_q, warmup,
                  r_units, q_units, floor):  # fmt: skip  # pragma: no cover - compiled
    """(x, P, Q, R, gated) of `SageHusaKF`: R's sample before the gain, Q's from the
    correction, each projected in units of its starting standard deviations (`r_units`,
    `q_units`); a measurement outside the gate is counted, neither used nor adapted on."""
    steps, n, nw, nz = z.shape[0], x0.shape[0], Q.shape[0], R.shape[0]
    xs, Ps = np.empty((steps, n)), np.empty((steps, n, n))
    Qs, Rs = np.empty((steps, nw, nw)), np.empty((steps, nz, nz))
    x, P, Q, R = x0.copy(), P0.copy(), Q.copy(), R.copy()
    R_hat, Q_hat = R.copy(), Q.copy()
    F_prev, G_prev, P_prev = np.empty((n, n)), np.empty((n, nw)), np.empty((n, n))
    gated = 0
    for k in range(steps):
        nu = _wrap(z[k] - h(x, k, p), angles)
        Hk = H(x, k, p)
        if _outside_gate(nu, Hk, P, R, gate):
            gated += 1
        else:
            if adapt_r:
                d = 1.0 / (k + 1) if b == 1.0 else (1.0 - b) / (1.0 - b ** (k + 1))
                R_hat = (1.0 - d) * R_hat + d * (_outer(nu, nu) - _mmt(_mm(Hk, P), Hk))
                if k + 1 >= warmup:
                    R = _nearest_psd(R_hat / r_units, floor) * r_units
            x_prior = x
            x, P = _joseph(x, P, nu, Hk, R)
            if adapt_q and k > 0:
                dx = x - x_prior
                G_pinv = np.linalg.pinv(G_prev)
                sample = _outer(dx, dx) + P - _mmt(_mm(F_prev, P_prev), F_prev)
                sample = _mmt(_mm(G_pinv, 0.5 * (sample + sample.T)), G_pinv)
                j = k - 1
                d = 1.0 / (j + 1) if b == 1.0 else (1.0 - b) / (1.0 - b ** (j + 1))
                Q_hat = (1.0 - d) * Q_hat + d * _symmetric(sample)
                if k + 1 >= warmup:
                    Q = _nearest_psd(Q_hat / q_units, floor) * q_units
        xs[k], Ps[k], Qs[k], Rs[k] = x, P, Q, R
        P_prev = P
        x, P, F_prev, G_prev = _predict(f, F, G, p, x, P, Q, k)
    return xs, Ps, Qs, Rs, gated


@njit((*MODEL_ARGS, A1, A2, A2, A2, A2, F64, F64, I64, F64), cache=True)
def vbr_run(f, F, G, h, H, p, angles, x0, P0, Q, R, z, gate, rho, iterations,
            dof):  # fmt: skip  # pragma: no cover - compiled
    """(x, P, R, gated) of `VBRKF`: R ~ IW(dof, V), E[R^-1]^-1 = V / dof in the update; a
    measurement outside the gate (with the R in force) leaves the posterior as it was."""
    steps, n, m = z.shape[0], x0.shape[0], R.shape[0]
    xs, Ps, Rs = np.empty((steps, n)), np.empty((steps, n, n)), np.empty((steps, m, m))
    x, P, R = x0.copy(), P0.copy(), R.copy()
    V = dof * R
    x_post, P_post = x, P
    gated = 0
    for k in range(steps):
        if _outside_gate(_wrap(z[k] - h(x, k, p), angles), H(x, k, p), P, R, gate):
            gated += 1
            xs[k], Ps[k], Rs[k] = x, P, R
            x, P, _, _ = _predict(f, F, G, p, x, P, Q, k)
            continue
        nu_prior = rho * (dof - m - 1.0) + m + 1.0
        V_prior = rho * V
        dof = nu_prior + 1.0
        Vk = V_prior
        for _ in range(iterations):
            Rk = Vk / dof
            nu_z = _wrap(z[k] - h(x, k, p), angles)
            x_post, P_post = _joseph(x, P, nu_z, H(x, k, p), Rk)
            r = _wrap(z[k] - h(x_post, k, p), angles)
            Hp = H(x_post, k, p)
            Vk = V_prior + _outer(r, r) + _mmt(_mm(Hp, P_post), Hp)
        V = _symmetric(Vk)
        R = V / dof
        x, P = x_post, P_post
        xs[k], Ps[k], Rs[k] = x, P, R
        x, P, _, _ = _predict(f, F, G, p, x, P, Q, k)
    return xs, Ps, Rs, gated


@njit(cache=True)
def _from_vech(theta, m):  # pragma: no cover - compiled
    M, i_theta = np.zeros((m, m)), 0
    for i in range(m):
        for j in range(i, m):
            M[i, j] = M[j, i] = theta[i_theta]
            i_theta += 1
    return M


@njit((*MODEL_ARGS, A1, A2, A2, A2, A2, F64, A2, A2, A2, A2, I64, I64, I64, I64, F64, F64),
      cache=True)  # fmt: skip
def als_run(f, F, G, h, H, p, angles, x0, P0, Q, R, z, gate, Fm, Hm, K, pinv, lags, every, burn,
            min_steps, q_floor, r_floor):  # fmt: skip  # pragma: no cover - compiled
    """(x, P, Q, R, gated) of `ALSKF`: the fixed-gain predictor's innovations, their
    autocovariances so far, (Q, R) by the identifier's pseudo-inverse every `every` steps; a
    measurement outside the gate is counted and skipped, by the predictor too."""
    steps, n, nw, nz = z.shape[0], x0.shape[0], Q.shape[0], R.shape[0]
    nq = nw * (nw + 1) // 2
    xs, Ps = np.empty((steps, n)), np.empty((steps, n, n))
    Qs, Rs = np.empty((steps, nw, nw)), np.empty((steps, nz, nz))
    x, P, Q, R = x0.copy(), P0.copy(), Q.copy(), R.copy()
    xp = x0.copy()
    ys = np.empty((max(steps - burn, 0), nz))
    sums, counts = np.zeros((lags, nz, nz)), np.zeros(lags)
    used, gated = 0, 0
    for k in range(steps):
        nu = _wrap(z[k] - h(x, k, p), angles)
        Hk = H(x, k, p)
        if _outside_gate(nu, Hk, P, R, gate):
            gated += 1
            xs[k], Ps[k], Qs[k], Rs[k] = x, P, Q, R
            x, P, _, _ = _predict(f, F, G, p, x, P, Q, k)
            continue
        y = z[k] - _mv(Hm, xp)
        if k >= burn:
            ys[used] = y
            used += 1
            for j in range(min(used, lags)):
                sums[j] += _outer(y, ys[used - 1 - j])
                counts[j] += 1
            if used >= min_steps and (used - min_steps) % every == 0:
                C = np.empty((lags, nz, nz))
                for j in range(lags):
                    C[j] = sums[j] / counts[j]
                theta = _mv(pinv, C.ravel())
                Q = _nearest_psd(_from_vech(theta[:nq], nw), q_floor)
                R = _nearest_psd(_from_vech(theta[nq:], nz), r_floor)
        xp = _mv(Fm, xp) + _mv(K, y)
        x, P = _joseph(x, P, nu, Hk, R)
        xs[k], Ps[k], Qs[k], Rs[k] = x, P, Q, R
        x, P, _, _ = _predict(f, F, G, p, x, P, Q, k)
    if used >= lags:
        C = np.empty((lags, nz, nz))
        for j in range(lags):
            C[j] = sums[j] / counts[j]
        theta = _mv(pinv, C.ravel())
        Qs[steps - 1] = _nearest_psd(_from_vech(theta[:nq], nw), q_floor)
        Rs[steps - 1] = _nearest_psd(_from_vech(theta[nq:], nz), r_floor)
    return xs, Ps, Qs, Rs, gated


def ekf_run(f, F, G, h, H, p, angles, x0, P0, Q, R, z, gate):
    """(x, P, gated) of `GenericKF.run` with fixed Q and R: Sage-Husa's loop adapting neither
    (one compiled loop fewer; the same arithmetic)."""
    xs, Ps, _, _, gated = sage_husa_run(f, F, G, h, H, p, angles, x0, P0, Q, R, z, gate, 1.0,
                                        0, 0, 0, np.ones(R.shape), np.ones(Q.shape),
                                        0.0)  # fmt: skip
    return xs, Ps, gated


def gate_of(problem) -> float:
    """The problem's gate threshold as the loops take it (inf: no gate)."""
    return np.inf if problem.gate is None else float(problem.gate)


def as_arrays(*arrays) -> tuple:
    """Contiguous float64 copies the loops' signatures accept."""
    return tuple(np.ascontiguousarray(a, dtype=float) for a in arrays)
