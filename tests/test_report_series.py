"""The one series type over time (`report.data.RunSeries`): runs on one time axis (a simulated
scenario) and ragged runs (recorded segments and drives of different lengths), their per-step
statistics over the runs present at each step, and the figures that draw them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from anfekf_bench.analysis.metrics import rmse_curve
from anfekf_bench.report import plots
from anfekf_bench.report.data import BAND_PERCENTILES, FilterSeries, RunSeries, ScenarioData

RAGGED = RunSeries(
    runs=(0, 1, 2),
    t=(np.array([0.0, 1.0, 2.0]), np.array([0.0, 1.0]), np.array([0.0])),
    values=(np.array([1.0, 2.0, 3.0]), np.array([3.0, 4.0]), np.array([5.0])),
)


def test_ragged_runs_give_per_step_statistics_over_the_runs_present():
    band = RAGGED.band()
    # step 0: runs 1, 3, 5; step 1: runs 2, 4; step 2: run 3 only (hand-computed)
    assert RAGGED.ragged and RAGGED.present().tolist() == [3, 2, 1]
    np.testing.assert_array_equal(band.line, [3.0, 3.0, 3.0])
    np.testing.assert_array_equal(band.median, [3.0, 3.0, 3.0])
    lo, hi = BAND_PERCENTILES  # 10 and 90 %: linear between the order statistics
    np.testing.assert_allclose(band.lo, [1 + 4 * lo / 100, 2 + 2 * lo / 100, 3.0])
    np.testing.assert_allclose(band.hi, [1 + 4 * hi / 100, 2 + 2 * hi / 100, 3.0])
    rms = RAGGED.band(rms=True).line
    np.testing.assert_allclose(rms, [math.sqrt(35 / 3), math.sqrt(10), 3.0])
    t, grid = RAGGED.grid()
    assert t.tolist() == [0.0, 1.0, 2.0] and np.isnan(grid[2, 1:]).all()


def test_runs_of_one_length_keep_the_plain_statistics_bit_for_bit():
    """The simulated figures' bands are what they were before the series type: numpy's mean,
    percentiles and median over runs, the RMSE curve over runs (a NaN value stays NaN)."""
    rng = np.random.default_rng(3)
    values = rng.normal(size=(7, 40))
    values[2, 5] = np.nan
    s = RunSeries.aligned(np.arange(40) * 0.1, values, runs=[3, 4, 5, 6, 7, 8, 9])
    assert not s.ragged and s.runs == (3, 4, 5, 6, 7, 8, 9)
    band, err = s.band(), s.band(rms=True)
    lo, hi = np.percentile(values, BAND_PERCENTILES, axis=0)
    pairs = [(band.line, values.mean(axis=0)), (band.lo, lo), (band.hi, hi),
             (band.median, np.median(values, axis=0)), (err.line, rmse_curve(values))]  # fmt: skip
    for got, want in pairs:
        np.testing.assert_array_equal(got, want)
    assert np.isnan(band.line[5])
    empty = RunSeries.aligned(np.arange(4.0), np.zeros((0, 4))).band()
    assert empty.line.shape == (4,) and np.isnan(empty.line).all()


def test_joined_breaks_the_line_between_runs():
    t, v = RAGGED.joined()
    assert t[:3].tolist() == [0.0, 1.0, 2.0] and np.isnan(t[3])
    # each run, then a NaN: 3 + 1 + 2 + 1 + 1 + 1 points
    assert len(t) == len(v) == 9
    assert np.isnan(v[[3, 6, 8]]).all() and v[~np.isnan(v)].tolist() == [1, 2, 3, 3, 4, 5]
    one = RAGGED.run(1)
    assert one.runs == (1,) and one.values[0].tolist() == [3.0, 4.0]
    assert RAGGED.map(np.sqrt).values[1].tolist() == [math.sqrt(3.0), 2.0]


def test_of_steps_reads_each_run_on_its_own_time_axis():
    steps = pd.DataFrame({
        "run": [0, 0, 0, 1, 1], "step": [1, 2, 3, 1, 2],
        "t_abs": [10.0, 10.5, 11.0, 50.0, 50.5], "pos_err": [0.1, 0.2, 0.3, 0.4, 0.5],
    })  # fmt: skip
    s = RunSeries.of_steps(steps, "pos_err", time="t_abs")
    assert s.runs == (0, 1) and s.ragged
    assert [x.tolist() for x in s.t] == [[10.0, 10.5, 11.0], [50.0, 50.5]]
    np.testing.assert_allclose(s.band().line, [0.25, 0.35, 0.3])


def _series(name: str, kind: str, s: RunSeries) -> FilterSeries:
    t, _ = s.grid()
    noise = dict.fromkeys(("R_rr", "R_bb", "Q_vv", "Q_gg"), s.band())
    summary = {"rmse_pos": 1.0, "rmse_heading": 0.1}
    return FilterSeries(name=name, kind=kind, adapts=frozenset(), runs=len(s.runs),
                        runs_used=len(s.runs), t=t, pos=s.band(rms=True), heading=s.band(rms=True),
                        nees=np.ones(len(t)), nees_median=np.ones(len(t)), bounds=(0.5, 2.0),
                        noise=noise, summary=summary)  # fmt: skip


def test_the_rmse_figure_draws_ragged_runs():
    """Runs of different lengths (recorded segments) in the simulated scenarios' RMSE figure:
    each step's RMSE over the runs that reach it, on the longest run's time axis."""
    longer = RunSeries(RAGGED.runs, RAGGED.t, tuple(v * 2 for v in RAGGED.values))
    sc = ScenarioData(name="ragged", description="", folder=Path("."), runs=3, seed=None,
                      filters=[_series("ekf", "ekf", RAGGED), _series("anfekf", "anfekf", longer)],
                      true_noise={}, landmarks=np.zeros((0, 2)), waypoints=np.zeros((0, 2)),
                      track=None)  # fmt: skip
    fig = plots.rmse_figure(sc)
    line = next(a for a in fig.findobj() if a.get_gid() == "rmse_pos/anfekf")
    np.testing.assert_allclose(line.get_ydata(), 2 * RAGGED.band(rms=True).line)
    ratio = next(a for a in fig.findobj() if a.get_gid() == "rmse_ratio/anfekf")
    np.testing.assert_allclose(ratio.get_ydata(), [2.0, 2.0, 2.0])


@pytest.mark.parametrize("runs", [1, 3])
def test_draw_runs_draws_each_run_at_its_own_times(runs):
    from matplotlib.figure import Figure

    s = RunSeries(RAGGED.runs[:runs], RAGGED.t[:runs], RAGGED.values[:runs])
    ax = Figure().subplots()
    plots.draw_runs(ax, s, "x/f", "f", lw=0.5)
    (line,) = ax.get_lines()
    assert line.get_gid() == "x/f" and line.get_label() == "f"
    np.testing.assert_array_equal(line.get_xdata(), s.joined()[0])
