"""Variational-Bayes noise-adaptive EKFs: `vb-r` (Sarkka & Nummenmaa 2009) and `vbakf` (Huang et
al. 2018).

Both iterate a fixed point between the Gaussian posterior of the state and a conjugate posterior
of the noise (inverse-gamma per channel of R; inverse-Wishart on P- and R), every iteration an
EKF update from the SAME prior x-, P- (H at x-, as the plain EKF) with the current noise estimate.

Where the iteration runs: in `before_gain`, so that (a) innovations the gate rejects still feed
the noise posterior (SPEC 7, `adapt_from: all`), and (b) the gate and NIS see the R (and P-) of
the last iteration, the ones the gain uses. The last iteration's state update is the filter's own
update (filterpy's Joseph form, `RobotEKF.correct`) with that R and P-, so x, P are the posterior
of the last iteration. Research notes, sections 4 and 5; docs/DESIGN.md, "VB filters".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy import linalg

from ..models import h, residual_z
from ..schema import PositiveFloat
from .adaptive import AdaptiveEKF, clip_to_bounds
from .augmented import Augmentable
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext

RHO = 1.0 - math.exp(-4.0)  # the forgetting factor of Huang et al. (2018)'s simulations

Residual = Callable[[np.ndarray], np.ndarray]
"""e(x) = z - h(x) with the bearing wrapped: the measurement residual at a state iterate."""


# -- the shared pieces ------------------------------------------------------------------------


def kalman_update(
    x: np.ndarray, P: np.ndarray, nu: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """x+ = x- + K nu, P+ = (I - K H) P- (I - K H)^T + K R K^T, K = P- H^T S^-1, S = H P- H^T + R.

    The same arithmetic as filterpy's `ExtendedKalmanFilter.update` (Joseph form), so the last
    VB iterate and the filter's own update agree to round-off.
    """
    PHt = P @ H.T
    S = H @ PHt + R
    # check_finite off: a non-finite S gives NaNs that the gate's NIS reports as divergence,
    # as the plain EKF's, instead of scipy's ValueError
    K = PHt @ linalg.inv(S, check_finite=False)
    I_KH = np.eye(len(x)) - K @ H
    return x + K @ nu, I_KH @ P @ I_KH.T + K @ R @ K.T


def clip_covariance(
    R: np.ndarray, start_diag: np.ndarray, bounds: tuple[float, float]
) -> np.ndarray:
    """R with its variances clipped to the bounds (SPEC 7) and its correlations kept
    (`clip_covariance_2`); R itself (the same object) when no variance is outside the bounds."""
    changed, Rc = clip_covariance_2(
        (R[0, 0], R[0, 1], R[1, 0], R[1, 1]), start_diag[0], start_diag[1], bounds[0], bounds[1]
    )
    return np.array(Rc).reshape(2, 2) if changed else R


def clip_covariance_2(R, start0, start1, floor, ceiling):
    """A 2 x 2 R (row-major 4-tuple) with its variances clipped to [floor, ceiling] times their
    starting values (SPEC 7) and its correlations kept: R' = D R D with
    D = diag(sqrt(clipped / raw)), so that R' stays positive definite. Returns (whether a
    variance was clipped, R')."""
    c0 = clip_to_bounds(R[0], start0, (floor, ceiling))
    c1 = clip_to_bounds(R[3], start1, (floor, ceiling))
    if c0 == R[0] and c1 == R[3]:
        return False, R
    s0 = np.sqrt(c0 / R[0])  # np: NaN (not an error) for a negative variance
    s1 = np.sqrt(c1 / R[3])
    return True, (R[0] * (s0 * s0), R[1] * (s0 * s1), R[2] * (s1 * s0), R[3] * (s1 * s1))


def vbakf_prior(P_i, dxdx, P, tau):
    """Huang et al.'s P^- = T / (t - n - 1) = (A + tau P~-) / (tau + 1), A = P^(i) + dx dx^T
    (elementwise: arrays or one element)."""
    return (P_i + dxdx + tau * P) / (tau + 1.0)


