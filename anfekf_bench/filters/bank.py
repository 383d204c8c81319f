"""Multiple-model banks over noise hypotheses: static MMAE and IMM (SPEC 13; research notes,
noise-identification.md section 1; Magill 1965, Maybeck 1982, Li & Bar-Shalom 1994).

One EKF per hypothesis i = (Qu_i, R_i) on a log grid of factors on the assumed noise. At every
landmark each member computes its own innovation nu_i, S_i = H_i P_i- H_i^T + R_i and

    log w_i <- log w_i + log N(nu_i; 0, S_i)                                          (B.1)

and once per scan that saw a landmark the weights are normalised in log space (log-sum-exp),
floored at `weight_floor` and normalised again (B.2). The bank's estimate is the moment-matched
mixture over the members whose weight is at least `mixture_threshold` (renormalised; the most
probable member always counts), heading differences wrapped about the most probable member's:

    x = sum w_i x_i,   P = sum w_i [P_i + (x_i - x)(x_i - x)^T]                       (B.3)

and its adapted R, Qu (what a run records) are the same weights' average of the hypotheses'.

IMM (Markov switching, `p_stay` per scan, switching uniform over the other members): after a
scan's updates, c_j = sum_i p_ij w_i, mu_i|j = p_ij w_i / c_j, and member j restarts from the
mixture (B.3) of all members with weights mu_.|j (headings wrapped about member j's own); then
w_j <- c_j (B.4). Mixing happens once per scan, after its updates, so that every member predicts
from its mixed start with its own Qu (the textbook interaction / predict / update cycle).

The rules are plain module-level functions on floats and float arrays (members' x as (M, 3),
P as (M, 9) row-major), so that the filterpy-engine class below and the fast engine's compiled
bank kernel (engines/kernels_bank.py) call the same code; the one exception is B.4's form: the
filterpy engine mixes by the dense rule (`imm_mix`), the fast engine by running sums
(`imm_mix_by_sums`: the same starts in O(M log h + h), equal to rounding). Design decisions
(the gate, the counts, adaptation off, the sums' tolerance) are in docs/DESIGN.md
("Multiple-model banks").
"""

from __future__ import annotations

import itertools
import math
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from .adaptive import AdaptiveEKF
from .ekf import Innovation, RobotEKF
from .spec import AdaptiveSpec, FilterContext

LOG_2PI = math.log(2.0 * math.pi)
HALF_DECADE = (0.1, 10.0**-0.5, 1.0, 10.0**0.5, 10.0)
MAX_MODELS = 5000

# ---------------------------------------------------------------------------------------------
# The rules (both engines)


def _wrap(a):
    """models.angles.wrap_scalar, repeated here so that numba can compile the rules (the
    modulo skipped where it is the identity: the same bits)."""
    y = -a + math.pi
    if not (0.0 <= y < 2.0 * math.pi):
        y = y % (2.0 * math.pi)
    return -(y - math.pi)


def innovation_loglik(nis, S00, S01, S10, S11, censor_at):
    """log N(nu; 0, S) of a 2-vector from its NIS nu^T S^-1 nu (B.1); NIS above `censor_at`
    counts as `censor_at` (adapt_from accepted: a member gains nothing by rejecting). A
    non-positive det S gives -inf."""
    det = S00 * S11 - S01 * S10
    if not det > 0.0:
        return -math.inf
    if nis > censor_at:
        nis = censor_at
    return -0.5 * (nis + math.log(det)) - LOG_2PI


def log_sum_exp(logw):
    """log sum exp(logw_i), NaN propagating; -inf for an all -inf array."""
    top = -math.inf
    for v in logw:
        if v > top:
            top = v
    if top == -math.inf:
        return top
    s = 0.0
    for v in logw:
        s += math.exp(v - top)
    return top + math.log(s)


