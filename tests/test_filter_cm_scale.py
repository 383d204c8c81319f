"""cm-scale (the ANFEKF without the ANFIS): hand-computed R and Q steps, the clip, the events,
equality with the EKF when off, positivity, and the direction it moves a wrong R or Q."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import ANFEKF, ANFEKFSpec, Innovation, build_filter
from anfekf_bench.filters.cm_scale import CMScaleEKF, CMScaleSpec, log_scale
from anfekf_bench.models import Bicycle
from anfekf_bench.sources.simulator import simulate_run, simulate_truth

from .conftest import small_scenario

T, B = 0.025, 4.0
R0 = np.diag([0.01, 1e-4])
QU0 = np.diag([0.09, 2.7e-3])
H_ANY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])  # only carried: the rule reads H P- H^T
HPH = np.diag([0.01, 1e-4])


def make(window=2, **kw) -> CMScaleEKF:
    spec = CMScaleSpec(name="cm", kind="cm-scale", window=window, **kw)
    return CMScaleEKF(
        x0=np.zeros(3), P0=np.eye(3), Qu=QU0, R=R0, model=Bicycle(T, B), dt=T, gate=None,
        params=spec,
    )  # fmt: skip


def inn(nu, hph=HPH) -> Innovation:
    nu = np.asarray(nu, float)
    return Innovation(z=nu, landmark=np.zeros(2), z_hat=np.zeros(2), nu=nu, H=H_ANY, HPHt=hph)


# Hand case: H P- H^T = R = diag(0.01, 1e-4), so S = diag(0.02, 2e-4); innovations
# (0.2, 0.01) and (0, 0.01) give diag C = (0.04 / 2, 2e-4 / 2) = (0.02, 1e-4);
# d = ((0.02 - 0.02) / 0.04, (2e-4 - 1e-4) / 3e-4) = (0, 1/3).
NU1, NU2 = [0.2, 0.01], [0.0, 0.01]
EXP_M_THIRD = 0.7165313105737893  # e^(-1/3)
EXP_M_SIXTH = 0.8464817248906141  # e^(-1/6)


def test_log_scale_is_minus_kappa_d_clipped():
    np.testing.assert_allclose(log_scale(np.array([0.0, 1 / 3]), 1.0, 1.0), [0.0, -1 / 3])
    np.testing.assert_allclose(log_scale(np.array([-0.5, 0.5]), 3.0, 1.0), [1.0, -1.0])


def test_r_step_by_hand():
    flt = make()
    flt.begin_scan()
    flt.before_gain(inn(NU1))
    np.testing.assert_array_equal(flt.R, R0)  # warm-up: the window is not full
    flt.before_gain(inn(NU2))
    np.testing.assert_allclose(np.diag(flt.R), [0.01, 1e-4 * EXP_M_THIRD], rtol=1e-12)
    np.testing.assert_array_equal(flt.Qu, QU0)  # adapt R leaves Qu alone


def test_r_step_is_clipped_like_the_anfekf_output():
    # kappa = 6: o = -6 / 3 = -2, clipped to -output_clip = -1
    flt = make(kappa=6.0)
    flt.before_gain(inn(NU1))
    flt.before_gain(inn(NU2))
    np.testing.assert_allclose(np.diag(flt.R), [0.01, 1e-4 * math.exp(-1.0)], rtol=1e-12)


def test_q_step_by_hand_at_the_first_landmark_of_a_scan_only():
    flt = make(adapt="Q")
    flt.begin_scan()
    flt.before_gain(inn(NU1))
    flt.end_scan()
    flt.begin_scan()
    flt.before_gain(inn(NU2))  # window full, first landmark: Qu <- Qu e^(-mean d) = e^(-1/6)
    np.testing.assert_allclose(np.diag(flt.Qu), np.diag(QU0) * EXP_M_SIXTH, rtol=1e-12)
    flt.before_gain(inn(NU2))  # second landmark of the scan: no Q event
    np.testing.assert_allclose(np.diag(flt.Qu), np.diag(QU0) * EXP_M_SIXTH, rtol=1e-12)
    np.testing.assert_array_equal(flt.R, R0)
    flt.end_scan()
    flt.begin_scan()
    # next scan: the window holds (0, 0.01) twice, diag C = (0, 1e-4);
    # d = ((0.02 - 0) / 0.02, 1/3) = (1, 1/3): Qu <- Qu e^(-2/3)
    flt.before_gain(inn([0.0, 0.01]))
    scale = math.exp(-2 / 3)
    np.testing.assert_allclose(np.diag(flt.Qu), np.diag(QU0) * EXP_M_SIXTH * scale, rtol=1e-12)


def test_rq_scales_both_from_the_same_mismatch():
    """Like the ANFEKF's RQ: the R step, then the Q step from the same d (not re-matched)."""
    flt = make(adapt="RQ")
    flt.begin_scan()
    flt.before_gain(inn(NU1))
    flt.before_gain(inn(NU2))  # not the first landmark: R only
    np.testing.assert_allclose(np.diag(flt.R), [0.01, 1e-4 * EXP_M_THIRD], rtol=1e-12)
    np.testing.assert_array_equal(flt.Qu, QU0)
    flt.begin_scan()
    # window (0, .01), (.2, .01): C = (0.02, 1e-4); S = (0.02, 1e-4 + 1e-4 e^(-1/3))
    flt.before_gain(inn(NU1))
    R_b = 1e-4 * EXP_M_THIRD
    d_b = (1e-4 + R_b - 1e-4) / (1e-4 + R_b + 1e-4)
    np.testing.assert_allclose(np.diag(flt.R), [0.01, R_b * math.exp(-d_b)], rtol=1e-12)
    np.testing.assert_allclose(np.diag(flt.Qu), np.diag(QU0) * math.exp(-d_b / 2), rtol=1e-12)


