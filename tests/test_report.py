"""`anfekf report`: every figure's data equals the metrics of steps.parquet; files are valid images.

The plotted series are read back from the figures (artists carry gids such as "rmse_pos/ekf")
and compared with values computed here straight from steps.parquet with pandas, not through
report.py, so a wrong series in the report cannot agree with itself.
"""

from __future__ import annotations

import math
import re
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import load_scenario
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.report import plots
from anfekf_bench.report.report import (
    BAND_PERCENTILES,
    find_scenarios,
    load_scenario_data,
    summary_rows,
    write_report,
)
from anfekf_bench.storage import ResultsError, read_steps

from .conftest import SMALL_WORLD, small_scenario, write_scenario

runner = CliRunner()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURE_KINDS = ("rmse", "nees", "noise", "map")
SCENARIOS = {
    # Wrong R, the ANFEKF adapts R.
    "tiny_r": {},
    # Wrong Q, the ANFEKF adapts Q.
    "tiny_q": {
        "filter_noise": {"sigma_v": 0.03, "sigma_gamma_deg": 0.5},
        "filters": [
            {"name": "ekf", "kind": "ekf"},
            {"name": "anfekf", "kind": "anfekf", "adapt": "Q"},
            {"name": "ekf-oracle", "kind": "ekf-oracle"},
        ],
    },
}
RUNS = 3


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """Two tiny scenarios (3 runs, a ~60 m route, recorded at the sensor rate) in one folder."""
    root = tmp_path_factory.mktemp("report")
    out = root / "results"
    for name, overrides in SCENARIOS.items():
        doc = small_scenario(name=name, runs=RUNS, record_every=8, **overrides)
        scenario, world = load_scenario(write_scenario(root / f"{name}.yaml", doc))
        execute(make_plan(scenario, world, None, None, 1), out)  # 1 job: no worker start-up
    return out


@pytest.fixture(scope="module")
def report_dir(results: Path) -> tuple[Path, str]:
    """The report of `results`, written by the command line; returns (folder, its stdout)."""
    out = results / "report"
    result = runner.invoke(app, ["report", str(results), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out, result.output


def _pivot(steps: pd.DataFrame, name: str, column: str) -> np.ndarray:
    """(runs, steps) array of one column of one filter, straight from the steps table."""
    sub = steps[steps["filter"] == name]
    return sub.pivot(index="run", columns="step", values=column).to_numpy(dtype=float)


def _artist(fig, gid: str):
    found = [a for ax in fig.axes for a in (*ax.lines, *ax.collections, *ax.patches)]
    found = [a for a in found if a.get_gid() == gid]
    assert len(found) == 1, f"expected one artist {gid!r}, found {len(found)}"
    return found[0]


def _legend_texts(fig) -> list[str]:
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend())]
    return [t.get_text() for leg in legends for t in leg.get_texts()]


# --------------------------------------------------------------------------- files


def test_report_holds_every_figure_and_the_markdown(report_dir):
    out, stdout = report_dir
    expected = [f"{s}_{k}.png" for s in SCENARIOS for k in FIGURE_KINDS] + ["overview.png"]
    for name in expected:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000, name
    md = (out / "report.md").read_text(encoding="utf-8")
    embedded = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert sorted(embedded) == sorted(expected)
    for name in SCENARIOS:
        assert f"| {name} | anfekf | {RUNS}/{RUNS} |" in md
    assert "tiny_q" in stdout and "anfekf" in stdout and "report.md" in stdout


