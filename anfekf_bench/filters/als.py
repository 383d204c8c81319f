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
squares (scipy.optimize.nnls) every `every` scans (end of scan, a Q event); then
Qu = diag(qv, qg), R = diag(rr, rb), within the common bounds. Which innovations feed it:
`adapt_from` (all, with K = 0 for a rejected one; or only those the gate accepted).

The rule is written once as plain functions on arrays (`predict_sensitivities`,
`update_sensitivities`, `innovation_rows`, `solve_variances`), tested on a linear model where
the answer is known; `ALSEKF` calls them from the EKF's hooks.
"""

from __future__ import annotations

from collections import deque
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy.optimize import nnls

from .adaptive import AdaptiveEKF
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext

# ---------------------------------------------------------------------------------------------
# The rule, as plain functions (any state and measurement dimension)


def predict_sensitivities(
    M: np.ndarray, D: list[np.ndarray], F: np.ndarray, Q_basis: np.ndarray
) -> np.ndarray:
    """One prediction: M_i <- F M_i F^T + Q_basis_i (Q_basis (p, n, n): the state-space noise
    of a unit value of unknown i; zero for the measurement unknowns); every stored cross term
    D_l (p, n, m) <- F D_l in place. Returns the new M (p, n, n)."""
    for j, d in enumerate(D):
        D[j] = np.einsum("ab,pbc->pac", F, d)
    return np.einsum("ab,pbc,dc->pad", F, M, F) + Q_basis


def update_sensitivities(
    M: np.ndarray,
    D: list[np.ndarray],
    H: np.ndarray,
    K: np.ndarray,
    R_basis: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """One measurement (gain K, zero for a rejected one): the innovation's cross term
    C_i = A M_i H^T - K R_basis_i (A = I - K H), every stored D_l <- A D_l in place, and
    M_i <- A M_i A^T + K R_basis_i K^T. Returns (new M, C)."""
    A = np.eye(M.shape[1]) - K @ H
    C = np.einsum("ab,pbc,dc->pad", A, M, H) - np.einsum("ab,pbc->pac", K, R_basis)
    for j, d in enumerate(D):
        D[j] = np.einsum("ab,pbc->pac", A, d)
    M_new = np.einsum("ab,pbc,dc->pad", A, M, A) + np.einsum("ab,pbc,dc->pad", K, R_basis, K)
    return M_new, C


def innovation_rows(
    nu: np.ndarray,
    H: np.ndarray,
    M: np.ndarray,
    R_basis: np.ndarray,
    past: list[tuple[np.ndarray, np.ndarray]],
    S: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The rows of one innovation nu (before its update): lag 0 (the upper triangle of nu nu^T)
    and, for each (nu_l, D_l) in `past` (D_l propagated to now), the entries of nu nu_l^T.
    Returns (A (rows, p), b (rows,)), every row divided by sqrt(S_aa S_bb)."""
    m = len(nu)
    lag0 = np.einsum("ab,pbc,dc->pad", H, M, H) + R_basis  # (p, m, m)
    scale = np.sqrt(np.outer(np.diag(S), np.diag(S)))
    iu = np.triu_indices(m)
    A_rows = [lag0[:, iu[0], iu[1]].T / scale[iu][:, None]]
    b_rows = [np.outer(nu, nu)[iu] / scale[iu]]
    for nu_l, D_l in past:
        cross = np.einsum("ab,pbc->pac", H, D_l)  # (p, m, m)
        A_rows.append(cross.reshape(len(cross), -1).T / scale.reshape(-1, 1))
        b_rows.append(np.outer(nu, nu_l).ravel() / scale.ravel())
    return np.vstack(A_rows), np.concatenate(b_rows)


def solve_variances(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The non-negative theta minimising ||A theta - b|| (scipy.optimize.nnls)."""
    return nnls(A, b)[0]


# ---------------------------------------------------------------------------------------------
# The filter


class ALSSpec(AdaptiveSpec):
    """Online LTV autocovariance least squares on Qu and R (module doc)."""

    kind: Literal["als"]
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


_E_V = np.array([[1.0, 0.0], [0.0, 0.0]])
_E_G = np.array([[0.0, 0.0], [0.0, 1.0]])


class ALSEKF(AdaptiveEKF):
    """EKF plus online ALS (module doc)."""

    params: ALSSpec
    adapts = frozenset({"R", "Q"})

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        p = 4
        self.M = np.zeros((p, 3, 3))
        self.R_basis = np.zeros((p, 2, 2))
        self.R_basis[2, 0, 0] = 1.0
        self.R_basis[3, 1, 1] = 1.0
        self.past: deque = deque(maxlen=self.params.lags)  # (nu_l, D_l) of recent innovations
        self.rows: deque = deque(maxlen=self.params.window)  # (A, b) per innovation
        self.pending: tuple | None = None  # the innovation before its update
        self.scans = 0
        self.theta = np.full(4, np.nan)  # the last identification (qv, qg, rr, rb)

    def _finish_pending(self, K: np.ndarray | None) -> None:
        """Propagate the sensitivities through the pending innovation's update (K None:
        rejected, no update)."""
        if self.pending is None:
            return
        nu, H = self.pending
        self.pending = None
        gain = np.zeros((3, 2)) if K is None else K
        D = [d for _, d in self.past]
        self.M, C = update_sensitivities(self.M, D, H, gain, self.R_basis)
        self.past = deque(
            ((n, d) for (n, _), d in zip(self.past, D, strict=True)), maxlen=self.params.lags
        )
        if self.params.lags:
            self.past.append((nu, C))

    def predict(self, u=0, dt: float | None = None):
        self._finish_pending(None)
        super().predict(u, dt)
        Q_basis = np.zeros((4, 3, 3))
        Q_basis[0] = self.model.Q(self.G, _E_V, self.dt)
        Q_basis[1] = self.model.Q(self.G, _E_G, self.dt)
        D = [d for _, d in self.past]
        self.M = predict_sensitivities(self.M, D, self.F, Q_basis)
        self.past = deque(
            ((n, d) for (n, _), d in zip(self.past, D, strict=True)), maxlen=self.params.lags
        )

    def before_gain(self, inn: Innovation) -> None:
        self._finish_pending(None)  # the previous landmark of this scan, if the gate refused it
        if not self.feeds_adaptation(inn):
            return
        S = inn.HPHt + self.R
        self.rows.append(innovation_rows(inn.nu, inn.H, self.M, self.R_basis, list(self.past), S))
        self.pending = (inn.nu.copy(), inn.H.copy())

    def after_update(self, inn: Innovation) -> None:
        self._finish_pending(self.K.copy())

    def end_scan(self) -> None:
        self._finish_pending(None)
        self.scans += 1
        if not self.params.adaptation or self.scans % self.params.every:
            return
        if len(self.rows) < min(self.params.warmup, self.params.window):
            return
        A = np.vstack([a for a, _ in self.rows])
        b = np.concatenate([b for _, b in self.rows])
        self.theta = solve_variances(A, b)
        if "Q" in self.params.adapt:
            self.set_Qu_diag(self.theta[:2])
        if "R" in self.params.adapt:
            self.set_R_diag(self.theta[2:])