def test_window_and_mismatch_are_the_anfekfs():
    """The same innovations give the ANFEKF and cm-scale the same window (shared code)."""
    cm = make(window=3)
    anf = ANFEKF(
        x0=np.zeros(3), P0=np.eye(3), Qu=QU0, R=R0, model=Bicycle(T, B), dt=T, gate=None,
        params=ANFEKFSpec(name="a", kind="anfekf", window=3, adaptation=False),
    )  # fmt: skip
    for nu in (NU1, NU2, [0.3, -0.02], [0.1, 0.0]):
        cm.before_gain(inn(nu))
        anf.before_gain(inn(nu))
    np.testing.assert_array_equal(np.array(cm.window), np.array(anf.window))


@pytest.mark.parametrize("adapt", ["R", "Q", "RQ"])
@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e3, 1e12], ids=["tiny", "small", "big", "huge"])
def test_r_and_qu_stay_positive_and_in_bounds(adapt, scale):
    rng = np.random.default_rng(0)
    flt = make(adapt=adapt, window=5, bounds=(1e-2, 1e2))
    for _ in range(300):
        flt.begin_scan()
        flt.before_gain(inn(rng.standard_normal(2) * scale))
        flt.end_scan()
        for M, M0 in ((flt.R, R0), (flt.Qu, QU0)):
            assert np.all(np.isfinite(M)) and np.all(np.diag(M) > 0)
            assert np.all(np.diag(M) >= 1e-2 * np.diag(M0) * (1 - 1e-12))
            assert np.all(np.diag(M) <= 1e2 * np.diag(M0) * (1 + 1e-12))
    # the extremes reach a bound and stay there
    if adapt != "Q":
        bound = 1e-2 if scale < 1 else 1e2
        np.testing.assert_allclose(np.diag(flt.R), bound * np.diag(R0), rtol=1e-9)


# -- on a short simulated run --------------------------------------------------------------


def _simulated(**noise):
    scenario = parse_scenario(small_scenario(**noise))
    world = resolve_world(scenario.world, Path("x.yaml"))
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(3))
    return scenario, world, data


def _run(spec, scenario, world, data):
    return run_filter(build_filter(spec, scenario, world), data, world, 1)


@pytest.mark.parametrize("adapt", ["R", "Q", "RQ"])
def test_without_adaptation_equals_the_ekf(adapt):
    scenario, world, data = _simulated()
    ekf = _run(scenario.filters[0], scenario, world, data)
    off = _run(CMScaleSpec(name="c", kind="cm-scale", adapt=adapt, adaptation=False), scenario,
               world, data)  # fmt: skip
    for key in ("x", "P"):
        np.testing.assert_allclose(off[key], ekf[key], rtol=0, atol=1e-12)
    for key in ("R_diag", "Q_diag"):
        np.testing.assert_array_equal(off[key], ekf[key])


def test_wrong_r_moves_toward_the_truth():
    """The filter assumes sr = 2 m (true 0.1) and sb = 0.1 deg (true 1)."""
    scenario, world, data = _simulated()
    trace = _run(CMScaleSpec(name="c", kind="cm-scale"), scenario, world, data)
    assert not trace["diverged"]
    r_true = np.array([0.1**2, math.radians(1.0) ** 2])
    R_first, R_last = trace["R_diag"][0], trace["R_diag"][-1]
    assert R_last[0] < 0.1 * R_first[0]
    assert R_last[1] > 10.0 * R_first[1]
    assert np.all(np.abs(np.log(R_last / r_true)) < np.abs(np.log(R_first / r_true)))


def test_wrong_q_moves_qu_up():
    """The filter assumes sv = 0.03 m/s, sg = 0.5 deg (true 0.3, 3): Qu grows."""
    scenario, world, data = _simulated(filter_noise={"sigma_v": 0.03, "sigma_gamma_deg": 0.5})
    trace = _run(CMScaleSpec(name="c", kind="cm-scale", adapt="Q"), scenario, world, data)
    assert not trace["diverged"]
    assert np.all(np.nanmean(trace["Q_diag"][-200:], axis=0) > 3.0 * trace["Q_diag"][0])
    np.testing.assert_array_equal(trace["R_diag"][-1], trace["R_diag"][0])
