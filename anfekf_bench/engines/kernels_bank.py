"""The fast engine's kernel of the multiple-model banks, `mmae`, `imm` (filters/bank.py) and
`vb-imm` (filters/vb_bank.py): M EKFs on kernels.py's primitives, the banks' rules as written in
filters/bank.py and filters/vb_bank.py (registered with numba so that compiled code calls them).
Not on the one loop (`engines/loop.py`): the loop runs one EKF, a bank M of them and their
mixture.

One kernel runs every bank: members that hold their R hypothesis (`RULE_GRID`: mmae, imm and
vb-imm's grid rule) or adapt it (`RULE_VB`, `RULE_SAGE_HUSA`: vb-imm's members), weighted by the
Gaussian (`dof` inf) or Student-t predictive likelihood, interacting once per scan or not.

Between two events (a scan, a record) the members' predicts are shared (`interval_add`,
`predict_members_over`): the same predicts as member by member in exact arithmetic, one sin and
cos a member per interval instead of one a step (docs/DESIGN.md, "Multiple-model banks").

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
numba's disk cache of the kernel is stamped with every source it reaches (this file, kernels.py,
filters/bank.py, filters/vb_bank.py, ...: compiled.use_reached_sources_stamp), so an edited
rule compiles it anew.
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import bank as _bank
from ..filters import vb_bank as _vb_bank
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
step_terms, noise_scale, wrap = _k.step_terms, _k.noise_scale, _k.wrap
innovation, nis, correct, healthy, record, hph_diag, feeds_adaptation = (
    _k.innovation, _k.nis, _k.correct, _k.healthy, _k.record, _k.hph_diag, _k.feeds_adaptation,
)  # fmt: skip
clip_to_bounds = _k.clip_to_bounds
stamp_input, NO_TALLY = _k.stamp_input, _k.NO_TALLY
vb_r_predict, vb_r_beta, vb_r_bounded_beta = _k.vb_r_predict, _k.vb_r_beta, _k.vb_r_bounded_beta
next_beta, fading_mean, r_sample = _k.next_beta, _k.fading_mean, _k.r_sample
MOTION_UNICYCLE = _k.MOTION_UNICYCLE
# The members' R rule (filters.vb_bank.R_RULE_CODE): adapted by VB or Sage-Husa, or held
RULE_VB = _vb_bank.R_RULE_CODE["vb"]
RULE_SAGE_HUSA = _vb_bank.R_RULE_CODE["sage-husa"]
RULE_GRID = _vb_bank.R_RULE_CODE["grid"]


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


_k.jitable(  # what the rules below call
    _bank._wrap, _bank.log_sum_exp, _bank.mix_moments, _bank.imm_mix, _bank.predicted_weights,
    _bank.heavy_members, _bank.mixed_start,
)  # fmt: skip
(
    innovation_loglik, normalise_log_weights, most_probable, mixture_weights, mix_moments_at,
    active_members, weighted_noise, imm_mix_by_sums, predictive_loglik,
) = _k.jitable(
    _bank.innovation_loglik, _bank.normalise_log_weights, _bank.most_probable,
    _bank.mixture_weights, _bank.mix_moments_at, _bank.active_members, _bank.weighted_noise,
    _bank.imm_mix_by_sums, _vb_bank.predictive_loglik,
)  # fmt: skip


# The members' predicts between two events (a scan, a record), shared: every member takes the
# same controls, and a member's heading enters a step only through cos and sin of (its heading +
# a turn common to all), so each step's Jacobians, position step and noise are polynomials in
# (c, s) = (cos, sin) of the member's heading at the interval's start (F is a shear, and shears
# compose by adding their columns). `interval_add` accumulates their coefficients once per step
# for the whole bank; `predict_members_over` gives every member the interval's predict from its
# own (c, s) and Qu diagonal at the interval's end: one sin and cos a member per interval instead
# of one per step. The same predicts in exact arithmetic; in floating point the sums run in
# another order (tests/test_fast_bank.py: to 1e-12 of the per-step predict's scale, and the
# whole runs to the filterpy engine's 1e-9).
#
# The accumulator (floats): the heading's step H, the coefficients on (c, s) of the steps'
# f02 sums (A; y -= A) and f12 sums (B; x += B), and the noise accumulated over the interval R,
# per control channel (0: speed, 1: steering; a member scales them by its Qu diagonal): R00, R01,
# R11 on (cc, cs, ss), R02, R12 on (c, s), R22 on 1.
ACC_H, ACC_A, ACC_B = 0, 1, 3
ACC_R00, ACC_R01, ACC_R11, ACC_R02, ACC_R12, ACC_R22 = 5, 11, 17, 23, 27, 31
ACC_SIZE = 33


@maybe_njit
def interval_add(acc, terms, q_scale):
    """One step's predict (its `step_terms`, its factor `q_scale` on G Qu G^T) added to the
    interval's accumulator `acc`: R <- F R F^T + Q with F, Q as polynomials in (c, s)."""
    turn, cf0, cf1, cg0, cg1, cg3, g20, g21, dh = terms
    phi = acc[ACC_H] + turn
    C = math.cos(phi)
    S = math.sin(phi)
    # a member's cos(a) = c C - s S and sin(a) = s C + c S; f02 = cf0 sin(a), f12 = cf1 cos(a)
    ac = cf0 * S
    as_ = cf0 * C
    bc = cf1 * C
    bs = -cf1 * S
    for q in range(2):
        if q == 0:  # G's speed column: (cg0 cos a, cg0 sin a, g20)
            uc, us, vc, vs, z = cg0 * C, -cg0 * S, cg0 * S, cg0 * C, g20
        else:  # its steering column: (cg1 sin a, cg3 cos a, g21)
            uc, us, vc, vs, z = cg1 * S, cg1 * C, cg3 * C, -cg3 * S, g21
        o02 = ACC_R02 + 2 * q
        o12 = ACC_R12 + 2 * q
        r02c = acc[o02]
        r02s = acc[o02 + 1]
        r12c = acc[o12]
        r12s = acc[o12 + 1]
        r22 = acc[ACC_R22 + q]
        kz = q_scale * z
        o = ACC_R00 + 3 * q  # R00 + 2 f02 R02 + f02^2 R22 + Q00
        acc[o] += 2.0 * ac * r02c + ac * ac * r22 + q_scale * uc * uc
        acc[o + 1] += (2.0 * (ac * r02s + as_ * r02c) + 2.0 * ac * as_ * r22
                       + 2.0 * q_scale * uc * us)  # fmt: skip
        acc[o + 2] += 2.0 * as_ * r02s + as_ * as_ * r22 + q_scale * us * us
        o = ACC_R01 + 3 * q  # R01 + f02 R12 + f12 R02 + f02 f12 R22 + Q01
        acc[o] += ac * r12c + bc * r02c + ac * bc * r22 + q_scale * uc * vc
        acc[o + 1] += (ac * r12s + as_ * r12c + bc * r02s + bs * r02c
                       + (ac * bs + as_ * bc) * r22 + q_scale * (uc * vs + us * vc))  # fmt: skip
        acc[o + 2] += as_ * r12s + bs * r02s + as_ * bs * r22 + q_scale * us * vs
        o = ACC_R11 + 3 * q  # R11 + 2 f12 R12 + f12^2 R22 + Q11
        acc[o] += 2.0 * bc * r12c + bc * bc * r22 + q_scale * vc * vc
        acc[o + 1] += (2.0 * (bc * r12s + bs * r12c) + 2.0 * bc * bs * r22
                       + 2.0 * q_scale * vc * vs)  # fmt: skip
        acc[o + 2] += 2.0 * bs * r12s + bs * bs * r22 + q_scale * vs * vs
        acc[o02] = r02c + ac * r22 + kz * uc  # R02 + f02 R22 + Q02
        acc[o02 + 1] = r02s + as_ * r22 + kz * us
        acc[o12] = r12c + bc * r22 + kz * vc  # R12 + f12 R22 + Q12
        acc[o12 + 1] = r12s + bs * r22 + kz * vs
        acc[ACC_R22 + q] = r22 + kz * z
    acc[ACC_A] += ac
    acc[ACC_A + 1] += as_
    acc[ACC_B] += bc
    acc[ACC_B + 1] += bs
    acc[ACC_H] += dh


