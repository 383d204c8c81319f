"""The fast engine's kernel of `vb-imm` (filters/vb_bank.py): a bank over Qu factors whose
members adapt R (VB, Sage-Husa) or hold an R hypothesis (grid), interacting once per scan.

It runs filters.vb_bank.VBIMMEKF as the filterpy engine does: every member's begin_scan, then per
landmark every member's adaptation, gate and update with the predictive likelihood (D.1) from the
R it held before the landmark, then every member's end_scan, the weights (bank.py's rules), the
mixture and the IMM interaction. The member rules are filters/vb.py's and filters/sage_husa.py's
functions (compiled in kernels.py), the EKF steps kernels.py's primitives.

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import vb_bank as _vb_bank
from . import kernels as _kernels
from . import kernels_bank as _kernels_bank

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
_b = _kernels_bank.pure_module() if _PURE_COPY else _kernels_bank  # the bank's rules, registered
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
step_terms, jacobians_at, noise_scale, predict_from = (
    _k.step_terms, _k.jacobians_at, _k.noise_scale, _k.predict_from,
)  # fmt: skip
innovation, nis, correct, record, hph_diag = (
    _k.innovation, _k.nis, _k.correct, _k.record, _k.hph_diag,
)  # fmt: skip
clip_to_bounds = _k.clip_to_bounds
vb_r_predict, vb_r_beta, vb_r_bounded_beta = _k.vb_r_predict, _k.vb_r_beta, _k.vb_r_bounded_beta
next_beta, fading_mean, r_sample = _k.next_beta, _k.fading_mean, _k.r_sample
most_probable, mix_moments_at = _b.most_probable, _b.mix_moments_at
predict_members, imm_scratch, mixture, end_scan = (
    _b.predict_members, _b.imm_scratch, _b.mixture, _b.end_scan,
)  # fmt: skip
MOTION_UNICYCLE = _k.MOTION_UNICYCLE

if JIT and not _PURE_COPY:
    from numba.extending import register_jitable

    register_jitable(_vb_bank.predictive_loglik)
predictive_loglik = _vb_bank.predictive_loglik

RULE_VB = 0  # filters.vb_bank.R_RULE_CODE
RULE_SAGE_HUSA = 1
RULE_GRID = 2


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


@maybe_njit
def run_vb_imm_kernel(
    u_odo, dt, scan_start, scan_lm, scan_z,
    motion, B, T0, x0, P0, Qu_m, R_m, R0, gate, has_gate,
    rule, from_all, floor, ceiling, rho, iterations, alpha0, b_fade,
    censor_at, dof, log_floor, threshold, p_stay,
    record_at, out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """One run of VBIMMEKF. Qu_m (M, 2): the members' Qu diagonals; R_m (M, 2): their starting
    R diagonals; R0 (4,): the assumed R (the bounds' reference); rule: RULE_*; p_stay 1: no
    interaction. Returns (diverged, rows written, nis_sum, n_updates, n_rejected) as
    kernels.run_bank_kernel (counts: the most probable member's at each scan's start)."""
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
    interact = p_stay < 1.0 and M > 1
    n_active = mixture(logw, threshold, X, Pm, Rm, Qu_m, w, active, Rw, Qw, xm, Pmix)
    nis_sum = 0.0
    n_updates = 0
    n_rejected = 0
    n_rows = out_x.shape[0]
    j = 0
    bad_record = False
    for k in range(K):
        u0 = u_odo[k, 0]
        u1 = u_odo[k, 1]
        dt_k = dt[k]
        terms = step_terms(u0, u1, dt_k, motion, B)
        q_scale = noise_scale(dt_k, motion, T0) if motion == MOTION_UNICYCLE else 1.0
        predict_members(X, Pm, Qu_m, terms, q_scale)  # the bank's, member by member
        first = scan_start[k]
        last = scan_start[k + 1]
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
                        feeds = True
                        if not from_all and has_gate:
                            ok, nis_a = nis(HPHt, R, nu[0], nu[1])
                            if not ok:
                                return True, j, nis_sum, n_updates, n_rejected
                            feeds = nis_a <= gate
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
            j, bad = record(j, xm, Pmix, R4, (Qw[0], 0.0, 0.0, Qw[1]), out_x, out_P, out_R, out_Q)
            bad_record = bad_record or bad
    return bad_record, j, nis_sum, n_updates, n_rejected
