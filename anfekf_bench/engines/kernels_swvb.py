"""The fast engine's kernel of `swvb` (filters/swvb.py): the sliding-window VB on Qu and R, its
rules as written there (numpy on 3 x 3 arrays, compiled as they are), on kernels.py's
primitives. Not on the one loop (`engines/loop.py`): every scan runs `iterations` passes of its
sequential updates from the same x-, where the loop runs each landmark once.

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
numba's disk cache of the kernel is stamped with every source it reaches (filters/swvb.py
included: compiled.use_reached_sources_stamp), so an edited rule compiles it anew.
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import swvb as _swvb
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
jacobians, noise_scale, predict_with, interval_step = (
    _k.jacobians, _k.noise_scale, _k.predict_with, _k.interval_step,
)  # fmt: skip
innovation, nis, correct, healthy, record, wrap = (
    _k.innovation, _k.nis, _k.correct, _k.healthy, _k.record, _k.wrap,
)  # fmt: skip
stamp_input, NO_TALLY = _k.stamp_input, _k.NO_TALLY
as_matrix, matmul, inv, qu_least_squares, clip_to_bounds = (
    _k.as_matrix, _k.matmul, _k.inv, _k.qu_least_squares, _k.clip_to_bounds,
)  # fmt: skip
ZERO9, EYE9 = _k.ZERO9, _k.EYE9


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


interval_prior, process_noise_moment = _k.jitable(_swvb.interval_prior, _swvb.process_noise_moment)


@maybe_njit
def flat9(A):
    """A 3 x 3 array as a row-major 9-tuple."""
    return (
        A[0, 0], A[0, 1], A[0, 2], A[1, 0], A[1, 1], A[1, 2], A[2, 0], A[2, 1], A[2, 2],
    )  # fmt: skip


@maybe_njit
def swvb_interval(P_s, F_s, A_v, A_g):
    """What the rules read of the interval, the same over a scan's passes, as 3 x 3 arrays:
    (F_s P_s F_s^T, A_v, A_g) from row-major 9-tuples."""
    F = as_matrix(F_s)
    return matmul(matmul(F, as_matrix(P_s)), F.T), as_matrix(A_v), as_matrix(A_g)


@maybe_njit
def swvb_interval_prior(interval, qv, qg):
    """`interval_prior` of `swvb_interval`'s arrays, as a row-major 9-tuple and as the array."""
    FPF, A_v, A_g = interval
    P_m = interval_prior(FPF, A_v, A_g, qv, qg)
    return flat9(P_m), P_m


@maybe_njit
def swvb_qu_sample(x, x_m, P, P_m_a, interval):
    """A pass's sample of diag(Qu) in SWVBEKF.update_scan, not clipped: the smoother's moment
    (`process_noise_moment`, dx = x - x_m with its heading wrapped) mapped to (qv, qg) with the
    weight P_m^-1; (ok, (qv, qg)), ok False where P_m is singular or not finite (LinAlgError:
    the filter diverged). x, x_m 3-tuples, P a row-major 9-tuple, P_m_a the 3 x 3 array,
    `interval` the arrays of `swvb_interval`."""
    FPF, A_v, A_g = interval
    dx = np.array([x[0] - x_m[0], x[1] - x_m[1], wrap(x[2] - x_m[2])])
    try:
        P_m_inv = inv(P_m_a)
        W = process_noise_moment(dx, FPF, P_m_inv, as_matrix(P))
        q = qu_least_squares(W, A_v, A_g, P_m_inv)
    except Exception:  # numba catches no narrower class
        return False, (0.0, 0.0)
    return True, (q[0], q[1])


