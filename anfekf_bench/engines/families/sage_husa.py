"""Fading-memory Sage-Husa on the fast engine's loop (`engines/loop.py`): the hooks of
filterpy_engine.run_filter with filters.sage_husa.SageHusaEKF. R per landmark before its gain
(the scan's samples pooled, `r_sample`, `fading_mean`), Qu (adapt_Q) at the end of a scan from
the correction and the interval's accumulators (`q_sample`), d_k (`next_beta`) once per scan
that fed adaptation, the estimates in force after `warmup` events.
"""

from __future__ import annotations

import collections

import numpy as np

from ...filters.adaptive import clip_to_bounds
from ...filters.sage_husa import SageHusaSpec, fading_mean, next_beta, q_sample, r_sample
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
feeds_adaptation, interval_step, qu_estimate, as_matrix, wrap = (
    _k.feeds_adaptation, _k.interval_step, _k.qu_estimate, _k.as_matrix, _k.wrap,
)  # fmt: skip
ZERO9, EYE9 = _k.ZERO9, _k.EYE9

Params = collections.namedtuple("Params", "adaptation from_all lo hi adapt_Q b warmup unbiased")


def params(spec: SageHusaSpec, ctx) -> Params:
    return Params(
        bool(spec.adaptation), spec.adapt_from == "all", *(float(b) for b in spec.bounds),
        "Q" in spec.adapt, float(spec.b), int(spec.warmup), spec.q_sample == "unbiased",
    )  # fmt: skip


def qu_sample(x, x_prior, P, P_scan_start, F_scan, A_v, A_g, unbiased):
    """SageHusaEKF._adapt_Qu's sample before the bounds: the scan's Q sample (`q_sample`, dx the
    correction x - x_prior, heading wrapped) mapped to (qv, qg); (ok, (qv, qg)) as
    `kernels.qu_estimate`. P, P_scan_start, F_scan, A_v, A_g row-major 9-tuples."""
    dx = np.array([x[0] - x_prior[0], x[1] - x_prior[1], wrap(x[2] - x_prior[2])])
    Q_hat = q_sample(dx, as_matrix(P), as_matrix(P_scan_start), as_matrix(F_scan), unbiased)
    return qu_estimate(Q_hat, A_v, A_g, P)


def start(fam, x, P, Qu, R, scan_start):
    # the start's noise (the bounds' reference); (beta, events); the estimates R_hat, Qu_hat;
    # the interval (A_v, A_g, F_scan, P at its start); the scan (d, R_hat at its start, x-,
    # the sums of R samples, landmarks fed, landmarks fused)
    return (
        (R[0], R[3], Qu[0], Qu[3]), (1.0, 0), (R[0], R[3], Qu[0], Qu[3]),
        (ZERO9, ZERO9, EYE9, P), (1.0, R[0], R[3], x, 0.0, 0.0, 0, 0),
    )  # fmt: skip


def predicted(fam, st, f02, f12, G, c, Q):
    if not fam.adapt_Q:  # AdaptiveEKF.predict's interval accumulators
        return st
    start0, events, hat, interval, scan = st
    A_v, A_g, F_scan = interval_step(interval[0], interval[1], interval[2], f02, f12, G, c)
    return start0, events, hat, (A_v, A_g, F_scan, interval[3]), scan


def begin_scan(fam, st, x, P, R, Qu):  # SageHusaEKF.begin_scan
    start0, events, hat, interval, _ = st
    return (start0, events, hat, interval, (events[0], hat[0], hat[1], x, 0.0, 0.0, 0, 0)), R


def before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    if not fam.adaptation:
        return True, st, P, R, Qu, HPHt
    ok, feeds = feeds_adaptation(HPHt, R, nu, fam.from_all, gate, has_gate)
    if not ok:
        return False, st, P, R, Qu, HPHt
    if not feeds:
        return True, st, P, R, Qu, HPHt
    # SageHusaEKF.before_gain
    start0, events, hat, interval, scan = st
    d, R_start0, R_start1, x_prior, rho_sum0, rho_sum1, n_fed, n_accepted = scan
    rho_sum0 = rho_sum0 + r_sample(nu[0], HPHt[0], fam.lo * start0[0], fam.hi * start0[0])
    rho_sum1 = rho_sum1 + r_sample(nu[1], HPHt[3], fam.lo * start0[1], fam.hi * start0[1])
    n_fed += 1
    R_hat0 = fading_mean(d, R_start0, rho_sum0, n_fed)
    R_hat1 = fading_mean(d, R_start1, rho_sum1, n_fed)
    if events[1] >= fam.warmup:
        bounds = (fam.lo, fam.hi)
        R = (
            clip_to_bounds(R_hat0, start0[0], bounds), 0.0,
            0.0, clip_to_bounds(R_hat1, start0[1], bounds),
        )  # fmt: skip
    scan = (d, R_start0, R_start1, x_prior, rho_sum0, rho_sum1, n_fed, n_accepted)
    return True, (start0, events, (R_hat0, R_hat1, hat[2], hat[3]), interval, scan), P, R, Qu, HPHt


def corrected(fam, st, x_prior, P_prior, x, P, R, H, lm, z):
    start0, events, hat, interval, scan = st
    d, R_start0, R_start1, x_scan, rho_sum0, rho_sum1, n_fed, n_accepted = scan
    scan = (d, R_start0, R_start1, x_scan, rho_sum0, rho_sum1, n_fed, n_accepted + 1)
    return (start0, events, hat, interval, scan), R


def end_scan(fam, st, x, P, R, Qu):  # SageHusaEKF.end_scan
    start0, events, hat, interval, scan = st
    d, _, _, x_prior, _, _, n_fed, n_accepted = scan
    if fam.adapt_Q:
        if fam.adaptation and n_fed > 0 and n_accepted > 0:
            A_v, A_g, F_scan, P_scan_start = interval
            ok, q = qu_sample(x, x_prior, P, P_scan_start, F_scan, A_v, A_g, fam.unbiased)
            if not ok:
                return False, st, R, Qu
            bounds = (fam.lo, fam.hi)
            Qu_hat0 = fading_mean(d, hat[2], clip_to_bounds(q[0], start0[2], bounds), 1)
            Qu_hat1 = fading_mean(d, hat[3], clip_to_bounds(q[1], start0[3], bounds), 1)
            hat = (hat[0], hat[1], Qu_hat0, Qu_hat1)
            if events[1] >= fam.warmup:
                Qu = (
                    clip_to_bounds(Qu_hat0, start0[2], bounds), 0.0,
                    0.0, clip_to_bounds(Qu_hat1, start0[3], bounds),
                )  # fmt: skip
        interval = (ZERO9, ZERO9, EYE9, P)
    if n_fed > 0:
        events = (next_beta(events[0], fam.b), events[1] + 1)
    return True, (start0, events, hat, interval, scan), R, Qu
