"""The EKF, the ANFEKF and cm-scale on the fast engine's loop (`engines/loop.py`): the hooks of
filterpy_engine.run_filter with RobotEKF, ANFEKF or CMScaleEKF.

The supervisor (ANFEKF.supervise): a window of the squared innovations of the landmarks that
feed adaptation; once full, the mismatches d (eq. 31) and their change dd drive the R-ANFIS of
each channel (anfekf.r_step, eq. 33) and, at the first landmark of a scan, the Q-ANFIS
(anfekf.q_step, eq. 44) on the interval's process noise Qi; cm-scale replaces both ANFIS by its
proportional rule (filters.cm_scale). Neither adapts: the plain EKF (and ekf-oracle, ekf-ml,
ekf-tuned).
"""

from __future__ import annotations

import collections
import functools
import math

import numpy as np

from ...filters import anfis
from ...filters.anfekf import ANFEKFSpec
from ...filters.cm_scale import CMScaleSpec
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
feeds_adaptation, clip_nan, r_step, q_step, hqh_diag = (
    _k.feeds_adaptation,
    _k.clip_nan,
    _k.r_step,
    _k.q_step,
    _k.hqh_diag,
)
proportional_step, mean_mismatch = _k.proportional_step, _k.mean_mismatch
N_ANFIS = _k.N_ANFIS


RULE_ANFIS = 0  # the ANFEKF's ANFIS
RULE_PROPORTIONAL = 1  # cm-scale's proportional rule of gain kappa (filters.cm_scale)

# adapt_R / adapt_Q select the supervisors (both False: the EKF); `anf` (3, 27) holds the ANFIS
# parameters (rows 0, 1: R of range and bearing; row 2: Qu), trained in place.
Params = collections.namedtuple(
    "Params",
    "adapt_R adapt_Q adaptation learning from_all lo hi window clip eta_m eta_d eta_w anf rule"
    " kappa win grad ws",
)

ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def params(spec, ctx) -> Params:
    """The loop's parameters of an ANFEKFSpec, a CMScaleSpec or a plain EKF's spec."""
    if isinstance(spec, ANFEKFSpec):
        return Params(
            "R" in spec.adapt, "Q" in spec.adapt, bool(spec.adaptation), bool(spec.learning),
            spec.adapt_from == "all", *(float(b) for b in spec.bounds), int(spec.window),
            float(spec.output_clip), *(float(e) for e in spec.learning_rate),
            anfis_rows(spec), RULE_ANFIS, 1.0, *_work(spec.window),
        )  # fmt: skip
    if isinstance(spec, CMScaleSpec):  # the ANFEKF's supervisor with the proportional rule
        return Params(
            "R" in spec.adapt, "Q" in spec.adapt, bool(spec.adaptation), False,
            spec.adapt_from == "all", *(float(b) for b in spec.bounds), int(spec.window),
            float(spec.output_clip), 0.0, 0.0, 0.0, np.zeros((3, N_ANFIS)), RULE_PROPORTIONAL,
            float(spec.kappa), *_work(spec.window),
        )  # fmt: skip
    return Params(
        False, False, False, False, True, 1.0, 1.0, 1, 1.0, 0.0, 0.0, 0.0,
        np.zeros((3, N_ANFIS)), RULE_ANFIS, 1.0, *_work(1),
    )  # fmt: skip


def _work(window: int) -> tuple:
    """The supervisor's arrays, updated in place by the hooks (parameters rather than state:
    the state passes through a hook at every step, and arrays in it cost reference counts):
    the window of squared innovations, the ANFIS gradient and its workspace."""
    return np.zeros((max(int(window), 1), 2)), np.empty(N_ANFIS), np.empty(40)


def anfis_rows(spec: ANFEKFSpec) -> np.ndarray:
    """The starting ANFIS parameters as ANFEKF.__init__ makes them, one row each: the R-ANFIS
    of range and of bearing (rows 0, 1) and the Q-ANFIS (row 2); a fresh copy (the loop
    trains them in place)."""
    key = (
        tuple(spec.centres_d), float(spec.width_d), tuple(spec.centres_dd),
        float(spec.width_dd), float(spec.singleton_scale),
    )  # fmt: skip
    return _anfis_start(*key).copy()


@functools.lru_cache(maxsize=64)
def _anfis_start(
    centres_d: tuple, width_d: float, centres_dd: tuple, width_dd: float, singleton_scale: float
) -> np.ndarray:
    r_init = anfis.init_params(
        centres0=centres_d, width0=width_d, centres1=centres_dd, width1=width_dd,
        singleton_scale=singleton_scale,
    )  # fmt: skip
    # The Q-ANFIS's inputs d_11 and d_22 are two mismatches of the same scale.
    q_init = anfis.init_params(
        centres0=centres_d, width0=width_d, centres1=centres_d, width1=width_d,
        singleton_scale=singleton_scale,
    )  # fmt: skip
    rows = np.empty((3, N_ANFIS))
    for i, p in enumerate((r_init, r_init, q_init)):
        rows[i] = np.concatenate([p.m.ravel(), p.delta.ravel(), p.w])
    rows.setflags(write=False)
    return rows


