"""`anfekf report`: every figure's data equals the metrics of steps.parquet; files are valid images.

The plotted series are read back from the figures (artists carry gids such as "rmse_pos/ekf")
and compared with values computed here straight from steps.parquet with pandas, not through
report.py, so a wrong series in the report cannot agree with itself.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2
from typer.testing import CliRunner

from anfekf_bench.analysis.metrics import format_sig
from anfekf_bench.cli import app
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.filters.registry import role_of
from anfekf_bench.report import plots, summary_figures
from anfekf_bench.report.report import (
    BAND_PERCENTILES,
    OUTLIER_FACTOR,
    claim_interval_problem,
    find_scenarios,
    load_scenario_data,
    summary_rows,
    write_report,
)
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import ResultsError, parquet_provenance, read_steps, write_parquet

from .conftest import SMALL_WORLD, small_scenario, write_scenario

runner = CliRunner()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURE_KINDS = ("rmse", "nees", "noise", "map")
SCENARIOS = {
    # Wrong R, the ANFEKF adapts R; a claim (3 runs: its interval may well be too wide).
    "tiny_r": {
        "claims": [{"filter": "anfekf", "vs": "ekf", "metric": "rmse_pos", "at_most": 0.9}],
    },
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
    expected = [f"{s}_{k}.png" for s in SCENARIOS for k in FIGURE_KINDS]
    expected += ["overview.png", "leaderboard.png"]
    for name in expected:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000, name
    md = (out / "report.md").read_text(encoding="utf-8")
    embedded = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert sorted(embedded) == sorted(expected)
    # every figure written is in the report, counted against the files, and the count printed
    written = sorted(p.name for p in out.iterdir() if p.suffix == ".png")
    assert written == sorted(expected)
    assert f"({len(written)} figures)" in stdout
    page = (out / "report.html").read_text(encoding="utf-8")
    assert page.count("<img ") == len(written)
    assert all(f'href="{name}"' in page for name in written)
    assert "<strong>Contents</strong>" in page and 'href="#leaderboard"' in page
    assert "[Leaderboard](#leaderboard)" in md and '<a id="leaderboard"></a>' in md
    # the leaderboard's table: filters x scenarios, sortable by any scenario and the median
    board = page.split('id="leaderboard"')[1].split("</table>")[0]
    assert '<table class="sortable">' in board and ">median</th>" in board
    assert all(f">{name}</th>" in board for name in SCENARIOS)
    for name in SCENARIOS:
        assert f"| {name} | anfekf | {RUNS}/{RUNS} |" in md
    assert "tiny_q" in stdout and "anfekf" in stdout and "report.md" in stdout
    assert "report.html" in stdout
    assert (out / "report.html").read_text(encoding="utf-8").startswith("<!DOCTYPE html>")


@pytest.mark.parametrize(
    ("fmt", "header"),
    [("svg", b"<svg"), ("pdf", b"%PDF-")],
    ids=["svg", "pdf"],
)
def test_other_formats_are_valid_files(results, tmp_path, fmt, header):
    """SVG and PDF figures; report.md embeds SVG but links PDF files (a markdown viewer shows no
    PDF image), and report.html embeds an image of every figure either way."""
    out = tmp_path / "rep"
    result = runner.invoke(
        app, ["report", str(results / "tiny_r"), "--out", str(out), "--format", fmt]
    )
    assert result.exit_code == 0, result.output
    files = sorted(out.glob(f"*.{fmt}"))
    assert [f.name for f in files] == sorted(
        [f"tiny_r_{k}.{fmt}" for k in FIGURE_KINDS] + [f"overview.{fmt}", f"leaderboard.{fmt}"]
    )
    for f in files:
        head = f.read_bytes()[:2000]
        assert header in head and f.stat().st_size > 1000, f.name
    md = (out / "report.md").read_text(encoding="utf-8")
    assert f"tiny_r_map.{fmt}" in md
    embedded = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    linked = re.findall(r"(?<!!)\[[^\]]*\]\(([^)]+\.pdf)\)", md)
    if fmt == "pdf":
        assert embedded == [] and sorted(linked) == [f.name for f in files]
    else:
        assert sorted(embedded) == [f.name for f in files] and linked == []
    page = (out / "report.html").read_text(encoding="utf-8")
    mime = "image/svg+xml" if fmt == "svg" else "image/png"
    assert page.count(f'<img src="data:{mime};base64,') == len(files)


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
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert labels == ["position RMSE [m]", "heading RMSE [deg]", "position RMSE / ekf-oracle (log)"]


def _sig3(x: float) -> str:
    """x to 3 significant digits, written independently of format_sig."""
    text = f"{x:#.3g}"
    assert "e" not in text, x
    return text.rstrip(".")


@pytest.mark.parametrize(
    ("value", "text"),
    [(0.0574, "0.0574"), (1.0449, "1.04"), (18.94, "18.9"), (121.61, "122"), (9.996, "10.0"),
     (0.203, "0.203"), (3.602, "3.60"), (12345.6, "12346"), (1e-6, "0.00000100"), (0, "0"),
     (math.nan, "-"), (math.inf, "-"), (-0.5, "-0.500")],
)  # fmt: skip
def test_numbers_have_three_significant_digits_in_plain_notation(value, text):
    assert format_sig(value) == text


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_legend_numbers_are_the_saved_summary(results, scenario):
    summary = pd.read_parquet(results / scenario / "summary.parquet").set_index("filter")
    sc = load_scenario_data(results / scenario)
    rmse_texts = _legend_texts(plots.rmse_figure(sc))
    nees_texts = _legend_texts(plots.nees_figure(sc))
    for name, rec in summary.iterrows():
        head = math.degrees(rec.rmse_heading)
        rmse = f"{name}: {_sig3(rec.rmse_pos)} m, {_sig3(head)} deg"
        assert rmse in rmse_texts
        nees = f"{name}: ANEES {_sig3(rec.anees)}, {100 * rec.nees_in_bounds:.1f} % in bounds"
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
    assert f"95 % bounds, {RUNS} runs: [{_sig3(lo)}, {_sig3(hi)}]" in _legend_texts(fig)
    assert fig.axes[0].get_yscale() == "log"
    # The median over runs beside the mean: a single run cannot hide what a typical run does.
    for name in ("ekf", "anfekf", "ekf-oracle"):
        median = _artist(fig, f"nees_median/{name}").get_ydata()
        np.testing.assert_allclose(median, np.median(_pivot(steps, name, "nees"), axis=0))


def _deg2(sigma_deg: float) -> float:
    """A variance in deg² (the noise figure shows angles in degrees, like the whole report)."""
    return sigma_deg**2


_SHOWN = {"R_rr": 1.0, "R_bb": math.degrees(1.0) ** 2, "Q_vv": 1.0, "Q_gg": math.degrees(1.0) ** 2}


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
        stored = _pivot(steps, "anfekf", col) * _SHOWN[col]  # rad² in the file, deg² shown
        adapted = _artist(fig, f"noise/{col}/anfekf").get_ydata()
        np.testing.assert_allclose(adapted, stored.mean(axis=0))
        median = _artist(fig, f"noise_median/{col}/anfekf").get_ydata()
        np.testing.assert_allclose(median, np.median(stored, axis=0))
        assert adapted[0] == pytest.approx(assumed)  # starts from the filter's assumption
        assert _artist(fig, f"noise_true/{col}").get_ydata()[0] == pytest.approx(true)
        fixed = _artist(fig, f"noise_fixed/{col}/ekf").get_ydata()
        np.testing.assert_allclose(fixed, assumed)
    assert all(ax.get_yscale() == "log" for ax in fig.axes if ax.get_visible())
    assert all("rad" not in ax.get_ylabel() for ax in fig.axes)  # one angle unit: degrees


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


def test_summary_rows_and_overview_ratios_equal_the_saved_summary_and_comparisons(results):
    scenarios = [load_scenario_data(results / s) for s in SCENARIOS]
    rows = summary_rows(scenarios)
    fig = summary_figures.overview_figure(rows)
    for scenario in SCENARIOS:
        saved = pd.read_parquet(results / scenario / "summary.parquet").set_index("filter")
        comp = pd.read_parquet(results / scenario / "comparisons.parquet")
        comp = comp.set_index(["filter", "vs", "metric"])
        for row in (r for r in rows if r.scenario == scenario):
            rec = saved.loc[row.filter]
            assert row.rmse_pos == pytest.approx(rec.rmse_pos)
            assert row.anees == pytest.approx(rec.anees)
            assert row.nees_in_bounds == pytest.approx(rec.nees_in_bounds)
            assert row.vs_ekf == pytest.approx(rec.rmse_pos / saved.loc["ekf"].rmse_pos)
            assert row.vs_oracle == pytest.approx(rec.rmse_pos / saved.loc["ekf-oracle"].rmse_pos)
            bar = _artist(fig, f"overview_nees_in_bounds/{scenario}/{row.filter}")
            assert bar.get_height() == pytest.approx(100 * rec.nees_in_bounds)
            if row.filter == "ekf-oracle":
                continue  # the reference: the dashed line at 1
            for key, metric in (("rmse_ratio", "rmse_pos"), ("anees_ratio", "anees")):
                saved_ratio = rec[metric] / saved.loc["ekf-oracle"][metric]
                c = comp.loc[(row.filter, "ekf-oracle", metric)]
                point = _artist(fig, f"overview_{key}/{scenario}/{row.filter}").get_ydata()[0]
                # No run diverged: the paired estimate is the summaries' ratio.
                assert point == pytest.approx(saved_ratio) == pytest.approx(c.estimate)
                if np.isfinite(c.lo) and np.isfinite(c.hi) and c.hi > c.lo:
                    segment = _artist(fig, f"overview_{key}_ci/{scenario}/{row.filter}")
                    lo_hi = segment.get_segments()[0][:, 1]
                    assert sorted(lo_hi) == pytest.approx([c.lo, c.hi])
    ratio_axes = [ax for ax in fig.axes if ax.get_yscale() == "log"]
    assert len(ratio_axes) == 2


def test_rmse_ratio_panel_shows_the_gap_to_the_oracle(results):
    """Where ANFEKF's line lies on the oracle's, the ratio panel separates them: the plotted
    ratio is the ratio of the RMSE-over-runs curves, its level line the summary's ratio."""
    steps = read_steps(results / "tiny_r")
    saved = pd.read_parquet(results / "tiny_r" / "summary.parquet").set_index("filter")
    fig = plots.rmse_figure(load_scenario_data(results / "tiny_r"))
    oracle = np.sqrt((_pivot(steps, "ekf-oracle", "pos_err") ** 2).mean(axis=0))
    for name in ("ekf", "anfekf"):
        mine = np.sqrt((_pivot(steps, name, "pos_err") ** 2).mean(axis=0))
        curve = _artist(fig, f"rmse_ratio/{name}").get_ydata()
        np.testing.assert_allclose(curve, mine / oracle)
        level = _artist(fig, f"rmse_ratio_mean/{name}").get_ydata()[0]
        assert level == pytest.approx(saved.loc[name].rmse_pos / saved.loc["ekf-oracle"].rmse_pos)
        legend = f"{name}: {_sig3(level)}"
        assert any(t.startswith(legend) for t in _legend_texts(fig))
    assert fig.axes[2].get_yscale() == "log"


