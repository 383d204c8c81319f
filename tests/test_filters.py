"""EKF against hand-written Kalman equations; ANFEKF reduces to the EKF; adaptation behaviour."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import (
    ANFEKF,
    ANFEKFSpec,
    RobotEKF,
    anfis,
    build_filter,
    gate_threshold,
    q_step,
    r_step,
)
from anfekf_bench.models import Bicycle, H_jacobian, f, h, jacobians, wrap_scalar
from anfekf_bench.sources.simulator import simulate_run, simulate_truth

from .conftest import small_scenario

T, B = 0.025, 4.0
Qu = np.diag([0.3**2, math.radians(3) ** 2])
R = np.diag([0.1**2, math.radians(1) ** 2])


def make_ekf(gate=None, cls=RobotEKF, **kw):
    P0 = np.diag([0.2, 0.3, 0.05])
    return cls(
        x0=np.array([1.0, 2.0, 0.3]), P0=P0, Qu=Qu, R=R, model=Bicycle(T, B), dt=T, gate=gate, **kw
    )


def test_one_ekf_step_equals_hand_written_kalman_step():
    ekf = make_ekf()
    x, P = ekf.x.copy(), ekf.P.copy()
    u = np.array([3.0, 0.2])
    lm = np.array([12.0, 7.0])
    z = np.array([12.5, 0.15])

    # predict, eqs. (19)-(21)
    a = x[2] + u[1]
    F = np.array([[1, 0, -T * u[0] * math.sin(a)], [0, 1, T * u[0] * math.cos(a)], [0, 0, 1]])
    G = jacobians(x, u, T, B)[1]
    x_pred = f(x, u, T, B)
    P_pred = F @ P @ F.T + G @ Qu @ G.T
    # update, eqs. (22)-(29) with the Joseph form
    H = H_jacobian(x_pred, lm)
    nu = z - h(x_pred, lm)
    nu[1] = wrap_scalar(nu[1])
    S = H @ P_pred @ H.T + R
    K = P_pred @ H.T @ np.linalg.inv(S)
    x_post = x_pred + K @ nu
    I_KH = np.eye(3) - K @ H
    P_post = I_KH @ P_pred @ I_KH.T + K @ R @ K.T

    ekf.predict(u)
    np.testing.assert_allclose(ekf.x, x_pred, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ekf.P, P_pred, rtol=0, atol=1e-12)
    assert ekf.update_landmark(z, lm)
    np.testing.assert_allclose(ekf.x, x_post, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ekf.P, P_post, rtol=0, atol=1e-12)
    assert np.array_equal(ekf.P, ekf.P.T)


def test_joseph_update_equals_simple_form_for_optimal_gain():
    """Two forms of one algorithm: (I-KH)P(I-KH)^T + KRK^T == (I-KH)P when K is optimal."""
    ekf = make_ekf()
    ekf.predict(np.array([3.0, -0.1]))
    lm = np.array([-4.0, 15.0])
    H = H_jacobian(ekf.x, lm)
    P = ekf.P.copy()
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    ekf.update_landmark(h(ekf.x, lm) + np.array([0.05, 0.01]), lm)
    np.testing.assert_allclose(ekf.P, (np.eye(3) - K @ H) @ P, rtol=0, atol=1e-12)


def test_gate_rejects_outlier_and_counts_it():
    ekf = make_ekf(gate=gate_threshold(0.999))
    assert gate_threshold(0.999) == pytest.approx(13.8155, abs=1e-3)
    assert gate_threshold(None) is None
    lm = np.array([10.0, 2.0])
    x_before = ekf.x.copy()
    assert not ekf.update_landmark(h(ekf.x, lm) + np.array([50.0, 0.0]), lm)
    assert np.array_equal(ekf.x, x_before)
    assert (ekf.n_rejected, ekf.n_updates) == (1, 0)
    assert ekf.update_landmark(h(ekf.x, lm) + np.array([0.05, 0.0]), lm)
    assert (ekf.n_rejected, ekf.n_updates) == (1, 1)


def test_bearing_innovation_is_wrapped_across_pi():
    ekf = make_ekf()
    ekf.x = np.array([0.0, 0.0, 0.0])
    lm = np.array([-10.0, 1e-3])  # bearing just below +pi
    z = np.array([10.0, -math.pi + 1e-3])  # measured just above -pi: a tiny true difference
    ekf.update_landmark(z, lm)
    assert abs(ekf.y[1]) < 0.01


@pytest.fixture(scope="module")
def small_run():
    scenario = parse_scenario(small_scenario())
    world = resolve_world(scenario.world, __import__("pathlib").Path("x.yaml"))
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(3))
    return scenario, world, data


def _run(spec, scenario, world, data):
    flt = build_filter(spec, scenario, world)
    return flt, run_filter(flt, data, world, 1)


def test_anfekf_without_adaptation_or_learning_equals_ekf(small_run):
    scenario, world, data = small_run
    ekf_spec = scenario.filters[0]
    frozen = ANFEKFSpec(name="a", kind="anfekf", adaptation=False, learning=False)
    _, ekf = _run(ekf_spec, scenario, world, data)
    _, ada = _run(frozen, scenario, world, data)
    np.testing.assert_allclose(ada["x"], ekf["x"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ada["P"], ekf["P"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ada["R_diag"], ekf["R_diag"])


@pytest.mark.parametrize("adapt", ["R", "Q"])
def test_anfekf_adapts_and_learns(small_run, adapt):
    scenario, world, data = small_run
    spec = ANFEKFSpec(name="a", kind="anfekf", adapt=adapt)
    flt, trace = _run(spec, scenario, world, data)
    col = "R_diag" if adapt == "R" else "Q_diag"
    assert not np.allclose(trace[col][-1], trace[col][0])
    untrained = anfis.init_params(singleton_scale=spec.singleton_scale)
    assert not np.allclose(flt.anfis_params[0].w, untrained.w)
    assert not np.allclose(
        flt.anfis_params[0].m, _run(frozen_spec(adapt), *small_run)[0].anfis_params[0].m
    )


def frozen_spec(adapt):
    return ANFEKFSpec(name="f", kind="anfekf", adapt=adapt, learning=False)


def _supervised(nu_scale: float, adapt: str, n: int = 60, seed: int = 0):
    """Feed innovations of a chosen spread into the supervisor with a fixed H P H^T."""
    ekf = make_ekf(cls=ANFEKF, params=ANFEKFSpec(name="a", kind="anfekf", adapt=adapt, window=10))
    rng = np.random.default_rng(seed)
    HPHt = np.diag([0.01, 1e-4])
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])
    ekf.Q_interval = np.diag([1e-3, 1e-3, 1e-4])
    R0, Q0 = np.diag(ekf.R).copy(), np.diag(ekf.Qu).copy()
    for _ in range(n):
        ekf.supervise(rng.standard_normal(2) * nu_scale, H, HPHt)
    return ekf, R0, Q0


def test_positive_mismatch_lowers_R_and_negative_raises_it():
    """S > C (innovations smaller than predicted) -> R shrinks; S < C -> R grows."""
    small, R0, _ = _supervised(1e-4, "R")
    assert np.all(np.diag(small.R) < R0)
    large, R0, _ = _supervised(10.0, "R")
    assert np.all(np.diag(large.R) > R0)


def test_positive_mismatch_lowers_Q_and_negative_raises_it():
    small, _, Q0 = _supervised(1e-4, "Q")
    assert np.all(np.diag(small.Qu) < Q0)
    large, _, Q0 = _supervised(10.0, "Q")
    assert np.all(np.diag(large.Qu) > Q0)


@pytest.mark.parametrize("adapt", ["R", "Q"])
@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e3, 1e12], ids=["tiny", "small", "big", "huge"])
def test_covariances_stay_positive_definite_under_extreme_innovations(adapt, scale):
    ekf, _, _ = _supervised(scale, adapt, n=300)
    for M in (ekf.R, ekf.Qu):
        assert np.all(np.isfinite(M))
        assert np.all(np.linalg.eigvalsh(M) > 0)
    for p in ekf.anfis_params:
        assert np.all(np.isfinite(p.w)) and np.all(p.delta > 0)


def test_supervisor_waits_for_a_full_window():
    ekf = make_ekf(cls=ANFEKF, params=ANFEKFSpec(name="a", kind="anfekf", window=20))
    H = H_jacobian(ekf.x, np.array([10.0, 5.0]))
    for _ in range(19):
        ekf.supervise(np.array([5.0, 0.5]), H, np.diag([0.01, 1e-4]))
    np.testing.assert_array_equal(ekf.R, R)
    ekf.supervise(np.array([5.0, 0.5]), H, np.diag([0.01, 1e-4]))
    assert not np.array_equal(ekf.R, R)
    np.testing.assert_allclose(np.mean(ekf.window, axis=0), [25.0, 0.25])


PARAM_SETS = {
    "default": anfis.init_params(),
    "perturbed": anfis.ANFISParams(
        m=anfis.init_params().m + np.random.default_rng(1).normal(0, 0.05, (2, 5)),
        delta=anfis.init_params().delta * np.random.default_rng(2).uniform(0.8, 1.3, (2, 5)),
        w=anfis.init_params().w + np.random.default_rng(3).normal(0, 0.05, 7),
    ),
}


def _fd_check(loss, params: anfis.ANFISParams, grad: anfis.ANFISParams, eps=1e-6):
    """Central differences of loss(params) for every parameter against the analytic grad."""
    for kind in ("m", "delta", "w"):
        base = getattr(params, kind)
        analytic = getattr(grad, kind)
        for idx in np.ndindex(base.shape):
            plus, minus = base.copy(), base.copy()
            plus[idx] += eps
            minus[idx] -= eps
            num = (
                loss(dataclasses.replace(params, **{kind: plus}))
                - loss(dataclasses.replace(params, **{kind: minus}))
            ) / (2 * eps)
            assert num == pytest.approx(analytic[idx], rel=1e-5, abs=1e-8), (kind, idx)


@pytest.mark.parametrize("params", PARAM_SETS.values(), ids=PARAM_SETS.keys())
@pytest.mark.parametrize(
    "u, R_ii, HPH_ii, C_ii",
    [
        ((0.6, 0.05), 4.0, 0.5, 0.3),
        ((-0.4, -0.1), 0.01, 0.002, 0.5),
        ((0.1, 0.0), 1e-4, 1e-4, 2e-4),
    ],
    ids=["S-above-C", "S-below-C", "near-match"],
)
def test_r_step_loss_gradient_matches_finite_differences(params, u, R_ii, HPH_ii, C_ii):
    """The filter-level dE/dW (eq. 42 through R' = R e^o) against differences of E(W)."""
    _, _, grad = r_step(params, u, R_ii, HPH_ii, C_ii, clip=1.0)
    assert grad is not None
    _fd_check(lambda p: r_step(p, u, R_ii, HPH_ii, C_ii, clip=1.0)[1], params, grad)


@pytest.mark.parametrize("params", PARAM_SETS.values(), ids=PARAM_SETS.keys())
@pytest.mark.parametrize(
    "u, S, C, dS",
    [((0.5, 0.3), [0.2, 0.01], [0.1, 0.008], [0.05, 0.004]),
     ((-0.6, -0.2), [0.02, 0.001], [0.3, 0.004], [0.015, 0.0008])],
    ids=["S-above-C", "S-below-C"],
)  # fmt: skip
def test_q_step_loss_gradient_matches_finite_differences(params, u, S, C, dS):
    S, C, dS = np.array(S), np.array(C), np.array(dS)
    _, _, grad = q_step(params, u, S, C, dS, clip=1.0)
    assert grad is not None
    _fd_check(lambda p: q_step(p, u, S, C, dS, clip=1.0)[1], params, grad)


def test_clipped_output_has_no_gradient():
    big = anfis.init_params(singleton_scale=5.0)  # outputs far beyond the clip
    R_new, _, grad = r_step(big, (-1.0, -0.2), 1.0, 0.1, 5.0, clip=1.0)
    assert grad is None and R_new == pytest.approx(math.e)


def test_learning_step_lowers_the_remaining_mismatch():
    """One SD step on the filter's own loss moves E down (the sign of eq. 42 is right)."""
    params = anfis.init_params()
    u, R_ii, HPH_ii, C_ii = (0.5, 0.05), 2.0, 0.1, 0.2
    _, E0, grad = r_step(params, u, R_ii, HPH_ii, C_ii, clip=1.0)
    stepped = anfis.sgd_step(params, grad, 0.5)
    assert r_step(stepped, u, R_ii, HPH_ii, C_ii, clip=1.0)[1] < E0


def test_update_equals_filterpy_linear_kalman_filter_on_the_linearised_model():
    """EKF = KF where the model is linear: fusing z with H at x- is the KF update of
    z_lin = nu + H x- (filterpy's KalmanFilter, an independent implementation)."""
    from filterpy.kalman import KalmanFilter

    ekf = make_ekf()
    ekf.predict(np.array([3.0, 0.1]))
    kf = KalmanFilter(dim_x=3, dim_z=2)
    kf.x, kf.P = ekf.x.copy(), ekf.P.copy()
    for lm, noise in (
        (np.array([12.0, 7.0]), [0.1, -0.02]),
        (np.array([-3.0, 9.0]), [-0.05, 0.01]),
    ):
        H = H_jacobian(ekf.x, lm)
        z = h(ekf.x, lm) + np.array(noise)
        nu = z - h(ekf.x, lm)
        kf.update(nu + H @ kf.x, R=R, H=H)
        ekf.update_landmark(z, lm)
        np.testing.assert_allclose(ekf.x, kf.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ekf.P, kf.P, rtol=0, atol=1e-12)
