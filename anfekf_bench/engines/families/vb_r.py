"""Sarkka & Nummenmaa's VB-AKF on diag R on the fast engine's loop (`engines/loop.py`): the
hooks of filterpy_engine.run_filter with filters.vb.VBREKF. Per scan with a landmark the
forgetting of (alpha, beta) (`vb_r_predict`); per landmark that feeds adaptation `iterations`
EKF updates from the same (x-, P-) with R = clip(beta / alpha) (`vb_r_beta`), then the filter's
own gate and update with the last iteration's R; between scans R is beta / alpha.
"""

from __future__ import annotations

import collections

from ...filters.adaptive import clip_to_bounds
from ...filters.vb import VBRSpec, vb_r_beta, vb_r_bounded_beta, vb_r_predict
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
feeds_adaptation, correct, innovation, hph_diag = (
    _k.feeds_adaptation, _k.correct, _k.innovation, _k.hph_diag,
)  # fmt: skip

Params = collections.namedtuple("Params", "adaptation from_all floor ceiling rho iterations alpha0")


def params(spec: VBRSpec, ctx) -> Params:
    return Params(
        bool(spec.adaptation), spec.adapt_from == "all", float(spec.bounds[0]),
        float(spec.bounds[1]), float(spec.rho), int(spec.iterations), float(spec.alpha0),
    )  # fmt: skip


def start(fam, x, P, Qu, R, scan_start):
    # (alpha, beta) of range and bearing, R0's diagonal (the bounds' reference)
    a = fam.alpha0
    return a, a, a * R[0], a * R[3], R[0], R[3]


def begin_scan(fam, st, x, P, R, Qu):
    if not fam.adaptation:
        return st, R
    a0, a1, b0, b1, R00, R11 = st
    a0, b0 = vb_r_predict(a0, b0, fam.rho)
    a1, b1 = vb_r_predict(a1, b1, fam.rho)
    return (a0, a1, b0, b1, R00, R11), R


def before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    if not fam.adaptation:
        return True, st, P, R, Qu, HPHt
    a0, a1, b0, b1, R00, R11 = st
    R = (b0 / a0, 0.0, 0.0, b1 / a1)  # the posterior estimate
    ok, feeds = feeds_adaptation(HPHt, R, nu, fam.from_all, gate, has_gate)
    if not ok:
        return False, st, P, R, Qu, HPHt
    if feeds:  # filters.vb.vb_r_update
        bounds = (fam.floor, fam.ceiling)
        ap0 = a0 + 0.5
        ap1 = a1 + 0.5
        bn0 = b0
        bn1 = b1
        for _ in range(fam.iterations):
            R = (
                clip_to_bounds(bn0 / ap0, R00, bounds), 0.0,
                0.0, clip_to_bounds(bn1 / ap1, R11, bounds),
            )  # fmt: skip
            ok, xn, Pn = correct(x, P, H, zh, z[0], z[1], R)
            if not ok:
                return False, st, P, R, Qu, HPHt
            _, _, e, _ = innovation(xn, Pn, lm[0], lm[1], z[0], z[1])
            hph0, hph1 = hph_diag(H, Pn)
            bn0 = vb_r_beta(b0, e[0], hph0)
            bn1 = vb_r_beta(b1, e[1], hph1)
        a0 = ap0
        a1 = ap1
        b0, b1 = vb_r_bounded_beta(a0, a1, bn0, bn1, R00, R11, fam.floor, fam.ceiling)
    return True, (a0, a1, b0, b1, R00, R11), P, R, Qu, HPHt


def end_scan(fam, st, x, P, R, Qu):
    if fam.adaptation:
        R = (st[2] / st[0], 0.0, 0.0, st[3] / st[1])
    return True, st, R, Qu