def _rewrite(path: Path, df: pd.DataFrame) -> None:
    """Edit a result file in place, keeping its batch's metadata (seed, fingerprint, units)."""
    write_parquet(path, df, parquet_provenance(path))


def test_diverged_runs_are_left_out_of_curves_bounds_and_table(results, tmp_path):
    """Mark anfekf's run 2 diverged (NaN from mid-route), as the runner records a divergence."""
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    steps = read_steps(folder)
    lost = (steps["filter"] == "anfekf") & (steps["run"] == 2)
    steps.loc[lost, "diverged"] = True
    late = lost & (steps["step"] > steps["step"].median())
    steps.loc[late, ["x_est", "y_est", "P_xx", "P_xy", "P_yy", "pos_err", "nees", "R_rr"]] = np.nan
    _rewrite(folder / "steps.parquet", steps)
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
    oracles = [f.name for f in sc.filters if role_of(f.kind) == "oracle"]
    assert oracles == ["ekf-oracle"]
    with plots.palette([f.name for f in sc.filters], oracles):
        figs = [plots.rmse_figure(sc), plots.nees_figure(sc), plots.map_figure(sc)]
        for name in ("ekf", "anfekf", "ekf-oracle"):
            colours = {
                _artist(fig, gid).get_color()
                for fig, gid in zip(
                    figs, [f"rmse_pos/{name}", f"nees/{name}", f"map_est/{name}"], strict=True
                )
            }
            assert colours == {plots.filter_colour(name)}


