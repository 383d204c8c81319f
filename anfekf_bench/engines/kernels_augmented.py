"""The fast engine's kernel of `ekf-aug` (filters/augmented.py): the EKF on the pose plus the
odometry's scale factors, turn bias and range bias (those estimated).

The state has 3 + m entries (m estimated parameters), so the kernel works on small numpy arrays
with loops rather than kernels.py's fixed 3-state tuples; the motion models are kernels.py's
(`jacobians`, `noise_scale`: both models, the motion an argument). The arithmetic is
`AugmentedEKF`'s: the corrected controls (`filters.augmented.true_controls`, its scale floor),
F and Q of the augmented step, filterpy's Joseph-form update, the heading wrapped and P
symmetrised; it agrees with the filterpy engine to round-off (the products are summed in
another order), which tests/test_augmented.py and the equivalence test check to 1e-9.

`pure_module()` gives a never-compiled copy. numba's disk cache is keyed on THIS file.
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import augmented as _aug
from ..filters import sage_husa as _sh
from ..filters import vb as _vb
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT
maybe_njit = _k.maybe_njit
jacobians = _k.jacobians
noise_scale = _k.noise_scale
wrap = _k.wrap
feeds_adaptation = _k.feeds_adaptation
stamp_input, NO_TALLY = _k.stamp_input, _k.NO_TALLY
MOTION_BICYCLE, MOTION_UNICYCLE = _k.MOTION_BICYCLE, _k.MOTION_UNICYCLE

true_controls, control_derivative = _k.jitable(_aug.true_controls, _aug.control_derivative)
clip_to_bounds = _k.clip_to_bounds
r_sample, fading_mean, next_beta = _k.r_sample, _k.fading_mean, _k.next_beta
vb_r_predict, vb_r_beta, vb_r_bounded_beta = _k.vb_r_predict, _k.vb_r_beta, _k.vb_r_bounded_beta

# The R rule the state is combined with (`augment:` on an adaptive family's spec), and the
# layout of its parameters `rp` (float64, 8): rule, adaptation, adapt_from all, floor,
# ceiling, then Sage-Husa's b, warmup or VB-R's rho, iterations, alpha0.
RULE_NONE, RULE_SAGE_HUSA, RULE_VB_R = 0, 1, 2


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


@maybe_njit
def _positive_definite(P):
    """numpy's Cholesky succeeds (the lower triangle read), every entry finite."""
    n = P.shape[0]
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            s = P[i, j]
            for c in range(j):
                s -= L[i, c] * L[j, c]
            if i == j:
                if not s > 0.0:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@maybe_njit
def _healthy(x, P, R, Qu):
    for v in x:
        if not math.isfinite(v):
            return False
    for v in P.ravel():
        if not math.isfinite(v):
            return False
    if not _positive_definite(P):
        return False
    return R[0] > 0.0 and R[3] > 0.0 and Qu[0] > 0.0 and Qu[3] > 0.0


@maybe_njit
def _parameters(x, theta0, est):
    theta = theta0.copy()
    for i in range(est.shape[0]):
        theta[est[i]] = x[3 + i]
    return theta


# -- the R rules on the augmented state (filters.sage_husa.SageHusaEKF, filters.vb.VBREKF with
# filters.augmented.AugmentedState first in their method order); their state `rs` (float64,
# 12): Sage-Husa: beta, events, d, R at the scan's start (2), sums of samples (2), landmarks
# fed, R_hat (2); VB-R: alpha (2), beta (2). R (4, row-major) is changed in place.


@maybe_njit
def rule_start(rp, R):
    rs = np.zeros(12)
    if rp[0] == RULE_SAGE_HUSA:
        rs[0] = 1.0
        rs[8] = R[0]
        rs[9] = R[3]
    elif rp[0] == RULE_VB_R:
        rs[0] = rp[7]
        rs[1] = rp[7]
        rs[2] = rp[7] * R[0]
        rs[3] = rp[7] * R[3]
    return rs


