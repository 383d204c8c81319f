"""The ANFEKF (SPEC 4): the EKF plus an ANFIS supervisor adapting R, Qu, or both."""

from __future__ import annotations

import math
from collections import deque
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from ..schema import FiniteFloat, NonNegativeFloat, PositiveFloat
from . import anfis
from .adaptive import AdaptiveEKF
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext


def mismatch(S: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Normalised mismatch d = (S - C) / (S + C) in (-1, 1) (SPEC 4; the paper's DOM, eq. 31)."""
    return (S - C) / (S + C)


def _clip(o: float, limit: float) -> tuple[float, bool]:
    """o clipped to +-limit, and whether it was inside (the clipped output has no slope)."""
    return (o, True) if -limit <= o <= limit else (math.copysign(limit, o), False)


def _scaled(g: anfis.ANFISParams, k: float) -> anfis.ANFISParams:
    return anfis.ANFISParams(m=g.m * k, delta=g.delta * k, w=g.w * k)


def r_step(
    params: anfis.ANFISParams, u: tuple[float, float], R_ii: float, HPH_ii: float, C_ii: float,
    clip: float,
) -> tuple[float, float, anfis.ANFISParams | None]:  # fmt: skip
    """One diagonal element of R: eq. (33) with DeltaR = R (e^o - 1), and the loss gradient.

    Returns R'_ii = R_ii exp(o), E = e^2 / 2 with e = mismatch(S', C) and S' = H P H^T + R'
    (eqs. 39-40 on the normalised scale), and dE/dW = e de/dS' dS'/do do/dW (eq. 42), where
    de/dS' = 2 C / (S' + C)^2 and dS'/do = R'; None when o was clipped.
    """
    o_raw, do_dW = anfis.output_and_gradient(params, u)
    o, inside = _clip(o_raw, clip)
    R_new = R_ii * math.exp(o)
    S_new = HPH_ii + R_new
    e = (S_new - C_ii) / (S_new + C_ii)
    dE_do = e * 2.0 * C_ii / (S_new + C_ii) ** 2 * R_new
    return R_new, 0.5 * e * e, _scaled(do_dW, dE_do) if inside else None


def q_step(
    params: anfis.ANFISParams, u: tuple[float, float], S: np.ndarray, C: np.ndarray,
    dS: np.ndarray, clip: float,
) -> tuple[float, float, anfis.ANFISParams | None]:  # fmt: skip
    """The scale of Qu: eq. (44) with DeltaQ = e^o, and the loss gradient.

    The first-order model S'(o) = S + (e^o - 1) dS, dS the diagonal of H Q_int H^T (SPEC 4);
    E = (e_1^2 + e_2^2) / 2 with e = mismatch(S', C). Returns (e^o, E, dE/dW or None if clipped).
    """
    o_raw, do_dW = anfis.output_and_gradient(params, u)
    o, inside = _clip(o_raw, clip)
    scale = math.exp(o)
    S_new = S + (scale - 1.0) * dS
    e = (S_new - C) / (S_new + C)
    dE_do = float(np.sum(e * 2.0 * C / (S_new + C) ** 2 * scale * dS))
    return scale, 0.5 * float(e @ e), _scaled(do_dW, dE_do) if inside else None


class ANFEKFSpec(AdaptiveSpec):
    """The adaptive neuro-fuzzy EKF (SPEC section 4). Defaults are shared by every scenario."""

    kind: Literal["anfekf"]
    fast_family: ClassVar[str | None] = "anfekf"  # engines/families/anfekf.py
    robot_only_because: ClassVar[str] = (
        "its two ANFIS watch the range and bearing channels, the paper's design"
    )
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    adapt: Literal["R", "Q", "RQ"] = Field(
        "R", description="R: two ANFIS on R (paper 5.1); Q: one on Qu (5.2); RQ: both at once"
    )
    window: int = Field(20, ge=2, le=10_000, description="innovations in the matching window, N")
    learning_rate: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] = Field(
        (0.01, 0.01, 0.05), description="steepest-descent rates for (centres, widths, singletons)"
    )
    singleton_scale: PositiveFloat = Field(0.1, description="a: S1..S7 = a * (-3..3)")
    centres_d: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat] = (
        -1.0, -0.5, 0.0, 0.5, 1.0,
    )  # fmt: skip
    centres_dd: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat] = (
        -0.2, -0.1, 0.0, 0.1, 0.2,
    )  # fmt: skip
    width_d: PositiveFloat = 0.35
    width_dd: PositiveFloat = 0.1
    output_clip: PositiveFloat = Field(1.0, description="|o| limit: one step scales by <= e^clip")
    learning: bool = Field(True, description="false: freeze the ANFIS parameters")

    def build(self, ctx: FilterContext) -> ANFEKF:
        return ANFEKF(**ctx.kwargs(), params=self)


