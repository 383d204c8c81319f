"""The simulator's compiled and vectorised paths (issue 37) give the bytes of the plain loops."""

from __future__ import annotations

import dataclasses
import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from anfekf_bench.models import wrap_angle, wrap_scalar
from anfekf_bench.sources import simulator
from anfekf_bench.sources.simulator import (
    RouteNotCompleted,
    Scan,
    Scans,
    scan_geometry,
    simulate_run,
    simulate_truth,
)
from anfekf_bench.timeline import clear_cache, from_run


def reference_truth(world) -> tuple[np.ndarray, np.ndarray]:
    """The truth loop as it was written before it was compiled: one Python step at a time."""
    wp = world.waypoints
    tol2 = world.waypoint_tolerance**2
    max_delta = world.max_steer_rate * world.T
    T, V, B = world.T, world.V, world.B
    x, y, phi = (float(v) for v in world.x0)
    gamma = 0.0
    iwp, loops_left = 0, world.loops
    xs, us = [(x, y, phi)], []
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
            raise RouteNotCompleted("max_steps")
    return np.array(xs), np.array(us).reshape(-1, 2)


@pytest.fixture
def small_world(small_world_and_scenario):
    return small_world_and_scenario[1]


@pytest.fixture
def small_world_and_scenario():
    from anfekf_bench.config import parse_scenario, resolve_world

    from .conftest import small_scenario

    scenario = parse_scenario(small_scenario())
    return scenario, resolve_world(scenario.world, Path("x.yaml"))


def _worlds(world):
    yield world
    yield dataclasses.replace(world, loops=3)
    yield dataclasses.replace(world, x0=np.array([1.0, -2.0, 0.7]), V=1.3, max_steer=0.3)
    yield dataclasses.replace(world, waypoints=world.waypoints[::-1].copy(), T=0.04)


def test_truth_is_the_plain_loops_bytes(small_world, monkeypatch):
    monkeypatch.setattr(simulator, "_STEPS_PER_CALL", 97)  # resume across many buffers
    for world in _worlds(small_world):
        simulator._TRUTHS.clear()
        x, u = reference_truth(world)
        truth = simulate_truth(world)
        assert truth.x.tobytes() == x.tobytes() and truth.u.tobytes() == u.tobytes()
        again = simulate_truth(world)  # kept per world: the same bytes, a copy of its own
        assert again.x.tobytes() == x.tobytes() and again.x is not truth.x


def test_route_not_completed_at_the_same_step(small_world, monkeypatch):
    monkeypatch.setattr(simulator, "_STEPS_PER_CALL", 50)
    steps = len(reference_truth(small_world)[1])
    for limit in (steps, steps + 1, 49, 50, 51):
        world = dataclasses.replace(small_world, max_steps=limit)
        simulator._TRUTHS.clear()
        try:
            expected = len(reference_truth(world)[1])
        except RouteNotCompleted:
            with pytest.raises(RouteNotCompleted, match=f"max_steps = {limit} control"):
                simulate_truth(world)
        else:
            assert len(simulate_truth(world).u) == expected


def test_scan_geometry_is_one_sight_at_a_time(small_world):
    truth = simulate_truth(small_world)
    geometry = scan_geometry(small_world, truth)
    for i, k in enumerate(geometry.steps):
        d = small_world.landmarks - truth.x[k, :2]
        rng = np.hypot(d[:, 0], d[:, 1])
        bearing = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - truth.x[k, 2])
        seen = (rng < small_world.max_range) & (np.abs(bearing) < small_world.half_fov)
        assert geometry.range[i].tobytes() == rng.tobytes()
        assert geometry.bearing[i].tobytes() == bearing.tobytes()
        np.testing.assert_array_equal(geometry.ids[i], np.flatnonzero(seen))


def test_scans_are_a_tuple_of_scan_in_every_use(small_world_and_scenario):
    scenario, world = small_world_and_scenario
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(3))
    scans = data.scans
    assert isinstance(scans, Scans) and len(scans) == len(scan_geometry(world, truth).steps)
    as_tuple = tuple(scans)
    assert all(isinstance(s, Scan) for s in as_tuple)
    assert scans[0] is as_tuple[0] and scans[1:3] == as_tuple[1:3] and scans == as_tuple
    assert scans.index(as_tuple[2]) == 2  # built once: the same objects every time
    flat_z = np.concatenate([s.z for s in as_tuple])
    assert flat_z.tobytes() == scans.z.tobytes()
    back = pickle.loads(pickle.dumps(scans))
    assert len(back) == len(as_tuple) and back.z.tobytes() == scans.z.tobytes()
    for a, b in zip(back, as_tuple, strict=True):
        assert a.step == b.step and a.ids.tobytes() == b.ids.tobytes()
        assert a.z.tobytes() == b.z.tobytes()


def test_timeline_reads_the_flat_scans_as_the_scan_objects(small_world_and_scenario):
    scenario, world = small_world_and_scenario
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(5))
    clear_cache()
    flat = from_run(data, world, 4)
    clear_cache()
    objects = from_run(dataclasses.replace(data, scans=tuple(data.scans)), world, 4)
    clear_cache()
    for field in ("t", "dt", "u", "lm", "z", "xy", "record"):
        a, b = getattr(flat, field), getattr(objects, field)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), field
    assert not np.shares_memory(flat.z, data.scans.z)  # the timeline's z is its own