@maybe_njit
def rule_begin_scan(rp, rs):
    if rp[0] == RULE_SAGE_HUSA:  # SageHusaEKF.begin_scan
        rs[2] = rs[0]
        rs[3] = rs[8]
        rs[4] = rs[9]
        rs[5] = 0.0
        rs[6] = 0.0
        rs[7] = 0.0
    elif rp[0] == RULE_VB_R and rp[1] != 0.0:  # VBREKF.begin_scan
        rs[0], rs[2] = vb_r_predict(rs[0], rs[2], rp[5])
        rs[1], rs[3] = vb_r_predict(rs[1], rs[3], rp[5])


@maybe_njit
def _joseph(x, P, nu0, nu1, H, r0, r1):
    """filters.vb.kalman_update with R = diag(r0, r1): (ok, x+, P+) on the augmented state."""
    n = x.shape[0]
    PHt = P @ H.T
    S = H @ PHt
    s00 = S[0, 0] + r0
    s01 = S[0, 1]
    s10 = S[1, 0]
    s11 = S[1, 1] + r1
    det = s00 * s11 - s01 * s10
    if det == 0.0 or not math.isfinite(det):
        return False, x, P
    Kg = np.empty((n, 2))
    for i in range(n):
        Kg[i, 0] = (PHt[i, 0] * s11 - PHt[i, 1] * s10) / det
        Kg[i, 1] = (-PHt[i, 0] * s01 + PHt[i, 1] * s00) / det
    xn = x.copy()
    for i in range(n):
        xn[i] = x[i] + Kg[i, 0] * nu0 + Kg[i, 1] * nu1
    A = np.eye(n) - Kg @ H
    KR = np.empty((n, 2))
    for i in range(n):
        KR[i, 0] = Kg[i, 0] * r0
        KR[i, 1] = Kg[i, 1] * r1
    return True, xn, A @ P @ A.T + KR @ Kg.T


@maybe_njit
def _residual(x, lm0, lm1, z0, z1, range_col, range_bias0):
    """wrap(z - h(x)) at an augmented iterate (AugmentedState.residual_of)."""
    dx = lm0 - x[0]
    dy = lm1 - x[1]
    r = math.hypot(dx, dy) + (x[range_col] if range_col >= 0 else range_bias0)
    return z0 - r, wrap(z1 - wrap(math.atan2(dy, dx) - x[2]))