def test_colours_go_by_order_within_a_report_and_thirty_filters_are_told_apart():
    names = [f"zoo-{i}" for i in range(30)]  # names that hashed onto one colour collided
    with plots.palette(names):
        pairs = [(plots.filter_colour(n), str(plots.filter_linestyle(n))) for n in names]
        markers = [(plots.filter_colour(n), plots.filter_marker(n)) for n in names]
        assert plots.filter_colour("zoo-0") == plots.PALETTE[0]
        # the reference, grey: by its kind's role, whatever its name; by name where the palette
        # lists it among the report's oracles (figures that know a filter by name only)
        assert plots.filter_style("truth", "ekf-oracle") == plots.ORACLE_STYLE
        assert plots.filter_colour("ekf-oracle") != plots.ORACLE_COLOUR  # a name, not a kind
    with plots.palette(names, oracles=["truth"]):
        assert plots.filter_colour("truth") == plots.ORACLE_COLOUR
        assert plots.filter_style("zoo-0", "ekf").colour == plots.PALETTE[0]
    assert len(set(pairs)) == len(set(markers)) == 30
    assert plots.ORACLE_COLOUR not in plots.PALETTE
    with plots.palette(["b", "a"]):  # order, not the name, picks the colour
        assert plots.filter_colour("a") == plots.PALETTE[1]
    with plots.palette(["a", "b"]):
        assert plots.filter_colour("a") == plots.PALETTE[0]


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
    """Neither steps.parquet nor summary.parquet (a result without steps has a summary)."""
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    (folder / "steps.parquet").unlink()
    (folder / "summary.parquet").unlink()
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
    "no_steps_or_summary_parquet": (_no_steps, "no results found"),
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


