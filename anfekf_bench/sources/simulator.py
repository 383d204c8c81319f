"""Truth simulation (SPEC section 1): waypoint-driven car, noisy odometry, range-bearing scans."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..config import World
from ..error_sources import ErrorSources
from ..models import wrap_angle, wrap_scalar
from ..schedule import CHANNELS, NoiseSchedule


class RouteNotCompleted(RuntimeError):
    """The controller did not reach the last waypoint within `max_steps`."""


@dataclass(frozen=True)
class Truth:
    """Noise-free trajectory: `x[k]` is the pose after k control steps, `u[k-1]` drove it there."""

    x: np.ndarray  # (K + 1, 3)
    u: np.ndarray  # (K, 2): commanded (V, gamma)


@dataclass(frozen=True)
class Scan:
    """The landmarks seen at control step `step` and their noisy measurements."""

    step: int
    ids: np.ndarray  # (n,) landmark indices
    z: np.ndarray  # (n, 2) range [m], bearing [rad]


@dataclass(frozen=True)
class RunData:
    """Everything one Monte Carlo run feeds to every filter (common random numbers)."""

    truth: Truth
    u_odo: np.ndarray  # (K, 2) odometry the filters receive
    scans: tuple[Scan, ...]


def simulate_truth(world: World) -> Truth:
    """Drive the waypoints with Bailey's steering controller on the TRUE pose (SPEC 1)."""
    wp = world.waypoints
    tol2 = world.waypoint_tolerance**2
    max_delta = world.max_steer_rate * world.T
    T, V, B = world.T, world.V, world.B
    x, y, phi = (float(v) for v in world.x0)
    gamma = 0.0
    iwp, loops_left = 0, world.loops
    xs = [(x, y, phi)]
    us = []
    while True:
        if (wp[iwp, 0] - x) ** 2 + (wp[iwp, 1] - y) ** 2 < tol2:
            iwp += 1
            if iwp == len(wp):
                loops_left -= 1
                if loops_left == 0:
                    break
                iwp = 0
        delta = wrap_scalar(math.atan2(wp[iwp, 1] - y, wp[iwp, 0] - x) - phi - gamma)
        delta = min(max(delta, -max_delta), max_delta)
        gamma = min(max(gamma + delta, -world.max_steer), world.max_steer)
        x += T * V * math.cos(phi + gamma)
        y += T * V * math.sin(phi + gamma)
        phi = wrap_scalar(phi + T * V * math.sin(gamma) / B)
        xs.append((x, y, phi))
        us.append((V, gamma))
        if len(us) >= world.max_steps:
            raise RouteNotCompleted(
                f"route not completed within world.max_steps = {world.max_steps} control steps"
            )
    return Truth(x=np.array(xs), u=np.array(us).reshape(-1, 2))


