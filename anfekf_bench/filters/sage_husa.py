"""Fading-memory Sage-Husa adaptive EKF (SPEC 7; research notes, section 1).

Sage and Husa (1969) estimate the noise statistics by averaging the samples the filter produces;
the fading-memory form of the INS literature (Gao, You, Katayama 2012; PSINS `CKalman::RAdaptive`)
weights them with

    d_k = (1 - b) / (1 - b^(k+1)),   i.e. beta_0 = 1, beta_(k+1) = beta_k / (beta_k + b),   (1.1)

where k counts adaptation events; d_k -> 1 - b, a memory of about 1 / (1 - b) events.

R (per channel c in range, bearing; before the gain, the PSINS order; noise mean taken as 0):

    rho_c = clip(nu_c^2 - (H P- H^T)_cc, R_min,c, R_max,c)                              (1.2)
    R_c   = (1 - d_k) R_c + d_k rho_c                                                    (1.2)

Q (option, once per scan that saw a landmark): the scan's total correction Delta x = x+ - x-
gives a sample of the interval's state-space process noise

    Q_hat = Delta x Delta x^T + P+ - F_scan P+_prev F_scan^T     ("unbiased", eq. 1.1)
    Q_hat = Delta x Delta x^T                                     ("biased", PD-safe)

mapped to the control noise Qu by least squares through the interval's G-terms (notes 0.4a),
clamped to the bounds and averaged like R: Qu = (1 - d_k) Qu + d_k q_hat.

The once-per-scan rule (SPEC 7) and the pooling of a scan's landmarks are explained in
docs/DESIGN.md ("Sage-Husa").
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field

from ..models import wrap_scalar
from .adaptive import AdaptiveEKF, clip_to_bounds, matmul, outer
from .augmented import Augmentable
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext


def next_beta(beta: float, b: float) -> float:
    """beta_(k+1) = beta_k / (beta_k + b): the PSINS recursion for d_k of eq. (1.1)."""
    return beta / (beta + b)


def fading_weight(k: int, b: float) -> float:
    """d_k = (1 - b) / (1 - b^(k+1)), the closed form of `next_beta` from beta_0 = 1."""
    return (1.0 - b) / (1.0 - b ** (k + 1))


def fading_mean(d, old, total, n):
    """(1 - d) old + d total / n: the estimate after an event of weight d whose n samples sum to
    `total` (eq. 1.2; n pools a scan's landmarks). Floats or arrays, elementwise."""
    return (1.0 - d) * old + d * total / n


def r_sample(nu, hph, R_min, R_max):
    """rho_c = nu_c^2 - (H P- H^T)_cc per channel, clamped to [R_min, R_max] (PSINS's fix of the
    positivity problem: the unclamped sample is negative whenever nu_c^2 < (H P- H^T)_cc); hph
    is diag(H P- H^T). Floats or arrays, elementwise (np.clip's result)."""
    return np.minimum(np.maximum(nu * nu - hph, R_min), R_max)


def q_sample(
    dx: np.ndarray, P_post: np.ndarray, P_prev: np.ndarray, F_scan: np.ndarray, unbiased: bool
) -> np.ndarray:
    """The state-space process-noise sample of one scan (eq. 1.1's Q term, over the interval).

    dx is the scan's total correction x+ - x- (heading wrapped); P_post = P+ after the scan's
    last update, P_prev = P+ at the previous Q event, F_scan the interval's transition. Its
    expectation is the interval's Q_scan: E[dx dx^T] = P- - P+ and P- = F_scan P_prev F_scan^T +
    Q_scan. The biased form drops P+ - F P_prev F^T (usually negative semidefinite) and stays PSD.
    """
    Q_hat = outer(dx, dx)
    if unbiased:
        Q_hat = Q_hat + P_post - matmul(matmul(F_scan, P_prev), F_scan.T)
    return 0.5 * (Q_hat + Q_hat.T)


class SageHusaSpec(AdaptiveSpec, Augmentable):
    """Fading-memory Sage-Husa (Sage & Husa 1969): R per channel before the gain, Qu optional."""

    kind: Literal["sage-husa"]
    fast_family: ClassVar[str | None] = "sage_husa"  # engines/families/sage_husa.py
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "tracking", "module"})
    problem_form: ClassVar[str | None] = "filters:SageHusaSpec"  # problems/filters.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    b: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = Field(
        0.97,
        description="fading factor b: d_k = (1 - b) / (1 - b^(k+1)) -> 1 - b, a memory of"
        " about 1 / (1 - b) scans (usual: 0.95-0.99)",
    )
    adapt: Literal["R", "RQ"] = Field(
        "R",
        description="R: measurement noise only (the recommended default); RQ: also Qu, once per"
        " scan, from the scan's total correction",
    )
    warmup: int = Field(
        0,
        ge=0,
        le=100_000,
        description="adaptation events (scans) during which the estimates are built but the"
        " starting R, Qu stay in force (0: Sage-Husa as published, the first scan's samples"
        " replace R0 since d_0 = 1)",
    )
    q_sample: Literal["unbiased", "biased"] = Field(
        "unbiased",
        description="Q sample: dx dx^T + P+ - F P+_prev F^T (Sage-Husa's, can be indefinite) or"
        " dx dx^T alone (PSD, biased); only with adapt RQ",
    )

    def build(self, ctx: FilterContext) -> SageHusaEKF:
        if self.augment is not None:
            return self.build_augmented(SageHusaEKF, ctx)
        return SageHusaEKF(**ctx.kwargs(), params=self)