def inflation_cap(trace_prior, trace_predicted, max_inflation):
    """The factor that caps tr(P^-) / tr(P~-) at max_inflation (research notes 5.3): 1 when
    it is within the cap."""
    inflation = trace_prior / trace_predicted
    if inflation > max_inflation:
        return max_inflation / inflation
    return 1.0


def landmark_residual(z: np.ndarray, landmark: np.ndarray) -> Residual:
    """e(x) = wrap(z - h(x)): the nonlinear residual at an iterate (research notes 4.5.3, 5.5.1)."""
    return lambda x: residual_z(np.asarray(z, dtype=float), h(x, landmark))


# -- Sarkka & Nummenmaa (2009): inverse-gamma on each diagonal element of R ------------------


@dataclass(frozen=True)
class VBRPosterior:
    """The outcome of one VB-AKF measurement update.

    alpha, beta: the inverse-gamma posterior of each channel of R (alpha- + 1/2, beta^(N));
    R_gain: diag R^(N) = beta^(N-1) / alpha, the R of the last iteration's gain;
    x, P: the last iterate x^(N), P^(N) (the filter's own update recomputes them).
    """

    alpha: np.ndarray
    beta: np.ndarray
    R_gain: np.ndarray
    x: np.ndarray
    P: np.ndarray


def vb_r_beta(beta, e, hph):
    """beta^(n) = beta- + 1/2 (e^2 + (H P^(n) H^T)_ii) of one channel (or of an array of
    channels): the VB-AKF's scale update from the residual e at the iterate."""
    return beta + 0.5 * (e * e + hph)


def vb_r_bounded_beta(alpha0, alpha1, beta0, beta1, R00, R11, floor, ceiling):
    """The stored posterior kept within the bounds: (beta0, beta1) unchanged when both
    beta_i / alpha_i are within [floor R0_ii, ceiling R0_ii], else both set to
    clip(beta_i / alpha_i) alpha_i, so that beta / alpha is the R in force."""
    r0 = beta0 / alpha0
    r1 = beta1 / alpha1
    c0 = clip_to_bounds(r0, R00, (floor, ceiling))
    c1 = clip_to_bounds(r1, R11, (floor, ceiling))
    if c0 == r0 and c1 == r1:
        return beta0, beta1
    return c0 * alpha0, c1 * alpha1


def vb_r_update(
    x: np.ndarray, P: np.ndarray, nu: np.ndarray, H: np.ndarray, alpha: np.ndarray,
    beta: np.ndarray, iterations: int, residual: Residual,
    clip: Callable[[np.ndarray], np.ndarray] = lambda r: r,
) -> VBRPosterior:  # fmt: skip
    """One measurement update of the VB-AKF (Sarkka & Nummenmaa 2009, update step):

        alpha = alpha- + 1/2;  beta^(0) = beta-
        n = 1..N:  R^(n) = diag(beta^(n-1) / alpha)
                   x^(n), P^(n) = EKF update of (x-, P-) with R^(n)
                   beta^(n) = beta- + 1/2 (e^(n))^2 + 1/2 diag(H P^(n) H^T),  e^(n) = z - h(x^(n))

    `alpha`, `beta` are the predicted parameters (after the forgetting of `vb_r_predict`);
    `clip` bounds every R^(n) (SPEC 7 floors and ceilings).
    """
    alpha_post = alpha + 0.5
    beta_n = beta
    for _ in range(iterations):
        R_n = clip(beta_n / alpha_post)
        x_n, P_n = kalman_update(x, P, nu, H, np.diag(R_n))
        e = residual(x_n)
        beta_n = vb_r_beta(beta, e, np.einsum("ij,jk,ik->i", H, P_n, H))
    return VBRPosterior(alpha=alpha_post, beta=beta_n, R_gain=R_n, x=x_n, P=P_n)