@maybe_njit
def predict_members_over(X, Pm, Qu_m, acc):
    """The interval's predict (`interval_add`'s `acc`) of every member i in place: its state
    X[i], covariance Pm[i] row-major, its control noise diagonal Qu_m[i]; then `acc` zeroed
    for the next interval. P <- S P S^T + R, S = I + (A, B, 0) e2^T the steps' F composed."""
    H = acc[ACC_H]
    for i in range(X.shape[0]):
        th = X[i, 2]
        c = math.cos(th)
        s = math.sin(th)
        cc = c * c
        cs = c * s
        ss = s * s
        q0 = Qu_m[i, 0]
        q1 = Qu_m[i, 1]
        A = acc[ACC_A] * c + acc[ACC_A + 1] * s
        B = acc[ACC_B] * c + acc[ACC_B + 1] * s
        o = ACC_R00
        R00 = (q0 * (acc[o] * cc + acc[o + 1] * cs + acc[o + 2] * ss)
               + q1 * (acc[o + 3] * cc + acc[o + 4] * cs + acc[o + 5] * ss))  # fmt: skip
        o = ACC_R01
        R01 = (q0 * (acc[o] * cc + acc[o + 1] * cs + acc[o + 2] * ss)
               + q1 * (acc[o + 3] * cc + acc[o + 4] * cs + acc[o + 5] * ss))  # fmt: skip
        o = ACC_R11
        R11 = (q0 * (acc[o] * cc + acc[o + 1] * cs + acc[o + 2] * ss)
               + q1 * (acc[o + 3] * cc + acc[o + 4] * cs + acc[o + 5] * ss))  # fmt: skip
        o = ACC_R02
        R02 = q0 * (acc[o] * c + acc[o + 1] * s) + q1 * (acc[o + 2] * c + acc[o + 3] * s)
        o = ACC_R12
        R12 = q0 * (acc[o] * c + acc[o + 1] * s) + q1 * (acc[o + 2] * c + acc[o + 3] * s)
        R22 = q0 * acc[ACC_R22] + q1 * acc[ACC_R22 + 1]
        # (S P S^T)_rs = P_rs + w_r P_2s + P_r2 w_s + w_r w_s P_22, w = (A, B, 0)
        p02 = Pm[i, 2]
        p12 = Pm[i, 5]
        p20 = Pm[i, 6]
        p21 = Pm[i, 7]
        p22 = Pm[i, 8]
        Pm[i, 0] = Pm[i, 0] + A * p20 + p02 * A + A * A * p22 + R00
        Pm[i, 1] = Pm[i, 1] + A * p21 + p02 * B + A * B * p22 + R01
        Pm[i, 2] = p02 + A * p22 + R02
        Pm[i, 3] = Pm[i, 3] + B * p20 + p12 * A + B * A * p22 + R01
        Pm[i, 4] = Pm[i, 4] + B * p21 + p12 * B + B * B * p22 + R11
        Pm[i, 5] = p12 + B * p22 + R12
        Pm[i, 6] = p20 + p22 * A + R02
        Pm[i, 7] = p21 + p22 * B + R12
        Pm[i, 8] = p22 + R22
        X[i, 0] = X[i, 0] + B
        X[i, 1] = X[i, 1] - A
        X[i, 2] = wrap(th + H)
    for r in range(ACC_SIZE):
        acc[r] = 0.0


