"""The default filter (SPEC 19): an interacting bank over Qu hypotheses whose members adapt R
online (VB-IMM; docs/default-filter.md), for a user who does not know whether R, Qu or
both are wrong, or whether they change.

Why this composition (the zoo's own findings, docs/results/zoo.md): the R adapters (vb-r,
sage-husa, ...) fail where Qu is wrong, because covariance matching on lag-0 innovations cannot
tell Qu from R and pushes the error into R; the banks over fixed (Qu, R) grids fail where the truth
lies off their R grid. Here the bank covers Qu, where the likelihood separates hypotheses by the
innovations' time structure, and each member adapts R continuously, so no R grid has to contain
the truth. One EKF per Qu factor q_i (times the assumed Qu); member i keeps its own R posterior.

At every landmark each member computes its innovation nu_i and the predictive covariance with the
R it held BEFORE this measurement, S_i = H_i P_i- H_i^T + R_i-, and

    log w_i <- log w_i + log N(nu_i; 0, S_i)                                          (D.1)

(the one-step predictive likelihood: the R a member adapts to this very innovation would score it
against itself); then the member adapts R by its rule and updates as its single-filter version
does. Once per scan the weights are normalised and floored, the output is the moment-matched
mixture, and (IMM, p_stay < 1) the members restart from their mixed starts (bank.py's B.2-B.4).
The R posteriors are not mixed: each stays with its Qu hypothesis.

Member R rules (`r_rule`), the designs compared in the research note:
- "vb": Sarkka & Nummenmaa's VB-AKF on diag R (vb.VBREKF): VB-IMM / VB-MMAE;
- "sage-husa": fading-memory Sage-Husa on diag R (sage_husa.SageHusaEKF);
- "grid": no adaptation in a member; R hypotheses as a grid (range_factors x bearing_factors)
  crossed with the Qu factors: the plain IMM with a pruned mixture, the zoo's `imm`.
With p_stay = 1 the bank is static (MMAE). The rules are the zoo's own functions; the fast
engine's kernel is engines/kernels_bank.py.
"""

from __future__ import annotations

import itertools
import math
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from .bank import (
    Factors,
    MemberBank,
    innovation_loglik,
)
from .ekf import Innovation, RobotEKF
from .sage_husa import SageHusaEKF, SageHusaSpec
from .spec import AdaptiveSpec, FilterContext
from .vb import RHO, VBREKF, VBRSpec

# Half-decade steps over four decades: the zoo's Qu mismatches (0.01x..100x in variance) inside.
WIDE_HALF_DECADE = tuple(10.0 ** (k / 2.0) for k in range(-4, 5))
R_RULES = ("vb", "sage-husa", "grid")
R_RULE_CODE = {rule: i for i, rule in enumerate(R_RULES)}  # the kernel's int argument
LOG_2PI = math.log(2.0 * math.pi)


def predictive_loglik(nis, S00, S01, S10, S11, censor_at, dof):
    """The log predictive density of a 2-vector innovation from its NIS nu^T S^-1 nu (D.1):
    Gaussian, log N(nu; 0, S) (bank.innovation_loglik), for dof = inf; else the Student-t with
    `dof` degrees of freedom and scale S, which for two dimensions is

        log t = -log(2 pi) - 1/2 log det S - (dof + 2) / 2 log(1 + nis / dof)

    (Gamma((dof + 2) / 2) / Gamma(dof / 2) = dof / 2): an outlier costs every member about the log
    of its NIS instead of the NIS itself, so one outlier cannot hand the weight to the widest
    hypotheses. NIS above `censor_at` counts as `censor_at`; det S <= 0 gives -inf."""
    if dof == math.inf:
        return innovation_loglik(nis, S00, S01, S10, S11, censor_at)
    det = S00 * S11 - S01 * S10
    if not det > 0.0:
        return -math.inf
    if nis > censor_at:
        nis = censor_at
    return -0.5 * math.log(det) - 0.5 * (dof + 2.0) * math.log1p(nis / dof) - LOG_2PI


