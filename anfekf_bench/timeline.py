"""The one data contract for a run's inputs (SPEC 12): `Timeline`, whatever the source.

A run is a sequence of stamps. At stamp k a filter

1. predicts over dt[k] > 0 with the command u[k] held over (t[k-1], t[k]] (zero-order hold);
2. if landmarks were measured at that stamp (rows lm[k]:lm[k+1] of z and xy), runs them as ONE
   scan (`update_scan`), then checks its health;
3. if record[k], records its (posterior) state: an evaluation time.

Both engines step exactly this (`engines.filterpy_engine.run_filter`, `engines.fast`), whatever
the source: a simulated run (`from_run`: a fixed step T, a scan every `sensor_every` steps,
records every `record_every` steps) or a recorded log (`timeline`: the distinct stamps of a
span's odometry and landmark events, jittered dt, several landmarks at one stamp).

This module sits low (numpy only): sources make timelines, engines consume them.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

# The kinds of a recorded log's events (`sources.mrclam.Events.kind`)
ODOMETRY = 0
LANDMARK = 1


@dataclass(frozen=True, eq=False)
class Timeline:
    """A run's inputs, stamp by stamp (see the module doc).

    For stamp k: t[k], dt[k] = t[k] - t[k-1] (dt[0] from t_start, > 0), u[k] the command held
    over (t[k-1], t[k]], landmarks lm[k]:lm[k+1] of `z` (range, bearing) and `xy` (map
    position), record[k] whether the state is recorded there (an evaluation time).
    """

    t_start: float
    t: np.ndarray  # (n,)
    dt: np.ndarray  # (n,)
    u: np.ndarray  # (n, 2)
    lm: np.ndarray  # (n + 1,) offsets into z / xy
    z: np.ndarray  # (m, 2)
    xy: np.ndarray  # (m, 2)
    record: np.ndarray  # (n,) bool

    @property
    def record_t(self) -> np.ndarray:
        """The evaluation times."""
        return self.t[self.record]

    def __len__(self) -> int:
        return len(self.t)


def timeline(ev) -> Timeline:
    """Group the events of a recorded span (`sources.mrclam.Events`) by stamp: the command over
    (t[k-1], t[k]] is the one in force after the last event of stamp k-1; landmarks of one stamp
    form one scan; the odometry stamps are the evaluation times."""
    n_ev = len(ev)
    if n_ev and not ev.t[0] > ev.t_start:
        raise ValueError("events must lie strictly after the span's start")
    first = np.flatnonzero(np.r_[True, np.diff(ev.t) > 0]) if n_ev else np.zeros(0, int)
    last = np.r_[first[1:], n_ev] - 1
    t = ev.t[first]
    dt = np.diff(np.r_[ev.t_start, t])
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
        lm=lm.astype(np.int64),
        z=np.ascontiguousarray(np.column_stack([ev.range[is_lm], ev.bearing[is_lm]])).reshape(
            -1, 2
        ),
        xy=np.ascontiguousarray(ev.landmark_xy[is_lm], dtype=float).reshape(-1, 2),
        record=record,
    )


_last_run: tuple[weakref.ref, weakref.ref, int, Timeline] | None = None


def from_run(data, world, record_every: int) -> Timeline:
    """A simulated run (`sources.simulator.RunData` in `config.World`) as a timeline.

    Control step k (1-based) is stamp k - 1: dt = world.T, u = data.u_odo[k - 1]; the scan
    data.scans[k // every - 1] is at the stamp of step k when k % every == 0 (every =
    world.sensor_every), its landmarks' map positions world.landmarks[ids]; records at
    k % record_every == 0 (none for record_every <= 0). The last run's timeline is kept, so
    that the filters of one run (called one after the other on the same RunData) build it once.
    """
    global _last_run
    if _last_run is not None:
        data_ref, lm_ref, every_r, tl = _last_run
        if data_ref() is data and lm_ref() is world.landmarks and every_r == record_every:
            return tl
    u = np.ascontiguousarray(data.u_odo, dtype=float).reshape(-1, 2)
    K = len(u)
    every = int(world.sensor_every)
    n_scans = K // every
    if len(data.scans) < n_scans:
        raise ValueError(f"{K} control steps need {n_scans} scans; the run has {len(data.scans)}")
    flat = getattr(data.scans, "start", None)  # simulator.Scans: the scans already flat
    if flat is not None:
        counts = np.diff(flat[: n_scans + 1])
    else:
        scans = data.scans[:n_scans]
        counts = np.fromiter((len(s.ids) for s in scans), dtype=np.int64, count=n_scans)
    per_stamp = np.zeros(K, dtype=np.int64)
    per_stamp[np.arange(1, n_scans + 1) * every - 1] = counts
    lm = np.zeros(K + 1, dtype=np.int64)
    np.cumsum(per_stamp, out=lm[1:])
    if lm[-1] and flat is not None:
        ids = data.scans.ids[: flat[n_scans]]
        z = np.array(data.scans.z[: flat[n_scans]], dtype=float).reshape(-1, 2)  # a copy, as below
        xy = np.ascontiguousarray(world.landmarks[ids], dtype=float).reshape(-1, 2)
    elif lm[-1]:
        ids = np.concatenate([s.ids for s in scans])
        z = np.ascontiguousarray(np.concatenate([s.z for s in scans]), dtype=float).reshape(-1, 2)
        xy = np.ascontiguousarray(world.landmarks[ids], dtype=float).reshape(-1, 2)
    else:
        z = xy = np.zeros((0, 2))
    steps = np.arange(1, K + 1)
    record = steps % record_every == 0 if record_every > 0 else np.zeros(K, bool)
    T = float(world.T)
    tl = Timeline(t_start=0.0, t=steps * T, dt=np.full(K, T), u=u, lm=lm, z=z, xy=xy, record=record)
    try:
        _last_run = (weakref.ref(data), weakref.ref(world.landmarks), record_every, tl)
    except TypeError:  # not weak-referenceable: no cache
        _last_run = None
    return tl


def clear_cache() -> None:
    """Forget the last run's timeline (the bench times building it too)."""
    global _last_run
    _last_run = None