class SageHusaEKF(AdaptiveEKF):
    """EKF plus fading-memory Sage-Husa estimation of diag(R) and, optionally, diag(Qu).

    Events (SPEC 7): R changes at every landmark that feeds adaptation, before its gain; Qu at
    the end of a scan that saw a landmark. The fading weight d_k advances once per scan that
    fed adaptation, and the landmarks of one scan share it: the R used for the m-th landmark is

        R = (1 - d_k) R_(k-1) + d_k mean(rho_1 .. rho_m)

    so by the end of the scan its samples count as one pooled sample, old estimates fade once
    per scan however many landmarks it saw, and each gain already uses the scan's samples so far.
    """

    params: SageHusaSpec

    def __init__(self, *args, params: SageHusaSpec, **kwargs):
        self.adapts = frozenset(params.adapt)
        super().__init__(*args, params=params, **kwargs)
        r0 = np.diag(self.R0)
        self.R_min, self.R_max = self.bounds[0] * r0, self.bounds[1] * r0
        self.beta = 1.0  # d_k of the next adaptation event (eq. 1.1, beta_0 = 1)
        self.n_events = 0
        # The Sage-Husa estimates; in force (self.R, self.Qu) once the warm-up is over.
        self.R_hat = r0.copy()
        self.Qu_hat = np.diag(self.Qu0).copy()
        self._begin(self.x)

    def _begin(self, x_prior: np.ndarray) -> None:
        self.d = self.beta
        self.R_start = self.R_hat.copy()  # R_(k-1): the estimate the scan fades
        self.x_prior_scan = np.array(x_prior, dtype=float)  # x- of the scan (Delta x)
        self.rho_sum = np.zeros(2)
        self.n_fed = 0
        self.n_accepted = 0

    @property
    def warm(self) -> bool:
        """Whether the estimates are in force (the warm-up's events are over)."""
        return self.n_events >= self.params.warmup

    def begin_scan(self) -> None:
        self._begin(self.x)

    def before_gain(self, inn: Innovation) -> None:
        if not self.params.adaptation or not self.feeds_adaptation(inn):
            return
        self.rho_sum += r_sample(inn.nu, np.diag(inn.HPHt), self.R_min, self.R_max)
        self.n_fed += 1
        # A convex combination of in-bound values: in bounds, positive.
        self.R_hat = fading_mean(self.d, self.R_start, self.rho_sum, self.n_fed)
        if self.warm:
            self.set_R_diag(self.R_hat)

    def after_update(self, inn: Innovation) -> None:
        self.n_accepted += 1

    def end_scan(self) -> None:
        if "Q" in self.adapts:
            if self.params.adaptation and self.n_fed and self.n_accepted:
                self._adapt_Qu()
            # The next interval starts at this scan's posterior, updated or not.
            self.reset_interval()
        if self.n_fed:
            self.beta = next_beta(self.beta, self.params.b)
            self.n_events += 1

    def _adapt_Qu(self) -> None:
        """Qu = (1 - d_k) Qu + d_k q_hat, q_hat the least-squares Qu of the scan's sample."""
        dx = self.x - self.x_prior_scan
        dx[2] = wrap_scalar(dx[2])
        Q_hat = q_sample(
            dx, self.P, self.P_scan_start, self.F_scan, self.params.q_sample == "unbiased"
        )
        # PSINS's clamp, on the sample: the least squares of an indefinite Q_hat can be < 0.
        q_hat = clip_to_bounds(self.qu_estimate(Q_hat), np.diag(self.Qu0), self.bounds)
        self.Qu_hat = fading_mean(self.d, self.Qu_hat, q_hat, 1)
        if self.warm:
            self.set_Qu_diag(self.Qu_hat)