class VBIMMSpec(AdaptiveSpec):
    """The default filter: an IMM over Qu factors whose members adapt R (VB by default); no
    per-scenario settings, no training runs."""

    kind: Literal["vb-imm"]
    fast_kernel: ClassVar[str | None] = "kernels_bank"
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    default_filter: ClassVar[bool] = True
    qu_factors: Factors = Field(
        WIDE_HALF_DECADE,
        description="factors on the assumed Qu variances, one member each (default half-decade"
        " steps 0.01x..100x)",
    )
    r_rule: Literal["vb", "sage-husa", "grid"] = Field(
        "vb",
        description="how a member adapts R: vb (Sarkka-Nummenmaa VB-AKF), sage-husa (fading"
        " memory), grid (no adaptation: range_factors x bearing_factors members per Qu factor)",
    )
    range_factors: Factors = Field(
        (1.0,), description="r_rule grid: factors on the assumed range variance (crossed)"
    )
    bearing_factors: Factors = Field(
        (1.0,), description="r_rule grid: factors on the assumed bearing variance (crossed)"
    )
    p_stay: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.9999,
        description="probability that the noise stays in its Qu hypothesis from one scan to the"
        " next (1: a static bank, MMAE)",
    )
    rho: float = Field(
        0.9, gt=0, le=1, allow_inf_nan=False,
        description="r_rule vb: forgetting factor of each member's (alpha, beta), once per scan"
        f" (memory about 10 scans; vb-r's default is {RHO:.4g})",
    )  # fmt: skip
    iterations: int = Field(
        3, ge=1, le=100, description="r_rule vb: VB fixed-point iterations per landmark"
    )
    alpha0: float = Field(
        1.0, gt=0, allow_inf_nan=False, description="r_rule vb: initial inverse-gamma shape"
    )
    b: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = Field(
        0.97, description="r_rule sage-husa: fading factor b (memory about 1 / (1 - b) scans)"
    )
    likelihood_dof: Annotated[float, Field(gt=0)] = Field(
        4.0,
        description="degrees of freedom of the members' predictive likelihood: inf (Gaussian) or"
        " a Student-t (robust: an outlier does not move the weights to the widest hypotheses)",
    )
    weight_floor: Annotated[float, Field(gt=0, lt=1e-2, allow_inf_nan=False)] = Field(
        1e-30, description="floor of every member's weight, once per scan"
    )
    mixture_threshold: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = Field(
        1e-4, description="members below this weight stay in the bank but out of the mixture"
    )

    def n_models(self) -> int:
        n_r = len(self.range_factors) * len(self.bearing_factors) if self.r_rule == "grid" else 1
        return len(self.qu_factors) * n_r

    @model_validator(mode="after")
    def _grid_within_bounds(self) -> VBIMMSpec:
        if self.n_models() > 500:
            raise ValueError(f"the bank has {self.n_models()} members; at most 500")
        lo, hi = self.bounds
        for name, values in (
            ("qu_factors", self.qu_factors),
            ("range_factors", self.range_factors),
            ("bearing_factors", self.bearing_factors),
        ):
            if not all(lo <= v <= hi for v in values):
                raise ValueError(f"{name}: every factor must lie within bounds {lo}..{hi}")
        return self

    def build(self, ctx: FilterContext) -> VBIMMEKF:
        return VBIMMEKF(**ctx.kwargs(), params=self)


def member_factors(spec: VBIMMSpec) -> np.ndarray:
    """One row (qu, range, bearing) of factors on the assumed variances per member, in member
    order: every Qu factor, crossed (grid rule) with the R factors; one R (1, 1) otherwise."""
    if not spec.adaptation:
        return np.ones((1, 3))
    if spec.r_rule == "grid":
        rows = itertools.product(spec.qu_factors, spec.range_factors, spec.bearing_factors)
        return np.array(list(rows), dtype=float)
    return np.array([(q, 1.0, 1.0) for q in spec.qu_factors], dtype=float)


# ---------------------------------------------------------------------------------------------
# The members (filterpy engine): each records the R it held before its adaptation (D.1).


class _FixedMember(RobotEKF):
    def before_gain(self, inn: Innovation) -> None:
        self.R_prior = self.R
        self.inn = inn


class _VBMember(VBREKF):
    def before_gain(self, inn: Innovation) -> None:
        self.R_prior = self.R_estimate() if self.params.adaptation else self.R
        super().before_gain(inn)
        self.inn = inn


class _SHMember(SageHusaEKF):
    def before_gain(self, inn: Innovation) -> None:
        self.R_prior = self.R
        super().before_gain(inn)
        self.inn = inn


def _member(spec: VBIMMSpec, x0, P0, Qu, R, model, dt, gate) -> RobotEKF:
    common = dict(bounds=spec.bounds, adapt_from=spec.adapt_from)
    if spec.r_rule == "vb" and spec.adaptation:
        params = VBRSpec(
            name="member", kind="vb-r", rho=spec.rho, iterations=spec.iterations,
            alpha0=spec.alpha0, **common,
        )  # fmt: skip
        return _VBMember(x0, P0, Qu, R, model, dt, gate, params=params)
    if spec.r_rule == "sage-husa" and spec.adaptation:
        params = SageHusaSpec(name="member", kind="sage-husa", b=spec.b, **common)
        return _SHMember(x0, P0, Qu, R, model, dt, gate, params=params)
    return _FixedMember(x0, P0, Qu, R, model, dt, gate)


class VBIMMEKF(MemberBank):
    """A bank of members (module doc): x, P the mixture, R and Qu the mixture weights' average
    of the members' current R and Qu; counts are the most probable member's, as in BankEKF (the
    bank's cycle is bank.MemberBank's); a member's innovation scores by the predictive
    likelihood from the R it held before the landmark (D.1)."""

    params: VBIMMSpec

    def __init__(self, *args, params: VBIMMSpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        factors = member_factors(params)
        qu0, r0 = np.diag(self.Qu0), np.diag(self.R0)
        Qu_members = np.outer(factors[:, 0], qu0)
        members = [
            _member(params, self.x, self.P, np.diag(qu), np.diag(f[1:] * r0), self.model,
                    self.dt, self.gate)
            for qu, f in zip(Qu_members, factors, strict=True)
        ]  # fmt: skip
        p_stay = params.p_stay if params.adaptation else 1.0
        self._start_bank(members, Qu_members, p_stay, p_stay < 1.0 and len(members) > 1)

    def member_R(self) -> np.ndarray:
        return np.array([np.diag(m.R) for m in self.members])

    def member_loglik(self, m: RobotEKF) -> float:
        S = m.inn.HPHt + m.R_prior
        nis = float(m.inn.nu @ np.linalg.solve(S, m.inn.nu))
        return predictive_loglik(
            nis, S[0, 0], S[0, 1], S[1, 0], S[1, 1], self.censor_at, self.params.likelihood_dof
        )