@maybe_njit
def rule_before_gain(rp, rs, R, R00, R11, x, P, H, HPHt, nu0, nu1, lm0, lm1, z0, z1,
                     gate, has_gate, range_col, range_bias0):  # fmt: skip
    """The rule's before_gain: may set R; False where a matrix is singular (diverged)."""
    if rp[0] == RULE_NONE or rp[1] == 0.0:
        return True
    bounds = (rp[3], rp[4])
    hph = (HPHt[0, 0], HPHt[0, 1], HPHt[1, 0], HPHt[1, 1])
    if rp[0] == RULE_VB_R:  # VBREKF.before_gain
        R[0] = rs[2] / rs[0]
        R[1] = 0.0
        R[2] = 0.0
        R[3] = rs[3] / rs[1]
    ok, feeds = feeds_adaptation(hph, (R[0], R[1], R[2], R[3]), (nu0, nu1), rp[2] != 0.0,
                                 gate, has_gate)  # fmt: skip
    if not ok:
        return False
    if not feeds:
        return True
    if rp[0] == RULE_SAGE_HUSA:  # SageHusaEKF.before_gain
        rs[5] += r_sample(nu0, hph[0], rp[3] * R00, rp[4] * R00)
        rs[6] += r_sample(nu1, hph[3], rp[3] * R11, rp[4] * R11)
        rs[7] += 1.0
        rs[8] = fading_mean(rs[2], rs[3], rs[5], rs[7])
        rs[9] = fading_mean(rs[2], rs[4], rs[6], rs[7])
        if rs[1] >= rp[6]:
            R[0] = clip_to_bounds(rs[8], R00, bounds)
            R[1] = 0.0
            R[2] = 0.0
            R[3] = clip_to_bounds(rs[9], R11, bounds)
        return True
    # filters.vb.vb_r_update, the iterates on the augmented state
    ap0 = rs[0] + 0.5
    ap1 = rs[1] + 0.5
    bn0 = rs[2]
    bn1 = rs[3]
    for _ in range(int(rp[6])):
        R[0] = clip_to_bounds(bn0 / ap0, R00, bounds)
        R[3] = clip_to_bounds(bn1 / ap1, R11, bounds)
        ok, xn, Pn = _joseph(x, P, nu0, nu1, H, R[0], R[3])
        if not ok:
            return False
        e0, e1 = _residual(xn, lm0, lm1, z0, z1, range_col, range_bias0)
        HPn = H @ Pn
        hph0 = 0.0
        hph1 = 0.0
        for c in range(x.shape[0]):
            hph0 += HPn[0, c] * H[0, c]
            hph1 += HPn[1, c] * H[1, c]
        bn0 = vb_r_beta(rs[2], e0, hph0)
        bn1 = vb_r_beta(rs[3], e1, hph1)
    rs[0] = ap0
    rs[1] = ap1
    rs[2], rs[3] = vb_r_bounded_beta(ap0, ap1, bn0, bn1, R00, R11, rp[3], rp[4])
    return True


@maybe_njit
def rule_end_scan(rp, rs, R):
    if rp[0] == RULE_SAGE_HUSA:  # SageHusaEKF.end_scan (R only)
        if rs[7] > 0.0:
            rs[0] = next_beta(rs[0], rp[5])
            rs[1] += 1.0
    elif rp[0] == RULE_VB_R and rp[1] != 0.0:  # VBREKF.end_scan
        R[0] = rs[2] / rs[0]
        R[1] = 0.0
        R[2] = 0.0
        R[3] = rs[3] / rs[1]