def normalise_log_weights(logw, log_floor):
    """In place (B.2): normalise, floor each log weight at `log_floor`, normalise again (so a
    weight can end a rounding below the floor, never lower). NaN stays NaN."""
    c = log_sum_exp(logw)
    for i in range(logw.shape[0]):
        v = logw[i] - c
        logw[i] = v if (v != v or v > log_floor) else log_floor
    c = log_sum_exp(logw)
    for i in range(logw.shape[0]):
        logw[i] = logw[i] - c


def most_probable(logw):
    """The index of the largest log weight (the first of equals)."""
    best = 0
    for i in range(1, logw.shape[0]):
        if logw[i] > logw[best]:
            best = i
    return best


def mixture_weights(logw, threshold, w):
    """Into `w`: the weights exp(logw_i), 0 below `threshold` (except the most probable
    member's), renormalised over the rest (B.3). NaN stays NaN."""
    best = most_probable(logw)
    s = 0.0
    for i in range(logw.shape[0]):
        wi = math.exp(logw[i])
        if wi < threshold and i != best:
            wi = 0.0
        w[i] = wi
        s += wi
    for i in range(logw.shape[0]):
        w[i] = w[i] / s


def mix_moments(w, X, P, ref, out_x, out_P):
    """The moment-matched mixture (B.3) of all members into out_x (3,) and out_P (9,): heading
    differences wrapped about `ref`, members with zero weight skipped."""
    mix_moments_at(w, np.arange(w.shape[0]), w.shape[0], X, P, ref, out_x, out_P)


def active_members(w, members):
    """Into `members`: the indices of the members whose weight is not 0 (NaN counts), in
    order; returns how many. The mixture over them is the mixture over all."""
    n = 0
    for i in range(w.shape[0]):
        if w[i] != 0.0:
            members[n] = i
            n += 1
    return n


def mix_moments_at(w, members, n, X, P, ref, out_x, out_P):
    """`mix_moments` over the members members[:n] (increasing indices; w, X, P indexed by
    member): the same sums in the same order as over all members when every member left out
    has weight 0, so the same bits at the cost of the few members that count."""
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    for k in range(n):
        i = members[k]
        wi = w[i]
        if wi == 0.0:
            continue
        m0 += wi * X[i, 0]
        m1 += wi * X[i, 1]
        m2 += wi * _wrap(X[i, 2] - ref)
    h = _wrap(ref + m2)
    out_x[0] = m0
    out_x[1] = m1
    out_x[2] = h
    for c in range(9):
        out_P[c] = 0.0
    for k in range(n):
        i = members[k]
        wi = w[i]
        if wi == 0.0:
            continue
        d0 = X[i, 0] - m0
        d1 = X[i, 1] - m1
        d2 = _wrap(X[i, 2] - h)
        out_P[0] += wi * (P[i, 0] + d0 * d0)
        out_P[1] += wi * (P[i, 1] + d0 * d1)
        out_P[2] += wi * (P[i, 2] + d0 * d2)
        out_P[3] += wi * (P[i, 3] + d1 * d0)
        out_P[4] += wi * (P[i, 4] + d1 * d1)
        out_P[5] += wi * (P[i, 5] + d1 * d2)
        out_P[6] += wi * (P[i, 6] + d2 * d0)
        out_P[7] += wi * (P[i, 7] + d2 * d1)
        out_P[8] += wi * (P[i, 8] + d2 * d2)


def weighted_noise(w, N, out):
    """Into `out` (2,): sum w_i N_i, N (M, 2) the members' (R or Qu) diagonals."""
    out[0] = 0.0
    out[1] = 0.0
    for i in range(w.shape[0]):
        if w[i] != 0.0:
            out[0] += w[i] * N[i, 0]
            out[1] += w[i] * N[i, 1]


