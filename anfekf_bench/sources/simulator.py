"""Truth simulation (SPEC section 1): waypoint-driven car, noisy odometry, range-bearing scans."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import World
from ..models import wrap_angle, wrap_scalar


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


def observe(world: World, pose: np.ndarray, noise: np.ndarray, step: int) -> Scan:
    """Scan of every landmark in range (< max_range) and in the field of view, eq. (18)."""
    d = world.landmarks - pose[:2]
    rng_ = np.hypot(d[:, 0], d[:, 1])
    bearing = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - pose[2])
    seen = (rng_ < world.max_range) & (np.abs(bearing) < world.half_fov)
    ids = np.flatnonzero(seen)
    z = np.column_stack([rng_[ids] + noise[ids, 0], wrap_angle(bearing[ids] + noise[ids, 1])])
    return Scan(step=step, ids=ids, z=z)


def simulate_run(
    world: World,
    truth: Truth,
    true_sigmas: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> RunData:
    """Odometry and scans of one run, every draw from `rng` (SPEC 6).

    Draw order is fixed: all odometry noise, then all measurement noise (one pair per landmark per
    scan, seen or not), so a run's data depend on its seed only.
    """
    sv, sg, sr, sb = true_sigmas
    K = len(truth.u)
    u_odo = truth.u + rng.standard_normal((K, 2)) * np.array([sv, sg])
    scan_steps = range(world.sensor_every, K + 1, world.sensor_every)
    noise = rng.standard_normal((len(scan_steps), len(world.landmarks), 2)) * np.array([sr, sb])
    scans = tuple(observe(world, truth.x[k], noise[i], k) for i, k in enumerate(scan_steps))
    return RunData(truth=truth, u_odo=u_odo, scans=scans)