@maybe_njit
def run_augmented_kernel(
    u_odo, dt, scan_start, scan_lm, scan_z,
    motion, B, T0, x0, P0, Qu, R, gate, has_gate,
    est, theta0, sigma0, drift, rp,
    record_at, out_x, out_P, out_R, out_Q, out_theta,
):  # fmt: skip
    """One `ekf-aug` over one run (filterpy_engine.run_filter with `AugmentedEKF`).

    The common head as every kernel (kernels.run_kernel); est (m,) int64: the indices of the
    estimated parameters (filters.augmented.PARAMETERS), theta0, sigma0, drift (4,): their
    start values, start standard deviations and random-walk rates; rp (8,): the R rule
    combined with the state (RULE_NONE: `ekf-aug`; `rule_start`). Records the pose block in
    out_x (n, 3), out_P (n, 3, 3), R and Qu's diagonals, and the four parameters in
    out_theta (n, 4). Returns (diverged, rows written, nis_sum, n_updates, n_rejected).
    """
    K = u_odo.shape[0]
    m = est.shape[0]
    R = R.copy()  # the rule adapts it
    R00 = R[0]
    R11 = R[3]
    rs = rule_start(rp, R)
    n = 3 + m
    x = np.zeros(n)
    P = np.zeros((n, n))
    for i in range(3):
        x[i] = x0[i]
        for c in range(3):
            P[i, c] = P0[3 * i + c]
    for i in range(m):
        x[3 + i] = theta0[est[i]]
        P[3 + i, 3 + i] = sigma0[est[i]] * sigma0[est[i]]
    q00, q01, q10, q11 = Qu[0], Qu[1], Qu[2], Qu[3]
    F = np.zeros((n, n))
    Q = np.zeros((n, n))
    H = np.zeros((2, n))
    PHt = np.zeros((n, 2))
    Kg = np.zeros((n, 2))
    A = np.zeros((n, n))
    n_rows = out_x.shape[0]
    bad_record, j, nis_sum, n_updates, n_rejected = NO_TALLY
    range_col = np.int64(-1)  # not the literal -1: numba would compile the rule for it as well
    for i in range(m):
        if est[i] == 3:
            range_col = 3 + i
    for k in range(K):
        # -- predict: the model on the corrected controls, F and Q of the augmented step
        theta = _parameters(x, theta0, est)
        u0, u1, h_dt = stamp_input(u_odo, dt, k)
        ut0, ut1, kv, kw = true_controls(u0, u1, theta)
        f02, f12, G = jacobians(x[2], ut0, ut1, h_dt, motion, B)
        g00, g01, g10, g11, g20, g21 = G
        if motion == MOTION_UNICYCLE:
            dh = ut1 * h_dt
        else:
            dh = h_dt * ut0 * math.sin(ut1) / B
        c = noise_scale(h_dt, motion, T0)
        # G diag(1 / k) and Q_pose = c (G Qu G^T)
        e00, e01 = g00 / kv, g01 / kw
        e10, e11 = g10 / kv, g11 / kw
        e20, e21 = g20 / kv, g21 / kw
        a00 = e00 * q00 + e01 * q10
        a01 = e00 * q01 + e01 * q11
        a10 = e10 * q00 + e11 * q10
        a11 = e10 * q01 + e11 * q11
        a20 = e20 * q00 + e21 * q10
        a21 = e20 * q01 + e21 * q11
        Q[:, :] = 0.0
        Q[0, 0] = c * (a00 * e00 + a01 * e01)
        Q[0, 1] = c * (a00 * e10 + a01 * e11)
        Q[0, 2] = c * (a00 * e20 + a01 * e21)
        Q[1, 0] = c * (a10 * e00 + a11 * e01)
        Q[1, 1] = c * (a10 * e10 + a11 * e11)
        Q[1, 2] = c * (a10 * e20 + a11 * e21)
        Q[2, 0] = c * (a20 * e00 + a21 * e01)
        Q[2, 1] = c * (a20 * e10 + a21 * e11)
        Q[2, 2] = c * (a20 * e20 + a21 * e21)
        F[:, :] = 0.0
        for i in range(n):
            F[i, i] = 1.0
        F[0, 2] = f02
        F[1, 2] = f12
        for i in range(m):
            d0, d1 = control_derivative(est[i], ut0, ut1, kv, kw)
            F[0, 3 + i] = g00 * d0 + g01 * d1
            F[1, 3 + i] = g10 * d0 + g11 * d1
            F[2, 3 + i] = g20 * d0 + g21 * d1
            Q[3 + i, 3 + i] = drift[est[i]] * drift[est[i]] * h_dt
        x[0] = x[0] + f12
        x[1] = x[1] - f02
        x[2] = wrap(x[2] + dh)
        P = F @ P @ F.T + Q
        # -- the stamp's landmarks, one scan
        first = scan_start[k]
        last = scan_start[k + 1]
        if last > first:
            rule_begin_scan(rp, rs)
            for mm in range(first, last):
                z0 = scan_z[mm, 0]
                z1 = scan_z[mm, 1]
                dx = scan_lm[mm, 0] - x[0]
                dy = scan_lm[mm, 1] - x[1]
                q = dx * dx + dy * dy
                r = math.sqrt(q)
                H[:, :] = 0.0
                H[0, 0] = -dx / r
                H[0, 1] = -dy / r
                H[1, 0] = dy / q
                H[1, 1] = -dx / q
                H[1, 2] = -1.0
                zh0 = math.hypot(dx, dy)
                if range_col >= 0:
                    H[0, range_col] = 1.0
                    zh0 += x[range_col]
                else:
                    zh0 += theta0[3]
                zh1 = wrap(math.atan2(dy, dx) - x[2])
                nu0 = z0 - zh0
                nu1 = wrap(z1 - zh1)
                PHt[:, :] = P @ H.T
                S = H @ PHt
                if not rule_before_gain(
                    rp, rs, R, R00, R11, x, P, H, S, nu0, nu1, scan_lm[mm, 0], scan_lm[mm, 1],
                    z0, z1, gate, has_gate, range_col, theta0[3],
                ):  # fmt: skip
                    return True, j, nis_sum, n_updates, n_rejected
                s00 = S[0, 0] + R[0]
                s01 = S[0, 1] + R[1]
                s10 = S[1, 0] + R[2]
                s11 = S[1, 1] + R[3]
                det = s00 * s11 - s01 * s10
                if det == 0.0 or not math.isfinite(det):
                    return True, j, nis_sum, n_updates, n_rejected
                i00 = s11 / det
                i01 = -s01 / det
                i10 = -s10 / det
                i11 = s00 / det
                v = nu0 * (i00 * nu0 + i01 * nu1) + nu1 * (i10 * nu0 + i11 * nu1)
                if not math.isfinite(v):
                    return True, j, nis_sum, n_updates, n_rejected
                if has_gate and not v <= gate:
                    n_rejected += 1
                    continue
                nis_sum += v
                n_updates += 1
                for i in range(n):
                    Kg[i, 0] = PHt[i, 0] * i00 + PHt[i, 1] * i10
                    Kg[i, 1] = PHt[i, 0] * i01 + PHt[i, 1] * i11
                for i in range(n):
                    x[i] = x[i] + (Kg[i, 0] * nu0 + Kg[i, 1] * nu1)
                A[:, :] = 0.0
                for i in range(n):
                    A[i, i] = 1.0
                A -= Kg @ H
                KR = np.empty((n, 2))
                for i in range(n):
                    KR[i, 0] = Kg[i, 0] * R[0] + Kg[i, 1] * R[2]
                    KR[i, 1] = Kg[i, 0] * R[1] + Kg[i, 1] * R[3]
                P = A @ P @ A.T + KR @ Kg.T
                P = 0.5 * (P + P.T)
                x[2] = wrap(x[2])
            rule_end_scan(rp, rs, R)
            if not _healthy(x, P, R, Qu):
                return True, j, nis_sum, n_updates, n_rejected
        if record_at[k] and j < n_rows:
            theta = _parameters(x, theta0, est)
            bad = False
            for i in range(3):
                out_x[j, i] = x[i]
                bad = bad or not math.isfinite(x[i])
                for c2 in range(3):
                    out_P[j, i, c2] = P[i, c2]
                    bad = bad or not math.isfinite(P[i, c2])
            for i in range(4):
                out_theta[j, i] = theta[i]
            out_R[j, 0] = R[0]
            out_R[j, 1] = R[3]
            out_Q[j, 0] = Qu[0]
            out_Q[j, 1] = Qu[3]
            bad_record = bad_record or bad
            j += 1
    return bad_record, j, nis_sum, n_updates, n_rejected


def rule_params(spec) -> np.ndarray:
    """`rp` of `run_augmented_kernel` for a spec: `ekf-aug`'s (no rule) or an adaptive family's
    with `augment:` (Sage-Husa R, VB-R)."""
    rp = np.zeros(8)
    if isinstance(spec, _aug.AugmentedSpec):
        return rp
    rp[1:5] = (bool(spec.adaptation), spec.adapt_from == "all", *spec.bounds)
    if isinstance(spec, _sh.SageHusaSpec):
        rp[0], rp[5], rp[6] = RULE_SAGE_HUSA, spec.b, spec.warmup
    elif isinstance(spec, _vb.VBRSpec):
        rp[0], rp[5], rp[6], rp[7] = RULE_VB_R, spec.rho, spec.iterations, spec.alpha0
    else:
        raise ValueError(f"the fast engine does not combine {type(spec).__name__} with augment")
    return rp