def imm_mix(logw, p_stay, threshold, X, P, X0, P0, w, c, mu, x_tmp, P_tmp, heavy, members):
    """The IMM interaction (B.4): the members' mixed starts into X0 (M, 3), P0 (M, 9), and the
    (normalised) logw replaced by the predicted log c_j. Switching is uniform: p_jj = p_stay,
    p_ij = (1 - p_stay) / (M - 1). As in the output mixture, the mixing weights mu_i|j below
    `threshold` are left out of member j's start (its own never is) and the rest renormalised.
    w, c, mu (M,), x_tmp (3,), P_tmp (9,), heavy and members (M,) int are scratch.

    Cost O(M h), h the number of members that can reach the threshold: mu_i|j =
    p_off w_i / c_j <= p_off w_i / min c, so a member with p_off w_i below half of
    threshold * min c has mu_i|j below the threshold for every j (the half covers the roundings)
    and is left out of every start without its division; the others are computed as the dense
    rule computes them, in the same order (the same bits)."""
    M = logw.shape[0]
    p_off, _, cut = predicted_weights(logw, p_stay, threshold, w, c)
    n_heavy = heavy_members(p_off, w, cut, heavy)
    for j in range(M):
        mixed_start(j, p_stay, p_off, threshold, X, P, X0, P0, w, c[j], mu, x_tmp, P_tmp, heavy,
                     n_heavy, members)  # fmt: skip
    for j in range(M):
        logw[j] = math.log(c[j])


def predicted_weights(logw, p_stay, threshold, w, c):
    """B.4's weights: w_i = exp(logw_i) and the predicted c_j = sum_i p_ij w_i (O(1) per member)
    into w, c (M,). Returns (p_off, their total, cut): p_off = (1 - p_stay) / (M - 1), and the
    cut below which p_off w_i leaves member i out of every start but its own (half of
    threshold * min c: the half covers the roundings; -inf where it is not finite: every member
    counts, as the dense rule)."""
    M = logw.shape[0]
    p_off = (1.0 - p_stay) / (M - 1) if M > 1 else 0.0
    total = 0.0
    for i in range(M):
        w[i] = math.exp(logw[i])
        total += w[i]
    c_min = math.inf
    for j in range(M):
        c[j] = p_off * (total - w[j]) + p_stay * w[j]
        if c[j] < c_min:
            c_min = c[j]
    cut = 0.5 * threshold * c_min
    if not (cut >= 0.0 and cut < math.inf):
        cut = -math.inf  # NaN or inf weights
    return p_off, total, cut


def heavy_members(p_off, w, cut, heavy):
    """Into `heavy`: the members i with p_off w_i at `cut` or above, in increasing order;
    returns how many."""
    n = 0
    for i in range(w.shape[0]):
        if not p_off * w[i] < cut:
            heavy[n] = i
            n += 1
    return n


def mixed_start(j, p_stay, p_off, threshold, X, P, X0, P0, w, cj, mu, x_tmp, P_tmp, heavy,
                 n_heavy, members):  # fmt: skip
    """Member j's mixed start (imm_mix) into X0[j], P0[j], over its candidates: the heavy
    members heavy[:n_heavy] (increasing indices) and j itself."""
    n = 0
    own = False
    for k in range(n_heavy):
        i = heavy[k]
        if not own and j <= i:
            own = True
            if j < i:
                members[n] = j
                n += 1
        members[n] = i
        n += 1
    if not own:
        members[n] = j
        n += 1
    s = 0.0
    for k in range(n):
        i = members[k]
        m = (p_stay if i == j else p_off) * w[i] / cj
        if m < threshold and i != j:
            m = 0.0
        mu[i] = m
        s += m
    for k in range(n):
        i = members[k]
        mu[i] = mu[i] / s
    mix_moments_at(mu, members, n, X, P, X[j, 2], x_tmp, P_tmp)
    for k in range(3):
        X0[j, k] = x_tmp[k]
    for k in range(9):
        P0[j, k] = P_tmp[k]


# The heading spread (rad) within which the running sums of `imm_mix_by_sums` wrap every heading
# difference as the dense rule does (about member j's own heading, then about the mixed mean's):
# a member further from the heaviest one gets the dense rule.
SUMS_HEADING_SPREAD = 1.0


