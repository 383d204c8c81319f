"""Akhlaghi et al.'s residual-based R and innovation-based Qu on the fast engine's loop
(`engines/loop.py`): the hooks of filterpy_engine.run_filter with
filters.akhlaghi.AkhlaghiEKF. After every landmark update (and, with adapt_from all, the update
a gate-rejected landmark would have made) the residual sample feeds R (eq. 11, the scan's mean,
forgotten once per scan) and the correction x+ - x- the scan's dx; at the end of the scan Qu
from eq. (15) through the interval's accumulators.
"""

from __future__ import annotations

import collections

import numpy as np

from ...filters.adaptive import clip_to_bounds
from ...filters.akhlaghi import (
    AkhlaghiSpec,
    forget,
    residual_variance,
    state_noise_estimate,
)  # fmt: skip
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
interval_step, qu_estimate, as_matrix, wrap, correct, innovation, hph_diag = (
    _k.interval_step, _k.qu_estimate, _k.as_matrix, _k.wrap, _k.correct, _k.innovation,
    _k.hph_diag,
)  # fmt: skip
ZERO9, EYE9 = _k.ZERO9, _k.EYE9

Params = collections.namedtuple("Params", "adapt_R adapt_Q adaptation from_all floor ceiling alpha")


def params(spec: AkhlaghiSpec, ctx) -> Params:
    return Params(
        "R" in spec.adapt, "Q" in spec.adapt, bool(spec.adaptation), spec.adapt_from == "all",
        float(spec.bounds[0]), float(spec.bounds[1]), float(spec.alpha),
    )  # fmt: skip


def qu_sample(Qu, A_v, A_g, P, dx0, dx1, dx2, alpha):
    """AkhlaghiEKF.adapt_Q before the bounds: eq. (15) on the interval (Q_scan = qv A_v + qg A_g,
    the scan's correction dx) mapped to (qv, qg); (ok, (qv, qg)) as `kernels.qu_estimate`."""
    Q_scan = Qu[0] * as_matrix(A_v) + Qu[3] * as_matrix(A_g)
    Q_hat = state_noise_estimate(Q_scan, np.array([dx0, dx1, dx2]), alpha)
    return qu_estimate(Q_hat, A_v, A_g, P)


def start(fam, x, P, Qu, R, scan_start):
    # the start's noise; the interval's accumulators (A_v, A_g, F_scan); the scan (R_(k-1) of
    # eq. 11, the sums of residual samples and their count, the correction dx, whether fed)
    return (R[0], R[3], Qu[0], Qu[3]), (ZERO9, ZERO9, EYE9), _scan(R)


def _scan(R):
    return R[0], R[3], 0.0, 0.0, 0, 0.0, 0.0, 0.0, False


def predicted(fam, st, f02, f12, G, c, Q):
    if not fam.adapt_Q:  # AdaptiveEKF.predict's interval accumulators
        return st
    start0, interval, scan = st
    return start0, interval_step(interval[0], interval[1], interval[2], f02, f12, G, c), scan


def begin_scan(fam, st, x, P, R, Qu):
    return (st[0], st[1], _scan(R)), R


def feed(fam, start0, scan, x_prior, xp, Pp, R, H, lm, z):
    """One landmark's samples: the residual at the update (xp, Pp) for R, x+ - x- for dx; the
    scan's part of the state and R (only that part passes through the call, not the interval's
    27 floats)."""
    Rs0, Rs1, sum0, sum1, n_samples, dx0, dx1, dx2, _ = scan
    _, _, e, _ = innovation(xp, Pp, lm[0], lm[1], z[0], z[1])
    hph0, hph1 = hph_diag(H, Pp)
    if fam.adapt_R:
        sum0 += residual_variance(e[0], hph0)
        sum1 += residual_variance(e[1], hph1)
        n_samples += 1
    dx0 += xp[0] - x_prior[0]
    dx1 += xp[1] - x_prior[1]
    dx2 += wrap(xp[2] - x_prior[2])
    if fam.adapt_R:
        bounds = (fam.floor, fam.ceiling)
        R = (
            clip_to_bounds(forget(Rs0, sum0 / n_samples, fam.alpha), start0[0], bounds),
            0.0, 0.0,
            clip_to_bounds(forget(Rs1, sum1 / n_samples, fam.alpha), start0[1], bounds),
        )  # fmt: skip
    return (Rs0, Rs1, sum0, sum1, n_samples, dx0, dx1, dx2, True), R


def rejected(fam, st, x, P, R, H, zh, lm, z):
    # a rejected landmark feeds through the update it would have made (nothing changes x, P or
    # R before the class settles it at the next landmark)
    if not (fam.adaptation and fam.from_all):
        return True, st, P, R
    ok, xp, Pp = correct(x, P, H, zh, z[0], z[1], R)
    if not ok:
        return False, st, P, R
    scan, R = feed(fam, st[0], st[2], x, xp, Pp, R, H, lm, z)
    return True, (st[0], st[1], scan), P, R


def corrected(fam, st, x_prior, P_prior, x, P, R, H, lm, z):
    if not fam.adaptation:
        return st, R
    scan, R = feed(fam, st[0], st[2], x_prior, x, P, R, H, lm, z)
    return (st[0], st[1], scan), R


def end_scan(fam, st, x, P, R, Qu):
    start0, interval, scan = st
    if fam.adaptation and fam.adapt_Q and scan[8]:
        A_v, A_g, _ = interval
        ok, q = qu_sample(Qu, A_v, A_g, P, scan[5], scan[6], scan[7], fam.alpha)
        if not ok:
            return False, st, R, Qu
        bounds = (fam.floor, fam.ceiling)
        Qu = (
            clip_to_bounds(q[0], start0[2], bounds), 0.0,
            0.0, clip_to_bounds(q[1], start0[3], bounds),
        )  # fmt: skip
        interval = (ZERO9, ZERO9, EYE9)
    return True, (start0, interval, scan), R, Qu