@maybe_njit
def imm_scratch(M):
    """The scratch arrays of `end_scan`'s IMM interaction for M members: the mixed starts
    X0 (M, 3) and P0 (M, 9), then imm_mix_by_sums's w, c, mu, x_tmp, P_tmp, heavy, members,
    order, W, E, Q and spread."""
    return (
        np.empty((M, 3)), np.empty((M, 9)), np.empty(M), np.empty(M), np.empty(M), np.empty(3),
        np.empty(9), np.empty(M, np.int64), np.empty(M, np.int64), np.empty(M, np.int64),
        np.empty(M + 1), np.empty((M + 1, 3)), np.empty((M + 1, 9)), np.empty(M + 1),
    )  # fmt: skip


@maybe_njit
def mixture(logw, threshold, X, Pm, R_m, Qu_m, w, active, Rw, Qw, xm, Pmix):
    """From the log weights: the mixture weights `w`, their members `active` (weight not 0),
    the weighted R and Qu diagonals (Rw, Qw) and the mixture (xm, Pmix) of the members' states
    X, Pm. R_m (M, 2): the R each member holds. Returns how many members are in the mixture."""
    mixture_weights(logw, threshold, w)
    n_active = active_members(w, active)
    weighted_noise(w, R_m, Rw)
    weighted_noise(w, Qu_m, Qw)
    mix_moments_at(w, active, n_active, X, Pm, X[most_probable(logw), 2], xm, Pmix)
    return n_active


