"""The fading-factor EKF on the fast engine's loop (`engines/loop.py`): the hooks of
filterpy_engine.run_filter with filters.fading.FadingEKF. P- is inflated by the fading factor
(filters.fading.fading_factor, F.2) at the first landmark of a scan that feeds adaptation, once
the window of nu^T nu is full; `inflation` is lambda of the last inflation (1 before the first).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from ...filters.fading import FadingSpec, fading_event
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
feeds_adaptation, hph = _k.feeds_adaptation, _k.hph

Params = collections.namedtuple("Params", "adaptation from_all window ceiling")


def params(spec: FadingSpec, ctx) -> Params:
    return Params(
        bool(spec.adaptation), spec.adapt_from == "all", int(spec.window), float(spec.bounds[1])
    )


def start(fam, x, P, Qu, R, scan_start):
    # (nu^T nu of the window, a ring; n_window; pos; lambda in force; first of the scan)
    return np.zeros(fam.window), 0, 0, 1.0, True


def begin_scan(fam, st, x, P, R, Qu):
    nu2, n_window, pos, infl, _ = st
    return (nu2, n_window, pos, infl, True), R


def before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    nu2, n_window, pos, infl, first_of_scan = st
    if fam.adaptation:
        ok, feeds = feeds_adaptation(HPHt, R, nu, fam.from_all, gate, has_gate)
        if not ok:
            return False, st, P, R, Qu, HPHt
        if feeds:  # FadingEKF.before_gain
            n_window, pos, lam = fading_event(
                nu2, n_window, pos, first_of_scan, nu[0], nu[1], R[0] + R[3],
                HPHt[0] + HPHt[3], fam.ceiling,
            )  # fmt: skip
            first_of_scan = False
            if math.isfinite(lam):
                infl = lam
                P = (
                    lam * P[0], lam * P[1], lam * P[2],
                    lam * P[3], lam * P[4], lam * P[5],
                    lam * P[6], lam * P[7], lam * P[8],
                )  # fmt: skip
    if infl != 1.0:  # RobotEKF.update_landmark: H P- H^T follows the scaled P-
        HPHt = hph(H, P)
    return True, (nu2, n_window, pos, infl, first_of_scan), P, R, Qu, HPHt


def inflation(fam, st):
    return st[3]