@pytest.mark.parametrize(
    ("fmt", "header"),
    [("svg", b"<svg"), ("pdf", b"%PDF-")],
    ids=["svg", "pdf"],
)
def test_other_formats_are_valid_files(results, tmp_path, fmt, header):
    out = tmp_path / "rep"
    result = runner.invoke(
        app, ["report", str(results / "tiny_r"), "--out", str(out), "--format", fmt]
    )
    assert result.exit_code == 0, result.output
    files = sorted(out.glob(f"*.{fmt}"))
    assert [f.name for f in files] == sorted(
        [f"tiny_r_{k}.{fmt}" for k in FIGURE_KINDS] + [f"overview.{fmt}"]
    )
    for f in files:
        head = f.read_bytes()[:2000]
        assert header in head and f.stat().st_size > 1000, f.name
    assert f"tiny_r_map.{fmt}" in (out / "report.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("fmt", ["png", "svg", "pdf"])
def test_figures_are_written_again_byte_for_byte(results, tmp_path, fmt):
    """No timestamps in the files: a committed report only changes when the results do."""
    written = []
    for attempt in ("a", "b"):
        fig = plots.nees_figure(load_scenario_data(results / "tiny_q"))
        plots.save_figure(fig, tmp_path / f"{attempt}.{fmt}", fmt)
        written.append((tmp_path / f"{attempt}.{fmt}").read_bytes())
    assert written[0] == written[1]


# --------------------------------------------------------------------------- figure data


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_rmse_figure_plots_the_rmse_over_runs_and_the_run_spread(results, scenario):
    steps = read_steps(results / scenario)
    sc = load_scenario_data(results / scenario)
    fig = plots.rmse_figure(sc)
    for f in sc.filters:
        pos = _pivot(steps, f.name, "pos_err")
        head = np.degrees(_pivot(steps, f.name, "heading_err"))
        for key, err in (("rmse_pos", pos), ("rmse_heading", head)):
            line = _artist(fig, f"{key}/{f.name}")
            np.testing.assert_allclose(line.get_ydata(), np.sqrt((err**2).mean(axis=0)))
            np.testing.assert_allclose(line.get_xdata(), np.sort(steps["t"].unique()))
            band = _artist(fig, f"{key}_band/{f.name}").get_paths()[0].vertices[:, 1]
            lo, hi = np.percentile(err, BAND_PERCENTILES, axis=0)
            assert band.min() == pytest.approx(lo.min()) and band.max() == pytest.approx(hi.max())
    assert f"{RUNS} runs" in fig.get_suptitle() and scenario in fig.get_suptitle()
    assert [ax.get_ylabel() for ax in fig.axes] == ["position RMSE [m]", "heading RMSE [deg]"]


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_legend_numbers_are_the_saved_summary(results, scenario):
    summary = pd.read_parquet(results / scenario / "summary.parquet").set_index("filter")
    sc = load_scenario_data(results / scenario)
    rmse_texts = _legend_texts(plots.rmse_figure(sc))
    nees_texts = _legend_texts(plots.nees_figure(sc))
    for name, rec in summary.iterrows():
        rmse = f"{name}: {rec.rmse_pos:.3f} m, {math.degrees(rec.rmse_heading):.3f} deg"
        assert rmse in rmse_texts
        nees = f"{name}: ANEES {rec.anees:.2f}, {100 * rec.nees_in_bounds:.1f} % in bounds"
        assert nees in nees_texts


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_nees_figure_plots_the_run_average_and_the_chi_square_bounds(results, scenario):
    steps = read_steps(results / scenario)
    fig = plots.nees_figure(load_scenario_data(results / scenario))
    for name in ("ekf", "anfekf", "ekf-oracle"):
        line = _artist(fig, f"nees/{name}")
        np.testing.assert_allclose(line.get_ydata(), _pivot(steps, name, "nees").mean(axis=0))
    lo = chi2.ppf(0.025, 3 * RUNS) / RUNS
    hi = chi2.ppf(0.975, 3 * RUNS) / RUNS
    assert _artist(fig, f"nees_bound_lo/{RUNS}").get_ydata()[0] == pytest.approx(lo)
    assert _artist(fig, f"nees_bound_hi/{RUNS}").get_ydata()[0] == pytest.approx(hi)
    assert f"95 % bounds, {RUNS} runs: [{lo:.2f}, {hi:.2f}]" in _legend_texts(fig)
    assert fig.axes[0].get_yscale() == "log"


def _deg2(sigma_deg: float) -> float:
    """A variance in rad² from a standard deviation in degrees."""
    return math.radians(sigma_deg) ** 2


@pytest.mark.parametrize(
    ("scenario", "columns", "true_var", "assumed_var"),
    [
        # (sigma_range, sigma_bearing): true (0.1 m, 1 deg), assumed (2 m, 0.1 deg)
        ("tiny_r", ["R_rr", "R_bb"], [0.1**2, _deg2(1.0)], [2.0**2, _deg2(0.1)]),
        # (sigma_v, sigma_gamma): true (0.3 m/s, 3 deg), assumed (0.03 m/s, 0.5 deg)
        ("tiny_q", ["Q_vv", "Q_gg"], [0.3**2, _deg2(3.0)], [0.03**2, _deg2(0.5)]),
    ],
    ids=["adapts_R", "adapts_Q"],
)  # fmt: skip
def test_noise_figure_plots_the_adapted_diagonal_against_the_truth(
    results, scenario, columns, true_var, assumed_var
):
    steps = read_steps(results / scenario)
    sc = load_scenario_data(results / scenario)
    assert sc.adapted_columns == columns
    fig = plots.noise_figure(sc)
    for col, true, assumed in zip(columns, true_var, assumed_var, strict=True):
        adapted = _artist(fig, f"noise/{col}/anfekf").get_ydata()
        np.testing.assert_allclose(adapted, _pivot(steps, "anfekf", col).mean(axis=0))
        assert adapted[0] == pytest.approx(assumed)  # starts from the filter's assumption
        assert _artist(fig, f"noise_true/{col}").get_ydata()[0] == pytest.approx(true)
        fixed = _artist(fig, f"noise_fixed/{col}/ekf").get_ydata()
        np.testing.assert_allclose(fixed, assumed)
    assert all(ax.get_yscale() == "log" for ax in fig.axes if ax.get_visible())


def test_map_figure_draws_the_world_run_zero_and_its_ellipses(results):
    steps = read_steps(results / "tiny_r")
    sc = load_scenario_data(results / "tiny_r")
    fig = plots.map_figure(sc)
    run0 = steps[(steps["run"] == 0) & (steps["filter"] == "ekf")].sort_values("step")
    truth = _artist(fig, "map_truth")
    np.testing.assert_allclose(truth.get_xdata(), run0["x_true"])
    np.testing.assert_allclose(truth.get_ydata(), run0["y_true"])
    landmarks = _artist(fig, "map_landmarks").get_offsets()
    np.testing.assert_allclose(landmarks, SMALL_WORLD["landmarks"])
    np.testing.assert_allclose(
        _artist(fig, "map_waypoints").get_offsets(), SMALL_WORLD["waypoints"]
    )
    for name in ("ekf", "anfekf", "ekf-oracle"):
        est = steps[(steps["run"] == 0) & (steps["filter"] == name)].sort_values("step")
        np.testing.assert_allclose(_artist(fig, f"map_est/{name}").get_xdata(), est["x_est"])
        k = int(sc.track.ellipse_index[-1])
        cov = est[["P_xx", "P_xy", "P_xy", "P_yy"]].to_numpy()[k].reshape(2, 2)
        ell = _artist(fig, f"map_ellipse/{name}/{k}")
        assert ell.width == pytest.approx(6 * math.sqrt(np.linalg.eigvalsh(cov)[-1]))
        assert ell.center == pytest.approx((est["x_est"].iloc[k], est["y_est"].iloc[k]))
    assert 3 <= len(sc.track.ellipse_index) <= 8
    assert {ax.get_xlabel() for ax in fig.axes} == {"x [m]"}


def test_summary_rows_and_overview_bars_equal_the_saved_summary(results):
    scenarios = [load_scenario_data(results / s) for s in SCENARIOS]
    rows = summary_rows(scenarios)
    fig = plots.overview_figure(rows)
    for scenario in SCENARIOS:
        saved = pd.read_parquet(results / scenario / "summary.parquet").set_index("filter")
        for row in (r for r in rows if r.scenario == scenario):
            rec = saved.loc[row.filter]
            assert row.rmse_pos == pytest.approx(rec.rmse_pos)
            assert row.anees == pytest.approx(rec.anees)
            assert row.nees_in_bounds == pytest.approx(rec.nees_in_bounds)
            assert row.vs_ekf == pytest.approx(rec.rmse_pos / saved.loc["ekf"].rmse_pos)
            assert row.vs_oracle == pytest.approx(rec.rmse_pos / saved.loc["ekf-oracle"].rmse_pos)
            bar = _artist(fig, f"overview_rmse_pos/{scenario}/{row.filter}")
            assert bar.get_height() == pytest.approx(rec.rmse_pos)
            bar = _artist(fig, f"overview_nees_in_bounds/{scenario}/{row.filter}")
            assert bar.get_height() == pytest.approx(100 * rec.nees_in_bounds)


def test_diverged_runs_are_left_out_of_curves_bounds_and_table(results, tmp_path):
    """Mark anfekf's run 2 diverged (NaN from mid-route), as the runner records a divergence."""
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    steps = read_steps(folder)
    lost = (steps["filter"] == "anfekf") & (steps["run"] == 2)
    steps.loc[lost, "diverged"] = True
    late = lost & (steps["step"] > steps["step"].median())
    steps.loc[late, ["x_est", "y_est", "P_xx", "P_xy", "P_yy", "pos_err", "nees", "R_rr"]] = np.nan
    steps.to_parquet(folder / "steps.parquet")
    sc = load_scenario_data(folder)
    anf = next(f for f in sc.filters if f.name == "anfekf")
    assert (anf.runs, anf.runs_used) == (RUNS, RUNS - 1)
    fig = plots.nees_figure(sc)
    kept = _pivot(steps, "anfekf", "nees")[:2]
    np.testing.assert_allclose(_artist(fig, "nees/anfekf").get_ydata(), kept.mean(axis=0))
    lo = chi2.ppf(0.025, 3 * (RUNS - 1)) / (RUNS - 1)
    assert _artist(fig, f"nees_bound_lo/{RUNS - 1}").get_ydata()[0] == pytest.approx(lo)
    assert any("1 of 3 runs diverged" in t for t in _legend_texts(fig))
    pos = _pivot(steps, "anfekf", "pos_err")[:2]
    row = next(r for r in summary_rows([sc]) if r.filter == "anfekf")
    assert row.runs_used == RUNS - 1
    assert row.rmse_pos == pytest.approx(np.sqrt((pos**2).mean(axis=0)).mean())


def test_a_filter_has_one_colour_in_every_figure(results):
    sc = load_scenario_data(results / "tiny_r")
    figs = [plots.rmse_figure(sc), plots.nees_figure(sc), plots.map_figure(sc)]
    for name in ("ekf", "anfekf", "ekf-oracle"):
        colours = {
            _artist(fig, gid).get_color()
            for fig, gid in zip(
                figs, [f"rmse_pos/{name}", f"nees/{name}", f"map_est/{name}"], strict=True
            )
        }
        assert colours == {plots.filter_colour(name)}
    assert len({plots.filter_colour(n) for n in plots.FILTER_COLOURS}) == len(plots.FILTER_COLOURS)


def test_unknown_filter_names_get_a_stable_fallback_colour():
    # crc32 of the name, not Python's per-process hash(): the same in every run of the report.
    expected = plots.FALLBACK_COLOURS[zlib.crc32(b"my-filter") % len(plots.FALLBACK_COLOURS)]
    assert plots.filter_colour("my-filter") == expected
    others = {plots.filter_colour(f"variant-{i}") for i in range(30)}
    assert len(others) > 1 and others <= set(plots.FALLBACK_COLOURS)
    assert not others & set(plots.FILTER_COLOURS.values())


# --------------------------------------------------------------------------- finding results


def test_the_report_folder_and_repeated_folders_are_skipped(results):
    both = find_scenarios([results, results / "tiny_q"], out_dir=results / "report")
    assert [p.name for p in both] == ["tiny_q", "tiny_r"]
    only_q = find_scenarios([results], out_dir=results / "tiny_r")
    assert [p.name for p in only_q] == ["tiny_q"]


def _copy_scenario(results: Path, target: Path) -> Path:
    target.mkdir(parents=True)
    for f in (results / "tiny_r").iterdir():
        (target / f.name).write_bytes(f.read_bytes())
    return target


def _missing(tmp_path, results) -> Path:
    return tmp_path / "nope"


def _empty(tmp_path, results) -> Path:
    (tmp_path / "empty").mkdir()
    return tmp_path / "empty"


def _no_steps(tmp_path, results) -> Path:
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    (folder / "steps.parquet").unlink()
    return folder


def _corrupt_steps(tmp_path, results) -> Path:
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    (folder / "steps.parquet").write_bytes(b"not parquet at all")
    return folder


def _no_manifest(tmp_path, results) -> Path:
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    (folder / "manifest.json").unlink()
    return folder


def _bad_manifest(tmp_path, results) -> Path:
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    (folder / "manifest.json").write_text('{"scenario": {"filters": 3}}', encoding="utf-8")
    return folder


def _same_scenario_twice(tmp_path, results) -> Path:
    _copy_scenario(results, tmp_path / "res" / "a" / "tiny_r")
    _copy_scenario(results, tmp_path / "res" / "b" / "tiny_r")
    return tmp_path / "res" / "a" / "tiny_r"


BAD_RESULTS = {
    "missing_folder": (_missing, "results folder does not exist"),
    "empty_folder": (_empty, "no results found"),
    "no_steps_parquet": (_no_steps, "no results found"),
    "corrupt_steps_parquet": (_corrupt_steps, "not a readable Parquet file"),
    "no_manifest": (_no_manifest, "no manifest.json"),
    "bad_manifest": (_bad_manifest, "scenario.filters"),
}


@pytest.mark.parametrize(("make", "message"), BAD_RESULTS.values(), ids=BAD_RESULTS.keys())
def test_bad_results_give_one_line_and_exit_2(results, tmp_path, make, message):
    target = make(tmp_path, results)
    out = tmp_path / "report-out"
    result = runner.invoke(app, ["report", str(target), "--out", str(out)])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], lines
    assert "Traceback" not in result.output
    assert not out.exists()  # nothing half-written


def test_two_results_of_one_scenario_are_refused(results, tmp_path):
    _same_scenario_twice(tmp_path, results)
    with pytest.raises(ResultsError, match="both hold scenario 'tiny_r'"):
        write_report(
            [tmp_path / "res" / "a" / "tiny_r", tmp_path / "res" / "b" / "tiny_r"], tmp_path / "o"
        )


def test_unknown_format_is_refused(results, tmp_path):
    result = runner.invoke(app, ["report", str(results), "--out", str(tmp_path), "--format", "jpg"])
    assert result.exit_code == 2
    assert "--format" in result.stderr and "png, svg, pdf" in result.stderr
