"""One report of everything: a sweep-only folder gets report.md and report.html too, every
figure written is in them (the sweep's section: its cells, figures and captions); the sweep
heatmaps use the report's one ratio scale (a ratio of 1 has one colour everywhere) and leave out
the oracle's constant panel."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.report import plots
from anfekf_bench.report.sweep import heatmap_figure, read_sweep
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.sweeps import cell_plans, expand, run_sweep

from .conftest import small_scenario, write_scenario

runner = CliRunner()
pytestmark = pytest.mark.slow  # a sweep of 4 cells end to end


@pytest.fixture(scope="module")
def sweep_folder(tmp_path_factory) -> Path:
    """A 2 x 2 sweep (R factor 0.5, 1; Qu factor 1, 2), 2 runs a cell, the true noise at 1."""
    root = tmp_path_factory.mktemp("sweep")
    doc = small_scenario(name="sw", runs=2, jobs=1, record_every=8)
    doc["filter_noise"] = {}
    doc["filters"] = [
        {"name": "ekf", "kind": "ekf"},
        {"name": "anfekf", "kind": "anfekf", "window": 5},
        {"name": "ekf-oracle", "kind": "ekf-oracle"},
    ]
    doc["sweep"] = {
        "axes": [{"scale": "R", "values": [0.5, 1.0]}, {"scale": "Qu", "values": [1.0, 2.0]}]
    }
    path = write_scenario(root / "sw.yaml", doc)
    scenario, _ = load_scenario(path)
    cells = expand(scenario, path)
    plans = cell_plans(cells, runs=None, seed=None, jobs=None)
    _, target = run_sweep(scenario.name, scenario.sweep.axes, cells, plans, root / "out")
    return target


def test_a_sweep_only_folder_gets_one_report_with_every_figure(sweep_folder, tmp_path):
    out = tmp_path / "report"
    result = runner.invoke(app, ["report", str(sweep_folder.parent), "--out", str(out)])
    assert result.exit_code == 0, result.output
    figures = sorted(p.name for p in out.iterdir() if p.suffix == ".png")
    assert figures, "the sweep's heatmaps"
    md = (out / "report.md").read_text(encoding="utf-8")
    assert "### Sweep sw" in md and "2 runs per cell" in md
    assert not (out / "sweeps.md").exists()  # one report: the sweep's section is in report.md
    # (a caption may hold brackets of its own: "position RMSE [m]")
    assert sorted(re.findall(r"\]\(([^)\s]+\.png)\)", md)) == figures
    page = (out / "report.html").read_text(encoding="utf-8")
    assert page.count('<img src="data:image/png;base64,') == len(figures)
    assert all(f'href="{name}"' in page for name in figures)
    assert 'href="#sweeps"' in page  # the table of contents
    assert f"({len(figures)} figures)" in result.output and "1 sweep" in result.output


def test_the_sweep_heatmap_uses_the_one_ratio_scale_without_the_oracle_panel(sweep_folder):
    data = read_sweep(sweep_folder)
    x, y = data.axes[:2]
    fig = heatmap_figure(data, x, y, data.table, "rmse_pos_vs_oracle", "position RMSE / oracle")
    panels = [ax for ax in fig.axes if ax.get_images()]
    assert [ax.get_title() for ax in panels] == ["ekf", "anfekf"]  # no constant oracle panel
    assert "interval" not in fig.get_suptitle()
    ekf = panels[0].get_images()[0]
    # the EKF at R factor 1 and Qu factor 1 is the oracle: a ratio of exactly 1
    xs, ys = sorted(data.table[x].unique()), sorted(data.table[y].unique())
    i, j = ys.index(1.0), xs.index(1.0)
    cell = ekf.get_array()[i, j]
    assert tuple(ekf.to_rgba(cell)) == pytest.approx(plots.ratio_colour(1.0))
    # ... the colour the leaderboard gives a ratio of 1 (a fixed scale, not from the data)
    bar = [ax for ax in fig.axes if not ax.get_images() and ax.get_visible()][-1]
    labels = {t.get_text() for t in bar.get_yticklabels()}
    ratio_ticks = {plots.plain_number(t) for t in plots.RATIO_TICK_PRIORITY}
    assert {"0.667", "1", "30"} <= labels <= ratio_ticks  # the ratio scale's ticks, as many as fit


def _run_sweep(root: Path, axes: list[dict]) -> Path:
    doc = small_scenario(name="sc", runs=2, jobs=1, record_every=8)
    doc["filter_noise"] = {}
    doc["filters"] = [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-oracle", "kind": "ekf-oracle"}]
    doc["sweep"] = {"axes": axes}
    path = write_scenario(root / "sc.yaml", doc)
    scenario, _ = load_scenario(path)
    cells = expand(scenario, path)
    plans = cell_plans(cells, runs=None, seed=None, jobs=None)
    return run_sweep(scenario.name, scenario.sweep.axes, cells, plans, root / "out")[1]


@pytest.mark.parametrize(
    "axis",
    [
        {"scale": "R", "factors": {"start": 0.5, "stop": 2.0, "num": 2}},  # as configs/sweeps
        {"scale": "Qu", "values": [0.5, 2.0]},
    ],
    ids=["scale-factors", "scale-values"],
)
def test_a_sweep_with_a_scale_axis_renders(axis, tmp_path):
    """A `scale:` axis has no `field` (its label is <scale>_factor): the report read the field
    of every `factors:` axis and crashed with an AttributeError on None."""
    target = _run_sweep(tmp_path, [axis])
    data = read_sweep(target)
    label = f"{axis['scale']}_factor"
    assert data.axes == [label] and data.factor_axes == {label}
    out = tmp_path / "report"
    result = runner.invoke(app, ["report", str(target.parent), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert (out / "sweep-sc.png").is_file()
    # a factor axis is drawn on a log scale
    fig = line_figure_of(data)
    assert all(ax.get_xscale() == "log" for ax in fig.axes if ax.axison)


def line_figure_of(data):
    from anfekf_bench.report.sweep import line_figure

    return line_figure(data, data.axes[0], data.table, data.name)
