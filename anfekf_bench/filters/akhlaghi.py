"""Akhlaghi, Zhou, Huang (2017): residual-based R and innovation-based Q with forgetting alpha.

S. Akhlaghi, N. Zhou, Z. Huang, "Adaptive Adjustment of Noise Covariance in Kalman Filter for
Dynamic State Estimation", IEEE PES General Meeting 2017, arXiv:1702.00884, Section III-B, Fig. 1:

    eps_k = z_k - h(x+_k)                                                  (residual, eq. 8)
    R_k   = alpha R_(k-1) + (1 - alpha) (eps_k eps_k^T + H_k P+_k H_k^T)   (eq. 11)
    Q_k   = alpha Q_(k-1) + (1 - alpha) K_k d_k d_k^T K_k^T                (eq. 15, d = innovation)

Adapted to this benchmark (SPEC 7, research notes 3.2; choices in docs/DESIGN.md, "Akhlaghi"):
R events are landmark updates, R is diagonal and is used from the NEXT update on (R_k needs the
posterior of update k); Q events are scans with a landmark, K d is the scan's total correction,
and the state-space estimate is mapped to Qu through the interval's G-terms; alpha forgets once
per scan. Landmarks the gate rejected feed both rules (by default) through the update they would
have made.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from ..models import h, residual_z, wrap_scalar
from .adaptive import AdaptiveEKF, outer
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext


def residual_variance(e, hph):
    """One channel of eq. (11)'s bracket: e^2 + (H P+ H^T)_ii (floats or arrays)."""
    return e * e + hph


def residual_sample(eps: np.ndarray, H: np.ndarray, P_post: np.ndarray) -> np.ndarray:
    """The bracket of eq. (11), diagonal only: diag(eps eps^T + H P+ H^T).

    For a linear h and the right R its expectation is R exactly (E[eps eps^T] = R S^-1 R,
    H P+ H^T = R - R S^-1 R), and it is a sum of PSD terms, so R stays positive.
    """
    return residual_variance(eps, np.einsum("ij,jk,ik->i", H, P_post, H))


def forget(previous: np.ndarray, sample: np.ndarray, alpha: float) -> np.ndarray:
    """The exponential forgetting of eqs. (11) and (15): alpha * previous + (1 - alpha) * sample."""
    return alpha * previous + (1.0 - alpha) * sample


def state_noise_estimate(Q_prev: np.ndarray, dx: np.ndarray, alpha: float) -> np.ndarray:
    """Eq. (15) with K d = dx, the correction: alpha Q_(k-1) + (1 - alpha) dx dx^T."""
    return forget(Q_prev, outer(dx, dx), alpha)


