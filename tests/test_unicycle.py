"""Unicycle model: Jacobians vs central differences, wrapping, hand steps, rate-consistent Q."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.models import MotionModel, Unicycle, wrap_angle

MODEL = Unicycle()
rng = np.random.default_rng(2024)


def central_diff(fun, x0: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(len(x0)):
        dx = np.zeros_like(x0)
        dx[i] = eps
        d = fun(x0 + dx) - fun(x0 - dx)
        d[2] = wrap_angle(d[2])  # the heading output is wrapped: difference across the cut
        cols.append(d / (2 * eps))
    return np.column_stack(cols)


def _cases():
    cases = [
        (np.array([0.0, 0.0, 0.0]), np.array([0.14, 0.0]), 0.12),
        (np.array([1.0, -4.0, math.pi - 1e-3]), np.array([0.165, 0.902]), 0.12),
        (np.array([-2.0, 3.0, -math.pi + 1e-3]), np.array([0.165, -1.003]), 0.368),
        (np.array([0.5, 0.5, math.pi]), np.array([0.0, 0.9]), 0.05),
    ]
    for _ in range(8):
        x = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-math.pi, math.pi)])
        u = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-2, 2)])
        cases.append((x, u, float(rng.uniform(0.01, 0.5))))
    return cases


CASES = _cases()


def test_is_a_motion_model():
    assert isinstance(MODEL, MotionModel)


@pytest.mark.parametrize("x, u, dt", CASES)
def test_F_matches_central_differences(x, u, dt):
    num = central_diff(lambda xx: MODEL.f(xx, u, dt), x)
    np.testing.assert_allclose(MODEL.jacobians(x, u, dt)[0], num, atol=1e-8)


@pytest.mark.parametrize("x, u, dt", CASES)
def test_G_matches_central_differences(x, u, dt):
    num = central_diff(lambda uu: MODEL.f(x, uu, dt), u)
    np.testing.assert_allclose(MODEL.jacobians(x, u, dt)[1], num, atol=1e-8)


def test_heading_is_wrapped():
    out = MODEL.f(np.array([0.0, 0.0, math.pi - 0.05]), np.array([0.0, 1.0]), 0.1)
    assert out[2] == pytest.approx(-math.pi + 0.05)
    out = MODEL.f(np.array([0.0, 0.0, -math.pi + 0.05]), np.array([0.0, -1.0]), 0.1)
    assert out[2] == pytest.approx(math.pi - 0.05)
    for x, u, dt in CASES:
        assert -math.pi < MODEL.f(x, u, dt)[2] <= math.pi


def test_straight_line_by_hand():
    x = np.array([1.0, 2.0, math.pi / 6])
    out = MODEL.f(x, np.array([0.5, 0.0]), 2.0)  # 1 m along 30 degrees
    np.testing.assert_allclose(out, [1.0 + math.sqrt(3) / 2, 2.5, math.pi / 6], atol=1e-12)


def test_pure_rotation_by_hand():
    x = np.array([1.0, 2.0, 0.3])
    out = MODEL.f(x, np.array([0.0, -0.5]), 0.4)
    np.testing.assert_allclose(out, [1.0, 2.0, 0.1], atol=1e-12)


def test_arc_uses_the_midpoint_heading():
    # v = 1, w = pi/2 for 1 s: chord of length 1 along heading pi/4
    out = MODEL.f(np.zeros(3), np.array([1.0, math.pi / 2]), 1.0)
    np.testing.assert_allclose(out, [math.sqrt(0.5), math.sqrt(0.5), math.pi / 2], atol=1e-12)


def _noise_in_steps(x, u, dt, n, Qu, model=MODEL):
    """Total state noise of n equal steps covering dt (first-order propagation)."""
    h = dt / n
    P = np.zeros((3, 3))
    for _ in range(n):
        F, G = model.jacobians(x, u, h)
        P = F @ P @ F.T + model.Q(G, Qu, h)
        x = model.f(x, u, h)
    return P


@pytest.mark.parametrize("x, u", [(c[0], c[1]) for c in CASES[:6]])
def test_rate_consistency_two_half_steps(x, u):
    Qu = np.diag([0.1**2, 0.2**2])
    errs = []
    for dt in (0.1, 0.05, 0.025):
        one = _noise_in_steps(x, u, dt, 1, Qu)
        two = _noise_in_steps(x, u, dt, 2, Qu)
        # the first-order (O(dt)) terms agree: what is left is O(dt^2), small against the total
        rel = np.linalg.norm(two - one) / np.linalg.norm(one)
        assert rel < 0.05 * dt / 0.1
        errs.append(rel)
    assert errs[2] <= errs[0] / 3 + 1e-12  # and it shrinks at least linearly with dt


def test_rate_consistency_many_steps_and_the_textbook_form_is_not():
    x, u, dt = np.array([0.0, 0.0, 0.4]), np.array([0.15, 0.9]), 0.12
    Qu = np.diag([0.05**2, 0.1**2])
    one = _noise_in_steps(x, u, dt, 1, Qu)
    ten = _noise_in_steps(x, u, dt, 10, Qu)
    np.testing.assert_allclose(np.diag(ten), np.diag(one), rtol=0.02)

    class Textbook(Unicycle):
        def Q(self, G, Qu, dt):
            return G @ Qu @ G.T

    tb = Textbook()
    ratio = np.diag(_noise_in_steps(x, u, dt, 2, Qu, tb)) / np.diag(
        _noise_in_steps(x, u, dt, 1, Qu, tb)
    )
    assert ratio[2] == pytest.approx(0.5)  # per-step noise halves when the interval is split


def test_a_step_of_T0_is_the_textbook_form_and_zero_dt_is_no_noise():
    x, u = np.array([0.3, 0.1, -2.0]), np.array([0.142, 0.0])
    Qu = np.diag([0.1**2, 0.1**2])
    G = MODEL.jacobians(x, u, MODEL.T0)[1]
    np.testing.assert_allclose(MODEL.Q(G, Qu, MODEL.T0), G @ Qu @ G.T)
    assert not MODEL.Q(MODEL.jacobians(x, u, 0.0)[1], Qu, 0.0).any()
    np.testing.assert_array_equal(MODEL.f(x, u, 0.0), x)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_bad_T0_is_refused(bad):
    with pytest.raises(ValueError, match="T0"):
        Unicycle(T0=bad)