def test_the_html_report_is_written_again_byte_for_byte(results, tmp_path):
    pages = []
    for attempt in ("a", "b"):
        write_report([results / "tiny_q"], tmp_path / attempt, dpi=40)
        pages.append((tmp_path / attempt / "report.html").read_bytes())
    assert pages[0] == pages[1]


# --------------------------------------------------------------------------- figure details


def _draw(fig) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig).draw()


def test_log_axes_have_plain_tick_labels(results):
    """2, 3, 5, 10, 0.5, never 2x10^0 or 10^-1."""
    sc = load_scenario_data(results / "tiny_q")
    figs = [plots.rmse_figure(sc), plots.nees_figure(sc), plots.noise_figure(sc)]
    figs.append(summary_figures.overview_figure(summary_rows([sc])))
    checked = 0
    for fig in figs:
        _draw(fig)
        for ax in fig.axes:
            if ax.get_yscale() != "log" or not ax.get_visible():
                continue
            labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
            assert len(labels) >= 2, (ax.get_ylabel(), labels)
            for text in labels:
                assert re.fullmatch(r"[0-9]+(\.[0-9]+)?", text), (ax.get_ylabel(), labels)
            checked += 1
    assert checked >= 5


@pytest.mark.parametrize(
    ("vmin", "vmax"), [(0.95, 1.1), (1.0, 20.0), (0.01, 3.0), (1e-6, 1e4), (2.0, 2.0)]
)
def test_the_log_locator_labels_every_range(vmin, vmax):
    ticks = plots.PlainLogLocator().tick_values(vmin, vmax)
    assert len(ticks) >= 1 and np.all(ticks > 0)
    texts = [plots.plain_number(t) for t in ticks]
    assert all(re.fullmatch(r"[0-9]+(\.[0-9]+)?", t) for t in texts), texts