@maybe_njit
def end_scan(logw, log_floor, threshold, interact, p_stay, X, Pm, R_m, Qu_m, w, active, Rw, Qw,
             xm, Pmix, scratch):  # fmt: skip
    """A bank after a scan's landmarks (filters.bank.BankEKF.end_scan): the log weights
    normalised and floored, the `mixture`; then, where the members `interact`, the IMM's mixed
    starts in X, Pm, and the weights and the weighted noise again (the mixture recorded is the
    one before the interaction, as filterpy's). Returns (members in the mixture, whether the
    mixture and its noise are healthy)."""
    normalise_log_weights(logw, log_floor)
    n_active = mixture(logw, threshold, X, Pm, R_m, Qu_m, w, active, Rw, Qw, xm, Pmix)
    if interact:
        X0, P0m, s_w, s_c, s_mu, s_x, s_P, s_heavy, s_members, s_order, s_W, s_E, s_Q, s_spread = (
            scratch
        )
        imm_mix_by_sums(logw, p_stay, threshold, X, Pm, X0, P0m, s_w, s_c, s_mu, s_x, s_P, s_heavy,
                        s_members, s_order, s_W, s_E, s_Q, s_spread)  # fmt: skip
        for i in range(X.shape[0]):
            for c in range(3):
                X[i, c] = X0[i, c]
            for c in range(9):
                Pm[i, c] = P0m[i, c]
        mixture_weights(logw, threshold, w)
        n_active = active_members(w, active)
        weighted_noise(w, R_m, Rw)
        weighted_noise(w, Qu_m, Qw)
    ok = healthy(
        (xm[0], xm[1], xm[2]),
        (Pmix[0], Pmix[1], Pmix[2], Pmix[3], Pmix[4], Pmix[5], Pmix[6], Pmix[7], Pmix[8]),
        (Rw[0], 0.0, 0.0, Rw[1]), (Qw[0], 0.0, 0.0, Qw[1]),
    )  # fmt: skip
    return n_active, ok


