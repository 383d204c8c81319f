"""The event-driven engine for recorded logs (SPEC 9): time-varying steps, one scan per stamp.

A recorded log is not a fixed-rate loop: odometry commands arrive about every 0.12 s with jitter
and gaps, landmark measurements at their own stamps, several of them at one stamp. `Timeline`
turns the events of a span (`sources.mrclam.events`) into its distinct stamps; at each stamp a
filter

1. predicts from the previous stamp with the command held over the interval (zero-order hold;
   no predict when two events share a stamp, so dt > 0 always);
2. if landmarks were measured at that stamp, runs them as ONE scan (`update_scan`: begin_scan,
   one landmark at a time in log order, end_scan), so Q events (once per scan) see the process
   noise since the previous scan, not a zero-length interval between two landmarks of a stamp;
3. if an odometry sample has that stamp, records the (posterior) state: the evaluation times are
   the odometry stamps;
4. switches to the command of the latest odometry sample at or before that stamp.

`run_filter_events` steps any filter of the zoo (a `RobotEKF` on the `Unicycle`) this way and
returns what the simulator's `run_filter` returns, so tables, metrics, storage and the report are
shared. The grid searches of `ekf-tuned` and the fit of `ekf-ml` run the plain EKF over a `Timeline`
on the compiled tuning kernel instead (`engines.tuning`), equal to `run_filter_events` with a
`RobotEKF` to round-off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..filters import FilterDiverged, RobotEKF
from ..sources.mrclam import LANDMARK, ODOMETRY, Events
from .filterpy_engine import StepRecorder, _healthy


@dataclass(frozen=True, eq=False)
class Timeline:
    """The distinct stamps of a span's events, in order (see the module doc).

    For stamp k: t[k], dt[k] = t[k] - t[k-1] (dt[0] from the span's start, > 0), u[k] the command
    held over (t[k-1], t[k]], landmarks lm[k]:lm[k+1] of `z` (range, bearing) and `xy` (map
    position), record[k] whether an odometry sample has that stamp (an evaluation time).
    """

    t_start: float
    t: np.ndarray
    dt: np.ndarray
    u: np.ndarray  # (n, 2)
    lm: np.ndarray  # (n + 1,) offsets into z / xy
    z: np.ndarray  # (m, 2)
    xy: np.ndarray  # (m, 2)
    record: np.ndarray  # (n,) bool

    @property
    def record_t(self) -> np.ndarray:
        """The evaluation times: the odometry stamps of the span."""
        return self.t[self.record]

    def __len__(self) -> int:
        return len(self.t)


def timeline(ev: Events) -> Timeline:
    """Group the events of a span by stamp (see `Timeline`)."""
    n_ev = len(ev)
    if n_ev and not ev.t[0] > ev.t_start:
        raise ValueError("events must lie strictly after the span's start")
    first = np.flatnonzero(np.r_[True, np.diff(ev.t) > 0]) if n_ev else np.zeros(0, int)
    last = np.r_[first[1:], n_ev] - 1
    t = ev.t[first]
    dt = np.diff(np.r_[ev.t_start, t])
    # The command over (t[k-1], t[k]] is the one in force after the last event of stamp k-1.
    v_after, w_after = ev.v[last], ev.w[last]
    u = np.column_stack(
        [np.r_[ev.u_start[0], v_after[:-1]], np.r_[ev.u_start[1], w_after[:-1]]]
    ).reshape(-1, 2)
    is_lm = ev.kind == LANDMARK
    stamp_of = np.cumsum(np.r_[True, np.diff(ev.t) > 0]) - 1 if n_ev else np.zeros(0, int)
    lm = np.searchsorted(stamp_of[is_lm], np.arange(len(t) + 1), side="left")
    record = np.zeros(len(t), bool)
    record[stamp_of[ev.kind == ODOMETRY]] = True
    return Timeline(
        t_start=float(ev.t_start),
        t=t.copy(),
        dt=dt,
        u=np.ascontiguousarray(u, dtype=float),
        lm=lm,
        z=np.column_stack([ev.range[is_lm], ev.bearing[is_lm]]).reshape(-1, 2),
        xy=np.ascontiguousarray(ev.landmark_xy[is_lm]).reshape(-1, 2),
        record=record,
    )


def run_filter_events(flt: RobotEKF, tl: Timeline) -> dict:
    """Run one filter over a span's stamps (see the module doc); record at odometry stamps.

    Returns the keys of the simulator's `run_filter` (x, P, R_diag, Q_diag, P_infl, diverged,
    nis_sum, n_updates, n_rejected), one row per evaluation time. A filter that stops being finite
    and positive definite is marked diverged and its remaining records stay NaN.
    """
    trace = StepRecorder(int(tl.record.sum()))
    diverged = False
    t_list, dt_list, rec_list, lm_list = (
        tl.t.tolist(), tl.dt.tolist(), tl.record.tolist(), tl.lm.tolist(),
    )  # fmt: skip
    try:
        for k in range(len(t_list)):
            flt.predict(tl.u[k], dt=dt_list[k])
            a, b = lm_list[k], lm_list[k + 1]
            if b > a:
                flt.update_scan(tl.z[a:b], tl.xy[a:b])
                if not _healthy(flt):
                    raise FilterDiverged(f"t = {t_list[k]:.3f} s")
            if rec_list[k]:
                trace.record(flt)
        trace.check_finite(flt.has_covariance)
    except (FilterDiverged, np.linalg.LinAlgError):
        diverged = True
    return trace.result(flt, diverged)
