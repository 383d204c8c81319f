"""The drive audit's numerics (analysis.audit) on synthetic data where the answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from anfekf_bench.analysis import audit
from anfekf_bench.analysis.metrics import nees_single_run, single_run_bounds


def _ar1(n: int, rho: float, rng) -> np.ndarray:
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x


def test_held_means_is_the_exact_time_mean_of_a_held_signal():
    t = np.array([0.0, 1.0, 3.0])
    v = np.array([2.0, 4.0, -1.0])
    edges = np.array([-1.0, 0.5, 2.0, 4.0])
    # [-1, 0.5]: 0 for 1 s then 2 for 0.5 s; [0.5, 2]: 2 x 0.5 + 4 x 1; [2, 4]: 4 x 1 - 1 x 1
    np.testing.assert_allclose(audit.held_means(t, v, edges), [1.0 / 1.5, 5.0 / 1.5, 1.5])


def test_truth_velocities_of_a_circle():
    # a circle of radius 2 m at 0.5 rad/s: v = 1 m/s, w = 0.5 rad/s
    t = np.linspace(0, 20, 4001)
    phi = 0.5 * t
    x, y = 2 * np.sin(phi), 2 - 2 * np.cos(phi)
    v, w = audit.truth_velocities(t, x, y, phi, np.arange(0, 20.01, 0.5))
    np.testing.assert_allclose(w, 0.5, atol=1e-9)
    np.testing.assert_allclose(v, 1.0, atol=1e-9)  # the arc, not the chord


def test_fit_scale_bias_recovers_the_injected_scale_and_bias_within_its_interval():
    rng = np.random.default_rng(3)
    n = 3000
    cmd = rng.choice([-1.0, 0.0, 0.9], size=n)
    true = 0.6 * cmd + 0.05 + 0.3 * _ar1(n, 0.8, rng) * 0.4  # autocorrelated noise
    fit = audit.fit_scale_bias(cmd, true, block=50, resamples=800, seed=1)
    assert fit["n"] == n
    assert fit["scale"] == pytest.approx(0.6, abs=0.02)
    assert fit["bias"] == pytest.approx(0.05, abs=0.02)
    assert fit["scale_lo"] < 0.6 < fit["scale_hi"]
    assert fit["bias_lo"] < 0.05 < fit["bias_hi"]
    # the block bootstrap sees the autocorrelation the OLS standard error ignores
    assert (fit["bias_hi"] - fit["bias_lo"]) > 2 * 1.96 * fit["bias_se"]
    # deterministic for a seed
    assert audit.fit_scale_bias(cmd, true, block=50, resamples=800, seed=1) == fit


def test_fit_scale_bias_without_varying_commands_is_nan():
    fit = audit.fit_scale_bias(np.ones(50), np.ones(50))
    assert math.isnan(fit["scale"]) and fit["n"] == 50


def test_residual_stats_and_outliers():
    rng = np.random.default_rng(0)
    dr = 0.05 + 0.1 * rng.normal(size=5000)
    db = -0.02 + 0.01 * rng.normal(size=5000)
    dr[:50] += 3.0  # 1 % gross errors
    st = audit.residual_stats(dr, db)
    assert st["range_median"] == pytest.approx(0.05, abs=0.01)
    assert st["range_robust_std"] == pytest.approx(0.1, rel=0.05)
    assert st["bearing_mean"] == pytest.approx(-0.02, abs=0.001)
    assert st["outlier_share"] == pytest.approx(0.01, abs=0.002)
    far = audit.outliers(dr, db)
    assert far[:50].all() and far[50:].sum() < 5


def test_range_dependence_recovers_a_range_scale_error():
    rng = np.random.default_rng(1)
    r = rng.uniform(0.5, 8, size=4000)
    d = (0.978 - 1) * r + 0.049 + 0.05 * rng.normal(size=4000)
    dep = audit.range_dependence(r, d)
    assert dep["range_slope"] == pytest.approx(-0.022, abs=3 * dep["range_slope_se"])
    assert dep["range_offset"] == pytest.approx(0.049, abs=3 * dep["range_offset_se"])


def test_range_bins():
    assert audit.range_bin(np.array([0.2, 1.5, 4.9, 12.0])).tolist() == [0, 1, 2, 3]
    assert audit.range_bin_labels() == ["0-1.5 m", "1.5-3 m", "3-5 m", ">= 5 m"]


def test_autocorrelation_white_and_ar1():
    rng = np.random.default_rng(2)
    white = rng.normal(size=20000)
    r = audit.autocorrelation(white, 10)
    assert np.all(np.abs(r) < audit.white_band(20000) * 1.5)
    q, p = audit.ljung_box(white, 10)
    assert p > 0.001
    ar = _ar1(20000, 0.7, rng)
    r = audit.autocorrelation(ar, 10)
    np.testing.assert_allclose(r[:3], [0.7, 0.49, 0.343], atol=0.03)
    q, p = audit.ljung_box(ar, 10)
    assert p < 1e-10 and q > chi2.ppf(0.999, 10)


def test_landmark_gaps():
    g = audit.landmark_gaps(np.array([1.0, 1.0, 2.0, 6.0]), 0.0, 10.0, min_s=1.5)
    np.testing.assert_allclose(g, [[2.0, 6.0], [6.0, 10.0]])


def test_episodes_and_lead_window():
    t = np.arange(0, 100, 0.5)
    err = np.full(len(t), 0.1)
    err[(t >= 40) & (t < 50)] = np.linspace(0.2, 0.9, 20)
    err[(t >= 50) & (t < 55)] = 1.5
    err[(t >= 57) & (t < 58)] = 1.2  # 2 s later: the same episode
    err[(t >= 80) & (t < 81)] = np.nan
    err[(t >= 90) & (t < 91)] = 1.1  # another
    ep = audit.episodes(t, err)
    assert [(t[a], t[b]) for a, b in ep] == [(50.0, 57.5), (90.0, 90.5)]
    start, onset = audit.lead_window(t, err, ep[0, 0])
    assert onset == 50.0 and start == t[np.flatnonzero(err[: ep[0, 0]] < 0.5)[-1]]
    # capped at 30 s and at least 5 s before the onset
    start, _ = audit.lead_window(t, np.full(len(t), 2.0), 100)
    assert start == pytest.approx(t[100] - 30.0)
    low_just_before = np.full(len(t), 2.0)
    low_just_before[99] = 0.1
    start, _ = audit.lead_window(t, low_just_before, 100)
    assert start == pytest.approx(t[100] - 5.0)


def test_episode_cause_lists_what_the_measurements_show():
    assert audit.episode_cause({"fixed_by_calibration": True}) == "odometry scale/bias"
    cause = audit.episode_cause(
        {"fixed_by_true_odometry": True, "longest_gap_s": 4.2, "turning_share": 0.5}
    )
    assert (
        cause
        == "odometry error beyond scale/bias + landmark gap (4.2 s) + manoeuvre (50 % turning)"
    )
    assert audit.episode_cause({"longest_gap_s": 1.0}) == "not removed by any correction"


def test_nees_single_run_uses_one_run_chi_square_bounds():
    rng = np.random.default_rng(4)
    nees = rng.chisquare(3, size=(4, 5000))
    nees[1] *= 10  # an overconfident run
    nees[2, :1000] = np.nan  # unscored steps
    out = nees_single_run(nees)
    assert (out["lo"], out["hi"]) == pytest.approx((chi2.ppf(0.025, 3), chi2.ppf(0.975, 3)))
    assert out["per_run"][0] == pytest.approx(0.95, abs=0.01)
    assert out["per_run"][1] < 0.6
    assert out["scored"].tolist() == [5000, 5000, 4000, 5000]
    inside = (nees > out["lo"]) & (nees < out["hi"])
    assert out["pooled"] == pytest.approx(inside.sum() / 19000)
    # two dof: position only
    assert single_run_bounds(2)[1] == pytest.approx(chi2.ppf(0.975, 2))