@maybe_njit
def run_bank_kernel(
    u_odo, dt, scan_start, scan_lm, scan_z,
    motion, B, T0, x0, P0, Qu_m, R_m, R0, gate, has_gate,
    rule, from_all, floor, ceiling, rho, iterations, alpha0, b_fade,
    censor_at, dof, log_floor, threshold, interact, p_stay,
    record_at, out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """A bank of M EKFs over one run (filterpy_engine.run_filter with filters.bank.BankEKF or
    filters.vb_bank.VBIMMEKF), as the filterpy engine runs it: every member's begin_scan, then
    per landmark every member's adaptation, gate and update, weighted by the predictive
    likelihood (D.1) from the R it held before the landmark, then every member's end_scan and
    the bank's `end_scan` (weights, mixture, the IMM interaction where the members `interact`).

    Qu_m (M, 2): the members' Qu diagonals; R_m (M, 2): their starting R diagonals; R0 (4,):
    the assumed R (the bounds' reference); rule: RULE_*; dof: the likelihood's degrees of
    freedom (inf: Gaussian); the rest as `kernels.run_kernel`. Records the mixture (x, P) and the
    weighted R and Qu. Returns (diverged, rows written, nis_sum, n_updates, n_rejected): the
    counts are the most probable member's at each scan's start."""
    K = u_odo.shape[0]
    M = Qu_m.shape[0]
    X = np.empty((M, 3))
    Pm = np.empty((M, 9))
    Rm = np.empty((M, 2))  # the R each member holds now
    Ra = np.empty((M, 2))  # VB: inverse-gamma shapes and scales per channel
    Rb = np.empty((M, 2))
    sh_beta = np.ones(M)  # Sage-Husa: d_k of the next event, and the scan's pooled samples
    sh_d = np.empty(M)
    R_start = np.empty((M, 2))
    rho_sum = np.zeros((M, 2))
    n_fed = np.zeros(M, np.int64)
    for i in range(M):
        for c in range(3):
            X[i, c] = x0[c]
        for c in range(9):
            Pm[i, c] = P0[c]
        Rm[i, 0] = R_m[i, 0]
        Rm[i, 1] = R_m[i, 1]
        Ra[i, 0] = alpha0
        Ra[i, 1] = alpha0
        Rb[i, 0] = alpha0 * R_m[i, 0]
        Rb[i, 1] = alpha0 * R_m[i, 1]
    bounds = (floor, ceiling)
    R_min0 = floor * R0[0]
    R_min1 = floor * R0[3]
    R_max0 = ceiling * R0[0]
    R_max1 = ceiling * R0[3]
    logw = np.full(M, -math.log(M))
    w = np.empty(M)
    Rw = np.empty(2)
    Qw = np.empty(2)
    xm = np.empty(3)
    Pmix = np.empty(9)
    n_upd = np.zeros(M, np.int64)
    n_rej = np.zeros(M, np.int64)
    nis_m = np.zeros(M)
    scratch = imm_scratch(M)
    active = np.empty(M, np.int64)
    acc = np.zeros(ACC_SIZE)  # the members' predicts since the last event (interval_add)
    n_active = mixture(logw, threshold, X, Pm, Rm, Qu_m, w, active, Rw, Qw, xm, Pmix)
    bad_record, j, nis_sum, n_updates, n_rejected = NO_TALLY
    n_rows = out_x.shape[0]
    for k in range(K):
        u0, u1, dt_k = stamp_input(u_odo, dt, k)
        terms = step_terms(u0, u1, dt_k, motion, B)
        q_scale = noise_scale(dt_k, motion, T0) if motion == MOTION_UNICYCLE else 1.0
        interval_add(acc, terms, q_scale)
        first = scan_start[k]
        last = scan_start[k + 1]
        if last > first or (record_at[k] and j < n_rows):  # an event: the members' predicts
            predict_members_over(X, Pm, Qu_m, acc)
        if last == first and record_at[k] and j < n_rows:
            mix_moments_at(w, active, n_active, X, Pm, X[most_probable(logw), 2], xm, Pmix)
        if last > first:
            best = most_probable(logw)
            before_nis = nis_m[best]
            before_upd = n_upd[best]
            before_rej = n_rej[best]
            for i in range(M):  # the members' begin_scan
                if rule == RULE_VB:
                    Ra[i, 0], Rb[i, 0] = vb_r_predict(Ra[i, 0], Rb[i, 0], rho)
                    Ra[i, 1], Rb[i, 1] = vb_r_predict(Ra[i, 1], Rb[i, 1], rho)
                elif rule == RULE_SAGE_HUSA:
                    sh_d[i] = sh_beta[i]
                    R_start[i, 0] = Rm[i, 0]
                    R_start[i, 1] = Rm[i, 1]
                    rho_sum[i, 0] = 0.0
                    rho_sum[i, 1] = 0.0
                    n_fed[i] = 0
            for m in range(first, last):
                z0 = scan_z[m, 0]
                z1 = scan_z[m, 1]
                lx = scan_lm[m, 0]
                ly = scan_lm[m, 1]
                for i in range(M):
                    x = (X[i, 0], X[i, 1], X[i, 2])
                    P = (
                        Pm[i, 0], Pm[i, 1], Pm[i, 2], Pm[i, 3], Pm[i, 4], Pm[i, 5], Pm[i, 6],
                        Pm[i, 7], Pm[i, 8],
                    )  # fmt: skip
                    H, zh, nu, HPHt = innovation(x, P, lx, ly, z0, z1)
                    if rule == RULE_VB:
                        R_prior = (Rb[i, 0] / Ra[i, 0], 0.0, 0.0, Rb[i, 1] / Ra[i, 1])
                    else:
                        R_prior = (Rm[i, 0], 0.0, 0.0, Rm[i, 1])
                    R = R_prior
                    if rule != RULE_GRID:
                        ok, feeds = feeds_adaptation(HPHt, R, nu, from_all, gate, has_gate)
                        if not ok:
                            return True, j, nis_sum, n_updates, n_rejected
                        if feeds and rule == RULE_VB:  # VBREKF.before_gain
                            a0 = Ra[i, 0]
                            a1 = Ra[i, 1]
                            b0 = Rb[i, 0]
                            b1 = Rb[i, 1]
                            ap0 = a0 + 0.5
                            ap1 = a1 + 0.5
                            bn0 = b0
                            bn1 = b1
                            for _ in range(iterations):
                                R = (
                                    clip_to_bounds(bn0 / ap0, R0[0], bounds), 0.0,
                                    0.0, clip_to_bounds(bn1 / ap1, R0[3], bounds),
                                )  # fmt: skip
                                ok, xn, Pn = correct(x, P, H, zh, z0, z1, R)
                                if not ok:
                                    return True, j, nis_sum, n_updates, n_rejected
                                _, _, e, _ = innovation(xn, Pn, lx, ly, z0, z1)
                                hph0, hph1 = hph_diag(H, Pn)
                                bn0 = vb_r_beta(b0, e[0], hph0)
                                bn1 = vb_r_beta(b1, e[1], hph1)
                            Ra[i, 0] = ap0
                            Ra[i, 1] = ap1
                            Rb[i, 0], Rb[i, 1] = vb_r_bounded_beta(
                                ap0, ap1, bn0, bn1, R0[0], R0[3], floor, ceiling
                            )
                        elif feeds:  # SageHusaEKF.before_gain
                            rho_sum[i, 0] = rho_sum[i, 0] + r_sample(nu[0], HPHt[0], R_min0, R_max0)
                            rho_sum[i, 1] = rho_sum[i, 1] + r_sample(nu[1], HPHt[3], R_min1, R_max1)
                            n_fed[i] += 1
                            rh0 = fading_mean(sh_d[i], R_start[i, 0], rho_sum[i, 0], n_fed[i])
                            rh1 = fading_mean(sh_d[i], R_start[i, 1], rho_sum[i, 1], n_fed[i])
                            R = (
                                clip_to_bounds(rh0, R0[0], bounds), 0.0,
                                0.0, clip_to_bounds(rh1, R0[3], bounds),
                            )  # fmt: skip
                    Rm[i, 0] = R[0]
                    Rm[i, 1] = R[3]
                    ok, v = nis(HPHt, R, nu[0], nu[1])
                    if not ok or not math.isfinite(v):
                        return True, j, nis_sum, n_updates, n_rejected
                    if has_gate and not v <= gate:
                        n_rej[i] += 1
                    else:
                        nis_m[i] += v
                        n_upd[i] += 1
                        ok, x, P = correct(x, P, H, zh, z0, z1, R)
                        if not ok:
                            return True, j, nis_sum, n_updates, n_rejected
                        for c in range(3):
                            X[i, c] = x[c]
                        for c in range(9):
                            Pm[i, c] = P[c]
                    vp = v  # a held R: the NIS above (R_prior is R)
                    if rule != RULE_GRID:
                        ok, vp = nis(HPHt, R_prior, nu[0], nu[1])
                        if not ok or not math.isfinite(vp):
                            return True, j, nis_sum, n_updates, n_rejected
                    logw[i] += predictive_loglik(
                        vp, HPHt[0] + R_prior[0], HPHt[1] + R_prior[1], HPHt[2] + R_prior[2],
                        HPHt[3] + R_prior[3], censor_at, dof,
                    )  # fmt: skip
            for i in range(M):  # the members' end_scan
                if rule == RULE_VB:
                    Rm[i, 0] = Rb[i, 0] / Ra[i, 0]
                    Rm[i, 1] = Rb[i, 1] / Ra[i, 1]
                elif rule == RULE_SAGE_HUSA and n_fed[i] > 0:
                    sh_beta[i] = next_beta(sh_beta[i], b_fade)
            nis_sum += nis_m[best] - before_nis
            n_updates += n_upd[best] - before_upd
            n_rejected += n_rej[best] - before_rej
            n_active, ok = end_scan(
                logw, log_floor, threshold, interact, p_stay, X, Pm, Rm, Qu_m, w, active, Rw, Qw,
                xm, Pmix, scratch,
            )  # fmt: skip
            if not ok:
                return True, j, nis_sum, n_updates, n_rejected
        if record_at[k] and j < n_rows:
            R4 = (Rw[0], 0.0, 0.0, Rw[1])
            x3 = (xm[0], xm[1], xm[2])  # tuples, as the other kernels: record compiles once
            P9 = (
                Pmix[0], Pmix[1], Pmix[2], Pmix[3], Pmix[4], Pmix[5], Pmix[6], Pmix[7], Pmix[8],
            )  # fmt: skip
            j, bad = record(j, x3, P9, R4, (Qw[0], 0.0, 0.0, Qw[1]), out_x, out_P, out_R, out_Q)
            bad_record = bad_record or bad
    return bad_record, j, nis_sum, n_updates, n_rejected
