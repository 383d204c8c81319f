"""Truth simulation (SPEC section 1): waypoint-driven car, noisy odometry, range-bearing scans."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..compiled import is_compiled, maybe_njit
from ..config import World
from ..error_sources import ErrorSources
from ..models import wrap_angle
from ..models.angles import wrap_scalar
from ..models.motion_terms import MOTION_BICYCLE, jacobians_at, step_terms
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


class Scans(Sequence):
    """A run's scans, held flat: scan i (control step `steps[i]`) saw landmarks
    `ids[start[i]:start[i + 1]]` with measurements `z[start[i]:start[i + 1]]`.

    A tuple of `Scan` in every use (indexing, slicing, iteration, ==), but the `Scan` objects
    are built on first use only: the fast engine's timeline reads the flat arrays (`timeline.
    from_run`), and building some 1,100 objects per run cost more than its filters."""

    def __init__(self, steps: np.ndarray, ids: np.ndarray, z: np.ndarray, start: np.ndarray):
        self.steps, self.ids, self.z, self.start = steps, ids, z, start
        self._scans: tuple[Scan, ...] | None = None

    @property
    def scans(self) -> tuple[Scan, ...]:
        if self._scans is None:
            bounds = zip(self.start[:-1].tolist(), self.start[1:].tolist(), strict=True)
            self._scans = tuple(
                Scan(step=k, ids=self.ids[a:b], z=self.z[a:b])
                for k, (a, b) in zip(self.steps.tolist(), bounds, strict=True)
            )
        return self._scans

    def __len__(self) -> int:
        return len(self.steps)

    def __getitem__(self, i):
        return self.scans[i]

    def __iter__(self):
        return iter(self.scans)

    def __eq__(self, other) -> bool:
        return tuple(self) == tuple(other) if isinstance(other, Sequence) else NotImplemented

    __hash__ = None

    def __getstate__(self) -> dict:  # the flat arrays only: the Scan objects are rebuilt
        return {"steps": self.steps, "ids": self.ids, "z": self.z, "start": self.start}

    def __setstate__(self, state: dict) -> None:
        self.__init__(**state)

    def __repr__(self) -> str:
        return f"Scans({len(self)} scans, {len(self.ids)} measurements)"


@dataclass(frozen=True)
class RunData:
    """Everything one Monte Carlo run feeds to every filter (common random numbers)."""

    truth: Truth
    u_odo: np.ndarray  # (K, 2) odometry the filters receive
    scans: tuple[Scan, ...] | Scans


_STEPS_PER_CALL = 1 << 16  # the truth loop's buffer: routes longer than this resume
# The bicycle's step as the filters' models take it (models.motion_terms, written once; the
# kernels compile the same terms). Compiled or not, the same scalar arithmetic (libm's sin, cos,
# atan2 and Python's float %), so the same bytes.
_step_terms, _jacobians_at, _wrap = (
    maybe_njit(step_terms), maybe_njit(jacobians_at), maybe_njit(wrap_scalar),
)  # fmt: skip


@maybe_njit
def _drive(wp, state, params, xs, us):
    """Bailey's steering controller from `state` = (x, y, phi, gamma, iwp, loops_left) until the
    route is done or the buffers xs (n + 1, 3) / us (n, 2) are full (xs[0] is the start pose);
    returns (steps written, done) and leaves the state for a next call in `state`."""
    T, V, B, tol2, max_delta, max_steer = params
    x, y, phi, gamma = state[0], state[1], state[2], state[3]
    iwp, loops_left = int(state[4]), int(state[5])
    xs[0, 0], xs[0, 1], xs[0, 2] = x, y, phi
    n, done = 0, False
    bicycle = np.int64(MOTION_BICYCLE)  # not the literal: step_terms compiles once, as the kernels'
    while n < len(us):
        if (wp[iwp, 0] - x) ** 2 + (wp[iwp, 1] - y) ** 2 < tol2:
            iwp += 1
            if iwp == len(wp):
                loops_left -= 1
                if loops_left == 0:
                    done = True
                    break
                iwp = 0
        delta = _wrap(math.atan2(wp[iwp, 1] - y, wp[iwp, 0] - x) - phi - gamma)
        delta = min(max(delta, -max_delta), max_delta)
        gamma = min(max(gamma + delta, -max_steer), max_steer)
        terms = _step_terms(V, gamma, T, bicycle, B)
        f02, f12, _ = _jacobians_at(phi, terms)
        x, y, phi = x + f12, y - f02, _wrap(phi + terms[8])
        n += 1
        xs[n, 0], xs[n, 1], xs[n, 2] = x, y, phi
        us[n - 1, 0], us[n - 1, 1] = V, gamma
    state[0], state[1], state[2], state[3] = x, y, phi, gamma
    state[4], state[5] = iwp, loops_left
    return n, done


JIT_TRUTH: bool = is_compiled(_drive)  # whether the truth loop is numba-compiled


def simulate_truth(world: World) -> Truth:
    """Drive the waypoints with Bailey's steering controller on the TRUE pose (SPEC 1).

    Computed once per world (kept for the next call: the plan's checks, the batch and the
    fits all drive the same route), the loop compiled when numba is installed (`_drive`)."""
    key = _truth_key(world)
    if key not in _TRUTHS:
        _TRUTHS[key] = _drive_route(world)
        while len(_TRUTHS) > 8:
            _TRUTHS.pop(next(iter(_TRUTHS)))
    x, u = _TRUTHS[key]
    return Truth(x=x.copy(), u=u.copy())


_TRUTHS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _truth_key(world: World) -> tuple:
    wp = np.ascontiguousarray(world.waypoints, dtype=float)
    x0 = np.ascontiguousarray(world.x0, dtype=float)
    scalars = (world.loops, world.V, world.B, world.max_steer, world.max_steer_rate, world.T)
    return (wp.shape, wp.tobytes(), x0.tobytes(), scalars, world.waypoint_tolerance,
            world.max_steps)  # fmt: skip


def _drive_route(world: World) -> tuple[np.ndarray, np.ndarray]:
    wp = np.ascontiguousarray(world.waypoints, dtype=float).reshape(-1, 2)
    x0 = [float(v) for v in world.x0]
    state = np.array([*x0, 0.0, 0.0, float(world.loops)])
    params = (float(world.T), float(world.V), float(world.B), world.waypoint_tolerance**2,
              world.max_steer_rate * world.T, float(world.max_steer))  # fmt: skip
    xs_parts, us_parts, total = [np.array([x0])], [], 0
    while True:
        room = min(_STEPS_PER_CALL, world.max_steps - total)
        xs, us = np.empty((room + 1, 3)), np.empty((room, 2))
        n, done = _drive(wp, state, params, xs, us)
        xs_parts.append(xs[1 : n + 1])
        us_parts.append(us[:n])
        total += n
        if done:
            break
        if total >= world.max_steps:
            raise RouteNotCompleted(
                f"route not completed within world.max_steps = {world.max_steps} control steps"
            )
    return np.concatenate(xs_parts), np.concatenate(us_parts).reshape(-1, 2)


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
    """Every scan's true landmark geometry along the truth path, once per world: `_sight` of
    every scan's pose at once (the same elementwise operations, so the same bytes)."""
    steps = np.arange(world.sensor_every, len(truth.u) + 1, world.sensor_every)
    poses = truth.x[steps]
    d = world.landmarks[None, :, :] - poses[:, None, :2]
    rng_ = np.hypot(d[..., 0], d[..., 1])
    bearing = wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - poses[:, 2:3])
    seen = (rng_ < world.max_range) & (np.abs(bearing) < world.half_fov)
    n, L = len(steps), len(world.landmarks)
    return ScanGeometry(
        steps=steps,
        range=rng_.reshape(n, L),
        bearing=bearing.reshape(n, L),
        ids=tuple(np.flatnonzero(row) for row in seen),
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
    if blackout is not None and blackout.any():  # a dark scan sees nothing
        lit = ~blackout[scan_of]
        ids, z = ids[lit], z[lit]
        start = np.zeros_like(start)
        np.cumsum(np.bincount(scan_of[lit], minlength=len(geometry.steps)), out=start[1:])
    scans = Scans(geometry.steps, ids, z, start)
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