def imm_mix_by_sums(logw, p_stay, threshold, X, P, X0, P0, w, c, mu, x_tmp, P_tmp, heavy,
                    members, order, W, E, Q, spread):  # fmt: skip
    """`imm_mix` (the same starts, logw replaced the same way) in O(M log h + h), h the members
    that can reach the threshold, where the dense rule takes O(M h). The members i != j in
    member j's start (p_off w_i / c_j at the threshold or above) are the heaviest ones: a
    prefix of the heavy members sorted by weight. So j's start comes from running sums over that
    order (weights W, first moments E, second moments Q about the heaviest member's state,
    heading differences wrapped), less j's own terms where j is in the prefix, plus j's own
    term p_stay w_j.

    Exact in real arithmetic; in floating point the sums are added in another order, so the
    starts differ from `imm_mix`'s by rounding (tests/test_filter_bank.py bounds it at 1e-12 of
    their scale). Taking j's terms out of the sums loses no precision that counts: where w_j is
    most of the prefix's weight, the rest enters j's start with the factor p_off / p_stay. The
    dense rule is the reference: the filterpy engine runs it, and the fast engine, which runs
    this one, equals it to 1e-9 over whole runs (tests/test_fast_bank.py). A member more than
    SUMS_HEADING_SPREAD in heading from the heaviest one, or a prefix that spreads more, takes
    the dense rule (the wraps could differ), as do weights that are not finite. Scratch as
    imm_mix's, and order (M,) int, W (M + 1,), E (M + 1, 3), Q (M + 1, 9), spread (M + 1,)."""
    M = logw.shape[0]
    p_off, total, cut = predicted_weights(logw, p_stay, threshold, w, c)
    n_heavy = heavy_members(p_off, w, cut, heavy) if cut > -math.inf and total < math.inf else 0
    if n_heavy == 0:  # weights not finite, or no member in another's start (p_stay 1)
        imm_mix(logw, p_stay, threshold, X, P, X0, P0, w, c, mu, x_tmp, P_tmp, heavy, members)
        return
    # the heavy members by weight, heaviest first (a prefix never splits equal weights: the
    # threshold test gives them the same answer), and their running sums
    for k in range(n_heavy):
        mu[k] = -w[heavy[k]]
    sorted_at = np.argsort(mu[:n_heavy], kind="mergesort")
    for k in range(n_heavy):
        order[k] = heavy[sorted_at[k]]
    a = order[0]
    a0 = X[a, 0]
    a1 = X[a, 1]
    a2 = X[a, 2]
    W[0] = 0.0
    spread[0] = 0.0
    for r in range(3):
        E[0, r] = 0.0
    for r in range(9):
        Q[0, r] = 0.0
    for k in range(n_heavy):
        i = order[k]
        wi = w[i]
        e = (X[i, 0] - a0, X[i, 1] - a1, _wrap(X[i, 2] - a2))
        W[k + 1] = W[k] + wi
        spread[k + 1] = max(spread[k], abs(e[2]))
        for r in range(3):
            E[k + 1, r] = E[k, r] + wi * e[r]
            for q in range(3):
                Q[k + 1, 3 * r + q] = Q[k, 3 * r + q] + wi * (P[i, 3 * r + q] + e[r] * e[q])
    n_dense = 0
    for j in range(M):
        cj = c[j]
        wj = w[j]
        e = (X[j, 0] - a0, X[j, 1] - a1, _wrap(X[j, 2] - a2))
        # t: how many of the heaviest have p_off w_i / c_j at the threshold or above
        lo = 0
        hi = n_heavy
        while lo < hi:
            mid = (lo + hi) // 2
            if p_off * w[order[mid]] / cj < threshold:
                hi = mid
            else:
                lo = mid + 1
        t = lo
        if abs(e[2]) > SUMS_HEADING_SPREAD or spread[t] > SUMS_HEADING_SPREAD:
            members[n_dense] = j  # the dense rule, below
            n_dense += 1
            continue
        inside = 0.0 if p_off * wj / cj < threshold else wj  # j among the t: its terms out
        own = p_stay * wj
        A = p_off * (W[t] - inside) + own
        m = (
            (p_off * (E[t, 0] - inside * e[0]) + own * e[0]) / A,
            (p_off * (E[t, 1] - inside * e[1]) + own * e[1]) / A,
            (p_off * (E[t, 2] - inside * e[2]) + own * e[2]) / A,
        )
        X0[j, 0] = a0 + m[0]
        X0[j, 1] = a1 + m[1]
        X0[j, 2] = _wrap(a2 + m[2])
        for r in range(3):
            for q in range(3):
                rq = 3 * r + q
                Pj = P[j, rq] + e[r] * e[q]
                P0[j, rq] = (p_off * (Q[t, rq] - inside * Pj) + own * Pj) / A - m[r] * m[q]
    if n_dense:
        # the dense rule's candidates: the heavy members in index order (`order` holds the
        # members listed for it from here)
        for k in range(n_dense):
            order[k] = members[k]
        n_heavy = heavy_members(p_off, w, cut, heavy)
        for k in range(n_dense):
            j = order[k]
            mixed_start(j, p_stay, p_off, threshold, X, P, X0, P0, w, c[j], mu, x_tmp, P_tmp,
                        heavy, n_heavy, members)  # fmt: skip
    for j in range(M):
        logw[j] = math.log(c[j])