@maybe_njit
def run_swvb_kernel(
    u_odo, dt, scan_start, scan_lm, scan_z,
    motion, B, T0, x0, P0, Qu0, R0, gate, has_gate,
    adaptation, from_all, floor, ceiling, rho, iterations, a0,
    record_at, out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """filterpy_engine.run_filter with filters.swvb.SWVBEKF: per scan with a landmark and
    adaptation, `iterations` passes of the scan's sequential EKF updates from the same x-, the
    first from the filter's P-, the others from the interval's prior with the last Qu estimate;
    after each pass the lag-one smoother's process-noise moment gives Qu, the posterior's
    residuals R (SWVBEKF.update_scan). Returns as `run_kernel`."""
    K = u_odo.shape[0]
    x = (x0[0], x0[1], x0[2])
    P = (P0[0], P0[1], P0[2], P0[3], P0[4], P0[5], P0[6], P0[7], P0[8])
    Qu = (Qu0[0], Qu0[1], Qu0[2], Qu0[3])
    R = (R0[0], R0[1], R0[2], R0[3])
    bounds = (floor, ceiling)
    # the inverse-gamma posteriors (a, b) of qv, qg, R_range, R_bearing, each channel a float
    a_q0 = a0
    a_q1 = a0
    b_q0 = a0 * Qu0[0]
    b_q1 = a0 * Qu0[3]
    a_r0 = a0
    a_r1 = a0
    b_r0 = a0 * R0[0]
    b_r1 = a0 * R0[3]
    A_v = ZERO9  # the interval's accumulators (filters.adaptive.AdaptiveEKF), row-major
    A_g = ZERO9
    F_scan = EYE9
    P_s = P  # P+ at the previous Q event
    fed = np.zeros(max(scan_lm.shape[0], 1), np.bool_)
    bad_record, j, nis_sum, n_updates, n_rejected = NO_TALLY
    n_rows = out_x.shape[0]
    for k in range(K):
        u0, u1, dt_k = stamp_input(u_odo, dt, k)
        f02, f12, G = jacobians(x[2], u0, u1, dt_k, motion, B)  # F, G before the predict
        A_v, A_g, F_scan = interval_step(
            A_v, A_g, F_scan, f02, f12, G, noise_scale(dt_k, motion, T0)
        )
        x, P, Q = predict_with(x, P, f02, f12, G, u0, u1, dt_k, motion, B, T0, Qu)
        first = scan_start[k]  # this stamp's landmarks first .. last - 1: one scan
        last = scan_start[k + 1]
        if last > first:
            passes = iterations if adaptation else 1
            if adaptation:
                a_q0 = rho * a_q0
                a_q1 = rho * a_q1
                b_q0 = rho * b_q0
                b_q1 = rho * b_q1
                a_r0 = rho * a_r0
                a_r1 = rho * a_r1
                b_r0 = rho * b_r0
                b_r1 = rho * b_r1
            x_m = x
            P_m = P
            counts = (nis_sum, n_updates, n_rejected)
            qu0 = Qu[0]
            qu1 = Qu[3]
            r0 = R[0]
            r1 = R[3]
            b_q0_n = b_q0
            b_q1_n = b_q1
            a_r0_n = a_r0
            a_r1_n = a_r1
            b_r0_n = b_r0
            b_r1_n = b_r1
            interval = swvb_interval(P_s, F_scan, A_v, A_g)
            P_m_a = as_matrix(P_m)
            for n in range(passes):
                if n > 0:
                    P_m, P_m_a = swvb_interval_prior(interval, qu0, qu1)
                x = x_m
                P = P_m
                if adaptation:
                    R = (r0, 0.0, 0.0, r1)
                nis_sum, n_updates, n_rejected = counts
                for m in range(first, last):
                    z0 = scan_z[m, 0]
                    z1 = scan_z[m, 1]
                    H, zh, nu, HPHt = innovation(x, P, scan_lm[m, 0], scan_lm[m, 1], z0, z1)
                    ok, v = nis(HPHt, R, nu[0], nu[1])
                    if not ok or not math.isfinite(v):
                        return True, j, nis_sum, n_updates, n_rejected
                    fed[m - first] = from_all or not has_gate or v <= gate
                    if has_gate and not v <= gate:
                        n_rejected += 1
                        continue
                    nis_sum += v
                    n_updates += 1
                    ok, x, P = correct(x, P, H, zh, z0, z1, R)
                    if not ok:
                        return True, j, nis_sum, n_updates, n_rejected
                if not adaptation:
                    break
                ok, q = swvb_qu_sample(x, x_m, P, P_m_a, interval)
                if not ok:
                    return True, j, nis_sum, n_updates, n_rejected
                b_q0_n = b_q0 + 0.5 * clip_to_bounds(q[0], Qu0[0], bounds)
                b_q1_n = b_q1 + 0.5 * clip_to_bounds(q[1], Qu0[3], bounds)
                qu0 = clip_to_bounds(b_q0_n / (a_q0 + 0.5), Qu0[0], bounds)
                qu1 = clip_to_bounds(b_q1_n / (a_q1 + 0.5), Qu0[3], bounds)
                a_r0_n = a_r0
                a_r1_n = a_r1
                b_r0_n = b_r0
                b_r1_n = b_r1
                n_fed = 0
                s0 = 0.0
                s1 = 0.0
                for m in range(first, last):  # swvb.r_moment at the posterior
                    if fed[m - first]:
                        n_fed += 1
                        _, _, e, HPH = innovation(
                            x, P, scan_lm[m, 0], scan_lm[m, 1], scan_z[m, 0], scan_z[m, 1]
                        )  # fmt: skip
                        s0 = s0 + e[0] * e[0] + HPH[0]
                        s1 = s1 + e[1] * e[1] + HPH[3]
                if n_fed > 0:
                    a_r0_n = a_r0 + 0.5 * n_fed
                    a_r1_n = a_r1 + 0.5 * n_fed
                    b_r0_n = b_r0 + 0.5 * s0
                    b_r1_n = b_r1 + 0.5 * s1
                r0 = clip_to_bounds(b_r0_n / a_r0_n, R0[0], bounds)
                r1 = clip_to_bounds(b_r1_n / a_r1_n, R0[3], bounds)
            if adaptation:
                a_q0 = a_q0 + 0.5
                a_q1 = a_q1 + 0.5
                b_q0 = b_q0_n
                b_q1 = b_q1_n
                a_r0 = a_r0_n
                a_r1 = a_r1_n
                b_r0 = b_r0_n
                b_r1 = b_r1_n
                Qu = (qu0, 0.0, 0.0, qu1)
                R = (r0, 0.0, 0.0, r1)
                A_v = ZERO9
                A_g = ZERO9
                F_scan = EYE9
                P_s = P
            if not healthy(x, P, R, Qu):
                return True, j, nis_sum, n_updates, n_rejected
        if record_at[k] and j < n_rows:
            j, bad = record(j, x, P, R, Qu, out_x, out_P, out_R, out_Q)
            bad_record = bad_record or bad
    return bad_record, j, nis_sum, n_updates, n_rejected
