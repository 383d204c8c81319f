"""The reference engine: each filter is a filterpy ExtendedKalmanFilter stepped over one run."""

from __future__ import annotations

import math

import numpy as np

from ..config import World
from ..filters import FilterDiverged, RobotEKF
from ..sources.simulator import RunData


def _healthy(flt: RobotEKF) -> bool:
    """x and P finite, P positive definite, the diagonals of R and Qu positive.

    Called after every scan that saw a landmark; on the 3 + 9 + 4 numbers it checks, plain
    floats cost a fraction of numpy's reductions (the same answer: math.isfinite and > 0 treat
    NaN as np.isfinite does).
    """
    if not all(map(math.isfinite, flt.x.ravel().tolist() + flt.P.ravel().tolist())):
        return False
    try:
        np.linalg.cholesky(flt.P)
    except np.linalg.LinAlgError:
        return False
    return all(v > 0 for v in flt.R.diagonal().tolist() + flt.Qu.diagonal().tolist())


def run_filter(flt: RobotEKF, data: RunData, world: World, record_every: int) -> dict:
    """Run one filter over one run's data; record every `record_every`-th control step.

    A filter that stops being finite and positive definite is marked diverged; its remaining
    records stay NaN and the caller goes on with the next filter.
    """
    K = len(data.u_odo)
    n = K // record_every
    x = np.full((n, 3), np.nan)
    P = np.full((n, 3, 3), np.nan)
    R = np.full((n, 2), np.nan)
    Qu = np.full((n, 2), np.nan)
    P_infl = np.full(n, np.nan)
    landmarks = world.landmarks
    every = world.sensor_every
    diverged = False
    j = 0
    try:
        for k in range(1, K + 1):
            flt.predict(data.u_odo[k - 1])
            if k % every == 0:
                scan = data.scans[k // every - 1]
                # Only updates (and the supervisor inside them) can break x, P, R or Qu: the
                # predict of a healthy filter stays healthy, so empty scans need no check.
                if len(scan.ids):
                    flt.update_scan(scan.z, landmarks[scan.ids])
                    if not _healthy(flt):
                        raise FilterDiverged(f"step {k}")
            if k % record_every == 0:
                x[j] = flt.x
                P[j] = flt.P
                R[j] = flt.R[0, 0], flt.R[1, 1]
                Qu[j] = flt.Qu[0, 0], flt.Qu[1, 1]
                P_infl[j] = flt.P_inflation
                j += 1
        # Health is checked at scans; a blow-up in the predictions after the last one shows here.
        if not (np.isfinite(x).all() and np.isfinite(P).all()):
            raise FilterDiverged("non-finite estimate after the last scan")
    except (FilterDiverged, np.linalg.LinAlgError):
        diverged = True
        x[j:] = P[j:] = R[j:] = Qu[j:] = P_infl[j:] = np.nan
    return {
        "x": x,
        "P": P,
        "R_diag": R,
        "Q_diag": Qu,
        "P_infl": P_infl,
        "diverged": diverged,
        "nis_sum": flt.nis_sum,
        "n_updates": flt.n_updates,
        "n_rejected": flt.n_rejected,
    }
