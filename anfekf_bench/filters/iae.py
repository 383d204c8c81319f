"""`iae`: Mohamed & Schwarz (1999) innovation-based adaptive estimation (SPEC 7; research notes 2).

A window of the last N associated innovations (R events, gated or not, pooled over landmarks
because R is a sensor property) estimates the innovation covariance

    C = (1/N) sum_j nu_j nu_j^T                                        (M&S: C_nu, the window)

and, once the window is full (warm-up: the nominal R0, Qu0 before), either

    adapt R:  R_hat = diag(C - mean_j H_j P-_j H_j^T)   (hph: window, default)
                   or diag(C - H P- H^T)                (hph: current, the paper's literal form)
              every landmark, before its gain;
    adapt Q:  Q_hat = sum_j K_j C K_j^T + P+_k - F P+_(k-1) F^T   (q_form: full, default)
                   or sum_j K_j C K_j^T                           (q_form: steady, the usual
                                                                   steady-state K C K^T)
              once per scan that saw a landmark (end_scan), j the scan's fused landmarks (one:
              K C K^T), F the transition since the previous Q event; each scan's Q_hat maps to a
              sample q_k of diag(Qu) through that interval's A_v, A_g (research notes 0.4 a),
              and Qu = the mean of the last N_Q samples (q_window; 1: each scan's own),
              clamped to the bounds.

With a consistent filter E[K_j nu_j nu_j^T K_j^T] = P-_j - P+_j, so the full form's expectation
is P-_k - F P+_(k-1) F^T = Q_scan, the interval's process noise, whatever the dynamics; the
steady-state form drops F P F^T - P, which is not small here (heading uncertainty grows into
position over a scan), and underestimates Q (docs/DESIGN.md). One scan's Q_hat is a small
difference of large matrices, hence the window of samples (averaged unclamped, so unbiased).

R_hat is a difference of PSD matrices and can be <= 0: each channel is clamped to the floor of
the common bounds (the positivity fix), or with `nonpositive: hold` keeps its previous value;
docs/DESIGN.md says why, and what each costs.
"""

from __future__ import annotations

from collections import deque
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from .adaptive import AdaptiveEKF, matmul
from .ekf import Innovation
from .spec import AdaptiveSpec, FilterContext


def window_covariance(nus: np.ndarray) -> np.ndarray:
    """C = (1/N) sum nu_j nu_j^T over the window, nus (N, 2) (Mohamed & Schwarz; no mean
    removed)."""
    return matmul(nus.T, nus) / len(nus)


def window_mean(a: np.ndarray) -> np.ndarray:
    """The mean over the first axis (a window of H P- H^T, or of Qu samples), as np.mean sums."""
    return np.sum(a, axis=0) / len(a)


def r_estimate(c, hph):
    """The diagonal of R_hat = C - H P- H^T from c = diag(C) and hph = diag(H P- H^T) (not yet
    clamped: may be <= 0). Floats or arrays, elementwise."""
    return c - hph


def hold_nonpositive(R_hat: np.ndarray, R_diag: np.ndarray) -> np.ndarray:
    """`nonpositive: hold`: a channel whose R_hat <= 0 keeps its previous value."""
    return np.where(R_hat > 0.0, R_hat, R_diag)


def q_estimate(Ks, C: np.ndarray, dP: np.ndarray | None = None) -> np.ndarray:
    """Q_hat = sum_j K_j C K_j^T (+ dP = P+_k - F P+_(k-1) F^T for M&S's full form); Ks a
    sequence of 3 x 2 gains (a list, or an (n, 3, 2) array)."""
    Q_hat = np.zeros((3, 3))
    for i in range(len(Ks)):  # indexed: numba's iteration would give arrays of any layout
        Q_hat = Q_hat + matmul(matmul(Ks[i], C), Ks[i].T)
    if dP is not None:
        Q_hat = Q_hat + dP
    return 0.5 * (Q_hat + Q_hat.T)