class CovarianceMatchingEKF(AdaptiveEKF):
    """Covariance matching over a window of innovations (SPEC 4, eqs. 30-32): the ANFEKF before
    its ANFIS, shared with its non-fuzzy ablation (`cm-scale`).

    At each landmark that feeds adaptation, before the gain: the squared innovation joins the
    window of the last N (gated or not), C = (1/N) sum nu nu^T (eq. 30, diagonal), the theoretical
    S = H P- H^T + R (eq. 24), the normalised mismatch d_ii = (S_ii - C_ii) / (S_ii + C_ii) and
    its change Delta d; once the window is full, the rule: `_adapt_R` at every landmark (R
    events), then `_adapt_Q` at the first landmark of a scan (Q events, SPEC 7: there P- holds
    exactly the interval's process noise), with S recomputed after an R step. `params` needs
    `adapt` ("R", "Q" or "RQ") and `window` (N) besides the common adaptive rules.
    """

    def __init__(self, *args, params: AdaptiveSpec, **kwargs):
        self.adapts = frozenset(params.adapt)
        super().__init__(*args, params=params, **kwargs)
        self.spec = params
        # Squared innovations (the diagonal of nu nu^T: only it is matched) of the last N.
        self.window: deque[np.ndarray] = deque(maxlen=params.window)
        self.d_prev: np.ndarray | None = None
        self._first_of_scan = True

    def begin_scan(self) -> None:
        self._first_of_scan = True

    def before_gain(self, inn: Innovation) -> None:
        if self.feeds_adaptation(inn):
            self.supervise(inn.nu, inn.H, inn.HPHt)
        self._first_of_scan = False

    def supervise(self, nu: np.ndarray, H: np.ndarray, HPHt: np.ndarray) -> None:
        """Covariance matching and the adaptation of one landmark (SPEC 4)."""
        self.window.append(nu * nu)
        if len(self.window) < self.window.maxlen or not self.spec.adaptation:
            return
        C = np.mean(self.window, axis=0)
        HPH = np.diag(HPHt)
        S = HPH + np.diag(self.R)
        d = mismatch(S, C)
        dd = np.zeros(2) if self.d_prev is None else d - self.d_prev
        self.d_prev = d
        if "R" in self.adapts:
            self._adapt_R(d, dd, HPH, C)
            S = HPH + np.diag(self.R)
        if "Q" in self.adapts and self._first_of_scan:
            self._adapt_Q(d, H, HPH, S, C)

    def _adapt_R(self, d: np.ndarray, dd: np.ndarray, HPH: np.ndarray, C: np.ndarray) -> None:
        """R from the mismatch d (and its change dd) of both channels."""
        raise NotImplementedError

    def _adapt_Q(
        self, d: np.ndarray, H: np.ndarray, HPH: np.ndarray, S: np.ndarray, C: np.ndarray
    ) -> None:
        """Qu from the mismatch d; S is the theoretical S after any R step of this landmark."""
        raise NotImplementedError


