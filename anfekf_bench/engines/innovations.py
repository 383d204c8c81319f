"""The plain EKF over one recorded timeline, compiled, with everything the drive audit reads:
every landmark's innovation, its covariance and the gate's decision, and the estimate at every
record stamp (drive_audit: innovation whiteness, lost-lock episodes and their counterfactual
re-runs).

The loop is the fast engine's plain EKF (`kernels.predict`, `kernels.innovation`, `kernels.nis`,
`kernels.correct`, `kernels.healthy` after every stamp that fused a landmark: RobotEKF's to
round-off, tests/test_drive_audit.py checks it against the filterpy engine), on the per-stamp
contract of a `timeline.Timeline`; it only writes more of what it computes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kernels import MOTION_UNICYCLE, correct, healthy, innovation, maybe_njit, nis, predict


@maybe_njit
def ekf_innovation_kernel(
    motion, dt, u, lm, z, xy, record, x0, P0, Qu, R, gate, has_gate, T0, B,
    out_nu, out_S, out_accepted, out_x, out_P,
):  # fmt: skip
    """Returns (diverged, landmarks seen). For landmark i (row of z): out_nu[i] (range,
    bearing innovation at the prior), out_S[i] (S00, S01, S11), out_accepted[i]; at the j-th
    record stamp the posterior out_x[j] and out_P[j] (row-major 9). Rows after a divergence
    keep their initial values (the caller fills NaN)."""
    x = (x0[0], x0[1], x0[2])
    P = (P0[0], P0[1], P0[2], P0[3], P0[4], P0[5], P0[6], P0[7], P0[8])
    Qt = (Qu[0], Qu[1], Qu[2], Qu[3])
    Rt = (R[0], R[1], R[2], R[3])
    j = 0
    for k in range(len(dt)):
        x, P, _ = predict(x, P, u[k, 0], u[k, 1], dt[k], motion, B, T0, Qt)
        first = lm[k]
        last = lm[k + 1]
        if last > first:
            for i in range(first, last):
                H, zh, nu, HPHt = innovation(x, P, xy[i, 0], xy[i, 1], z[i, 0], z[i, 1])
                ok, v = nis(HPHt, Rt, nu[0], nu[1])
                if not ok or not math.isfinite(v):
                    return True, i
                out_nu[i, 0] = nu[0]
                out_nu[i, 1] = nu[1]
                out_S[i, 0] = HPHt[0] + Rt[0]
                out_S[i, 1] = HPHt[1] + Rt[1]
                out_S[i, 2] = HPHt[3] + Rt[3]
                if has_gate and not v <= gate:
                    continue
                ok, x, P = correct(x, P, H, zh, z[i, 0], z[i, 1], Rt)
                if not ok:
                    return True, i
                out_accepted[i] = True
            if not healthy(x, P, Rt, Qt):
                return True, last
        if record[k]:
            for c in range(3):
                out_x[j, c] = x[c]
            for c in range(9):
                out_P[j, c] = P[c]
            j += 1
    return False, len(z)


@dataclass(frozen=True)
class InnovationTrace:
    """One plain-EKF run over a timeline: per landmark its innovation nu (m, 2), S (m, 3: S00,
    S01, S11), accepted (m,); per record stamp the estimate x (n_rec, 3) and P (n_rec, 3, 3).
    NaN from where it diverged."""

    nu: np.ndarray
    S: np.ndarray
    accepted: np.ndarray
    x: np.ndarray
    P: np.ndarray
    diverged: bool

    def normalised(self) -> np.ndarray:
        """(m, 2): each component of the innovation over its own predicted std (nu_i /
        sqrt(S_ii)): N(0, 1) for a consistent filter."""
        return self.nu / np.sqrt(self.S[:, [0, 2]])


def run_innovations(tl, x0, P0, sigmas, gate: float | None, T0: float) -> InnovationTrace:
    """The plain unicycle EKF with sigmas (s_v, s_w, s_range, s_bearing) over a recorded
    `Timeline` from (x0, P0)."""
    sv, sw, sr, sb = (float(s) for s in sigmas)
    m = len(tl.z)
    n_rec = int(np.sum(tl.record))
    nu, S = np.full((m, 2), np.nan), np.full((m, 3), np.nan)
    accepted = np.zeros(m, np.bool_)
    x, P = np.full((n_rec, 3), np.nan), np.full((n_rec, 9), np.nan)
    diverged, _ = ekf_innovation_kernel(
        MOTION_UNICYCLE, tl.dt, np.ascontiguousarray(tl.u), tl.lm, np.ascontiguousarray(tl.z),
        np.ascontiguousarray(tl.xy), np.ascontiguousarray(tl.record, dtype=np.bool_),
        np.ascontiguousarray(x0, dtype=float).reshape(3),
        np.ascontiguousarray(P0, dtype=float).ravel(), np.array([sv * sv, 0.0, 0.0, sw * sw]),
        np.array([sr * sr, 0.0, 0.0, sb * sb]), math.inf if gate is None else float(gate),
        gate is not None, float(T0), 0.0, nu, S, accepted, x, P,
    )  # fmt: skip
    return InnovationTrace(nu, S, accepted, x, P.reshape(-1, 3, 3), bool(diverged))
