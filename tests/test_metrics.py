"""Metrics against hand-computed small cases and the paper's chi-square bounds."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from anfekf_bench.analysis.metrics import (
    TRACE_METRICS_COMPILED,
    add_trace_metrics,
    nees,
    nees_bounds,
    pose_errors,
    rmse_curve,
    share_inside,
    summarize_filter,
)


@pytest.mark.parametrize(
    "runs, lo, hi", [(20, 2.02, 4.17), (50, 2.36, 3.72)], ids=["N20-paper", "N50"]
)
def test_chi_square_bounds_match_the_paper(runs, lo, hi):
    # Exact N = 20 values are [2.024, 4.165]; the paper prints them as [2.02, 4.17].
    got = nees_bounds(runs)
    assert got[0] == pytest.approx(lo, abs=0.006)
    assert got[1] == pytest.approx(hi, abs=0.006)


def test_pose_errors_wrap_heading():
    e = pose_errors(np.array([[1.0, 2.0, math.pi - 0.1]]), np.array([[0.5, 2.5, -math.pi + 0.1]]))
    np.testing.assert_allclose(e, [[0.5, -0.5, -0.2]], atol=1e-12)


def test_nees_by_hand():
    e = np.array([[1.0, 2.0, 0.5], [0.0, 0.0, 0.0]])
    P = np.stack([np.diag([1.0, 4.0, 0.25]), np.eye(3)])
    np.testing.assert_allclose(nees(e, P), [1.0 + 1.0 + 1.0, 0.0])
    Pc = np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    e1 = np.array([1.0, 1.0, 0.0])
    assert nees(e1[None], Pc[None])[0] == pytest.approx(e1 @ np.linalg.inv(Pc) @ e1)


def test_rmse_curve_by_hand():
    err = np.array([[3.0, 0.0], [4.0, 2.0]])
    np.testing.assert_allclose(rmse_curve(err), [math.sqrt(12.5), math.sqrt(2.0)])


def test_share_inside_is_strict():
    assert share_inside(np.array([1.0, 2.0, 3.0, 4.0]), 1.0, 4.0) == 0.5


def test_summary_by_hand_and_diverged_runs_left_out():
    pos = np.array([[1.0, 1.0], [3.0, 3.0], [np.nan, np.nan]])
    head = np.array([[0.1, 0.1], [0.1, 0.1], [np.nan, np.nan]])
    nees_ = np.array([[3.0, 30.0], [3.0, 30.0], [np.nan, np.nan]])
    rec = summarize_filter(pos, head, nees_, np.array([False, False, True]))
    assert rec["runs"] == 3 and rec["diverged"] == 1 and rec["runs_used"] == 2
    assert rec["rmse_pos"] == pytest.approx(math.sqrt(5.0))
    assert rec["rmse_heading"] == pytest.approx(0.1)
    assert rec["anees"] == pytest.approx(16.5)
    lo, hi = nees_bounds(2)
    assert (rec["nees_lo"], rec["nees_hi"]) == (lo, hi)
    assert rec["nees_in_bounds"] == 0.5


@pytest.mark.skipif(not TRACE_METRICS_COMPILED, reason="numba is not in use")
def test_compiled_trace_metrics_match_numpys():
    """The fast engine's one-pass metrics (`trace_metrics`) against numpy's: the errors bit for
    bit, the NEES (its own LU against LAPACK's) within 1e-12; non-finite rows NaN on both, an
    exactly singular P through the same pseudo-inverse, headings wrapped across +-pi."""
    rng = np.random.default_rng(5)
    n = 400
    A = rng.standard_normal((n, 3, 3))
    P = A @ A.transpose(0, 2, 1) + np.diag([1e-2, 1e-2, 1e-6])  # ill-conditioned, as late P is
    x_true = rng.standard_normal((n, 3)) * [50.0, 50.0, 3.0]
    x = x_true + rng.standard_normal((n, 3)) * [0.5, 0.5, 0.1]
    x_true[:20, 2], x[:20, 2] = math.pi - 0.01, -math.pi + 0.01  # across the wrap
    P[30] = 0.0  # p0 = 0 before the first updates
    P[31] = np.diag([1.0, 2.0, 0.0])
    P[32, 0, 2] = P[32, 2, 0] = np.inf
    x[33, 1] = np.nan
    x_true[34] = np.nan  # a recorded step without ground truth
    P[35] = np.nan  # a padded step
    G = rng.standard_normal((3, 2))
    P[36:40] = G @ np.diag([0.09, 3e-4]) @ G.T  # p0 = 0 after one predict: rank 2, not diagonal
    ours = add_trace_metrics({"x": x.copy(), "P": P.copy()}, x_true, compiled=True)
    numpys = add_trace_metrics({"x": x.copy(), "P": P.copy()}, x_true)
    for key in ("pos_err", "heading_err"):
        np.testing.assert_array_equal(ours[key], numpys[key])
    np.testing.assert_array_equal(np.isnan(ours["nees"]), np.isnan(numpys["nees"]))
    np.testing.assert_allclose(ours["nees"], numpys["nees"], rtol=1e-12, atol=0)
    assert np.isnan(ours["nees"][32:36]).all() and np.isfinite(ours["nees"][30:32]).all()
    assert ours["heading_err"][:20] == pytest.approx(0.02)


def test_a_run_is_scored_as_the_engine_that_ran_each_filter(monkeypatch):
    """runner.run_one asks for the compiled metrics where the fast engine's kernels ran the
    filter, numpy's elsewhere: the filterpy engine, and a filter the fast engine hands to filterpy
    (here the oracle told the true noise of every step), keep numpy's bits."""
    import dataclasses

    from anfekf_bench import runner
    from anfekf_bench.filters.context import filter_context
    from anfekf_bench.scenarios import load_scenario

    scenario, world = load_scenario(Path(__file__).parents[1] / "configs" / "correct.yaml")
    spec = scenario.filters[0]
    ctx = filter_context(spec, scenario, world)
    scheduled = dataclasses.replace(ctx, true_noise=object())
    asked = []
    monkeypatch.setattr(
        runner, "add_trace_metrics", lambda trace, x_true, compiled: asked.append(compiled)
    )
    monkeypatch.setattr(
        runner, "run_spec", lambda *a, **k: {key: np.zeros((2, 3)) for key in runner.TRACE_ARRAYS}
    )
    inputs = runner.RunInputs(0, None, np.arange(2), np.arange(2.0), np.zeros((2, 3)), 2)
    for engine, context in (("fast", ctx), ("filterpy", ctx), ("fast", scheduled)):
        runner.run_one(inputs, [(spec.name, spec, context)], engine)
    assert asked == [True, False, False]