def kalman_posterior(
    x: np.ndarray, P: np.ndarray, H: np.ndarray, R: np.ndarray, nu: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x+, P+, K) of one Kalman update in Joseph form, heading wrapped, P+ symmetric.

    The same update as `RobotEKF.correct` (filterpy's); here for the update a gate-rejected
    landmark would have made, which the filter never applies.
    """
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T  # P H^T S^-1 (S and P symmetric)
    x_post = x + K @ nu
    x_post[2] = wrap_scalar(x_post[2])
    I_KH = np.eye(len(x)) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ K.T
    return x_post, 0.5 * (P_post + P_post.T), K


class AkhlaghiSpec(AdaptiveSpec):
    """Akhlaghi et al. 2017: residual-based R, innovation-based Q, one forgetting factor."""

    kind: Literal["akhlaghi"]
    fast_family: ClassVar[str | None] = "akhlaghi"  # engines/families/akhlaghi.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    adapt: Literal["R", "Q", "RQ"] = Field(
        "RQ",
        description="R: residual-based R (eq. 11); Q: innovation-based Qu (eq. 15); RQ: both,"
        " as in the paper",
    )
    alpha: float = Field(
        0.3,
        ge=0.0,
        lt=1.0,
        allow_inf_nan=False,
        description="forgetting factor, applied once per scan: the paper's 0.3 (memory about"
        " 1 / (1 - alpha) = 1.4 scans); 0.97 is the slow setting (about 33 scans)",
    )

    def build(self, ctx: FilterContext) -> AkhlaghiEKF:
        return AkhlaghiEKF(**ctx.kwargs(), params=self)


class AkhlaghiEKF(AdaptiveEKF):
    """EKF plus the residual-based R and innovation-based Q of Akhlaghi et al. (2017).

    R (eq. 11), at every landmark update j of scan k, after the update:
        eps_j = wrap(z_j - h(x+_j)),  s_j = diag(eps_j eps_j^T + H_j P+_j H_j^T)
        R = alpha R_(k-1) + (1 - alpha) mean(s_1..s_j)        (used from update j + 1 on)
    with R_(k-1) the R at the start of the scan, so alpha forgets once per scan and a scan's
    landmarks weigh equally (one landmark: exactly eq. 11).

    Q (eq. 15), at the end of every scan with a landmark:
        dx_k = sum_j K_j nu_j  (= x+ - x- over the scan: K d of the stacked update)
        Q_hat = alpha Q_scan + (1 - alpha) dx_k dx_k^T,   Qu <- least squares of Q_hat on
    the interval's G-terms (`set_Qu_from_state_noise`), where Q_scan is the process noise the
    current Qu put into the interval: Q_(k-1) expressed on this interval.

    A landmark the gate rejected feeds both (unless `adapt_from: accepted`) through the update
    it would have made with the R in force: its residual, P+ and gain from `kalman_posterior`.
    """

    params: AkhlaghiSpec

    def __init__(self, *args, params: AkhlaghiSpec, **kwargs):
        self.adapts = frozenset(params.adapt)
        super().__init__(*args, params=params, **kwargs)
        self.alpha = params.alpha
        self._begin_samples()

    def _begin_samples(self) -> None:
        self.R_scan_start = np.diag(self.R).copy()  # R_(k-1) of eq. 11
        self.R_sample_sum = np.zeros(2)
        self.R_samples = 0
        self.dx_scan = np.zeros(3)  # the scan's correction K d (eq. 15)
        self.dx_fed = False
        self._pending: Innovation | None = None  # the last landmark, until its gate decision

    # -- hooks -----------------------------------------------------------------------------

    def begin_scan(self) -> None:
        self._begin_samples()

    def before_gain(self, inn: Innovation) -> None:
        self._settle_rejected()
        if self.params.adaptation:
            self._pending = inn

    def after_update(self, inn: Innovation) -> None:
        self._pending = None
        if not self.params.adaptation:
            return
        eps = residual_z(np.asarray(inn.z, dtype=float), h(self.x, inn.landmark))
        self.feed(residual_sample(eps, inn.H, self.P), self.K @ self.y)

    def end_scan(self) -> None:
        self._settle_rejected()
        if self.params.adaptation and "Q" in self.adapts and self.dx_fed:
            self.adapt_Q(self.dx_scan)
            self.reset_interval()

    # -- the two rules -----------------------------------------------------------------------

    def _settle_rejected(self) -> None:
        """A rejected landmark feeds the rules through the update it would have made.

        Nothing changed x, P or R since its gate decision: this runs first thing at the next
        landmark or at the end of the scan.
        """
        inn, self._pending = self._pending, None
        if inn is None or inn.accepted or not self.feeds_adaptation(inn):
            return
        x_post, P_post, K = kalman_posterior(self.x, self.P, inn.H, inn.R, inn.nu)
        eps = residual_z(np.asarray(inn.z, dtype=float), h(x_post, inn.landmark))
        self.feed(residual_sample(eps, inn.H, P_post), K @ inn.nu)

    def feed(self, R_sample: np.ndarray, dx: np.ndarray) -> None:
        """One landmark's samples: R at once (eq. 11), the correction kept for end_scan."""
        if "R" in self.adapts:
            self.R_sample_sum += R_sample
            self.R_samples += 1
            mean = self.R_sample_sum / self.R_samples
            self.set_R_diag(forget(self.R_scan_start, mean, self.alpha))
        self.dx_scan = self.dx_scan + dx
        self.dx_fed = True

    def adapt_Q(self, dx: np.ndarray) -> None:
        """Eq. (15) on the interval since the last Q event, mapped to Qu (research notes 0.4a)."""
        self.set_Qu_from_state_noise(state_noise_estimate(self.Q_scan, dx, self.alpha))
