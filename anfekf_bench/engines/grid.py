"""The plain EKF on the Unicycle for one noise setting over a recorded timeline, compiled, with
an early stop: the kernel of the cross-drive `ekf-tuned` grid search (real_experiment).

`engines.events.run_ekf_grid` runs every setting at once in numpy: at 65 Hz odometry (MRCLAM
Datasets 6 and 7) its per-stamp numpy overhead dominates. Here one setting is one compiled loop
(numba when installed, `engines.kernels.maybe_njit`), the landmark update is the fast engine's
(`kernels.innovation`, `kernels.nis`, `kernels.correct`: the RobotEKF update), and the predict is
the Unicycle's midpoint-Euler step with its rate-consistent process noise, written out as in
`run_ekf_grid`. The two agree to round-off (tests/test_cross_drive.py).

`bound`: the loop stops as soon as the summed squared position error exceeds it. The criterion
of the grid search is the pooled RMSE over the same scored times for every setting, so a setting
whose partial sum already exceeds the best complete sum can never win: branch and bound returns
the grid's exact minimiser while most settings (those that lose lock, and the clearly worse ones)
stop early.
"""

from __future__ import annotations

import math

import numpy as np

from .kernels import correct, innovation, maybe_njit, nis, wrap


@maybe_njit
def predict_unicycle(x, P, v, w, dt, T0, qv, qw):
    """Unicycle.f / F / Q of RobotEKF.predict: x+ = midpoint-Euler step with (v, w) held over dt,
    P+ = F P F^T + (T0 / dt) G diag(qv, qw) G^T."""
    x0, x1, x2 = x
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    a = x2 + 0.5 * w * dt
    c = math.cos(a)
    s = math.sin(a)
    vdt = v * dt
    f02 = -vdt * s
    f12 = vdt * c
    n00 = p00 + f02 * p20 + (p02 + f02 * p22) * f02
    n01 = p01 + f02 * p21 + (p02 + f02 * p22) * f12
    n02 = p02 + f02 * p22
    n11 = p11 + f12 * p21 + (p12 + f12 * p22) * f12
    n12 = p12 + f12 * p22
    half = 0.5 * v * dt * dt
    g00, g01, g10, g11, g21 = dt * c, -half * s, dt * s, half * c, dt
    k = T0 / dt
    q00 = k * (g00 * g00 * qv + g01 * g01 * qw)
    q01 = k * (g00 * g10 * qv + g01 * g11 * qw)
    q02 = k * (g01 * g21 * qw)
    q11 = k * (g10 * g10 * qv + g11 * g11 * qw)
    q12 = k * (g11 * g21 * qw)
    q22 = k * (g21 * g21 * qw)
    Pn = (
        n00 + q00, n01 + q01, n02 + q02,
        n01 + q01, n11 + q11, n12 + q12,
        n02 + q02, n12 + q12, p22 + q22,
    )  # fmt: skip
    return (x0 + vdt * c, x1 + vdt * s, wrap(x2 + w * dt)), Pn


@maybe_njit
def ekf_score(dt, u, lm, z, xy, record, x0, P0, qv, qw, rr, rb, gate, T0, truth_xy, scored, bound):
    """One setting over one timeline (`engines.events.Timeline` arrays): returns (sq_sum, max_err,
    n_updates, n_rejected, finished). Position errors are taken at the record stamps whose
    `scored` flag is set (truth_xy and scored are indexed by record stamp); an estimate that
    stops being finite scores infinity. `finished` is False when the sum passed `bound`."""
    x = (x0[0], x0[1], x0[2])
    P = (
        P0[0, 0], P0[0, 1], P0[0, 2], P0[1, 0], P0[1, 1], P0[1, 2],
        P0[2, 0], P0[2, 1], P0[2, 2],
    )  # fmt: skip
    R = (rr, 0.0, 0.0, rb)
    sq_sum = 0.0
    max_err = 0.0
    n_upd = 0
    n_rej = 0
    j = 0
    for k in range(len(dt)):
        x, P = predict_unicycle(x, P, u[k, 0], u[k, 1], dt[k], T0, qv, qw)
        for i in range(lm[k], lm[k + 1]):
            H, zh, nu, HPHt = innovation(x, P, xy[i, 0], xy[i, 1], z[i, 0], z[i, 1])
            ok, d2 = nis(HPHt, R, nu[0], nu[1])
            if not ok:
                return math.inf, math.inf, n_upd, n_rej, True
            if d2 <= gate:
                ok, x, P = correct(x, P, H, zh, z[i, 0], z[i, 1], R)
                if not ok:
                    return math.inf, math.inf, n_upd, n_rej, True
                n_upd += 1
            else:
                n_rej += 1
        if record[k]:
            if scored[j]:
                e = math.hypot(x[0] - truth_xy[j, 0], x[1] - truth_xy[j, 1])
                if not math.isfinite(e):
                    return math.inf, math.inf, n_upd, n_rej, True
                sq_sum += e * e
                if e > max_err:
                    max_err = e
                if sq_sum > bound:
                    return sq_sum, max_err, n_upd, n_rej, False
            j += 1
    return sq_sum, max_err, n_upd, n_rej, True


def score_setting(tl, x0, P0, sig, gate, T0, truth_xy, scored, bound=math.inf) -> tuple:
    """`ekf_score` for a `Timeline` and standard deviations sig = (sv, sw, sr, sb)."""
    sv, sw, sr, sb = (float(s) for s in sig)
    return ekf_score(
        tl.dt, tl.u, tl.lm, tl.z, tl.xy, tl.record, np.asarray(x0, float), np.asarray(P0, float),
        sv * sv, sw * sw, sr * sr, sb * sb, math.inf if gate is None else float(gate),
        float(T0), np.ascontiguousarray(truth_xy, dtype=float), scored,
        float(bound),
    )  # fmt: skip
