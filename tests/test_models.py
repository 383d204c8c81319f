"""Motion and measurement models: Jacobians against central finite differences, angle wrapping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.models import (
    H_jacobian,
    f,
    h,
    jacobians,
    residual_z,
    wrap_angle,
    wrap_scalar,
)

T, B = 0.025, 4.0
rng = np.random.default_rng(12)
POSES = {
    "origin": np.array([0.0, 0.0, 0.0]),
    "turned": np.array([3.0, -2.0, 2.5]),
    "near-pi": np.array([-10.0, 4.0, math.pi - 0.01]),
    "random": np.array([*rng.uniform(-50, 50, 2), rng.uniform(-3, 3)]),
}
CONTROLS = {
    "straight": np.array([3.0, 0.0]),
    "left": np.array([3.0, math.radians(25)]),
    "right-slow": np.array([0.7, -math.radians(30)]),
}
LANDMARKS = {"ahead": np.array([15.0, 3.0]), "behind-left": np.array([-20.0, 12.0])}


def central_diff(fun, x0: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(len(x0)):
        dx = np.zeros_like(x0)
        dx[i] = eps
        d = fun(x0 + dx) - fun(x0 - dx)
        cols.append(d / (2 * eps))
    return np.column_stack(cols)


def no_wrap_f(x, u):
    V, g = u
    return np.array(
        [
            x[0] + T * V * math.cos(x[2] + g),
            x[1] + T * V * math.sin(x[2] + g),
            x[2] + T * V * math.sin(g) / B,
        ]
    )


@pytest.mark.parametrize("u", CONTROLS.values(), ids=CONTROLS.keys())
@pytest.mark.parametrize("x", POSES.values(), ids=POSES.keys())
def test_motion_jacobians_match_finite_differences(x, u):
    F, G = jacobians(x, u, T, B)
    np.testing.assert_allclose(F, central_diff(lambda s: no_wrap_f(s, u), x), atol=1e-8)
    np.testing.assert_allclose(G, central_diff(lambda c: no_wrap_f(x, c), u), atol=1e-8)


@pytest.mark.parametrize("u", CONTROLS.values(), ids=CONTROLS.keys())
@pytest.mark.parametrize("x", POSES.values(), ids=POSES.keys())
def test_motion_model_is_paper_eq_17_with_wrapped_heading(x, u):
    out = f(x, u, T, B)
    ref = no_wrap_f(x, u)
    np.testing.assert_allclose(out[:2], ref[:2], atol=1e-14)
    assert out[2] == pytest.approx(wrap_scalar(ref[2]), abs=1e-14)


@pytest.mark.parametrize("lm", LANDMARKS.values(), ids=LANDMARKS.keys())
@pytest.mark.parametrize("x", POSES.values(), ids=POSES.keys())
def test_measurement_jacobian_matches_finite_differences(x, lm):
    def h_smooth(s):
        z = h(s, lm)
        # unwrap the bearing around its value at x so the difference quotient is smooth
        z[1] = h(x, lm)[1] + wrap_scalar(z[1] - h(x, lm)[1])
        return z

    np.testing.assert_allclose(H_jacobian(x, lm), central_diff(h_smooth, x), atol=1e-7)


def test_measurement_is_range_and_relative_bearing():
    z = h(np.array([1.0, 1.0, math.pi / 2]), np.array([1.0, 6.0]))
    assert z[0] == pytest.approx(5.0)
    assert z[1] == pytest.approx(0.0, abs=1e-15)
    z = h(np.array([0.0, 0.0, 0.0]), np.array([0.0, -3.0]))
    assert z[1] == pytest.approx(-math.pi / 2)


@pytest.mark.parametrize(
    "a, expected",
    [(math.pi, math.pi), (-math.pi, math.pi), (3 * math.pi, math.pi), (0.5, 0.5),
     (-0.5, -0.5), (2 * math.pi + 0.1, 0.1), (-2 * math.pi - 0.1, -0.1)],
    ids=["pi", "minus-pi", "3pi", "small", "small-neg", "over-2pi", "under-minus-2pi"],
)  # fmt: skip
def test_wrap_angle_maps_to_half_open_interval(a, expected):
    assert wrap_scalar(a) == pytest.approx(expected, abs=1e-12)
    assert float(wrap_angle(a)) == pytest.approx(expected, abs=1e-12)


def test_residual_wraps_bearing_only():
    y = residual_z(np.array([5.0, math.pi - 0.05]), np.array([4.0, -math.pi + 0.05]))
    assert y[0] == pytest.approx(1.0)
    assert y[1] == pytest.approx(-0.1)
