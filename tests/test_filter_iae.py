"""IAE (Mohamed-Schwarz): hand-computed R and Q steps, warm-up, equality with the EKF when off,
positivity under extreme innovations, and the direction it moves a wrong R or Q."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import Innovation, build_filter
from anfekf_bench.filters.iae import IAEEKF, IAESpec, q_estimate, r_estimate, window_covariance
from anfekf_bench.models import Bicycle
from anfekf_bench.models import h as h_of
from anfekf_bench.sources.simulator import simulate_run, simulate_truth

from .conftest import small_scenario

T, B = 0.025, 4.0
R0 = np.diag([0.04, 1e-3])
QU0 = np.diag([0.5, 0.4])
H_XY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def make(window=2, bounds=(1e-2, 1e2), R=R0, Qu=QU0, **kw) -> IAEEKF:
    spec = IAESpec(name="iae", kind="iae", window=window, bounds=bounds, **kw)
    return IAEEKF(
        x0=np.zeros(3), P0=np.eye(3), Qu=Qu, R=R, model=Bicycle(T, B), dt=T, gate=None,
        params=spec,
    )  # fmt: skip


def inn(nu, hph, H=H_XY) -> Innovation:
    nu = np.asarray(nu, float)
    return Innovation(
        z=nu, landmark=np.zeros(2), z_hat=np.zeros(2), nu=nu, H=H, HPHt=np.asarray(hph, float)
    )


def test_window_covariance_is_the_mean_outer_product():
    # nu1 = (2, 1), nu2 = (0, 1): ((4, 2), (2, 1)) / 2 + ((0, 0), (0, 1)) / 2
    np.testing.assert_allclose(window_covariance(np.array([[2.0, 1.0], [0.0, 1.0]])),
                               [[2.0, 1.0], [1.0, 1.0]])  # fmt: skip


def test_r_step_by_hand_window_and_current_forms():
    """N = 2; nu = (0.3, 0.02), (-0.1, 0.04): diag C = (0.05, 0.001); H P- H^T diagonals
    (0.02, 2e-4), (0.01, 4e-4): window mean (0.015, 3e-4), current (0.01, 4e-4)."""
    for hph, expected in (("window", [0.035, 7e-4]), ("current", [0.04, 6e-4])):
        flt = make(hph=hph)
        flt.begin_scan()
        flt.before_gain(inn([0.3, 0.02], np.diag([0.02, 2e-4])))
        np.testing.assert_array_equal(flt.R, R0)  # warm-up: the window is not full
        flt.before_gain(inn([-0.1, 0.04], np.diag([0.01, 4e-4])))
        np.testing.assert_allclose(np.diag(flt.R), expected, rtol=1e-12)
        assert flt.R[0, 1] == flt.R[1, 0] == 0.0
        # a third innovation pushes out the first: nu = (0.2, 0), H P- H^T diag (0.03, 1e-4)
        # diag C = ((0.01 + 0.04) / 2, (0.0016 + 0) / 2) = (0.025, 8e-4)
        flt.before_gain(inn([0.2, 0.0], np.diag([0.03, 1e-4])))
        third = {"window": [0.025 - 0.02, 8e-4 - 2.5e-4], "current": [0.025 - 0.03, 7e-4]}[hph]
        # current form: range 0.025 - 0.03 < 0 -> the floor 0.01 x 0.04 (the positivity fix)
        third = np.maximum(third, [4e-4, 1e-5])
        np.testing.assert_allclose(np.diag(flt.R), third, rtol=1e-12)


def test_nonpositive_hold_keeps_the_previous_value_of_that_channel():
    """The current form's third step of the case above: range R_hat = 0.025 - 0.03 < 0."""
    flt = make(hph="current", nonpositive="hold")
    flt.before_gain(inn([0.3, 0.02], np.diag([0.02, 2e-4])))
    flt.before_gain(inn([-0.1, 0.04], np.diag([0.01, 4e-4])))
    flt.before_gain(inn([0.2, 0.0], np.diag([0.03, 1e-4])))
    np.testing.assert_allclose(np.diag(flt.R), [0.04, 7e-4], rtol=1e-12)


def test_r_estimate_is_not_clamped_itself():
    np.testing.assert_allclose(r_estimate(np.array([0.01, 0.5]), np.array([0.02, 0.1])),
                               [-0.01, 0.4])  # fmt: skip
    assert r_estimate(0.01, 0.02) == pytest.approx(-0.01)  # one channel (the fast engine's)


