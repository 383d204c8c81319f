"""Sage-Husa: hand-computed adaptation steps, equality with the EKF when off, positivity, and
the direction it moves a wrong R or Q on a short simulated run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import Innovation, build_filter
from anfekf_bench.filters.sage_husa import (
    SageHusaEKF,
    SageHusaSpec,
    fading_weight,
    next_beta,
    q_sample,
    r_sample,
)
from anfekf_bench.models import Bicycle
from anfekf_bench.sources.simulator import simulate_run, simulate_truth

from .conftest import small_scenario

T, B = 0.025, 4.0
R0 = np.diag([1.0, 0.01])
QU0 = np.diag([0.5, 0.4])
H_ANY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -1.0]])  # not used by the R rule, only carried


def make(b=0.5, bounds=(1e-2, 1e2), **kw) -> SageHusaEKF:
    spec = SageHusaSpec(name="sh", kind="sage-husa", b=b, bounds=bounds, **kw)
    return SageHusaEKF(
        x0=np.zeros(3), P0=np.eye(3), Qu=QU0, R=R0, model=Bicycle(T, B), dt=T, gate=None,
        params=spec,
    )  # fmt: skip


def inn(nu, hph) -> Innovation:
    nu = np.asarray(nu, float)
    return Innovation(
        z=nu, landmark=np.zeros(2), z_hat=np.zeros(2), nu=nu, H=H_ANY, HPHt=np.diag(hph)
    )


def test_fading_weight_recursion_and_closed_form_agree():
    # b = 0.5: d_0 = 1, d_1 = 0.5 / 0.75 = 2/3, d_2 = 0.5 / 0.875 = 4/7
    assert [fading_weight(k, 0.5) for k in range(3)] == pytest.approx([1.0, 2 / 3, 4 / 7])
    assert next_beta(1.0, 0.5) == pytest.approx(2 / 3)
    assert next_beta(2 / 3, 0.5) == pytest.approx(4 / 7)
    # b = 0.97: d_1 = 0.03 / (1 - 0.9409) = 0.507614..., d -> 0.03
    assert fading_weight(1, 0.97) == pytest.approx(0.03 / 0.0591)
    beta = 1.0
    for k in range(200):
        assert beta == pytest.approx(fading_weight(k, 0.97), rel=1e-12)
        beta = next_beta(beta, 0.97)
    assert beta == pytest.approx(0.03, rel=3e-3)  # 0.03 / (1 - 0.97^201)


def test_r_sample_is_clamped_per_channel():
    lo, hi = np.array([0.01, 1e-4]), np.array([100.0, 1.0])
    # nu^2 - HPH = (4 - 0.5, 0.09 - 0.04) = (3.5, 0.05): inside
    np.testing.assert_allclose(r_sample(np.array([2.0, 0.3]), np.array([0.5, 0.04]), lo, hi),
                               [3.5, 0.05])  # fmt: skip
    # (1 - 2, 4 - 0) = (-1, 4): floor on range, ceiling on bearing
    np.testing.assert_allclose(r_sample(np.array([1.0, 2.0]), np.array([2.0, 0.0]), lo, hi),
                               [0.01, 1.0])  # fmt: skip
    # one channel as floats (the fast engine's kernel): the same clamp
    assert r_sample(1.0, 2.0, 0.01, 100.0) == 0.01
    assert r_sample(2.0, 0.5, 0.01, 100.0) == 3.5


def test_r_steps_by_hand_two_scans_one_pooled():
    """b = 0.5, R0 = diag(1, 0.01), bounds 0.01x..100x: numbers worked out by hand."""
    flt = make()
    # scan 0, d_0 = 1: R = rho = (4 - 0.5, 0.09 - 0.04)
    flt.begin_scan()
    flt.before_gain(inn([2.0, 0.3], [0.5, 0.04]))
    np.testing.assert_allclose(np.diag(flt.R), [3.5, 0.05], rtol=1e-12)
    flt.end_scan()
    # scan 1, d_1 = 2/3, two landmarks sharing it:
    flt.begin_scan()
    # rho_1 = (1 - 2 -> floor 0.01, 0.01 - 0.005) = (0.01, 0.005)
    # R = (1/3)(3.5, 0.05) + (2/3)(0.01, 0.005) = (1.17333..., 0.02)
    flt.before_gain(inn([1.0, 0.1], [2.0, 0.005]))
    np.testing.assert_allclose(np.diag(flt.R), [1.1733333333333333, 0.02], rtol=1e-12)
    # rho_2 = (9 - 1, 0.04 - 0) = (8, 0.04); mean = (4.005, 0.0225)
    # R = (1/3)(3.5, 0.05) + (2/3)(4.005, 0.0225) = (3.8366666..., 0.0316666...)
    flt.before_gain(inn([3.0, 0.2], [1.0, 0.0]))
    np.testing.assert_allclose(np.diag(flt.R), [3.8366666666666667, 0.0316666666666667])
    flt.end_scan()
    assert flt.n_events == 2
    assert flt.beta == pytest.approx(4 / 7)  # advanced once per scan, not per landmark


def test_scan_without_fed_innovation_does_not_advance_the_weight():
    flt = make(adapt_from="accepted")
    flt.gate = 1.0
    flt.begin_scan()
    flt.before_gain(inn([50.0, 0.0], [0.0, 0.0]))  # NIS 2500 > gate: does not feed
    flt.end_scan()
    np.testing.assert_array_equal(flt.R, R0)
    assert (flt.beta, flt.n_events) == (1.0, 0)


def test_q_sample_forms():
    dx = np.array([0.1, -0.2, 0.05])
    P_post, P_prev = np.eye(3), np.diag([0.2, 0.4, 0.5])
    F = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    # F P_prev F^T = [[0.325, 0, 0.25], [0, 0.4, 0], [0.25, 0, 0.5]]
    # dx dx^T     = [[0.01, -0.02, 0.005], [-0.02, 0.04, -0.01], [0.005, -0.01, 0.0025]]
    unbiased = [[0.685, -0.02, -0.245], [-0.02, 0.64, -0.01], [-0.245, -0.01, 0.5025]]
    biased = [[0.01, -0.02, 0.005], [-0.02, 0.04, -0.01], [0.005, -0.01, 0.0025]]
    np.testing.assert_allclose(q_sample(dx, P_post, P_prev, F, True), unbiased, atol=1e-15)
    np.testing.assert_allclose(q_sample(dx, P_post, P_prev, F, False), biased, atol=1e-15)


def _q_event(flt: SageHusaEKF) -> None:
    """One scan set up by hand: W = P+^-1 = I and orthogonal A_v = diag(1, 1, 0),
    A_g = diag(0, 0, 1), so the least squares gives qv = (Q11 + Q22) / 2, qg = Q33."""
    flt.begin_scan()
    flt.before_gain(inn([1.0, 0.1], [0.0, 0.0]))
    flt.after_update(inn([1.0, 0.1], [0.0, 0.0]))
    flt.x_prior_scan = np.array([5.0, 5.0, math.pi - 0.01])
    flt.x = np.array([5.1, 4.8, -math.pi + 0.04])  # heading correction +0.05 across +-pi
    flt.P = np.eye(3)
    flt.P_scan_start = np.diag([0.2, 0.4, 0.5])
    flt.F_scan = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    flt.A_v, flt.A_g = np.diag([1.0, 1.0, 0.0]), np.diag([0.0, 0.0, 1.0])
    flt.end_scan()


def test_q_step_by_hand_unbiased():
    flt = make(adapt="RQ")
    _q_event(flt)
    # sample (see test_q_sample_forms): qv = (0.685 + 0.64) / 2 = 0.6625, qg = 0.5025; d_0 = 1
    np.testing.assert_allclose(np.diag(flt.Qu), [0.6625, 0.5025], rtol=1e-12)
    # the interval restarts at this scan's posterior
    np.testing.assert_array_equal(flt.P_scan_start, np.eye(3))
    np.testing.assert_array_equal(flt.A_v, np.zeros((3, 3)))
    # second event, d_1 = 2/3: Qu = (1/3)(0.6625, 0.5025) + (2/3)(0.6625, 0.5025) = same
    _q_event(flt)
    np.testing.assert_allclose(np.diag(flt.Qu), [0.6625, 0.5025], rtol=1e-12)


def test_q_step_by_hand_biased_sample_is_clamped():
    flt = make(adapt="RQ", q_sample="biased")
    flt.Qu_hat = np.array([1.0, 0.1])  # the estimate before this event
    flt.beta = 2 / 3  # as at the second event with b = 0.5
    _q_event(flt)
    # sample qv = (0.01 + 0.04) / 2 = 0.025, qg = 0.0025 -> floor 0.01 * 0.4 = 0.004
    # Qu = (1/3)(1.0, 0.1) + (2/3)(0.025, 0.004) = (0.35, 0.036)
    np.testing.assert_allclose(np.diag(flt.Qu), [0.35, 0.036], rtol=1e-12)


def test_warmup_builds_the_estimate_but_keeps_R0_in_force():
    flt = make(warmup=1)
    flt.begin_scan()
    flt.before_gain(inn([2.0, 0.3], [0.5, 0.04]))
    np.testing.assert_array_equal(flt.R, R0)  # scan 0: still R0 in the gain
    np.testing.assert_allclose(flt.R_hat, [3.5, 0.05], rtol=1e-12)
    flt.end_scan()
    # scan 1, d_1 = 2/3: rho = (9 - 1, 0.04 - 0) = (8, 0.04)
    # R = (1/3)(3.5, 0.05) + (2/3)(8, 0.04) = (6.5, 0.0433333...)
    flt.begin_scan()
    flt.before_gain(inn([3.0, 0.2], [1.0, 0.0]))
    np.testing.assert_allclose(np.diag(flt.R), [6.5, 0.04333333333333333], rtol=1e-12)


def test_spec_validation():
    with pytest.raises(ValidationError):
        SageHusaSpec(name="s", kind="sage-husa", b=1.0)
    with pytest.raises(ValidationError):
        SageHusaSpec(name="s", kind="sage-husa", adapt="Q")
    spec = SageHusaSpec(name="s", kind="sage-husa")
    assert (spec.b, spec.adapt, spec.q_sample, spec.warmup) == (0.97, "R", "unbiased", 0)
    assert spec.adapt_from == "all" and spec.bounds == (1e-4, 1e4)


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e6, 1e12], ids=["zero", "tiny", "big", "huge"])
@pytest.mark.parametrize("adapt", ["R", "RQ"])
def test_R_and_Qu_stay_positive_and_in_bounds(scale, adapt):
    flt = make(b=0.97, bounds=(1e-4, 1e4), adapt=adapt)
    rng = np.random.default_rng(1)
    for k in range(200):
        flt.begin_scan()
        for _ in range(1 + k % 2):
            i = inn(rng.standard_normal(2) * scale, [0.5, 0.005])
            flt.before_gain(i)
            flt.after_update(i)
        flt.x = flt.x_prior_scan + rng.standard_normal(3) * scale
        flt.A_v, flt.A_g = np.diag([1.0, 1.0, 0.1]), np.diag([0.01, 0.1, 1.0])
        flt.end_scan()
        for M, M0 in ((flt.R, R0), (flt.Qu, QU0)):
            d = np.diag(M)
            assert np.all(np.isfinite(d)) and np.all(d > 0)
            assert np.all(d >= 1e-4 * np.diag(M0) * (1 - 1e-12))
            assert np.all(d <= 1e4 * np.diag(M0) * (1 + 1e-12))
    if scale < 1e-6:
        np.testing.assert_allclose(np.diag(flt.R), 1e-4 * np.diag(R0))
    if scale > 1e3:
        np.testing.assert_allclose(np.diag(flt.R), 1e4 * np.diag(R0))


# -- on a short simulated run ------------------------------------------------------------------


def _world_and_data(**overrides):
    scenario = parse_scenario(small_scenario(**overrides))
    world = resolve_world(scenario.world, Path("x.yaml"))
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(3))
    return scenario, world, data


@pytest.fixture(scope="module")
def wrong_r_run():
    return _world_and_data()  # the small scenario assumes sr = 2 m, sb = 0.1 deg


def _run(spec, scenario, world, data):
    flt = build_filter(spec, scenario, world)
    return flt, run_filter(flt, data, world, 1)


@pytest.mark.parametrize("adapt", ["R", "RQ"])
def test_without_adaptation_equals_the_ekf(wrong_r_run, adapt):
    scenario, world, data = wrong_r_run
    _, ekf = _run(scenario.filters[0], scenario, world, data)
    off = SageHusaSpec(name="s", kind="sage-husa", adapt=adapt, adaptation=False)
    _, sh = _run(off, scenario, world, data)
    np.testing.assert_allclose(sh["x"], ekf["x"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sh["P"], ekf["P"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sh["R_diag"], ekf["R_diag"])
    np.testing.assert_array_equal(sh["Q_diag"], ekf["Q_diag"])


def test_wrong_R_moves_toward_the_truth(wrong_r_run):
    """Assumed (2 m, 0.1 deg), true (0.1 m, 1 deg): range variance must fall, bearing rise."""
    scenario, world, data = wrong_r_run
    spec = SageHusaSpec(name="s", kind="sage-husa")
    flt, trace = _run(spec, scenario, world, data)
    assert not trace["diverged"] and flt.n_events > 10
    assert np.all(trace["P_infl"] == 1.0)
    r_end = trace["R_diag"][-1]
    assert r_end[0] < 0.1 * 2.0**2
    assert r_end[1] > 10 * math.radians(0.1) ** 2
    _, ekf = _run(scenario.filters[0], scenario, world, data)
    assert _rmse(trace, data) < _rmse(ekf, data)


def _rmse(trace, data) -> float:
    """Position RMSE over the run (record_every 1: row k is the pose after k + 1 steps)."""
    e = trace["x"][:, :2] - data.truth.x[1:, :2]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def test_wrong_Q_raises_Qu():
    """Assumed Qu 10x too small in standard deviation: adapt RQ must raise it."""
    scenario, world, data = _world_and_data(filter_noise={"sigma_v": 0.03, "sigma_gamma_deg": 0.3})
    spec = SageHusaSpec(name="s", kind="sage-husa", adapt="RQ")
    flt, trace = _run(spec, scenario, world, data)
    assert not trace["diverged"]
    assert np.all(trace["Q_diag"][-1] > np.diag(flt.Qu0))