def test_titles_do_not_repeat_the_scenario_name(results):
    """A scenario named 'consistency' once read 'consistency: consistency, ...'."""
    import dataclasses

    sc = dataclasses.replace(load_scenario_data(results / "tiny_r"), name="consistency")
    figs = [plots.rmse_figure(sc), plots.nees_figure(sc), plots.noise_figure(sc)]
    figs += [plots.map_figure(sc), summary_figures.overview_figure(summary_rows([sc]))]
    for fig in figs:
        titles = [fig.get_suptitle()] + [ax.get_title() for ax in fig.axes]
        for title in titles:
            words = re.findall(r"[a-z]+", title.lower())
            assert not any(a == b for a, b in zip(words, words[1:], strict=False)), title


def test_outlier_runs_are_marked_and_the_median_shown(results, tmp_path):
    """One run whose NEES is 1000 x the others' drags the run-averaged NEES and the mean adapted
    R far from every other run: it is named as an outlier, drawn thin, and the median stays."""
    folder = _copy_scenario(results, tmp_path / "res" / "tiny_r")
    steps = read_steps(folder)
    wild = (steps["filter"] == "anfekf") & (steps["run"] == 1)
    steps.loc[wild, "nees"] *= 1000.0
    steps.loc[wild, "R_rr"] *= 1000.0
    _rewrite(folder / "steps.parquet", steps)
    sc = load_scenario_data(folder)
    anf = next(f for f in sc.filters if f.name == "anfekf")
    assert anf.outliers == (1,)
    per_run = _pivot(steps, "anfekf", "nees").mean(axis=1)
    assert per_run[1] > OUTLIER_FACTOR * np.median(per_run)
    assert all(f.outliers == () for f in sc.filters if f.name != "anfekf")
    fig = plots.nees_figure(sc)
    np.testing.assert_allclose(_artist(fig, "nees_outlier/anfekf/1").get_ydata(),
                               _pivot(steps, "anfekf", "nees")[1])  # fmt: skip
    assert any("anfekf run 1: outlier" in t for t in _legend_texts(fig))
    # Off the top of the axis (its limits follow the averages): the figure says where.
    # (a triangle at the top, its peak in the legend: a text there printed over the others')
    marks = [a for a in fig.axes[0].lines if a.get_gid() == "nees_off_scale/anfekf/1"]
    assert len(marks) == 1 and not fig.axes[0].texts
    assert any("anfekf run 1: outlier" in t and "off scale (peak" in t for t in _legend_texts(fig))
    assert "outlier" in fig.axes[0].get_title()
    median = _artist(fig, "nees_median/anfekf").get_ydata()
    np.testing.assert_allclose(median, np.median(_pivot(steps, "anfekf", "nees"), axis=0))
    noise = plots.noise_figure(sc)
    np.testing.assert_allclose(_artist(noise, "noise_outlier/R_rr/anfekf/1").get_ydata(),
                               _pivot(steps, "anfekf", "R_rr")[1])  # fmt: skip
    assert "outlier" in noise.get_suptitle() and "median" in noise.get_suptitle()
    out = tmp_path / "rep"
    write_report([folder], out, dpi=40)
    md = (out / "report.md").read_text(encoding="utf-8")
    assert "outlier runs drawn thin: anfekf run 1" in md
    # The per-run table (runs.parquet) names it too.
    assert re.search(r"\| anfekf \|[^\n]*\| 1 \|", md), md


# --------------------------------------------------------------------------- report.md / html


