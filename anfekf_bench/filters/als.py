"""`als`: online LTV autocovariance least squares (Odelson, Rajamani & Rawlings 2006; LTV form:
Lima & Rawlings 2011), identifying the four noise variances (qv, qg, rr, rb) from the
correlations of the filter's own innovations (SPEC 13; research/noise-identification.md 2).

Whatever Q and R the filter assumes, its prior error e-_k = x_k - x-_k and innovation
nu_k = H_k e-_k + v_k obey, with the gains K actually used and A = I - K H:

    e+ = A e- - K v           (an accepted update; a rejected one: K = 0)
    e-' = F e+ + G w          (every control step; w ~ N(0, Qu))

so the true prior covariance is Sigma_k = sum_i theta_i M_i,k (+ the start's, ~0: runs start at
the truth), the sensitivities M_i propagated from zero along the run:

    M_i <- F M_i F^T + Q(G, E_i)         (i = qv, qg: E_i the unit control variance)
    M_i <- A M_i A^T + K E_i K^T         (i = rr, rb: E_i the unit measurement variance)

and, for an innovation l before k (Phi: the closed-loop transition from after l to before k),

    E[nu_k nu_k^T] = sum_i theta_i (H_k M_i,k H_k^T + E_i^R)                       (lag 0)
    E[nu_k nu_l^T] = sum_i theta_i H_k Phi_k,l (A_l M_i,l H_l^T - K_l E_i^R)         (lag j)

Every innovation gives the three distinct entries of its lag-0 product and the four of each of
its products with the `lags` innovations before it: rows linear in theta, each divided by
sqrt(S_aa S_bb) (the filter's S at the time) so that metres and radians weigh alike. The rows of
the last `window` innovations (once `warmup` of them exist) are solved by non-negative least
squares (`nnls_triangular`: Lawson & Hanson, as scipy.optimize.nnls) every `every` scans (end
of scan, a Q event); then Qu = diag(qv, qg), R = diag(rr, rb), within the common bounds. Which
innovations feed it: `adapt_from` (all, with K = 0 for a rejected one; or only those the gate
accepted). Each innovation's rows are kept only as the triangular factor of [A | b], the
window's factor by a two-stack queue (`window_push`), so a solve costs 4 x 4 whatever the
window; the sensitivities are brought up to date when an innovation feeds the rows, through the
interval's transition and unit noises (AdaptiveEKF's F_scan, A_v, A_g).

The rule is written once as plain functions on small arrays (`predict_sensitivities`,
`update_sensitivities`, `push_past`, `innovation_rows`, `triangularise`, `window_push`,
`window_factor`, `nnls_triangular`), tested on a linear model where the answer is known;
`ALSEKF` calls them from the EKF's hooks, and numba compiles them as they are into the fast
engine's kernel (engines/kernels_als.py).
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from .adaptive import AdaptiveEKF, matmul
from .ekf import FilterDiverged, Innovation
from .spec import AdaptiveSpec, FilterContext

# ---------------------------------------------------------------------------------------------
# Batched products: numpy's broadcasting matmul here; the fast engine compiles them as plain
# loops (engines/kernels_als.py), where a small array's allocation costs more than the product
# (hence the fused forms: one output array, no temporaries).


def batch_left(L: np.ndarray, X: np.ndarray) -> np.ndarray:
    """L X_i for every matrix X_i of the stack X (q, b, c): (q, a, c)."""
    return L @ X


def sandwich_plus(L: np.ndarray, X: np.ndarray, Rm: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """L X_i Rm^T + Y_i for every matrix X_i of the stack X (q, b, c): (q, a, d)."""
    return (L @ X) @ Rm.T + Y


def right_plus_sandwich(X: np.ndarray, Rm: np.ndarray, L: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """X_i Rm^T + L Y_i L^T for every pair of the stacks X (q, a, c), Y (q, b, e)."""
    return X @ Rm.T + (L @ Y) @ L.T


def right_minus_left(X: np.ndarray, Rm: np.ndarray, L: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """X_i Rm^T - L Y_i for every pair of the stacks X (q, a, c), Y (q, b, d)."""
    return X @ Rm.T - L @ Y


def dual(R: np.ndarray, c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """R^T (c - R x): minus the gradient of ||R x - c||^2 / 2 (Lawson & Hanson's w)."""
    return (c - R @ x) @ R


def left_in_place(L: np.ndarray, X: np.ndarray) -> None:
    """X_i <- L X_i for every matrix X_i of the stack X (q, b, c), in place."""
    X[...] = L @ X


def closed_loop(K: np.ndarray, H: np.ndarray) -> np.ndarray:
    """A = I - K H."""
    return np.eye(K.shape[0]) - matmul(K, H)


# ---------------------------------------------------------------------------------------------
# The rule, as plain functions (any state and measurement dimension; numba compiles them as
# they are). The last `lags` innovations are kept oldest first: their nu in `past_nu` (lags, m)
# and their cross terms D_l (p, n, m) stacked in `past_D` (lags * p, n, m), the first `n_past`
# of each in use.


def predict_sensitivities(
    M: np.ndarray, past_D: np.ndarray, n_past: int, F: np.ndarray, Q_basis: np.ndarray
) -> np.ndarray:
    """One prediction: M_i <- F M_i F^T + Q_basis_i (Q_basis (p, n, n): the state-space noise
    of a unit value of unknown i; zero for the measurement unknowns); every stored cross term
    D_l <- F D_l in place. Returns the new M (p, n, n)."""
    used = n_past * M.shape[0]
    if used:
        left_in_place(F, past_D[:used])
    return sandwich_plus(F, M, F, Q_basis)


def update_sensitivities(
    M: np.ndarray,
    past_D: np.ndarray,
    n_past: int,
    H: np.ndarray,
    K: np.ndarray,
    R_basis: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """One measurement (gain K, zero for a rejected one): the innovation's cross term
    C_i = A M_i H^T - K R_basis_i (A = I - K H), every stored D_l <- A D_l in place, and
    M_i <- A M_i A^T + K R_basis_i K^T. Returns (new M, C)."""
    A = closed_loop(K, H)
    AM = batch_left(A, M)
    C = right_minus_left(AM, H, K, R_basis)
    used = n_past * M.shape[0]
    if used:
        left_in_place(A, past_D[:used])
    return right_plus_sandwich(AM, A, K, R_basis), C


def push_past(
    past_nu: np.ndarray, past_D: np.ndarray, n_past: int, nu: np.ndarray, C: np.ndarray
) -> int:
    """Keep (nu, C) as the newest of the last `lags` innovations (the oldest dropped when they
    are all in use); returns the new count."""
    lags = past_nu.shape[0]
    if lags == 0:
        return 0
    p = C.shape[0]
    if n_past == lags:  # each one a place older, block by block (no overlapping copy)
        for j in range(lags - 1):
            past_nu[j] = past_nu[j + 1]
            past_D[j * p : (j + 1) * p] = past_D[(j + 1) * p : (j + 2) * p]
        n_past -= 1
    past_nu[n_past] = nu
    past_D[n_past * p : (n_past + 1) * p] = C
    return n_past + 1


def rows_per_innovation(m: int, lags: int) -> int:
    """Rows of one innovation with `lags` past ones: m (m + 1) / 2 at lag 0, m^2 per lag."""
    return m * (m + 1) // 2 + lags * m * m


def innovation_rows(
    nu: np.ndarray,
    H: np.ndarray,
    M: np.ndarray,
    R_basis: np.ndarray,
    past_nu: np.ndarray,
    past_D: np.ndarray,
    n_past: int,
    S: np.ndarray,
    out: np.ndarray,
) -> int:
    """The rows [A | b] of one innovation nu (before its update) into `out` (rows, p + 1): lag 0
    (the upper triangle of nu nu^T, row by row) and, for each stored (nu_l, D_l), oldest first,
    the entries of nu nu_l^T (row-major), every row divided by sqrt(S_aa S_bb). Returns how
    many rows it wrote."""
    m, p = len(nu), M.shape[0]
    lag0 = sandwich_plus(H, M, H, R_basis)  # (p, m, m)
    r = 0
    for a in range(m):
        for b in range(a, m):
            scale = math.sqrt(S[a, a] * S[b, b])
            for i in range(p):
                out[r, i] = lag0[i, a, b] / scale
            out[r, p] = nu[a] * nu[b] / scale
            r += 1
    cross = batch_left(H, past_D[: n_past * p])  # (n_past * p, m, m)
    for j in range(n_past):
        for a in range(m):
            for b in range(m):
                scale = math.sqrt(S[a, a] * S[b, b])
                for i in range(p):
                    out[r, i] = cross[j * p + i, a, b] / scale
                out[r, p] = nu[a] * past_nu[j, b] / scale
                r += 1
    return r


# ---------------------------------------------------------------------------------------------
# The window's least squares. ||A x - b||^2 over the rows of the last `window` innovations
# depends on them only through the triangular factor of [A | b] (Z = Q T: T^T T = Z^T Z), and
# the factor of stacked rows is the factor of their stacked factors. So each innovation's rows
# are reduced to their (p + 1) x (p + 1) factor once, and the window's factor is kept by a
# two-stack queue (sliding-window aggregation): the oldest innovations' suffix factors, the
# newest's running factor; a push or a pop merges one or two factors (amortised), a query one.


def triangularise(Z: np.ndarray) -> np.ndarray:
    """The upper-triangular factor T (k x k) of Z (r x k): Z = Q T (Householder; rows of zeros
    below when r < k); numpy's QR here, a plain loop in the fast engine."""
    T = np.zeros((Z.shape[1], Z.shape[1]))
    R = np.linalg.qr(Z, mode="r")
    T[: R.shape[0]] = R
    return T


def merge_factors(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The factor of the rows of X and of Y together (the factor of [X; Y])."""
    return triangularise(np.vstack((X, Y)))


def window_push(
    fac: np.ndarray,
    suf: np.ndarray,
    back: np.ndarray,
    head: int,
    count: int,
    n_front: int,
    new: np.ndarray,
) -> tuple[int, int, int]:
    """Add one innovation's factor `new` to the window (a ring of len(fac) innovations: their
    factors `fac`, slot `head` the oldest, `count` held), dropping the oldest when it is full.
    The oldest `n_front` have suffix factors `suf` (slot s: the factor of s and every newer one
    of them); `back` is the factor of the others. Returns (head, count, n_front)."""
    size = fac.shape[0]
    if count == size:
        if n_front == 0:  # every held innovation becomes the front: its suffix factors
            last = (head + count - 1) % size
            suf[last] = fac[last]
            for i in range(count - 2, -1, -1):
                s = (head + i) % size
                suf[s] = merge_factors(fac[s], suf[(s + 1) % size])
            n_front = count
        head = (head + 1) % size
        count -= 1
        n_front -= 1
    fac[(head + count) % size] = new
    if count == n_front:
        back[:] = new
    else:
        back[:] = merge_factors(back, new)
    return head, count + 1, n_front


def window_factor(
    fac: np.ndarray, suf: np.ndarray, back: np.ndarray, head: int, count: int, n_front: int
) -> np.ndarray:
    """The factor of every innovation's rows in the window (`window_push`)."""
    if n_front == 0:
        return back.copy()
    if n_front == count:
        return suf[head].copy()
    return merge_factors(suf[head], back)


_EPS = float(np.finfo(float).eps)


def _passive_solution(Rt: np.ndarray, c: np.ndarray, passive: np.ndarray) -> np.ndarray:
    """The least-squares solution over the passive columns, zero on the others: the factor of
    [Rt_passive | c] and back substitution; a column that adds nothing to the span of the
    earlier ones (|T_jj| at rounding level) gets zero."""
    n = Rt.shape[1]
    z = np.zeros(n)
    k = 0
    for i in range(n):
        if passive[i]:
            k += 1
    if k == 0:
        return z
    Z = np.empty((Rt.shape[0], k + 1))
    j = 0
    for i in range(n):
        if passive[i]:
            Z[:, j] = Rt[:, i]
            j += 1
    Z[:, k] = c
    T = triangularise(Z)
    tol = 10.0 * _EPS * max(Z.shape[0], k) * max(np.abs(Z[:, :k]).max(), 1e-300)
    sol = np.zeros(k)
    for j in range(k - 1, -1, -1):
        if abs(T[j, j]) > tol:
            t = T[j, k]
            for m in range(j + 1, k):
                t -= T[j, m] * sol[m]
            sol[j] = t / T[j, j]
    j = 0
    for i in range(n):
        if passive[i]:
            z[i] = sol[j]
            j += 1
    return z


def nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The non-negative x minimising ||A x - b|| (as scipy.optimize.nnls): `nnls_triangular`
    on the factor of [A | b]. NaN or infinite input gives NaN."""
    n = A.shape[1]
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        return np.full(n, np.nan)
    Z = np.empty((A.shape[0], n + 1))
    Z[:, :n] = A
    Z[:, n] = b
    T = triangularise(Z)
    return nnls_triangular(T[:n, :n], T[:n, n])


def nnls_triangular(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The non-negative x minimising ||R x - c|| for a square R (the factor of the rows: then
    ||A x - b||^2 = ||R x - c||^2 + const): Lawson & Hanson's active-set algorithm (Solving
    Least Squares Problems, 1974, ch. 23), as scipy.optimize.nnls runs it on A; every pass costs
    p x p whatever the number of rows. NaN or infinite input gives NaN."""
    n = R.shape[1]
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(c))):
        return np.full(n, np.nan)
    Rt = np.ascontiguousarray(R)
    c = np.ascontiguousarray(c)
    # Lawson & Hanson's tolerance on the dual and on zeroed variables
    tol = 10.0 * _EPS * n * max(np.abs(Rt).max(), 1e-300)
    x = np.zeros(n)
    passive = np.zeros(n, dtype=np.bool_)
    w = dual(Rt, c, x)
    skip = np.zeros(n, dtype=np.bool_)  # variables whose entry made no progress (w ~ 0)
    for _ in range(3 * n + 1):
        best, t = tol, -1
        for i in range(n):
            if not passive[i] and not skip[i] and w[i] > best:
                best, t = w[i], i
        if t < 0:
            break
        passive[t] = True
        z = _passive_solution(Rt, c, passive)
        if z[t] <= 0.0:  # rounding: the entering variable cannot move; try the next one
            passive[t] = False
            skip[t] = True
            continue
        skip[:] = False
        for _inner in range(3 * n):
            alpha, blocked = 2.0, False
            for i in range(n):
                if passive[i] and z[i] <= 0.0:
                    blocked = True
                    step = x[i] / (x[i] - z[i])
                    alpha = min(alpha, step)
            if not blocked:
                break
            x = x + alpha * (z - x)
            for i in range(n):
                if passive[i] and x[i] <= tol:
                    passive[i] = False
                    x[i] = 0.0
            z = _passive_solution(Rt, c, passive)
        x = z
        w = dual(Rt, c, x)
    return x