def _q_case(q_form: str, q_window: int = 1) -> IAEEKF:
    """P = I at the Q event, H = [I2 0], R = I; a window of 2 innovations (2, 1), (0, 1)."""
    flt = make(adapt="Q", q_form=q_form, q_window=q_window, R=np.eye(2), Qu=np.diag([0.3, 0.3]))
    flt.P = np.eye(3)
    flt.P_scan_start = np.diag([0.2, 0.2, 0.1])
    flt.F_scan = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    flt.A_v, flt.A_g = np.diag([1.0, 0.0, 0.0]), np.diag([0.0, 1.0, 0.0])
    # S = 2 I, K = P H^T S^-1 = [[.5, 0], [0, .5], [0, 0]]: the gain filterpy leaves in self.K
    flt.K = np.array([[0.5, 0.0], [0.0, 0.5], [0.0, 0.0]])
    return flt


@pytest.mark.parametrize(
    "q_form, expected",
    # C = ((2, 1), (1, 1)); K C K^T = ((.5, .25, 0), (.25, .25, 0), (0, 0, 0)).
    # full: F P+_(k-1) F^T = ((.2, 0, 0), (0, .3, .1), (0, .1, .1)), so P+_k - F P F^T =
    # ((.8, 0, 0), (0, .7, -.1), (0, -.1, .9)) and Q_hat = ((1.3, .25, 0), (.25, .95, -.1), ...).
    # With A_v = e1 e1^T, A_g = e2 e2^T and W = P^-1 = I the least squares reads the diagonal.
    [("full", [1.3, 0.95]), ("steady", [0.5, 0.25])],
)
def test_q_step_by_hand(q_form, expected):
    flt = _q_case(q_form)
    flt.begin_scan()
    first = inn([2.0, 1.0], H_XY @ H_XY.T)
    flt.before_gain(first)
    flt.after_update(first)
    flt.end_scan()
    np.testing.assert_array_equal(flt.Qu, np.diag([0.3, 0.3]))  # warm-up: 1 of 2
    assert np.array_equal(flt.A_v, np.zeros((3, 3)))  # the interval was reset all the same
    flt = _q_case(q_form)
    flt.nus.append(np.array([2.0, 1.0]))
    flt.begin_scan()
    second = inn([0.0, 1.0], H_XY @ H_XY.T)
    flt.before_gain(second)
    flt.after_update(second)
    flt.end_scan()
    np.testing.assert_allclose(np.diag(flt.Qu), expected, rtol=1e-12)
    np.testing.assert_array_equal(flt.R, np.eye(2))  # adapt Q leaves R alone


def test_qu_is_the_mean_of_the_last_q_window_samples():
    flt = _q_case("steady", q_window=2)
    flt.nus.append(np.array([2.0, 1.0]))
    for nu, A_v, A_g in (
        ([0.0, 1.0], np.diag([1.0, 0.0, 0.0]), np.diag([0.0, 1.0, 0.0])),
        # C = ((0, 0), (0, 5)): K C K^T = 1.25 e2 e2^T; this interval's A_g = 2 e2 e2^T
        ([0.0, 3.0], np.diag([1.0, 0.0, 0.0]), np.diag([0.0, 2.0, 0.0])),
    ):
        flt.begin_scan()
        flt.before_gain(inn(nu, H_XY @ H_XY.T))
        flt.after_update(inn(nu, H_XY @ H_XY.T))
        flt.A_v, flt.A_g = A_v, A_g
        flt.end_scan()
        if len(flt.q_samples) == 1:  # samples (0.5, 0.25), then (0, 0.625)
            np.testing.assert_array_equal(flt.Qu, np.diag([0.3, 0.3]))
    np.testing.assert_allclose(np.diag(flt.Qu), [0.25, 0.4375], rtol=1e-12)


def test_q_estimate_sums_the_scans_gains():
    K1, K2 = (
        np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]),
        np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 0.0]]),
    )
    C = np.array([[1.0, 0.5], [0.5, 2.0]])
    # K1 C K1^T = ((1, 0, .5), (0, 0, 0), (.5, 0, 2)); K2 C K2^T = 4 e2 e2^T
    np.testing.assert_allclose(q_estimate([K1, K2], C),
                               [[1.0, 0.0, 0.5], [0.0, 4.0, 0.0], [0.5, 0.0, 2.0]])  # fmt: skip


