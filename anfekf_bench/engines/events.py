"""Recorded spans on the one filterpy loop (kept for its callers).

A recorded span is a `timeline.Timeline` (`timeline.timeline(events)`: its distinct stamps,
jittered dt, one scan per stamp with landmarks, records at the odometry stamps), the same
contract as a simulated run, so `filterpy_engine.run_filter` steps it; `run_filter_events` is
that loop, and `Timeline` and `timeline` are re-exported from here for the same reason. The grid
searches of `ekf-tuned` and the fit of `ekf-ml` run the plain EKF over a `Timeline` on the
compiled tuning kernel instead (`engines.tuning`), equal to `run_filter` with a `RobotEKF` to
round-off.
"""

from __future__ import annotations

from ..filters import RobotEKF
from ..timeline import Timeline, timeline
from .filterpy_engine import run_filter

__all__ = ["Timeline", "run_filter_events", "timeline"]


def run_filter_events(flt: RobotEKF, tl: Timeline) -> dict:
    """`filterpy_engine.run_filter` (the one loop over a timeline); kept for its callers."""
    return run_filter(flt, tl)
