"""The motion models written once (models.motion_terms): the filterpy engine's `f` and
`jacobians` of both models are bit for bit what their own numpy formulas gave (kept below as the
reference), and the fast engine's kernels compile the very same functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.engines import kernels
from anfekf_bench.models import Bicycle, Unicycle, motion_terms
from anfekf_bench.models.angles import wrap_scalar


def _bicycle_before(x, u, T, B):
    """models.bicycle.f and jacobians as written before motion_terms (the reference)."""
    V, gamma = u[0], u[1]
    a = x[2] + gamma
    f = np.array([x[0] + T * V * math.cos(a), x[1] + T * V * math.sin(a),
                  wrap_scalar(x[2] + T * V * math.sin(gamma) / B)])  # fmt: skip
    ca, sa = math.cos(a), math.sin(a)
    TV = T * V
    F = np.array([[1.0, 0.0, -TV * sa], [0.0, 1.0, TV * ca], [0.0, 0.0, 1.0]])
    G = np.array([[T * ca, -TV * sa], [T * sa, TV * ca],
                  [T * math.sin(gamma) / B, TV * math.cos(gamma) / B]])  # fmt: skip
    return f, F, G


def _unicycle_before(x, u, dt):
    """models.unicycle.Unicycle.f and jacobians as written before motion_terms."""
    v, w = float(u[0]), float(u[1])
    a = x[2] + 0.5 * w * dt
    f = np.array([x[0] + v * dt * math.cos(a), x[1] + v * dt * math.sin(a),
                  wrap_scalar(x[2] + w * dt)])  # fmt: skip
    ca, sa = math.cos(a), math.sin(a)
    half = 0.5 * v * dt * dt
    F = np.array([[1.0, 0.0, -v * dt * sa], [0.0, 1.0, v * dt * ca], [0.0, 0.0, 1.0]])
    G = np.array([[dt * ca, -half * sa], [dt * sa, half * ca], [0.0, dt]])
    return f, F, G


def _cases(n=1000, seed=11):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        scale = 10.0 ** rng.integers(-6, 4)
        x = rng.normal(size=3) * np.array([50.0, 50.0, 4.0])
        u = rng.normal(size=2) * np.array([scale, 1.0])
        dt = float(rng.choice([0.025, 0.12, rng.uniform(0, 2), 0.0]))
        yield x, u, dt


@pytest.mark.parametrize("motion", ["bicycle", "unicycle"])
def test_the_models_are_their_former_formulas_bit_for_bit(motion):
    B = 4.0
    for x, u, dt in _cases():
        if motion == "bicycle":
            want = _bicycle_before(x, u, dt, B)
            model = Bicycle(dt, B)
        else:
            want = _unicycle_before(x, u, dt)
            model = Unicycle(0.12)
        got = (model.f(x, u, dt), *model.jacobians(x, u, dt))
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)


def test_the_kernels_compile_the_models_formulas():
    """engines.kernels' step and Jacobians are motion_terms' functions (compiled when numba is
    in use): the same numbers as the models' arrays."""
    if kernels.JIT:
        assert kernels.step_terms.py_func is motion_terms.step_terms
        assert kernels.jacobians_at.py_func is motion_terms.jacobians_at
    else:
        assert kernels.step_terms is motion_terms.step_terms
    B = 4.0
    for motion, model in ((kernels.MOTION_BICYCLE, None), (kernels.MOTION_UNICYCLE, Unicycle())):
        for x, u, dt in list(_cases(200, seed=5)):
            m = model or Bicycle(dt, B)
            f02, f12, G = kernels.jacobians(x[2], u[0], u[1], dt, motion, B)
            F_want, G_want = m.jacobians(x, u, dt)
            assert (f02, f12) == (F_want[0, 2], F_want[1, 2])
            np.testing.assert_array_equal(np.reshape(G, (3, 2)), G_want)


def test_the_simulators_truth_is_the_bicycle_model_step_by_step():
    """The truth loop (sources.simulator._drive, compiled when numba is in use) steps the pose
    with the same motion terms: every true pose is the filterpy engine's Bicycle.f of the one
    before and the true control, bit for bit."""
    from anfekf_bench.config import WorldConfig, resolve_world
    from anfekf_bench.sources import simulator

    if simulator.JIT_TRUTH:
        assert simulator._step_terms.py_func is motion_terms.step_terms
    world = resolve_world(WorldConfig(), ".")
    truth = simulator.simulate_truth(world)
    model = Bicycle(world.T, world.B)
    assert len(truth.u) > 1000
    for k in range(len(truth.u)):
        np.testing.assert_array_equal(model.f(truth.x[k], truth.u[k], world.T), truth.x[k + 1])
