"""Recorded logs on the reference engine (SPEC 9) and the ekf-tuned grid search.

A recorded span is a `timeline.Timeline` (`timeline.timeline(events)`: its distinct stamps,
jittered dt, one scan per stamp with landmarks, records at the odometry stamps), the same
contract as a simulated run, so `filterpy_engine.run_filter` steps it (`run_filter_events` is
that loop, kept for its callers; `Timeline` and `timeline` are re-exported from here for the
same reason). `run_ekf_grid` runs the plain EKF for many noise settings at once (vectorised over
the settings in plain numpy), the fast path of the `ekf-tuned` grid search; it computes what
`run_filter` computes for a `RobotEKF` on the `Unicycle`, up to round-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..filters import RobotEKF
from ..timeline import Timeline, timeline
from .filterpy_engine import run_filter

__all__ = ["GridScore", "Timeline", "run_ekf_grid", "run_filter_events", "timeline"]


def run_filter_events(flt: RobotEKF, tl: Timeline) -> dict:
    """`filterpy_engine.run_filter` (the one loop over a timeline); kept for its callers."""
    return run_filter(flt, tl)


# --------------------------------------------------------------------------------------------
# The plain EKF for many noise settings at once (the ekf-tuned grid search)


@dataclass(frozen=True)
class GridScore:
    """Per noise setting: squared position errors summed over the scored evaluation times, their
    count, the largest position error, and the gate's decisions."""

    sq_sum: np.ndarray
    count: np.ndarray
    max_err: np.ndarray
    n_updates: np.ndarray
    n_rejected: np.ndarray