class ANFEKF(CovarianceMatchingEKF):
    """EKF plus ANFIS supervisors: R (two ANFIS, Sec. 5.1), Qu (one, Sec. 5.2), or both.

    At each landmark, before the gain (SPEC 4): covariance matching over the last N innovations,
    C = (1/N) sum nu nu^T (eq. 30), theoretical S = H P- H^T + R (eq. 24), normalised mismatch
    d_ii = (S_ii - C_ii) / (S_ii + C_ii) and its change (`CovarianceMatchingEKF`); ANFIS output
    o; then R_ii <- R_ii exp(o_i) (eq. 33) at every landmark (R events) and Qu <- Qu exp(o)
    (eq. 44) at the first landmark of a scan (Q events, SPEC 7: there P- holds exactly the
    interval's process noise); then one steepest-descent step on E = e^2 / 2, e the mismatch left
    after the adaptation (eqs. 39-42). With adapt RQ the R step runs first and the Q step matches
    the S it leaves.
    """

    params: ANFEKFSpec

    def __init__(self, *args, params: ANFEKFSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        spec = params
        self.eta = tuple(spec.learning_rate)
        r_init = anfis.init_params(
            centres0=spec.centres_d, width0=spec.width_d, centres1=spec.centres_dd,
            width1=spec.width_dd, singleton_scale=spec.singleton_scale,
        )  # fmt: skip
        # The Q-ANFIS's inputs d_11 and d_22 are two mismatches of the same scale.
        q_init = anfis.init_params(
            centres0=spec.centres_d, width0=spec.width_d, centres1=spec.centres_d,
            width1=spec.width_d, singleton_scale=spec.singleton_scale,
        )  # fmt: skip
        # anfis_params: the R-ANFIS of range and bearing (adapt R), or the Q-ANFIS (adapt Q),
        # or all three (adapt RQ: range, bearing, Q).
        self.anfis_params = {"R": [r_init, r_init], "Q": [q_init], "RQ": [r_init, r_init, q_init]}[
            spec.adapt
        ]
        # Process noise G Qu G^T added since the last landmark update: what P- grew by, the
        # first-order dS/dQ model of SPEC 4.
        self.Q_interval = np.zeros((3, 3))
        self._updated_since_predict = False

    def predict(self, u=0, dt: float | None = None):
        super().predict(u, dt)
        if "Q" not in self.adapts:  # only the Q supervisor needs the interval's process noise
            return
        if self._updated_since_predict:
            self.Q_interval = np.zeros((3, 3))
            self._updated_since_predict = False
        self.Q_interval += self.Q

    def supervise(self, nu: np.ndarray, H: np.ndarray, HPHt: np.ndarray) -> None:
        self._updated_since_predict = True
        super().supervise(nu, H, HPHt)

    def _learn(self, i: int, grad: anfis.ANFISParams | None) -> None:
        if self.spec.learning and grad is not None:
            self.anfis_params[i] = anfis.sgd_step(self.anfis_params[i], grad, self.eta)

    def _adapt_R(self, d: np.ndarray, dd: np.ndarray, HPH: np.ndarray, C: np.ndarray) -> None:
        """Two ANFIS, one per diagonal element of R (paper 5.1)."""
        R_diag = np.diag(self.R).copy()
        for i in range(2):
            R_diag[i], _, grad = r_step(
                self.anfis_params[i], (d[i], dd[i]), R_diag[i], HPH[i], C[i],
                self.spec.output_clip,
            )  # fmt: skip
            self._learn(i, grad)
        self.set_R_diag(R_diag)

    def _adapt_Q(
        self, d: np.ndarray, H: np.ndarray, HPH: np.ndarray, S: np.ndarray, C: np.ndarray
    ) -> None:
        """One ANFIS scaling Qu (paper 5.2)."""
        # P- may have shrunk below the interval's process noise (a filter adapting from accepted
        # innovations only skips some first landmarks); capping the model at H P- H^T keeps
        # S' > 0 and bounds |dE/do| by sum |e_i| / 2 (uncapped, single huge steps once flipped
        # the singletons' signs).
        dS = np.minimum(np.einsum("ij,jk,ik->i", H, self.Q_interval, H), HPH)
        i = len(self.anfis_params) - 1
        scale, _, grad = q_step(self.anfis_params[i], (d[0], d[1]), S, C, dS, self.spec.output_clip)
        self._learn(i, grad)
        before = np.diag(self.Qu).copy()
        self.set_Qu_diag(before * scale)
        # What the bounds let through scales the interval's model too.
        self.Q_interval = self.Q_interval * (self.Qu[0, 0] / before[0])