def test_report_states_noise_mismatch_ratios_with_intervals_and_warnings(report_dir, results):
    out, _ = report_dir
    md = (out / "report.md").read_text(encoding="utf-8")
    # True against assumed noise (tiny_r: range 0.1 m true, 2 m assumed; bearing 1 vs 0.1 deg).
    assert "| range σr [m] | 0.100 | 2.00 | 20.0 |" in md
    assert "| bearing σb [deg] | 1.00 | 0.100 | 0.100 |" in md
    assert "**Noise mismatch:** the filters assume range σr 2.00 m for a true 0.100 m" in md
    # Links relative to the report folder: the report can be moved with its results.
    assert str(results) not in md and "[../tiny_r](../tiny_r)" in md
    # Ratio columns with the saved paired intervals.
    comp = pd.read_parquet(results / "tiny_r" / "comparisons.parquet")
    c = comp.set_index(["filter", "vs", "metric"]).loc[("anfekf", "ekf-oracle", "rmse_pos")]
    shown = f"{format_sig(c.estimate)} [{format_sig(c.lo)}, {format_sig(c.hi)}]"
    row = next(line for line in md.splitlines() if line.startswith("| tiny_r | anfekf |"))
    assert shown in row.split(" | ")[9]
    assert "RMSE / oracle [95 % CI]" in md
    # 3 runs: too few for the NEES bounds to discriminate.
    assert "> **Warning:** tiny_r: only 3 runs (fewer than 10)" in md
    assert "> **Warning:** tiny_q: only 3 runs" in md
    # The claims and their verdicts, with the warning each record carries.
    claims = json.loads((results / "tiny_r" / "claims.json").read_text(encoding="utf-8"))
    assert claims
    for claim in claims:
        line = next(x for x in md.splitlines() if x.startswith(f"| {claim['claim']} |"))
        assert f"| {claim['verdict']} |" in line
        assert (claim["warning"] or "") in line


@pytest.mark.parametrize(
    ("record", "problem"),
    [
        ({"at_most": 0.9, "estimate": 0.8, "lo": 0.7, "hi": 1.1, "method": "BCa"}, "straddles"),
        ({"at_most": 0.9, "estimate": 0.8, "lo": 0.7, "hi": 0.85, "method": "BCa"}, None),
        ({"at_least": 1, "estimate": 2, "lo": None, "hi": None, "method": "undefined"},
         "no 95 % interval"),
        ({"at_least": 0.85, "estimate": 0.9, "lo": None, "hi": None, "method": "point"}, None),
    ],
)  # fmt: skip
def test_a_claim_whose_interval_is_too_wide_is_a_warning(record, problem):
    found = claim_interval_problem(record)
    assert (found is None) if problem is None else (problem in found)


def test_dpi_sets_the_figure_resolution(results, tmp_path):
    sizes = {}
    for dpi in (40, 80):
        out = tmp_path / f"d{dpi}"
        result = runner.invoke(
            app, ["report", str(results / "tiny_q"), "--out", str(out), "--dpi", str(dpi)]
        )
        assert result.exit_code == 0, result.output
        head = (out / "overview.png").read_bytes()[16:24]
        sizes[dpi] = (int.from_bytes(head[:4], "big"), int.from_bytes(head[4:], "big"))
    assert sizes[80][0] == pytest.approx(2 * sizes[40][0], abs=2)
    bad = runner.invoke(app, ["report", str(results), "--out", str(tmp_path / "x"), "--dpi", "0"])
    assert bad.exit_code == 2 and "--dpi" in bad.stderr


def test_html_report_is_self_contained_with_sortable_tables(report_dir):
    out, _ = report_dir
    page = (out / "report.html").read_text(encoding="utf-8")
    figures = sorted(p.name for p in out.glob("*.png"))
    images = re.findall(r'<img src="([^"]+)"', page)
    assert len(images) == len(figures)
    assert all(src.startswith("data:image/png;base64,") for src in images)
    # Nothing fetched from anywhere: no external scripts, styles or images.
    assert not re.search(r'(src|href)="(https?:)?//', page)
    assert "<script src" not in page and "<link" not in page
    # Sortable tables: every header cell clickable, numbers sort by their value.
    assert page.count('<table class="sortable">') >= 1 + 2 * len(SCENARIOS)
    assert 'data-sort="' in page and 'addEventListener("click"' in page
    for name in SCENARIOS:
        assert f'id="scenario-{name}"' in page