def test_full_form_recovers_the_interval_noise_when_c_equals_s():
    """E[K nu nu^T K^T] = P- - P+: with C = S the full form returns Q_scan exactly (an identity
    of the Kalman update), the steady-state form does not."""
    flt = make(adapt="Q", window=20, R=np.diag([0.01, 3e-4]), Qu=np.diag([0.09, 2.7e-3]))
    flt.x = np.array([0.0, 0.0, 0.3])
    flt.P = np.diag([0.05, 0.08, 0.01])
    flt.reset_interval()
    for _ in range(8):
        flt.predict(np.array([3.0, 0.1]))
    lm = np.array([12.0, 7.0])
    inn_ = flt.innovation(h_of(flt.x, lm) + np.array([0.05, 0.01]), lm)
    S = inn_.HPHt + flt.R
    flt.begin_scan()
    flt.update_landmark(inn_.z, lm)
    dP = flt.P - flt.F_scan @ flt.P_scan_start @ flt.F_scan.T
    np.testing.assert_allclose(q_estimate(flt.Ks, S, dP), flt.Q_scan, rtol=1e-9, atol=1e-15)
    assert not np.allclose(q_estimate(flt.Ks, S), flt.Q_scan, rtol=0.1)


def test_adaptation_off_keeps_the_nominal_noise():
    flt = make(adaptation=False)
    for nu in ([5.0, 1.0], [4.0, -1.0], [3.0, 0.5]):
        flt.before_gain(inn(nu, np.diag([0.01, 1e-4])))
    np.testing.assert_array_equal(flt.R, R0)


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e3, 1e12], ids=["tiny", "small", "big", "huge"])
@pytest.mark.parametrize("adapt", ["R", "Q"])
def test_r_and_qu_stay_positive_and_in_bounds(adapt, scale):
    rng = np.random.default_rng(0)
    flt = make(adapt=adapt, window=5)
    bounds = np.array(flt.bounds)
    H = np.array([[0.8, 0.6, 0.0], [-0.03, 0.04, -1.0]])
    for _ in range(40):
        flt.predict(np.array([3.0, 0.1]))
        flt.begin_scan()
        flt.before_gain(inn(rng.standard_normal(2) * scale, H @ flt.P @ H.T, H=H))
        flt.end_scan()
        for M, M0 in ((flt.R, R0), (flt.Qu, QU0)):
            assert np.all(np.isfinite(M)) and np.all(np.diag(M) > 0)
            assert np.all(np.diag(M) >= bounds[0] * np.diag(M0) * (1 - 1e-12))
            assert np.all(np.diag(M) <= bounds[1] * np.diag(M0) * (1 + 1e-12))


# -- on a short simulated run --------------------------------------------------------------


def _simulated(**noise):
    doc = small_scenario(**noise)
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, Path("x.yaml"))
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(3))
    return scenario, world, data


def _run(spec, scenario, world, data):
    return run_filter(build_filter(spec, scenario, world), data, world, 1)


@pytest.mark.parametrize("adapt", ["R", "Q"])
def test_without_adaptation_equals_the_ekf(adapt):
    scenario, world, data = _simulated()
    ekf = _run(scenario.filters[0], scenario, world, data)
    off = _run(IAESpec(name="i", kind="iae", adapt=adapt, adaptation=False), scenario, world, data)
    for key in ("x", "P"):
        np.testing.assert_allclose(off[key], ekf[key], rtol=0, atol=1e-12)
    for key in ("R_diag", "Q_diag"):
        np.testing.assert_array_equal(off[key], ekf[key])


def test_wrong_r_moves_toward_the_truth():
    """The filter assumes sr = 2 m (true 0.1) and sb = 0.1 deg (true 1): range R falls, bearing
    R rises."""
    scenario, world, data = _simulated()
    trace = _run(IAESpec(name="i", kind="iae"), scenario, world, data)
    assert not trace["diverged"]
    r_true = np.array([0.1**2, math.radians(1.0) ** 2])
    R_first, R_last = trace["R_diag"][0], trace["R_diag"][-1]
    assert R_last[0] < 0.1 * R_first[0]
    assert R_last[1] > 10.0 * R_first[1]
    assert np.all(np.abs(np.log(R_last / r_true)) < np.abs(np.log(R_first / r_true)))


def test_wrong_q_moves_qu_up():
    """The filter assumes sv = 0.03 m/s, sg = 0.5 deg (true 0.3, 3): Qu grows."""
    scenario, world, data = _simulated(
        filter_noise={"sigma_v": 0.03, "sigma_gamma_deg": 0.5},
    )
    trace = _run(IAESpec(name="i", kind="iae", adapt="Q"), scenario, world, data)
    assert not trace["diverged"]
    Q_first = trace["Q_diag"][0]
    assert np.all(np.nanmean(trace["Q_diag"][-200:], axis=0) > Q_first)
    np.testing.assert_array_equal(trace["R_diag"][-1], trace["R_diag"][0])