class IAESpec(AdaptiveSpec):
    """Innovation-based adaptive estimation (Mohamed & Schwarz 1999): R or Q from a window."""

    kind: Literal["iae"]
    fast_family: ClassVar[str | None] = "iae"  # engines/families/iae.py
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    adapt: Literal["R", "Q"] = Field(
        "R", description="R: R_hat = C - H P- H^T (diagonal); Q: Q_hat from K C K^T, mapped to Qu"
    )
    window: int = Field(
        20, ge=2, le=10_000, description="associated innovations (R events) in the window, N"
    )
    hph: Literal["window", "current"] = Field(
        "window",
        description="adapt R: subtract the window's mean H_j P-_j H_j^T (each innovation's own"
        " geometry), or the current landmark's H P- H^T (the paper's literal form)",
    )
    nonpositive: Literal["floor", "hold"] = Field(
        "floor",
        description="adapt R, a channel whose R_hat <= 0: the floor of the bounds (clamp), or"
        " hold its previous value",
    )
    q_form: Literal["full", "steady"] = Field(
        "full",
        description="adapt Q: sum K C K^T + P+_k - F P+_(k-1) F^T (M&S's full form, unbiased"
        " for a consistent filter), or sum K C K^T alone (the steady-state approximation)",
    )
    q_window: int = Field(
        20,
        ge=1,
        le=10_000,
        description="adapt Q: Qu is the mean of the last N_Q scans' samples (Q events), N_Q",
    )

    def build(self, ctx: FilterContext) -> IAEEKF:
        return IAEEKF(**ctx.kwargs(), params=self)


class IAEEKF(AdaptiveEKF):
    """EKF with Mohamed-Schwarz IAE of R (every landmark) or Qu (every scan with landmarks)."""

    params: IAESpec

    def __init__(self, *args, params: IAESpec, **kwargs):
        self.adapts = frozenset(params.adapt)
        super().__init__(*args, params=params, **kwargs)
        self.spec = params
        # The last N innovations and their H P- H^T, as the filter saw them before each gain.
        self.nus: deque[np.ndarray] = deque(maxlen=params.window)
        self.hphs: deque[np.ndarray] = deque(maxlen=params.window)
        self.Ks: list[np.ndarray] = []  # gains of the scan's fused landmarks (adapt Q)
        self.q_samples: deque[np.ndarray] = deque(maxlen=params.q_window)  # unclamped diag(Qu)

    @property
    def window_full(self) -> bool:
        return len(self.nus) == self.nus.maxlen

    def begin_scan(self) -> None:
        self.Ks = []

    def before_gain(self, inn: Innovation) -> None:
        if not self.feeds_adaptation(inn):
            return
        self.nus.append(inn.nu.copy())
        self.hphs.append(inn.HPHt.copy())
        if "R" in self.adapts and self.window_full and self.spec.adaptation:
            self.adapt_R(inn)

    def after_update(self, inn: Innovation) -> None:
        # Only fused landmarks moved P from the prediction to P+_k: their gains make Q_hat.
        if "Q" in self.adapts:
            self.Ks.append(self.K.copy())

    def adapt_R(self, inn: Innovation) -> None:
        """R_hat = diag(C - H P- H^T), clamped to the bounds (floor: the positivity fix)."""
        C = window_covariance(np.array(self.nus))
        HPHt = window_mean(np.array(self.hphs)) if self.spec.hph == "window" else inn.HPHt
        R_hat = r_estimate(np.diag(C), np.diag(HPHt))
        if self.spec.nonpositive == "hold":
            R_hat = hold_nonpositive(R_hat, np.diag(self.R))
        self.set_R_diag(R_hat)

    def end_scan(self) -> None:
        """Q event: Qu from Q_hat through the interval's process noise."""
        if "Q" in self.adapts and self.spec.adaptation and self.window_full and self.Ks:
            C = window_covariance(np.array(self.nus))
            dP = None
            if self.spec.q_form == "full":
                dP = self.P - matmul(matmul(self.F_scan, self.P_scan_start), self.F_scan.T)
            Q_hat = q_estimate(self.Ks, C, dP)
            self.q_samples.append(self.qu_estimate(Q_hat))
            if len(self.q_samples) == self.q_samples.maxlen:
                self.set_Qu_diag(window_mean(np.array(self.q_samples)))
        # The next Q event's A_v, A_g cover only its own interval.
        self.reset_interval()