CHROMIUM = next(
    (shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None
)


def _chromium(page: Path, profile: Path, *args: str) -> subprocess.CompletedProcess:
    command = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
        "--no-first-run", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--hide-scrollbars", f"--user-data-dir={profile}", *args,
        page.resolve().as_uri(),
    ]  # fmt: skip
    return subprocess.run(command, capture_output=True, timeout=180, check=False)


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_html_report_opens_in_a_headless_browser_with_every_image(report_dir, tmp_path):
    """The acceptance check: Chromium loads report.html, every image decodes, and a screenshot
    of the page is not blank."""
    from PIL import Image

    out, _ = report_dir
    page = out / "report.html"
    dom = _chromium(page, tmp_path / "profile-dom", "--dump-dom")
    assert dom.returncode == 0, dom.stderr[-2000:]
    found = re.search(rb'data-images-ok="(\d+)/(\d+)"', dom.stdout)
    assert found, "the page's load handler did not run"
    ok, total = int(found.group(1)), int(found.group(2))
    assert total == len(list(out.glob("*.png"))) and ok == total
    # Sorting: a click on the RMSE header orders the rows by value (numbers, not text).
    probe = tmp_path / "sorted.html"
    click = (
        "<script>var t = document.querySelector('table.sortable');"
        " t.querySelectorAll('th')[4].click();"
        " document.body.setAttribute('data-sorted', [].map.call(t.tBodies[0].rows,"
        " function (r) { return r.cells[4].getAttribute('data-sort'); }).join(' '));</script>"
    )
    probe.write_text(page.read_text(encoding="utf-8").replace("</body>", click + "</body>"))
    dom = _chromium(probe, tmp_path / "profile-sort", "--dump-dom")
    found = re.search(rb'data-sorted="([^"]*)"', dom.stdout)
    assert found, dom.stderr[-2000:]
    values = [float(v) for v in found.group(1).split()]
    assert len(values) == 3 * len(SCENARIOS) and values == sorted(values)
    shot = tmp_path / "shot.png"
    done = _chromium(page, tmp_path / "profile-shot", f"--screenshot={shot}",
                     "--window-size=1280,2400")  # fmt: skip
    assert done.returncode == 0 and shot.exists(), done.stderr[-2000:]
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert pixels.shape == (2400, 1280)
    assert pixels.std() > 20  # text, tables and figures: far from one flat colour
    assert (pixels < 128).mean() > 0.01  # dark ink somewhere


