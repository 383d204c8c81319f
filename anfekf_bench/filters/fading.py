"""Strong tracking / adaptive fading-factor EKF (SPEC 13, a cheap control; Zhou & Frank 1996,
Yang & Gao, J. Geodesy 80:177-183, 2006; research notes, noise-identification.md section 5).

A window of the last N associated innovations (gated or not, pooled over landmarks) gives

    C_k = (1/N) sum_j nu_j nu_j^T                                                     (F.1)
    lambda_k = min(ceiling, max(1, tr(C_k - R) / tr(H P- H^T)))                        (F.2)
    P- <- lambda_k P-                                                                  (F.3)

once per scan that saw a landmark, at its first landmark that feeds adaptation, before the gain
(H P- H^T of that landmark; the window includes its innovation). Until the window is full
lambda = 1. The filter adapts neither R nor Qu: it inflates P- when the innovations are larger
than the filter predicts (a model-mismatch control). `P_inflation` holds the scan's lambda.
Decisions in docs/DESIGN.md ("Fading-factor EKF").
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from .adaptive import AdaptiveEKF
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext


def fading_factor(trace_C, trace_R, trace_HPHt, ceiling):
    """lambda = min(ceiling, max(1, (tr C - tr R) / tr(H P- H^T))) (F.2); NaN propagates."""
    lam = (trace_C - trace_R) / trace_HPHt
    if lam != lam:
        return lam
    if lam < 1.0:
        lam = 1.0
    if lam > ceiling:
        lam = ceiling
    return lam


def fading_event(nu2, n_window, pos, first_of_scan, nu0, nu1, trace_R, trace_HPHt, ceiling):
    """One landmark that feeds adaptation, the family's one definition (both engines call it:
    `FadingEKF.before_gain` and engines/families/fading.py): nu^T nu into the window's ring
    `nu2` (in place, at `pos`); at the scan's first such landmark, once the window is full,
    lambda (F.2) from the window's mean (oldest first). Returns (n_window, pos, lambda), lambda
    NaN where P- is not to be scaled (not due, or a NaN innovation: update_landmark reports
    the divergence)."""
    N = nu2.shape[0]
    nu2[pos] = nu0 * nu0 + nu1 * nu1
    pos = (pos + 1) % N
    if n_window < N:
        n_window += 1
    if not first_of_scan or n_window < N:
        return n_window, pos, math.nan
    trace_C = 0.0
    for i in range(N):  # oldest first
        trace_C += nu2[(pos + i) % N]
    trace_C = trace_C / N
    return n_window, pos, fading_factor(trace_C, trace_R, trace_HPHt, ceiling)


class FadingSpec(AdaptiveSpec):
    """Adaptive fading factor (strong tracking): P- inflated by lambda >= 1 once per scan."""

    kind: Literal["fading"]
    fast_family: ClassVar[str | None] = "fading"  # engines/families/fading.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"P"})
    window: int = Field(
        20,
        ge=1,
        le=10_000,
        description="innovations in the window of C_k (Mohamed & Schwarz's N = 20, as iae)",
    )

    def build(self, ctx: FilterContext) -> FadingEKF:
        return FadingEKF(**ctx.kwargs(), params=self)


class FadingEKF(AdaptiveEKF):
    """The EKF with an adaptive fading factor on P- (module doc); the ceiling of lambda is the
    upper bound of `bounds`."""

    adapts: ClassVar[frozenset[str]] = frozenset({"P"})
    params: FadingSpec

    def __init__(self, *args, params: FadingSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        self.nu2 = np.zeros(params.window)  # nu^T nu of the window's innovations, a ring
        self.n_window = 0
        self.pos = 0
        self._first_of_scan = True

    def begin_scan(self) -> None:
        self._first_of_scan = True

    def before_gain(self, inn: Innovation) -> None:
        if not self.params.adaptation or not self.feeds_adaptation(inn):
            return
        self.n_window, self.pos, lam = fading_event(
            self.nu2, self.n_window, self.pos, self._first_of_scan, inn.nu[0], inn.nu[1],
            self.R[0, 0] + self.R[1, 1], inn.HPHt[0, 0] + inn.HPHt[1, 1], self.bounds[1],
        )  # fmt: skip
        self._first_of_scan = False
        if math.isfinite(lam):
            self.P_inflation = lam
            self.P = lam * self.P
