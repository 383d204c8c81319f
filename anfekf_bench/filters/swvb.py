"""Sliding-window variational Bayes adapting Qu and R: `swvb` (SPEC 13; after Huang, Zhu, Jia,
Zhang, IEEE TCAS-II 67(12):3552-3556, 2020), a documented simplification.

The paper smooths a window of L steps (a fixed-interval RTS smoother) inside each VB iteration and
updates inverse-Wishart posteriors of Q and R from the smoothed states. Here the window is ONE
interval between Q events (L = 1 scan: a lag-one smoother), Q is the control noise Qu (two
variances, not a 3x3 state-space Q), and each variance has an inverse-gamma posterior (a, b),
point estimate b / a, as `vb-r`. Per scan that saw a landmark, after the forgetting
a <- rho a, b <- rho b (once per scan), iterate n = 1..N from the scan's prior x-:

    P-(n) = F_s P_s F_s^T + qv A_v + qg A_g                    (the interval's prediction with
                                                                 Qu(n-1); n = 1: the filter's P-)
    x+, P+ = the scan's sequential EKF updates from (x-, P-(n)) with R(n-1)               (S.1)
    lag-one smoother over the interval:  J = P_s F_s^T P-(n)^-1,
        m = (I - F_s J) dx,  dx = x+ - x- (heading wrapped)
        E[w w^T] = m m^T + P+ - P+ J^T F_s^T - F_s J P+ + F_s P_s|k F_s^T,
        P_s|k = P_s + J (P+ - P-(n)) J^T  (computed with L = I - F_s J)            (S.2)
    q = qu_least_squares(E[w w^T], A_v, A_g, P-(n)^-1) clipped to the bounds (notes 0.4a)
    Qu(n) = (b_q + q / 2) / (a_q + 1/2)                                                   (S.3)
    R(n)  = (b_r + 1/2 sum_l [e_l^2 + diag(H_l P+ H_l^T)]) / (a_r + n_l / 2),
        e_l = z_l - h(x+) (bearing wrapped), H_l at x+, over the scan's landmarks        (S.4)

then keep the last iteration's x+, P+ and (a, b) with their updates, and R(N), Qu(N) for the next
interval. F_s, P_s, A_v, A_g are the interval's transition, the previous scan's posterior and the
process-noise accumulators of `AdaptiveEKF`. Decisions in docs/DESIGN.md ("swvb").
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from ..models import h, residual_z, wrap_scalar
from ..models.range_bearing import H_jacobian
from ..schema import PositiveFloat
from .adaptive import AdaptiveEKF, clip_to_bounds, matmul, outer, qu_least_squares
from .spec import AdaptiveSpec, FilterContext

RHO = 1.0 - math.exp(-4.0)  # as vb-r and vbakf


def interval_prior(FPF, A_v, A_g, qv, qg):
    """P- of the interval for Qu = diag(qv, qg): F_s P_s F_s^T + qv A_v + qg A_g, with
    FPF = F_s P_s F_s^T (the same over a scan's iterations)."""
    return FPF + qv * A_v + qg * A_g


def process_noise_moment(dx, FPF, P_prior_inv, P_post):
    """E[w w^T] of the interval's process noise w = x_k - F_s x_s under the lag-one smoother
    (S.2), in terms of L = I - F_s J = I - FPF P-^-1 (FPF = F_s P_s F_s^T, the same over a
    scan's passes): m = L dx, and with F_s J P- = FPF,

        E[w w^T] = m m^T + P+ - P+ J^T F_s^T - F_s J P+ + F_s P_s|k F_s^T
                 = m m^T + (L P+ + FPF) L^T,

    three 3 x 3 products where J's form takes nine (equal to round-off). Symmetric to round-off
    and not symmetrised: `qu_least_squares` reads only its symmetric part (tr(W A W X^T) =
    tr(W A W X) for symmetric W and A). dx = x+ - x- with its heading wrapped,
    P_prior_inv = P-^-1 (the caller's: it also weighs the least squares). (`matmul` and
    `outer` are numpy's, compiled as plain loops on the fast engine.)"""
    L = np.eye(3) - matmul(FPF, P_prior_inv)
    m = matmul(L, dx)
    return outer(m, m) + matmul(matmul(L, P_post) + FPF, L.T)


def r_moment(zs, landmarks, x, P):
    """sum over the scan's landmarks of e^2 + diag(H P H^T) at the posterior (S.4)."""
    s = np.zeros(2)
    for z, lm in zip(zs, landmarks, strict=True):
        e = residual_z(np.asarray(z, float), h(x, lm))
        H = H_jacobian(x, lm)
        s = s + e * e + np.einsum("ij,jk,ik->i", H, P, H)
    return s


class SWVBSpec(AdaptiveSpec):
    """Sliding-window VB on Qu and R (Huang et al. 2020), window of one scan interval (a
    simplification: see the module doc)."""

    kind: Literal["swvb"]
    fast_kernel: ClassVar[str | None] = "kernels_swvb"
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    rho: float = Field(
        RHO, gt=0, le=1, allow_inf_nan=False,
        description="forgetting factor of every (a, b), applied once per scan; memory about"
        " 1/(1 - rho) scans",
    )  # fmt: skip
    iterations: int = Field(5, ge=1, le=100, description="VB fixed-point iterations per scan")
    a0: PositiveFloat = Field(
        1.0,
        description="initial inverse-gamma shape of each variance (confidence in the starting"
        " Qu and R); b0 = a0 x start so that b0 / a0 is the starting value",
    )

    def build(self, ctx: FilterContext) -> SWVBEKF:
        return SWVBEKF(**ctx.kwargs(), params=self)


class SWVBEKF(AdaptiveEKF):
    """The EKF with a one-interval sliding-window VB estimate of diag(Qu) and diag(R)."""

    adapts: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    params: SWVBSpec

    def __init__(self, *args, params: SWVBSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        a0 = params.a0
        self.a_q, self.b_q = np.full(2, a0), a0 * np.diag(self.Qu0)
        self.a_r, self.b_r = np.full(2, a0), a0 * np.diag(self.R0)

    def update_scan(self, zs: np.ndarray, landmarks: np.ndarray) -> None:
        if not self.params.adaptation:
            super().update_scan(zs, landmarks)
            return
        rho = self.params.rho
        a_q, b_q, a_r, b_r = rho * self.a_q, rho * self.b_q, rho * self.a_r, rho * self.b_r
        x_m, P_m1 = self.x.copy(), self.P.copy()
        counts = (self.nis_sum, self.n_updates, self.n_rejected)
        qu, r = np.diag(self.Qu).copy(), np.diag(self.R).copy()
        qu0, r0 = np.diag(self.Qu0), np.diag(self.R0)
        FPF = matmul(matmul(self.F_scan, self.P_scan_start), self.F_scan.T)
        for n in range(self.params.iterations):
            P_m = P_m1 if n == 0 else interval_prior(FPF, self.A_v, self.A_g, qu[0], qu[1])
            self.x, self.P, self.R = x_m.copy(), P_m, np.diag(r)
            self.nis_sum, self.n_updates, self.n_rejected = counts
            fed = []
            for z, lm in zip(zs, landmarks, strict=True):
                inn = self.innovation(z, lm)
                if self.feeds_adaptation(inn):
                    fed.append((z, lm))
                self.update_landmark(z, lm)
            dx = self.x - x_m
            dx[2] = wrap_scalar(dx[2])
            P_m_inv = np.linalg.inv(P_m)
            W = process_noise_moment(dx, FPF, P_m_inv, self.P)
            q = clip_to_bounds(qu_least_squares(W, self.A_v, self.A_g, P_m_inv), qu0, self.bounds)
            b_q_n = b_q + 0.5 * q
            qu = clip_to_bounds(b_q_n / (a_q + 0.5), qu0, self.bounds)
            a_r_n, b_r_n = a_r, b_r
            if fed:
                f_z, f_lm = zip(*fed, strict=True)
                a_r_n = a_r + 0.5 * len(fed)
                b_r_n = b_r + 0.5 * r_moment(f_z, f_lm, self.x, self.P)
            r = clip_to_bounds(b_r_n / a_r_n, r0, self.bounds)
        self.a_q, self.b_q, self.a_r, self.b_r = a_q + 0.5, b_q_n, a_r_n, b_r_n
        self.set_Qu_diag(qu)
        self.set_R_diag(r)
        self.reset_interval()
