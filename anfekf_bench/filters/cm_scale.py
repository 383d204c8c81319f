"""`cm-scale`: the ANFEKF without the ANFIS, the one-line covariance-matching rule (SPEC 7;
research notes 6.1). The ablation that asks what the neuro-fuzzy part adds.

The same window (the last N innovations, gated or not), the same normalised mismatch
d_ii = (S_ii - C_ii) / (S_ii + C_ii) and the same events as the ANFEKF (`CovarianceMatchingEKF`);
in place of the ANFIS a proportional rule on the log of the variance, o = -kappa d, clipped to
+-output_clip like the ANFEKF's output:

    R_ii <- R_ii exp(-kappa d_ii)            every landmark (R events)
    Qu   <- Qu exp(-kappa mean(d))           first landmark of a scan (Q events)

d > 0 means the predicted S exceeds the observed spread C, so the variance shrinks; d = 0 (S = C)
is the fixed point. Near it d ~ ln(S / C) / 2, so kappa = 1 moves ln R half-way to the matching
value per event when R dominates S (kappa = 2 would be dead-beat and pass the window's sampling
noise straight on): the default, set once for every scenario (docs/DESIGN.md).
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from ..schema import PositiveFloat
from .anfekf import CovarianceMatchingEKF
from .spec import AdaptiveSpec, FilterContext


def proportional_step(d, kappa, clip):
    """The proportional rule's output for one mismatch: o = clip(-kappa d, -clip, clip), the
    step in ln variance (NaN propagates). Plain float arithmetic: the fast engine compiles this
    very function (engines/kernels.py)."""
    o = -kappa * d
    if o != o:
        return o
    if o < -clip:
        o = -clip
    if o > clip:
        o = clip
    return o


def log_scale(d: np.ndarray | float, kappa: float, clip: float) -> np.ndarray:
    """`proportional_step` elementwise."""
    d = np.asarray(d, dtype=float)
    o = [proportional_step(float(v), kappa, clip) for v in d.ravel()]
    return np.array(o, dtype=float).reshape(d.shape)


def mean_mismatch(d0, d1):
    """The Q rule's input: mean(d) of the two channels, as np.mean sums two values."""
    return (d0 + d1) / 2.0


class CMScaleSpec(AdaptiveSpec):
    """Covariance-matching scaling: the ANFEKF's window and mismatch with a proportional rule."""

    kind: Literal["cm-scale"]
    fast_family: ClassVar[str | None] = "anfekf"  # engines/families/anfekf.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    adapt: Literal["R", "Q", "RQ"] = Field(
        "R", description="R: scale each R_ii; Q: scale Qu by the mean mismatch; RQ: both at once"
    )
    window: int = Field(20, ge=2, le=10_000, description="innovations in the matching window, N")
    kappa: PositiveFloat = Field(
        1.0,
        description="gain of the rule: ln variance moves by -kappa d per event (near the match"
        " d ~ ln(S/C)/2, so 1 goes half-way to S = C when R dominates S)",
    )
    output_clip: PositiveFloat = Field(
        1.0, description="|o| limit: one step scales by <= e^clip (as the ANFEKF's)"
    )

    def build(self, ctx: FilterContext) -> CMScaleEKF:
        return CMScaleEKF(**ctx.kwargs(), params=self)


class CMScaleEKF(CovarianceMatchingEKF):
    """EKF plus the proportional covariance-matching rule (module docstring)."""

    params: CMScaleSpec

    def __init__(self, *args, params: CMScaleSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)

    def _adapt_R(self, d: np.ndarray, dd: np.ndarray, HPH: np.ndarray, C: np.ndarray) -> None:
        """R_ii <- R_ii exp(o_i), o_i = -kappa d_ii clipped (the ANFEKF's eq. 33 form)."""
        # np.exp as on main (its last bit can differ from math.exp, which the kernel uses)
        o = log_scale(d, self.spec.kappa, self.spec.output_clip)
        self.set_R_diag(np.diag(self.R) * np.exp(o))

    def _adapt_Q(
        self, d: np.ndarray, H: np.ndarray, HPH: np.ndarray, S: np.ndarray, C: np.ndarray
    ) -> None:
        """Qu <- Qu exp(o), o = -kappa mean(d) clipped (the ANFEKF's eq. 44 form)."""
        o = proportional_step(
            mean_mismatch(float(d[0]), float(d[1])), self.spec.kappa, self.spec.output_clip
        )
        self.set_Qu_diag(np.diag(self.Qu) * math.exp(o))