# ---------------------------------------------------------------------------------------------
# The grid of hypotheses and the specs

Factors = Annotated[
    tuple[Annotated[float, Field(gt=0, allow_inf_nan=False)], ...],
    Field(min_length=1, max_length=50),
]


def hypotheses(spec: MMAESpec) -> np.ndarray:
    """The bank's hypotheses as factors on the assumed variances, one row (v, gamma, range,
    bearing) per member: qu_factors (both controls together) x v_factors x gamma_factors x
    range_factors x bearing_factors. With adaptation off, the assumed noise alone."""
    if not spec.adaptation:
        return np.ones((1, 4))
    rows = [
        (q * v, q * g, r, b)
        for q, v, g, r, b in itertools.product(
            spec.qu_factors, spec.v_factors, spec.gamma_factors, spec.range_factors,
            spec.bearing_factors,
        )
    ]  # fmt: skip
    return np.array(rows, dtype=float)


class MMAESpec(AdaptiveSpec):
    """Static multiple-model adaptive estimation over a log grid of noise factors (Magill 1965;
    Maybeck 1982): one EKF per hypothesis, likelihood weights, the moment-matched mixture."""

    kind: Literal["mmae"]
    fast_kernel: ClassVar[str | None] = "kernels_bank"
    robot_only_because: ClassVar[str] = (
        "its grid of hypotheses is over the robot's four noise sigmas"
    )
    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R", "Q"})
    qu_factors: Factors = Field(
        HALF_DECADE,
        description="factors on the assumed Qu variances, both controls together (default half-"
        "decade steps 0.1x..10x)",
    )
    v_factors: Factors = Field(
        (1.0,), description="further factors on sigma_v^2 alone (crossed with the others)"
    )
    gamma_factors: Factors = Field(
        (1.0,), description="further factors on sigma_gamma^2 alone (crossed with the others)"
    )
    range_factors: Factors = Field(
        HALF_DECADE, description="factors on the assumed range variance (default 0.1x..10x)"
    )
    bearing_factors: Factors = Field(
        HALF_DECADE, description="factors on the assumed bearing variance (default 0.1x..10x)"
    )
    weight_floor: Annotated[float, Field(gt=0, lt=1e-2, allow_inf_nan=False)] = Field(
        1e-30,
        description="floor of every member's weight, once per scan (a low floor: the research"
        " prototype lost lock on real data with 1e-6 and not with 1e-30)",
    )
    mixture_threshold: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = Field(
        1e-4,
        description="members below this weight stay in the bank but out of the mixture (the"
        " prototype: mixing hundreds of floored members inflated P)",
    )

    def n_models(self) -> int:
        sizes = (
            self.qu_factors, self.v_factors, self.gamma_factors, self.range_factors,
            self.bearing_factors,
        )  # fmt: skip
        return math.prod(len(f) for f in sizes)

    @model_validator(mode="after")
    def _grid_within_bounds(self) -> MMAESpec:
        if self.n_models() > MAX_MODELS:
            raise ValueError(f"the grid has {self.n_models()} models; at most {MAX_MODELS}")
        lo, hi = self.bounds
        qu = [q * f for q in self.qu_factors for f in (*self.v_factors, *self.gamma_factors)]
        for name, values in (
            ("qu_factors x v_factors / gamma_factors", qu),
            ("range_factors", self.range_factors),
            ("bearing_factors", self.bearing_factors),
        ):
            if not all(lo <= v <= hi for v in values):
                raise ValueError(f"{name}: every factor must lie within bounds {lo}..{hi}")
        return self

    def build(self, ctx: FilterContext) -> BankEKF:
        return BankEKF(**ctx.kwargs(), params=self)

    def adapted(self) -> frozenset[str] | None:
        # A bank adapts what its grid varies: an R-only bank (every Qu factor list [1]) keeps Qu.
        if self.adaptation is False:
            return frozenset()
        varies_q = any(len(set(f)) > 1 for f in (self.qu_factors, self.v_factors,
                                                 self.gamma_factors))  # fmt: skip
        varies_r = any(len(set(f)) > 1 for f in (self.range_factors, self.bearing_factors))
        return frozenset({"Q"} if varies_q else ()) | frozenset({"R"} if varies_r else ())