@dataclass(frozen=True)
class ScanGeometry:
    """What the scans of every run share (the truth is the same in every run, SPEC 1): at scan i,
    control step `steps[i]`, the true range and bearing of every landmark and the ones in view.

    Computed once per world (`scan_geometry`), so a run only adds its noise."""

    steps: np.ndarray  # (n,) control steps of the scans
    range: np.ndarray  # (n, landmarks) [m]
    bearing: np.ndarray  # (n, landmarks) [rad], wrapped
    ids: tuple[np.ndarray, ...]  # per scan: the landmarks in range and in the field of view

    @functools.cached_property
    def seen(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every scan's landmarks in view, flat: (scan index, landmark index) of each, and the
        offsets `start` (scan i's are entries start[i]:start[i + 1])."""
        counts = np.array([len(i) for i in self.ids], dtype=np.int64)
        start = np.zeros(len(self.ids) + 1, dtype=np.int64)
        np.cumsum(counts, out=start[1:])
        scan_of = np.repeat(np.arange(len(self.ids)), counts)
        ids = np.concatenate(self.ids) if self.ids else np.zeros(0, dtype=np.int64)
        return scan_of, ids.astype(np.int64, copy=False), start


def _sight(world: World, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True range, bearing (eq. 18) of every landmark from `pose`, and the ones seen: range
    strictly below max_range and bearing strictly inside the field of view."""
    d = world.landmarks - pose[:2]
    rng_ = np.hypot(d[:, 0], d[:, 1])
    bearing = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - pose[2])
    seen = (rng_ < world.max_range) & (np.abs(bearing) < world.half_fov)
    return rng_, bearing, np.flatnonzero(seen)


def scan_geometry(world: World, truth: Truth) -> ScanGeometry:
    """Every scan's true landmark geometry along the truth path, once per world."""
    steps = np.arange(world.sensor_every, len(truth.u) + 1, world.sensor_every)
    sights = [_sight(world, truth.x[k]) for k in steps]
    n, L = len(steps), len(world.landmarks)
    return ScanGeometry(
        steps=steps,
        range=np.array([s[0] for s in sights]).reshape(n, L),
        bearing=np.array([s[1] for s in sights]).reshape(n, L),
        ids=tuple(s[2] for s in sights),
    )


def observe(world: World, pose: np.ndarray, noise: np.ndarray, step: int) -> Scan:
    """Scan of every landmark in range (< max_range) and in the field of view, eq. (18)."""
    rng_, bearing, ids = _sight(world, pose)
    z = np.column_stack([rng_[ids] + noise[ids, 0], wrap_angle(bearing[ids] + noise[ids, 1])])
    return Scan(step=step, ids=ids, z=z)


def simulate_run(
    world: World,
    truth: Truth,
    true_sigmas: tuple[float, float, float, float],
    rng: np.random.Generator,
    geometry: ScanGeometry | None = None,
    schedule: NoiseSchedule | None = None,
    errors: ErrorSources | None = None,
) -> RunData:
    """Odometry and scans of one run, every draw from `rng` (SPEC 6).

    Draw order is fixed: all odometry noise, then all measurement noise (one pair per landmark per
    scan, seen or not), so a run's data depend on its seed only. `geometry` (the same for every
    run of a world) is computed here when not given; the data are the same bytes either way.

    A `schedule` (SPEC 14) scales the same standard-normal draws by the standard deviation in
    force at each step (t = k dt), then draws the outliers' variables after all of them (one
    uniform per landmark per scan, or one chi-square per component), and empties the scans in
    a blackout; without one, the draws and the data are those of a constant-noise run.

    `errors` (SPEC 18, `error_sources.ErrorSources`) scales and biases the odometry and biases
    the ranges; it draws nothing, so the draws are the same with it or without.
    """
    sv, sg, sr, sb = true_sigmas
    K = len(truth.u)
    geometry = scan_geometry(world, truth) if geometry is None else geometry
    if schedule is None:
        u_odo = truth.u + rng.standard_normal((K, 2)) * np.array([sv, sg])
        noise = rng.standard_normal((len(geometry.steps), len(world.landmarks), 2)) * np.array(
            [sr, sb]
        )
        blackout = None
    else:
        u_odo, noise, blackout = _scheduled_noise(
            world, truth, true_sigmas, rng, geometry, schedule
        )
    # Every seen landmark of every scan at once; scan i's measurements are rows
    # start[i]:start[i + 1] (the same elementwise sums as one scan at a time, so the same bytes).
    scan_of, ids, start = geometry.seen
    z = np.empty((len(ids), 2))
    z[:, 0] = geometry.range[scan_of, ids] + noise[scan_of, ids, 0]
    z[:, 1] = wrap_angle(geometry.bearing[scan_of, ids] + noise[scan_of, ids, 1])
    if errors is not None:
        u_odo = errors.odometry(truth.u, u_odo)
        z[:, 0] = errors.ranges(z[:, 0])
    bounds = zip(start[:-1].tolist(), start[1:].tolist(), strict=True)
    scans = tuple(
        Scan(step=k, ids=ids[a:b], z=z[a:b])
        for k, (a, b) in zip(geometry.steps.tolist(), bounds, strict=True)
    )
    if blackout is not None and blackout.any():
        scans = tuple(
            Scan(step=s.step, ids=s.ids[:0], z=s.z[:0]) if dark else s
            for s, dark in zip(scans, blackout.tolist(), strict=True)
        )
    return RunData(truth=truth, u_odo=u_odo, scans=scans)


def _scheduled_noise(
    world: World,
    truth: Truth,
    true_sigmas: tuple[float, float, float, float],
    rng: np.random.Generator,
    geometry: ScanGeometry,
    schedule: NoiseSchedule,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Odometry, the measurement noise of every landmark of every scan, and which scans are
    blacked out, under `schedule` (see `simulate_run` for the draw order)."""
    K = len(truth.u)
    base = np.asarray(true_sigmas, dtype=float)
    t_odo = np.arange(1, K + 1) * world.T  # u_odo[k - 1] drives step k
    sigma_odo = base[:2] * np.sqrt(schedule.variance_factors(t_odo)[:, :2])
    u_odo = truth.u + rng.standard_normal((K, 2)) * sigma_odo
    t_scan = geometry.steps * world.T
    sigma_z = base[2:] * np.sqrt(schedule.variance_factors(t_scan)[:, 2:])
    noise = rng.standard_normal((len(geometry.steps), len(world.landmarks), 2)) * sigma_z[:, None]
    out = schedule.outliers
    if out is not None:
        channels = sorted(CHANNELS.index(c) - 2 for c in out.affected())
        active = out.active(t_scan)
        if out.model == "contaminated":
            hit = rng.random(noise.shape[:2]) < out.probability
            hit &= active[:, None]
            for c in channels:
                noise[hit, c] *= math.sqrt(out.variance_factor)
        else:
            w = rng.chisquare(out.dof, noise.shape)
            for c in channels:
                noise[active, :, c] *= np.sqrt(out.dof / w[active, :, c])
    return u_odo, noise, schedule.blacked_out(t_scan)


@dataclass(frozen=True)
class WorldPath:
    """What every run of a world shares: the truth path and its scans' landmark geometry."""

    truth: Truth
    geometry: ScanGeometry


def world_path(world: World) -> WorldPath:
    """The truth path and scan geometry of a world, computed once and shipped to the runs."""
    truth = simulate_truth(world)
    return WorldPath(truth, scan_geometry(world, truth))
