"""The reference engine: each filter is a filterpy ExtendedKalmanFilter stepped over one run's
timeline (`timeline.Timeline`: a simulated run or a recorded span alike)."""

from __future__ import annotations

import math

import numpy as np

from ..config import World
from ..filters import FilterDiverged, RobotEKF
from ..sources.simulator import RunData
from ..timeline import Timeline, from_run


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
        # the pose block (an augmented filter's state carries more after it)
        self.x[j] = flt.x[:3]
        self.P[j] = flt.P[:3, :3]
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


def run_filter(
    flt: RobotEKF, tl: Timeline | RunData, world: World | None = None, record_every: int = 0
) -> dict:
    """Run one filter over one run's timeline (`timeline.Timeline`, the one loop of both sources).

    At each stamp: predict over dt[k] with u[k]; if the stamp has landmarks, one scan
    (`update_scan`) and a health check; record if record[k]. A simulated run may be passed as
    (RunData, world, record_every): `timeline.from_run` makes its timeline. A filter that stops
    being finite and positive definite is marked diverged; its remaining records stay NaN and
    the caller goes on with the next filter.
    """
    if not isinstance(tl, Timeline):
        tl = from_run(tl, world, record_every)
    record = tl.record.tolist()
    trace = StepRecorder(sum(record))
    dt, lm, u, z, xy = tl.dt.tolist(), tl.lm.tolist(), tl.u, tl.z, tl.xy
    diverged = False
    try:
        for k in range(len(dt)):
            flt.predict(u[k], dt=dt[k])
            a, b = lm[k], lm[k + 1]
            # Only updates (and the supervisor inside them) can break x, P, R or Qu: the
            # predict of a healthy filter stays healthy, so stamps without landmarks need no check.
            if b > a:
                flt.update_scan(z[a:b], xy[a:b])
                if not _healthy(flt):
                    raise FilterDiverged(f"stamp {k}, t = {float(tl.t[k]):.3f} s")
            if record[k]:
                trace.record(flt)
        trace.check_finite(flt.has_covariance)
    except (FilterDiverged, np.linalg.LinAlgError):
        diverged = True
    return trace.result(flt, diverged)
