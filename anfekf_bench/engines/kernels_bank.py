"""The fast engine's kernel of the multiple-model banks `mmae` and `imm` (filters/bank.py): M EKFs
on kernels.py's primitives, the bank's rules as written in filters/bank.py (registered with numba
so that compiled code calls them). Not on the one loop (`engines/loop.py`): the loop runs one
EKF, the bank M of them and their mixture.

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
numba's disk cache is keyed on THIS file's contents: after editing a rule in filters/bank.py,
delete __pycache__/kernels_bank.*.nbi (tests/test_fast_bank.py fails on a stale cache).
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import bank as _bank
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
step_terms, jacobians_at, noise_scale, predict_from = (
    _k.step_terms, _k.jacobians_at, _k.noise_scale, _k.predict_from,
)  # fmt: skip
innovation, nis, correct, healthy, record = (
    _k.innovation, _k.nis, _k.correct, _k.healthy, _k.record,
)  # fmt: skip
MOTION_UNICYCLE = _k.MOTION_UNICYCLE


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


if JIT and not _PURE_COPY:
    from numba.extending import register_jitable

    for _rule in (
        _bank._wrap, _bank.innovation_loglik, _bank.log_sum_exp, _bank.normalise_log_weights,
        _bank.most_probable, _bank.mixture_weights, _bank.mix_moments, _bank.weighted_noise,
        _bank.imm_mix, _bank.active_members, _bank.mix_moments_at,
    ):  # fmt: skip
        register_jitable(_rule)

innovation_loglik = _bank.innovation_loglik
normalise_log_weights = _bank.normalise_log_weights
most_probable = _bank.most_probable
mixture_weights = _bank.mixture_weights
mix_moments = _bank.mix_moments
mix_moments_at = _bank.mix_moments_at
active_members = _bank.active_members
weighted_noise = _bank.weighted_noise
imm_mix = _bank.imm_mix


@maybe_njit
def predict_members(X, Pm, Qu_m, terms, q_scale):
    """`predict` of every member i in place (its state X[i], covariance Pm[i] row-major, its
    control noise Qu_m[i]); `terms` (step_terms) hold what does not depend on the heading."""
    dh = terms[8]
    for i in range(X.shape[0]):
        f02, f12, G = jacobians_at(X[i, 2], terms)
        x, P, _ = predict_from(
            (X[i, 0], X[i, 1], X[i, 2]),
            (Pm[i, 0], Pm[i, 1], Pm[i, 2], Pm[i, 3], Pm[i, 4], Pm[i, 5], Pm[i, 6], Pm[i, 7],
             Pm[i, 8]),
            f02, f12, G, dh, q_scale, (Qu_m[i, 0], 0.0, 0.0, Qu_m[i, 1]),
        )  # fmt: skip
        for c in range(3):
            X[i, c] = x[c]
        for c in range(9):
            Pm[i, c] = P[c]


@maybe_njit
def imm_scratch(M):
    """The scratch arrays of `end_scan`'s IMM interaction for M members: the mixed starts
    X0 (M, 3) and P0 (M, 9), then imm_mix's w, c, mu, x_tmp, P_tmp, heavy and members."""
    return (
        np.empty((M, 3)), np.empty((M, 9)), np.empty(M), np.empty(M), np.empty(M), np.empty(3),
        np.empty(9), np.empty(M, np.int64), np.empty(M, np.int64),
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
        X0, P0m, s_w, s_c, s_mu, s_x, s_P, s_heavy, s_members = scratch
        imm_mix(logw, p_stay, threshold, X, Pm, X0, P0m, s_w, s_c, s_mu, s_x, s_P, s_heavy,
                s_members)  # fmt: skip
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
    motion, B, T0, x0, P0, Qu_m, R_m, gate, has_gate,
    censor_at, log_floor, threshold, imm, p_stay,
    record_at, out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """A bank of M EKFs over one run (filterpy_engine.run_filter with filters.bank.BankEKF).

    Qu_m, R_m (M, 2): the members' noise diagonals; the rest as `run_kernel`. Records the
    mixture (x, P) and the weighted R and Qu. Returns (diverged, rows written, nis_sum,
    n_updates, n_rejected): the counts are the most probable member's at each scan's start.
    """
    K = u_odo.shape[0]
    M = Qu_m.shape[0]
    X = np.empty((M, 3))
    Pm = np.empty((M, 9))
    for i in range(M):
        for c in range(3):
            X[i, c] = x0[c]
        for c in range(9):
            Pm[i, c] = P0[c]
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
    active = np.empty(M, np.int64)  # the members in the mixture (weight not 0): n_active
    n_active = mixture(logw, threshold, X, Pm, R_m, Qu_m, w, active, Rw, Qw, xm, Pmix)
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
        # `predict` of every member, what does not depend on its heading computed once
        terms = step_terms(u0, u1, dt_k, motion, B)
        q_scale = noise_scale(dt_k, motion, T0) if motion == MOTION_UNICYCLE else 1.0
        predict_members(X, Pm, Qu_m, terms, q_scale)
        first = scan_start[k]  # this stamp's landmarks first .. last - 1: one scan
        last = scan_start[k + 1]
        if last == first and record_at[k] and j < n_rows:
            # the predicted mixture is read only by a record without a scan (a scan mixes
            # again, before its health check and its record)
            mix_moments_at(w, active, n_active, X, Pm, X[most_probable(logw), 2], xm, Pmix)
        if last > first:
            best = most_probable(logw)
            before_nis = nis_m[best]
            before_upd = n_upd[best]
            before_rej = n_rej[best]
            for m in range(first, last):
                z0 = scan_z[m, 0]
                z1 = scan_z[m, 1]
                for i in range(M):
                    x = (X[i, 0], X[i, 1], X[i, 2])
                    P = (
                        Pm[i, 0], Pm[i, 1], Pm[i, 2], Pm[i, 3], Pm[i, 4], Pm[i, 5], Pm[i, 6],
                        Pm[i, 7], Pm[i, 8],
                    )  # fmt: skip
                    R = (R_m[i, 0], 0.0, 0.0, R_m[i, 1])
                    H, zh, nu, HPHt = innovation(x, P, scan_lm[m, 0], scan_lm[m, 1], z0, z1)
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
                    logw[i] += innovation_loglik(
                        v, HPHt[0] + R[0], HPHt[1] + R[1], HPHt[2] + R[2], HPHt[3] + R[3],
                        censor_at,
                    )  # fmt: skip
            nis_sum += nis_m[best] - before_nis
            n_updates += n_upd[best] - before_upd
            n_rejected += n_rej[best] - before_rej
            n_active, ok = end_scan(
                logw, log_floor, threshold, imm, p_stay, X, Pm, R_m, Qu_m, w, active, Rw, Qw, xm,
                Pmix, scratch,
            )  # fmt: skip
            if not ok:
                return True, j, nis_sum, n_updates, n_rejected
        if record_at[k] and j < n_rows:
            R4 = (Rw[0], 0.0, 0.0, Rw[1])
            j, bad = record(j, xm, Pmix, R4, (Qw[0], 0.0, 0.0, Qw[1]), out_x, out_P, out_R, out_Q)
            bad_record = bad_record or bad
    return bad_record, j, nis_sum, n_updates, n_rejected