class IMMSpec(MMAESpec):
    """Interacting multiple models over the same grid: Markov switching once per scan."""

    kind: Literal["imm"]
    fast_kernel: ClassVar[str | None] = "kernels_bank"
    p_stay: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.98,
        description="probability that the noise stays in its hypothesis from one scan to the"
        " next (the rest is spread evenly over the other members)",
    )


# ---------------------------------------------------------------------------------------------
# The filter (filterpy engine)


class _Member(RobotEKF):
    """One hypothesis: a plain EKF that keeps the innovation of its last landmark."""

    def before_gain(self, inn: Innovation) -> None:
        self.inn = inn


class MemberBank(AdaptiveEKF):
    """What every bank of member EKFs shares (`BankEKF`, vb_bank.VBIMMEKF): the engines see one
    filter, x, P the mixture of its members (B.3), R, Qu the mixture weights' average of the
    members' noise, recomputed after every predict and every scan. Per scan every member's
    begin_scan, each landmark through every member (its own gate, with its own S_i) and the
    member's log-likelihood added to its weight, every member's end_scan, the weights
    normalised and floored, the mixture, and where the members interact the IMM's mixed
    restarts (B.4). The NIS sum and update / rejection counts are the most probable member's at
    the start of each scan. A bank says how its members are made (`_start_bank`), the R each
    holds (`member_R`) and how a member's innovation scores (`member_loglik`).
    """

    adapts: ClassVar[frozenset[str]] = frozenset({"R", "Q"})

    def _start_bank(self, members: list, Qu_members: np.ndarray, p_stay: float, interacts: bool):
        self.members = members
        self.Qu_members = Qu_members
        M = len(members)
        self.logw = np.full(M, -math.log(M))
        self.w = np.empty(M)
        self.censor_at = (
            self.gate
            if (self.params.adapt_from == "accepted" and self.gate is not None)
            else math.inf
        )
        self.log_floor = math.log(self.params.weight_floor)
        self.p_stay = p_stay
        self.interacts = interacts
        self._weights_changed()
        self._output()

    def member_R(self) -> np.ndarray:
        """(M, 2): every member's R diagonal now."""
        raise NotImplementedError

    def member_loglik(self, m: RobotEKF) -> float:
        """The log-likelihood of member m's last innovation."""
        raise NotImplementedError

    def _weights_changed(self) -> None:
        mixture_weights(self.logw, self.params.mixture_threshold, self.w)
        self.active = np.flatnonzero(self.w != 0.0)
        R, Qu = np.empty(2), np.empty(2)
        weighted_noise(self.w, self.member_R(), R)
        weighted_noise(self.w, self.Qu_members, Qu)
        self.R, self.Qu = np.diag(R), np.diag(Qu)

    def _output(self) -> None:
        act = self.active
        X = np.array([self.members[i].x for i in act])
        P = np.array([self.members[i].P.ravel() for i in act])
        ref = self.members[most_probable(self.logw)].x[2]
        x, Pm = np.empty(3), np.empty(9)
        mix_moments(self.w[act], X, P, ref, x, Pm)
        self.x, self.P = x, Pm.reshape(3, 3)

    def predict(self, u=0, dt: float | None = None):
        if dt is not None:
            self.dt = dt
        for m in self.members:
            m.predict(u, dt)
        self._output()

    def update_scan(self, zs: np.ndarray, landmarks: np.ndarray) -> None:
        best = self.members[most_probable(self.logw)]
        before = (best.nis_sum, best.n_updates, best.n_rejected)
        for m in self.members:
            m.begin_scan()
        for z, landmark in zip(zs, landmarks, strict=True):
            for i, m in enumerate(self.members):
                m.update_landmark(z, landmark)
                self.logw[i] += self.member_loglik(m)
        for m in self.members:
            m.end_scan()
        self.nis_sum += best.nis_sum - before[0]
        self.n_updates += best.n_updates - before[1]
        self.n_rejected += best.n_rejected - before[2]
        normalise_log_weights(self.logw, self.log_floor)
        self._weights_changed()
        self._output()
        if self.interacts:
            self._interact()

    def _interact(self) -> None:
        """B.4 after the scan's output: members restart from their mixed starts."""
        M = len(self.members)
        X = np.array([m.x for m in self.members])
        P = np.array([m.P.ravel() for m in self.members])
        X0, P0 = np.empty_like(X), np.empty_like(P)
        imm_mix(
            self.logw, self.p_stay, self.params.mixture_threshold, X, P, X0, P0,
            np.empty(M), np.empty(M), np.empty(M), np.empty(3), np.empty(9),
            np.empty(M, np.int64), np.empty(M, np.int64),
        )  # fmt: skip
        for m, x0, p0 in zip(self.members, X0, P0, strict=True):
            m.x, m.P = x0, p0.reshape(3, 3)
        # The recorded R, Qu and the between-scan mixture now use the predicted weights c_j.
        self._weights_changed()


class BankEKF(MemberBank):
    """A bank of `_Member` EKFs, one per hypothesis of `hypotheses(params)` (module doc), each
    with fixed noise; the likelihood of a member's innovation is `innovation_loglik` (censored
    at the gate where it adapts from accepted landmarks)."""

    params: MMAESpec

    def __init__(self, *args, params: MMAESpec, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        factors = hypotheses(params)
        self.factors = factors
        qu0, r0 = np.diag(self.Qu0), np.diag(self.R0)
        Qu_members = factors[:, :2] * qu0
        self.R_members = factors[:, 2:] * r0
        members = [
            _Member(self.x, self.P, np.diag(qu), np.diag(r), self.model, self.dt, self.gate)
            for qu, r in zip(Qu_members, self.R_members, strict=True)
        ]
        imm = isinstance(params, IMMSpec)
        self._start_bank(members, Qu_members, params.p_stay if imm else 1.0, imm)

    def member_R(self) -> np.ndarray:
        return self.R_members

    def member_loglik(self, m: RobotEKF) -> float:
        S = m.inn.S
        return innovation_loglik(m.inn.nis, S[0, 0], S[0, 1], S[1, 0], S[1, 1], self.censor_at)