def test_a_result_without_steps_is_reported_from_its_tables(tmp_path):
    """`steps_table: false` writes no steps.parquet: the report still shows its summary rows,
    paired ratios, claims and per-run spread (no figures over time), and check still reads it."""
    doc = small_scenario(
        name="nosteps", runs=2, record_every=8, steps_table=False,
        claims=[{"filter": "anfekf", "vs": "ekf", "metric": "rmse_pos", "at_most": 1000.0}],
    )  # fmt: skip
    scenario, world = load_scenario(write_scenario(tmp_path / "nosteps.yaml", doc))
    _, target = execute(make_plan(scenario, world, None, None, 1), tmp_path / "results")
    assert not (target / "steps.parquet").exists()
    out = tmp_path / "report"
    result = runner.invoke(app, ["report", str(tmp_path / "results"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    md = (out / "report.md").read_text(encoding="utf-8")
    saved = pd.read_parquet(target / "summary.parquet").set_index("filter")
    row = next(line for line in md.splitlines() if line.startswith("| nosteps | anfekf |"))
    assert f"| {format_sig(saved.loc['anfekf'].rmse_pos)} |" in row
    assert "no steps.parquet" in md and "| anfekf rmse_pos <= 1000 x ekf |" in md
    assert sorted(p.name for p in out.glob("*.png")) == ["leaderboard.png", "overview.png"]
    checked = runner.invoke(app, ["check", str(tmp_path / "results")])
    assert checked.exit_code == 0, checked.output


def test_read_steps_orders_the_filters_by_first_appearance(tmp_path):
    """A steps table whose filter column is plain strings (not categorical) reads back with the
    filters as categories in the order they first appear (not sorted)."""
    pd.DataFrame(
        {"scenario": "s", "filter": ["vb", "ekf", "vb", "anfekf", "ekf"], "run": 0,
         "step": [0, 0, 1, 0, 1], "pos_err": 0.1, "nees": 3.0}
    ).to_parquet(tmp_path / "steps.parquet")  # fmt: skip
    steps = read_steps(tmp_path)
    assert list(steps["filter"].cat.categories) == ["vb", "ekf", "anfekf"]
    assert list(steps["filter"]) == ["vb", "ekf", "vb", "anfekf", "ekf"]


def test_sections_drawn_in_workers_are_the_same_files(results, tmp_path, monkeypatch):
    """A large report reads its scenarios and draws their sections in worker processes: the
    same report.md, report.html and figure files, byte for byte, as done in this process."""
    from anfekf_bench.report import report as report_module

    in_workers: list[str] = []

    class Recording(report_module.Parallel):
        def __call__(self, tasks):
            tasks = list(tasks)
            in_workers.append(tasks[0][0].__name__)
            return super().__call__(tasks)

    monkeypatch.setattr(report_module, "Parallel", Recording)
    monkeypatch.setattr(report_module, "PARALLEL_MIN_SERIES", 10**9)
    monkeypatch.setattr(report_module, "PARALLEL_MIN_STEPS_BYTES", 10**15)
    one = write_report([results], tmp_path / "one", dpi=40)
    assert in_workers == []
    monkeypatch.setattr(report_module, "PARALLEL_MIN_SERIES", 0)
    monkeypatch.setattr(report_module, "PARALLEL_MIN_STEPS_BYTES", 0)
    many = write_report([results], tmp_path / "many", dpi=40)
    assert in_workers == ["_load_one", "_draw_section"]
    assert len(one.files) == len(many.files) > 2
    for a, b in zip(one.files, many.files, strict=True):
        assert a.name == b.name
        assert a.read_bytes() == b.read_bytes(), a.name


def test_the_worst_case_table_ranks_by_the_worst_ratio_over_the_scenarios(report_dir, results):
    """worst_case.csv (report/suite.py): each filter's worst and geometric-mean ratio to the
    oracle equal the ratios of the scenarios' own summaries (summary.parquet), the worst first;
    the report has the section."""
    out, _ = report_dir
    table = pd.read_csv(out / "worst_case.csv").set_index("filter")
    ratios: dict[str, list[float]] = {}
    for name in SCENARIOS:
        summary = pd.read_parquet(results / name / "summary.parquet").set_index("filter")
        oracle = summary.loc["ekf-oracle", "rmse_pos"]
        for f in summary.index.drop("ekf-oracle"):
            ratios.setdefault(f, []).append(summary.loc[f, "rmse_pos"] / oracle)
    assert set(table.index) == set(ratios)
    for f, values in ratios.items():
        # the CSV holds six significant digits
        assert table.loc[f, "worst"] == pytest.approx(max(values), rel=1e-5)
        geomean = math.prod(values) ** (1 / len(values))
        assert table.loc[f, "geomean"] == pytest.approx(geomean, rel=1e-5)
        assert table.loc[f, "worst_lo"] <= table.loc[f, "worst_hi"]
    assert list(table["worst"]) == sorted(table["worst"])
    assert (out / "worst_case.parquet").is_file()
    assert "Worst case across scenarios" in (out / "report.md").read_text(encoding="utf-8")


def test_the_worst_case_takes_each_filters_runs_as_sorting_the_rows_would(results, tmp_path):
    """report/suite.py takes each filter's (runs, steps) arrays from the six columns it reads of
    a steps table (`filter_arrays` of those), the table in the order a batch writes it or in any
    other: the same arrays as a sort of the filter's rows by (run, step)."""
    import dataclasses

    from anfekf_bench.report.suite import suite_input

    sc = load_scenario_data(results / "tiny_q")
    steps = pd.read_parquet(results / "tiny_q" / "steps.parquet")
    shuffled = tmp_path / "tiny_q"
    shuffled.mkdir()
    steps.sample(frac=1.0, random_state=3).to_parquet(shuffled / "steps.parquet")
    for folder in (sc.folder, shuffled):
        got = suite_input(dataclasses.replace(sc, folder=folder))
        assert list(got.filters) == ["ekf", "anfekf", "ekf-oracle"]
        for name, runs in got.filters.items():
            mine = steps[steps["filter"] == name].sort_values(["run", "step"])
            for column in ("pos_err", "nees"):
                expected = mine[column].to_numpy().reshape(RUNS, -1)
                assert np.array_equal(getattr(runs, column), expected, equal_nan=True)
            assert np.array_equal(runs.diverged, mine["diverged"].to_numpy()[:: len(mine) // RUNS])