def run_ekf_grid(
    tl: Timeline,
    x0: np.ndarray,
    P0: np.ndarray,
    Qu_diag: np.ndarray,
    R_diag: np.ndarray,
    gate: float | None,
    T0: float,
    truth_xy: np.ndarray,
    scored: np.ndarray,
) -> GridScore:
    """The EKF of `RobotEKF` on the `Unicycle(T0)`, for G noise settings at once, scored.

    Qu_diag, R_diag: (G, 2) variances (sv^2, sw^2), (sr^2, sb^2). truth_xy: (n_rec, 2) ground
    truth at the evaluation times, scored: (n_rec,) which of them count. The arithmetic is the
    EKF's (midpoint-Euler predict, rate-consistent Q, sequential landmark updates in Joseph form,
    gate on the NIS), written out on (G,)-arrays. A setting whose estimate stops being finite gets
    an infinite error.
    """
    G = len(Qu_diag)
    qv, qw = Qu_diag[:, 0].copy(), Qu_diag[:, 1].copy()
    rr, rb = R_diag[:, 0].copy(), R_diag[:, 1].copy()
    X = np.tile(np.asarray(x0, float), (G, 1))
    x, y, ph = X[:, 0].copy(), X[:, 1].copy(), X[:, 2].copy()
    P0 = np.asarray(P0, float)
    p00, p01, p02 = (np.full(G, P0[0, i]) for i in range(3))
    p11, p12, p22 = np.full(G, P0[1, 1]), np.full(G, P0[1, 2]), np.full(G, P0[2, 2])
    sq_sum = np.zeros(G)
    max_err = np.zeros(G)
    n_upd = np.zeros(G, np.int64)
    n_rej = np.zeros(G, np.int64)
    count = 0
    gate_v = math.inf if gate is None else gate
    two_pi = 2.0 * math.pi
    j = 0
    lm = tl.lm.tolist()
    for k in range(len(tl.t)):
        dt = float(tl.dt[k])
        v, w = float(tl.u[k, 0]), float(tl.u[k, 1])
        # predict: x+ = f(x, u), P+ = F P F^T + (T0/dt) G Qu G^T
        a = ph + 0.5 * w * dt
        c, s = np.cos(a), np.sin(a)
        vdt = v * dt
        x = x + vdt * c
        y = y + vdt * s
        ph = -((-(ph + w * dt) + math.pi) % two_pi - math.pi)
        f02, f12 = -vdt * s, vdt * c
        n00 = p00 + 2.0 * f02 * p02 + f02 * f02 * p22
        n01 = p01 + f02 * p12 + f12 * p02 + f02 * f12 * p22
        n02 = p02 + f02 * p22
        n11 = p11 + 2.0 * f12 * p12 + f12 * f12 * p22
        n12 = p12 + f12 * p22
        half = 0.5 * v * dt * dt
        g00, g01, g10, g11, g21 = dt * c, -half * s, dt * s, half * c, dt
        scale = T0 / dt
        p00 = n00 + scale * (g00 * g00 * qv + g01 * g01 * qw)
        p01 = n01 + scale * (g00 * g10 * qv + g01 * g11 * qw)
        p02 = n02 + scale * (g01 * g21 * qw)
        p11 = n11 + scale * (g10 * g10 * qv + g11 * g11 * qw)
        p12 = n12 + scale * (g11 * g21 * qw)
        p22 = p22 + scale * (g21 * g21 * qw)
        for i in range(lm[k], lm[k + 1]):
            lx, ly = float(tl.xy[i, 0]), float(tl.xy[i, 1])
            z0, z1 = float(tl.z[i, 0]), float(tl.z[i, 1])
            dx, dy = lx - x, ly - y
            q = dx * dx + dy * dy
            r = np.sqrt(q)
            # H = [[h00, h01, 0], [h10, h11, -1]]
            h00, h01, h10, h11 = -dx / r, -dy / r, dy / q, -dx / q
            zb = -((-(np.arctan2(dy, dx) - ph) + math.pi) % two_pi - math.pi)
            nu0 = z0 - r
            nu1 = -((-(z1 - zb) + math.pi) % two_pi - math.pi)
            # P H^T (3x2)
            a00 = p00 * h00 + p01 * h01
            a10 = p01 * h00 + p11 * h01
            a20 = p02 * h00 + p12 * h01
            a01 = p00 * h10 + p01 * h11 - p02
            a11 = p01 * h10 + p11 * h11 - p12
            a21 = p02 * h10 + p12 * h11 - p22
            s00 = h00 * a00 + h01 * a10 + rr
            s01 = h00 * a01 + h01 * a11
            s11 = h10 * a01 + h11 * a11 - a21 + rb
            det = s00 * s11 - s01 * s01
            i00, i01, i11 = s11 / det, -s01 / det, s00 / det
            nis = nu0 * (i00 * nu0 + i01 * nu1) + nu1 * (i01 * nu0 + i11 * nu1)
            ok = nis <= gate_v
            n_upd += ok
            n_rej += ~ok
            # K = P H^T S^-1 (3x2), zero where the gate rejected
            okf = ok.astype(float)
            k00 = (a00 * i00 + a01 * i01) * okf
            k01 = (a00 * i01 + a01 * i11) * okf
            k10 = (a10 * i00 + a11 * i01) * okf
            k11 = (a10 * i01 + a11 * i11) * okf
            k20 = (a20 * i00 + a21 * i01) * okf
            k21 = (a20 * i01 + a21 * i11) * okf
            x = x + k00 * nu0 + k01 * nu1
            y = y + k10 * nu0 + k11 * nu1
            ph = ph + k20 * nu0 + k21 * nu1
            ph = -((-ph + math.pi) % two_pi - math.pi)
            # Joseph form: P = A P A^T + K R K^T, A = I - K H
            m00, m01, m02 = 1.0 - (k00 * h00 + k01 * h10), -(k00 * h01 + k01 * h11), k01
            m10, m11, m12 = -(k10 * h00 + k11 * h10), 1.0 - (k10 * h01 + k11 * h11), k11
            m20, m21, m22 = -(k20 * h00 + k21 * h10), -(k20 * h01 + k21 * h11), 1.0 + k21
            # B = A P
            b00 = m00 * p00 + m01 * p01 + m02 * p02
            b01 = m00 * p01 + m01 * p11 + m02 * p12
            b02 = m00 * p02 + m01 * p12 + m02 * p22
            b10 = m10 * p00 + m11 * p01 + m12 * p02
            b11 = m10 * p01 + m11 * p11 + m12 * p12
            b12 = m10 * p02 + m11 * p12 + m12 * p22
            b20 = m20 * p00 + m21 * p01 + m22 * p02
            b21 = m20 * p01 + m21 * p11 + m22 * p12
            b22 = m20 * p02 + m21 * p12 + m22 * p22
            p00 = b00 * m00 + b01 * m01 + b02 * m02 + k00 * k00 * rr + k01 * k01 * rb
            p11 = b10 * m10 + b11 * m11 + b12 * m12 + k10 * k10 * rr + k11 * k11 * rb
            p22 = b20 * m20 + b21 * m21 + b22 * m22 + k20 * k20 * rr + k21 * k21 * rb
            q01 = b00 * m10 + b01 * m11 + b02 * m12 + k00 * k10 * rr + k01 * k11 * rb
            q10 = b10 * m00 + b11 * m01 + b12 * m02 + k10 * k00 * rr + k11 * k01 * rb
            q02 = b00 * m20 + b01 * m21 + b02 * m22 + k00 * k20 * rr + k01 * k21 * rb
            q20 = b20 * m00 + b21 * m01 + b22 * m02 + k20 * k00 * rr + k21 * k01 * rb
            q12 = b10 * m20 + b11 * m21 + b12 * m22 + k10 * k20 * rr + k11 * k21 * rb
            q21 = b20 * m10 + b21 * m11 + b22 * m12 + k20 * k10 * rr + k21 * k11 * rb
            p01, p02, p12 = 0.5 * (q01 + q10), 0.5 * (q02 + q20), 0.5 * (q12 + q21)
        if tl.record[k]:
            if scored[j]:
                e = np.hypot(x - truth_xy[j, 0], y - truth_xy[j, 1])
                e = np.where(np.isfinite(e), e, np.inf)
                sq_sum += e * e
                np.maximum(max_err, e, out=max_err)
                count += 1
            j += 1
    return GridScore(
        sq_sum=sq_sum,
        count=np.full(G, count),
        max_err=max_err,
        n_updates=n_upd,
        n_rejected=n_rej,
    )