def vb_r_predict(alpha: np.ndarray, beta: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """The VB-AKF prediction of the noise parameters: alpha <- rho alpha, beta <- rho beta
    (Sarkka & Nummenmaa 2009, predict step: the variances' heuristic dynamics). The point
    estimate beta / alpha is unchanged; only its confidence (alpha) fades."""
    return rho * alpha, rho * beta


class VBRSpec(AdaptiveSpec, Augmentable):
    """Sarkka & Nummenmaa (2009) variational-Bayes adaptive EKF: diagonal R, inverse-gamma per
    channel."""

    kind: Literal["vb-r"]
    fast_family: ClassVar[str | None] = "vb_r"  # engines/families/vb_r.py
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "tracking", "module"})
    problem_form: ClassVar[str | None] = "filters:VBRSpec"  # problems/filters.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R"})
    rho: float = Field(
        RHO, gt=0, le=1, allow_inf_nan=False,
        description="forgetting factor of (alpha, beta), applied once per scan; 1: stationary R;"
        " memory about 1/(1 - rho) scans",
    )  # fmt: skip
    iterations: int = Field(3, ge=1, le=100, description="VB fixed-point iterations per landmark")
    alpha0: PositiveFloat = Field(
        1.0,
        description="initial inverse-gamma shape of each channel (confidence in the starting R:"
        " worth about 2 alpha0 measurements); beta0 = alpha0 R0 so that beta0 / alpha0 = R0",
    )

    def build(self, ctx: FilterContext) -> VBREKF:
        if self.augment is not None:
            return self.build_augmented(VBREKF, ctx)
        return VBREKF(**ctx.kwargs(), params=self)


