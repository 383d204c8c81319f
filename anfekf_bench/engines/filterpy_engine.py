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
    if not flt.has_covariance:  # P is NaN by design (KalmanNet): x must be finite
        return all(map(math.isfinite, flt.x.ravel().tolist()))
    if not all(map(math.isfinite, flt.x.ravel().tolist() + flt.P.ravel().tolist())):
        return False
    try:
        np.linalg.cholesky(flt.P)
    except np.linalg.LinAlgError:
        return False
    return all(v > 0 for v in flt.R.diagonal().tolist() + flt.Qu.diagonal().tolist())


class StepRecorder:
    """What an engine's loop records of one filter at its evaluation steps, and the dict it
    returns (x, P, R_diag, Q_diag, P_infl, diverged and the update counts), shared by the loops
    over simulated runs and over recorded logs. Rows after a divergence stay NaN."""

    def __init__(self, n: int):
        self.x = np.full((n, 3), np.nan)
        self.P = np.full((n, 3, 3), np.nan)
        self.R = np.full((n, 2), np.nan)
        self.Qu = np.full((n, 2), np.nan)
        self.P_infl = np.full(n, np.nan)
        self.j = 0

    def record(self, flt: RobotEKF) -> None:
        j = self.j
        self.x[j] = flt.x
        self.P[j] = flt.P
        self.R[j] = flt.R[0, 0], flt.R[1, 1]
        self.Qu[j] = flt.Qu[0, 0], flt.Qu[1, 1]
        self.P_infl[j] = flt.P_inflation
        self.j = j + 1

    def check_finite(self, has_covariance: bool = True) -> None:
        """Health is checked at scans; a blow-up in the predictions after the last one shows
        here (P only for a filter that has one)."""
        if not (np.isfinite(self.x).all() and (not has_covariance or np.isfinite(self.P).all())):
            raise FilterDiverged("non-finite estimate after the last scan")

    def result(self, flt: RobotEKF, diverged: bool) -> dict:
        if diverged:
            j = self.j
            self.x[j:] = self.P[j:] = self.R[j:] = self.Qu[j:] = self.P_infl[j:] = np.nan
        return {
            "x": self.x,
            "P": self.P,
            "R_diag": self.R,
            "Q_diag": self.Qu,
            "P_infl": self.P_infl,
            "diverged": diverged,
            "nis_sum": flt.nis_sum,
            "n_updates": flt.n_updates,
            "n_rejected": flt.n_rejected,
        }


def run_filter(flt: RobotEKF, data: RunData, world: World, record_every: int) -> dict:
    """Run one filter over one run's data; record every `record_every`-th control step.

    A filter that stops being finite and positive definite is marked diverged; its remaining
    records stay NaN and the caller goes on with the next filter.
    """
    K = len(data.u_odo)
    trace = StepRecorder(K // record_every)
    landmarks = world.landmarks
    every = world.sensor_every
    diverged = False
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
                trace.record(flt)
        trace.check_finite(flt.has_covariance)
    except (FilterDiverged, np.linalg.LinAlgError):
        diverged = True
    return trace.result(flt, diverged)