def start(fam, x, P, Qu, R, scan_start):
    # (n_win, pos, d_prev (have, d0, d1), Qi, updated_since_predict, first_of_scan, the
    #  bounds of R and Qu); the arrays are in `fam` (`_work`)
    bounds = (fam.lo * R[0], fam.hi * R[0], fam.lo * R[3], fam.hi * R[3],
              fam.lo * Qu[0], fam.hi * Qu[0], fam.lo * Qu[3], fam.hi * Qu[3])  # fmt: skip
    fam.win[:] = 0.0
    return 0, 0, (False, 0.0, 0.0), ZERO9, False, True, bounds


def predicted(fam, st, f02, f12, G, c, Q):
    if not fam.adapt_Q:
        return st
    n_win, pos, d_prev, Qi, updated, first_of_scan, bounds = st
    if updated:  # process noise since the last update
        Qi = ZERO9
        updated = False
    Qi = (
        Qi[0] + Q[0], Qi[1] + Q[1], Qi[2] + Q[2],
        Qi[3] + Q[3], Qi[4] + Q[4], Qi[5] + Q[5],
        Qi[6] + Q[6], Qi[7] + Q[7], Qi[8] + Q[8],
    )  # fmt: skip
    return n_win, pos, d_prev, Qi, updated, first_of_scan, bounds


def begin_scan(fam, st, x, P, R, Qu):
    n_win, pos, d_prev, Qi, updated, _, bounds = st
    return (n_win, pos, d_prev, Qi, updated, True, bounds), R


def before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    if not (fam.adapt_R or fam.adapt_Q):
        return True, st, P, R, Qu, HPHt
    n_win, pos, d_prev, Qi, updated, first_of_scan, bounds = st
    R_lo0, R_hi0, R_lo1, R_hi1, Q_lo0, Q_hi0, Q_lo1, Q_hi1 = bounds
    window, win, grad, ws = fam.window, fam.win, fam.grad, fam.ws
    ok, feeds = feeds_adaptation(HPHt, R, nu, fam.from_all, gate, has_gate)
    if not ok:
        return False, st, P, R, Qu, HPHt
    if feeds:
        # ANFEKF.supervise: window of squared innovations, then adapt
        updated = True
        win[pos, 0] = nu[0] * nu[0]
        win[pos, 1] = nu[1] * nu[1]
        pos = (pos + 1) % window
        if n_win < window:
            n_win += 1
        if n_win == window and fam.adaptation:
            c0 = 0.0
            c1 = 0.0
            for i in range(window):  # oldest first, as np.mean sums
                c0 += win[(pos + i) % window, 0]
                c1 += win[(pos + i) % window, 1]
            c0 = c0 / window
            c1 = c1 / window
            HPH0 = HPHt[0]
            HPH1 = HPHt[3]
            S0 = HPH0 + R[0]
            S1 = HPH1 + R[3]
            d0 = (S0 - c0) / (S0 + c0)
            d1 = (S1 - c1) / (S1 + c1)
            dd0 = 0.0
            dd1 = 0.0
            if d_prev[0]:
                dd0 = d0 - d_prev[1]
                dd1 = d1 - d_prev[2]
            d_prev = (True, d0, d1)
            clip, kappa, rule = fam.clip, fam.kappa, fam.rule
            if fam.adapt_R:
                if rule == RULE_PROPORTIONAL:
                    r0 = R[0] * math.exp(proportional_step(d0, kappa, clip))
                    r1 = R[3] * math.exp(proportional_step(d1, kappa, clip))
                else:
                    r0 = r_step(
                        fam.anf[0], d0, dd0, R[0], HPH0, c0, clip, fam.learning,
                        fam.eta_m, fam.eta_d, fam.eta_w, grad, ws,
                    )  # fmt: skip
                    r1 = r_step(
                        fam.anf[1], d1, dd1, R[3], HPH1, c1, clip, fam.learning,
                        fam.eta_m, fam.eta_d, fam.eta_w, grad, ws,
                    )  # fmt: skip
                R = (clip_nan(r0, R_lo0, R_hi0), 0.0, 0.0, clip_nan(r1, R_lo1, R_hi1))
                S0 = HPH0 + R[0]
                S1 = HPH1 + R[3]
            if fam.adapt_Q and first_of_scan and rule == RULE_PROPORTIONAL:
                scale = math.exp(proportional_step(mean_mismatch(d0, d1), kappa, clip))
                Qu = (
                    clip_nan(Qu[0] * scale, Q_lo0, Q_hi0), 0.0,
                    0.0, clip_nan(Qu[3] * scale, Q_lo1, Q_hi1),
                )  # fmt: skip
            elif fam.adapt_Q and first_of_scan:
                dS0, dS1 = hqh_diag(H, Qi, HPH0, HPH1)
                scale = q_step(
                    fam.anf[2], d0, d1, S0, S1, c0, c1, dS0, dS1, clip,
                    fam.learning, fam.eta_m, fam.eta_d, fam.eta_w, grad, ws,
                )  # fmt: skip
                b0 = Qu[0]
                Qu = (
                    clip_nan(b0 * scale, Q_lo0, Q_hi0), 0.0,
                    0.0, clip_nan(Qu[3] * scale, Q_lo1, Q_hi1),
                )  # fmt: skip
                f = Qu[0] / b0
                Qi = (
                    Qi[0] * f, Qi[1] * f, Qi[2] * f,
                    Qi[3] * f, Qi[4] * f, Qi[5] * f,
                    Qi[6] * f, Qi[7] * f, Qi[8] * f,
                )  # fmt: skip
    st = (n_win, pos, d_prev, Qi, updated, False, bounds)
    return True, st, P, R, Qu, HPHt