def r_basis() -> np.ndarray:
    """R_basis of (qv, qg, rr, rb): a unit variance on range, on bearing (zero for qv, qg)."""
    out = np.zeros((4, 2, 2))
    out[2, 0, 0] = 1.0
    out[3, 1, 1] = 1.0
    return out


# ---------------------------------------------------------------------------------------------
# The filter


class ALSSpec(AdaptiveSpec):
    """Online LTV autocovariance least squares on Qu and R (module doc)."""

    kind: Literal["als"]
    fast_kernel: ClassVar[str | None] = "kernels_als"
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "module"})
    problem_form: ClassVar[str | None] = "als:ALSSpec"  # problems/als.py
    robot_only_because: ClassVar[str] = (
        "beyond the robot, autocovariance least squares needs a linear time-invariant problem"
        " (constant F, G, H: the innovations' autocovariances are linear in Q and R only then;"
        " a module problem saying `linear = True`)"
    )
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    adapt: Literal["RQ", "R", "Q"] = Field(
        "RQ", description="which variances the identified values replace (all four are fitted)"
    )
    lags: int = Field(2, ge=0, le=20, description="innovation lags correlated, besides lag 0")
    window: int = Field(
        300, ge=10, le=100_000, description="innovations whose rows the least squares uses"
    )
    every: int = Field(5, ge=1, le=100_000, description="scans between re-identifications")
    warmup: int = Field(
        30, ge=1, le=100_000, description="innovations needed before the first identification"
    )

    def build(self, ctx: FilterContext) -> ALSEKF:
        return ALSEKF(**ctx.kwargs(), params=self)