class VBREKF(AdaptiveEKF):
    """The EKF with the VB-AKF of Sarkka & Nummenmaa (2009) on diag(R).

    State of the noise posterior: (alpha_i, beta_i) per channel (range, bearing), point estimate
    R_ii = beta_i / alpha_i (the inverse of E[1 / R_ii], as the paper's Sigma). Forgetting once per
    scan that saw a landmark (`begin_scan`); at every landmark the VB iteration (`vb_r_update`)
    in `before_gain`; R in force for the gate and the gain is R^(N); between scans self.R is the
    posterior estimate beta / alpha.
    """

    adapts: ClassVar[frozenset[str]] = frozenset({"R"})
    params: VBRSpec

    def __init__(self, *args, params: VBRSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        self.alpha = np.full(2, params.alpha0)
        self.beta = params.alpha0 * np.diag(self.R0)

    def R_estimate(self) -> np.ndarray:
        """diag(beta / alpha): the posterior point estimate of R."""
        return np.diag(self.beta / self.alpha)

    def begin_scan(self) -> None:
        if self.params.adaptation:
            self.alpha, self.beta = vb_r_predict(self.alpha, self.beta, self.params.rho)

    def before_gain(self, inn: Innovation) -> None:
        if not self.params.adaptation:
            return
        # The previous landmark left the R of its last gain; the gate of `adapt_from` and the
        # starting point of this iteration is the posterior estimate.
        self.R = self.R_estimate()
        if not self.feeds_adaptation(inn):
            return
        R0 = np.diag(self.R0)
        post = vb_r_update(
            self.x, self.P, inn.nu, inn.H, self.alpha, self.beta, self.params.iterations,
            self.residual_of(inn),
            clip=lambda r: clip_to_bounds(r, R0, self.bounds),
        )  # fmt: skip
        self.alpha = post.alpha
        # Keep beta / alpha within the bounds, so the stored posterior is the one in force.
        self.beta = np.array(
            vb_r_bounded_beta(
                post.alpha[0], post.alpha[1], post.beta[0], post.beta[1], R0[0], R0[1],
                self.bounds[0], self.bounds[1],
            )
        )  # fmt: skip
        self.R = np.diag(post.R_gain)

    def residual_of(self, inn: Innovation) -> Residual:
        """The residual at a VB iterate (an augmented state's adds its range bias)."""
        return landmark_residual(inn.z, inn.landmark)

    def end_scan(self) -> None:
        if self.params.adaptation:
            self.R = self.R_estimate()


# -- Huang, Zhang, Wu, Li, Chambers (2018): inverse-Wishart on P- and on R --------------------


@dataclass(frozen=True)
class VBAKFPosterior:
    """The outcome of one measurement update of Huang et al. (2018), Algorithm 1.

    P_prior: P^-^(N), the prior covariance of the last gain (the inverse of E[P-^-1]);
    R: R^(N), the R of the last gain (the inverse of E[R^-1]);
    u, U: the inverse-Wishart posterior of R (u^(N), U^(N), carried to the next update);
    x, P: the last iterate x^(N), P^(N).
    """

    P_prior: np.ndarray
    R: np.ndarray
    u: float
    U: np.ndarray
    x: np.ndarray
    P: np.ndarray


def vbakf_update(
    x: np.ndarray, P: np.ndarray, nu: np.ndarray, H: np.ndarray, u: float, U: np.ndarray,
    tau: float, iterations: int, residual: Residual, adapt_P: bool = True,
    diagonal_R: bool = True, clip_R: Callable[[np.ndarray], np.ndarray] = lambda R: R,
    max_inflation: float = math.inf,
) -> VBAKFPosterior:  # fmt: skip
    """The measurement update of Huang et al. (2018), Algorithm 1, from the prediction (x-, P~-)
    and the predicted (u, U) of `vbakf_predict`:

        t^ = n + tau + 1, T^ = tau P~-;  x^(0) = x-, P^(0) = P~-
        i = 0..N-1:
            A = P^(i) + (x^(i) - x-)(x^(i) - x-)^T;  t = t^ + 1,  T = T^ + A
            B = e e^T + H P^(i) H^T, e = z - h(x^(i));  u' = u + 1,  U' = U + B
            P^- = (E[P-^-1])^-1 = T / (t - n - 1) = (A + tau P~-) / (tau + 1)
            R^  = (E[R^-1])^-1  = U' / (u' - m - 1)
            x^(i+1), P^(i+1) = EKF update of (x-, P^-) with R^

    adapt_P false: the R branch only (P^- = P~-, a landmark after the first of a scan: its prior
    is already a posterior). diagonal_R: keep only diag(B) (diagonal R, SPEC 7). `clip_R` bounds
    R^ (SPEC 7); `max_inflation` caps tr(P^-) / tr(P~-) (research notes 5.3). Both papers' B uses
    the linear z - H x^(i); here the nonlinear residual at the iterate.
    """
    m = len(nu)
    u_post = u + 1.0
    x_i, P_i = x, P
    P_hat = P
    tr_P = np.trace(P)
    for _ in range(iterations):
        if adapt_P:
            dx = x_i - x  # = K nu: no heading to wrap (the iterates are not wrapped)
            P_hat = vbakf_prior(P_i, np.outer(dx, dx), P, tau)
            cap = inflation_cap(np.trace(P_hat), tr_P, max_inflation)
            if cap != 1.0:
                P_hat = P_hat * cap
        e = residual(x_i)
        B = np.outer(e, e) + H @ P_i @ H.T
        U_post = U + (np.diag(np.diag(B)) if diagonal_R else 0.5 * (B + B.T))
        R_raw = U_post / (u_post - m - 1.0)
        R_hat = clip_R(R_raw)
        x_i, P_i = kalman_update(x, P_hat, nu, H, R_hat)
    if R_hat is not R_raw:  # the bounds bit: keep the posterior consistent with the R in force
        U_post = (u_post - m - 1.0) * R_hat
    return VBAKFPosterior(P_prior=P_hat, R=R_hat, u=u_post, U=U_post, x=x_i, P=P_i)


def vbakf_predict(u: float, U: np.ndarray, rho: float, m: int = 2) -> tuple[float, np.ndarray]:
    """Huang et al. (2018), Algorithm 1, time update of the R posterior:
    u <- rho (u - m - 1) + m + 1, U <- rho U (the point estimate U / (u - m - 1) is unchanged)."""
    return rho * (u - m - 1.0) + m + 1.0, rho * U


class VBAKFSpec(AdaptiveSpec):
    """Huang, Zhang, Wu, Li, Chambers (2018) VBAKF: inverse-Wishart priors on the predicted
    covariance P- and on R."""

    kind: Literal["vbakf"]
    fast_family: ClassVar[str | None] = "vbakf"  # engines/families/vbakf.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "P"})
    tau: PositiveFloat = Field(
        3.0, description="confidence in the nominal P- (T = tau P-); the paper's range 2..6"
    )
    tau_R: PositiveFloat = Field(
        3.0,
        description="confidence in the starting R: u0 = m + 1 + tau_R, U0 = tau_R R0"
        " (the authors' script), so that E[R^-1]^-1 starts at R0",
    )
    rho: float = Field(
        RHO, gt=0, le=1, allow_inf_nan=False,
        description="forgetting factor of the R posterior, applied once per scan; range 0.9..1",
    )  # fmt: skip
    iterations: int = Field(10, ge=1, le=100, description="VB iterations N per landmark (N >= 6)")
    R_structure: Literal["diagonal", "full"] = Field(
        "diagonal",
        description="diagonal: estimate diag(R) only (SPEC 7); full: the paper's full"
        " inverse-Wishart R (its off-diagonal used in the gain and gate)",
    )

    def build(self, ctx: FilterContext) -> VBAKF:
        return VBAKF(**ctx.kwargs(), params=self)


class VBAKF(AdaptiveEKF):
    """The EKF with the VBAKF of Huang et al. (2018): adapts P- (no memory: re-estimated at the
    first landmark of every scan from the nominal prediction) and R (inverse-Wishart, forgotten
    once per scan, one measurement event per landmark, m = 2).

    self.P_inflation = tr(P^- used) / tr(P~- predicted) at the first landmark of a scan (1.0 at
    the others); self.R is R^ of the last gain (= U / (u - m - 1)). Qu stays nominal: the paper
    does not learn Q across steps.
    """

    adapts: ClassVar[frozenset[str]] = frozenset({"R", "P"})
    params: VBAKFSpec
    m: ClassVar[int] = 2

    def __init__(self, *args, params: VBAKFSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        self.u = self.m + 1.0 + params.tau_R
        self.U = params.tau_R * self.R0
        self._first_of_scan = True
        self._P_predicted: np.ndarray | None = None

    def R_estimate(self) -> np.ndarray:
        """U / (u - m - 1): the inverse of E[R^-1] (Algorithm 1)."""
        return self.U / (self.u - self.m - 1.0)

    def begin_scan(self) -> None:
        self._first_of_scan = True
        if self.params.adaptation:
            self.u, self.U = vbakf_predict(self.u, self.U, self.params.rho, self.m)

    def before_gain(self, inn: Innovation) -> None:
        first, self._first_of_scan = self._first_of_scan, False
        self._P_predicted = None
        if not self.params.adaptation:
            return
        self.P_inflation = 1.0
        self.R = self.R_estimate()
        if not self.feeds_adaptation(inn):
            return
        R0 = np.diag(self.R0)
        post = vbakf_update(
            self.x, self.P, inn.nu, inn.H, self.u, self.U, self.params.tau,
            self.params.iterations, landmark_residual(inn.z, inn.landmark), adapt_P=first,
            diagonal_R=self.params.R_structure == "diagonal",
            clip_R=lambda R: clip_covariance(R, R0, self.bounds), max_inflation=self.bounds[1],
        )  # fmt: skip
        self.u, self.U = post.u, post.U
        self.R = post.R
        if first:
            self._P_predicted = self.P
            self.P_inflation = float(np.trace(post.P_prior) / np.trace(self.P))
            self.P = post.P_prior

    def update_landmark(self, z: np.ndarray, landmark: np.ndarray) -> bool:
        """A landmark the gate rejects updates nothing but the R posterior: P- adapted for its
        gain goes back to the prediction (else rejected outliers would inflate P for good)."""
        accepted = super().update_landmark(z, landmark)
        if not accepted and self._P_predicted is not None:
            self.P = self._P_predicted
            self.P_inflation = 1.0
        self._P_predicted = None
        return accepted