class ALSEKF(AdaptiveEKF):
    """EKF plus online ALS (module doc)."""

    params: ALSSpec
    adapts = frozenset({"R", "Q"})

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        lags, window = self.params.lags, self.params.window
        self.M = np.zeros((4, 3, 3))
        self.R_basis = r_basis()
        self.past_nu = np.zeros((lags, 2))  # the last `lags` innovations, oldest first
        self.past_D = np.zeros((lags * 4, 3, 2))  # and their cross terms
        self.n_past = 0
        self.rows = np.empty((rows_per_innovation(2, lags), 5))  # one innovation's [A | b]
        # the window's factors (`window_push`; np.empty: pages are touched only as it fills)
        self.fac = np.empty((window, 5, 5))
        self.suf = np.empty((window, 5, 5))
        self.back = np.zeros((5, 5))
        self.head = self.count = self.n_front = 0
        self.steps = 0  # predicts since the sensitivities were last brought up to date
        self.pending: tuple | None = None  # the innovation before its update
        self.scans = 0
        self.theta = np.full(4, np.nan)  # the last identification (qv, qg, rr, rb)

    def _catch_up(self) -> None:
        """The sensitivities through the predicts since they were last brought up to date, at
        once: the interval's transition F_scan and unit noises A_v, A_g (AdaptiveEKF)."""
        if not self.steps:
            return
        Q_basis = np.zeros((4, 3, 3))
        Q_basis[0], Q_basis[1] = self.A_v, self.A_g
        self.M = predict_sensitivities(self.M, self.past_D, self.n_past, self.F_scan, Q_basis)
        self.reset_interval()
        self.steps = 0

    def _finish_pending(self, K: np.ndarray | None) -> None:
        """Propagate the sensitivities through the pending innovation's update (K None:
        rejected, no update)."""
        if self.pending is None:
            return
        nu, H = self.pending
        self.pending = None
        gain = np.zeros((3, 2)) if K is None else K
        self.M, C = update_sensitivities(self.M, self.past_D, self.n_past, H, gain, self.R_basis)
        self.n_past = push_past(self.past_nu, self.past_D, self.n_past, nu, C)

    def predict(self, u=0, dt: float | None = None):
        super().predict(u, dt)
        self.steps += 1

    def before_gain(self, inn: Innovation) -> None:
        self._finish_pending(None)  # the previous landmark of this scan, if the gate refused it
        if not self.feeds_adaptation(inn):
            return
        self._catch_up()
        S = inn.HPHt + self.R
        n = innovation_rows(
            inn.nu, inn.H, self.M, self.R_basis, self.past_nu, self.past_D, self.n_past, S,
            self.rows,
        )  # fmt: skip
        self.head, self.count, self.n_front = window_push(
            self.fac, self.suf, self.back, self.head, self.count, self.n_front,
            triangularise(self.rows[:n]),
        )  # fmt: skip
        self.pending = (inn.nu.copy(), inn.H.copy())

    def after_update(self, inn: Innovation) -> None:
        self._finish_pending(self.K.copy())

    def end_scan(self) -> None:
        self._finish_pending(None)
        self.scans += 1
        if not self.params.adaptation or self.scans % self.params.every:
            return
        if self.count < min(self.params.warmup, self.params.window):
            return
        T = window_factor(self.fac, self.suf, self.back, self.head, self.count, self.n_front)
        self.theta = nnls_triangular(T[:4, :4], T[:4, 4])
        if not np.all(np.isfinite(self.theta)):
            raise FilterDiverged("the ALS rows are not finite")
        if "Q" in self.params.adapt:
            self.set_Qu_diag(self.theta[:2])
        if "R" in self.params.adapt:
            self.set_R_diag(self.theta[2:])
