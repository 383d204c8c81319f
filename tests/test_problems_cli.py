"""A problem scenario through the command line (SPEC 17): `anfekf run` dispatches on
`problem:`, writes the problem tables, refuses to overwrite, is reproducible; `anfekf report`
shows problem results alone and beside the robot's; the robot's scenarios are untouched."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError
from anfekf_bench.problems.experiment import TABLES, read_problem_result
from anfekf_bench.scenarios import load_scenario, scenario_from_data

from .conftest import tiny_scenario, write_scenario

runner = CliRunner()

PROBLEM = {
    "name": "lin",
    "problem": "linear",
    "seed": 5,
    "runs": 3,
    "system": {"steps": 60},
    "training": {"runs": 2},
    "filters": [
        {"name": "kf", "kind": "ekf"},
        {"name": "oracle", "kind": "ekf-oracle"},
        {"name": "cm", "kind": "sage-husa", "adapt": "R"},
        {"name": "vb", "kind": "vb-r"},
        {"name": "als", "kind": "als", "min_steps": 20, "burn": 5},
        {"name": "ml", "kind": "ekf-ml", "maxiter": 20},
    ],
}


@pytest.fixture
def problem_yaml(tmp_path: Path) -> Path:
    return write_scenario(tmp_path / "lin.yaml", PROBLEM)


@pytest.mark.slow
def test_run_writes_the_problem_tables_and_refuses_to_overwrite(problem_yaml, tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(problem_yaml), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "Q and R at the last step" in result.output and "RMSE / oracle" in result.output
    folder = out / "lin"
    tables = read_problem_result(folder)
    assert list(tables["summary"]["filter"]) == [f["name"] for f in PROBLEM["filters"]]
    assert len(tables["runs"]) == 3 * 6 and len(tables["timing"]) == 3 * 6
    oracle = tables["summary"].set_index("filter").loc["oracle"]
    assert oracle["rmse_ratio"] == 1.0
    noise = tables["noise"].set_index(["filter", "matrix", "i", "j"])
    assert noise.loc[("oracle", "Q", 0, 1), "mean"] == -0.5  # the true Q, kept
    assert (
        not noise.loc[("cm", "Q", 0, 0), "estimated"] and noise.loc[("cm", "R", 0, 0), "estimated"]
    )
    first = {k: (folder / f).read_bytes() for k, f in TABLES.items() if k != "timing"}
    again = runner.invoke(app, ["run", str(problem_yaml), "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.output
    assert len(again.output.strip().splitlines()) == 2  # the start line and the one-line error
    forced = runner.invoke(app, ["run", str(problem_yaml), "--out", str(out), "--force"])
    assert forced.exit_code == 0, forced.output
    assert first == {k: (folder / f).read_bytes() for k, f in TABLES.items() if k != "timing"}


def test_runs_and_seed_options_apply(problem_yaml, tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(problem_yaml), "--out", str(out), "--runs", "2",
                                 "--seed", "9"])  # fmt: skip
    assert result.exit_code == 0, result.output
    m = read_problem_result(out / "lin")["manifest"]
    assert (m["runs"], m["seed"]) == (2, 9)


def test_a_bad_problem_file_is_one_line_with_exit_2(tmp_path):
    doc = {**PROBLEM, "filters": [{"name": "a", "kind": "anfekf"}]}
    path = write_scenario(tmp_path / "bad.yaml", doc)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert "filters.0" in result.output and "ANFIS" in result.output
    assert "Traceback" not in result.output


@pytest.mark.slow
def test_report_shows_problem_results_alone_and_beside_the_robot(problem_yaml, tmp_path):
    out = tmp_path / "out"
    robot = write_scenario(tmp_path / "robot.yaml", tiny_scenario(name="robot"))
    assert runner.invoke(app, ["run", str(problem_yaml), "--out", str(out)]).exit_code == 0
    alone = runner.invoke(app, ["report", str(out / "lin"), "--out", str(tmp_path / "r1")])
    assert alone.exit_code == 0, alone.output
    md = (tmp_path / "r1" / "report.md").read_text(encoding="utf-8")
    assert "Problems beyond the robot" in md and "(lin_estimates.png)" in md
    assert "1 problem result" in alone.output
    assert runner.invoke(app, ["run", str(robot), "--out", str(out)]).exit_code == 0
    both = runner.invoke(app, ["report", str(out), "--out", str(tmp_path / "r2")])
    assert both.exit_code == 0, both.output
    md = (tmp_path / "r2" / "report.md").read_text(encoding="utf-8")
    assert "Problems beyond the robot" in md and "robot" in md


def test_problem_robot_is_the_default_said_aloud(tmp_path):
    plain = write_scenario(tmp_path / "a.yaml", tiny_scenario(name="a"))
    said = write_scenario(tmp_path / "b.yaml", tiny_scenario(name="a", problem="robot"))
    assert load_scenario(plain)[0] == load_scenario(said)[0]


def test_the_robot_loader_names_a_problem_document_clearly():
    with pytest.raises(ScenarioError) as exc:
        scenario_from_data(PROBLEM, "lin.yaml")
    assert exc.value.field == "problem" and "anfekf run" in str(exc.value)


def test_problem_tables_are_parquet_with_the_documented_columns(problem_yaml, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(app, ["run", str(problem_yaml), "--out", str(out)]).exit_code == 0
    summary = pd.read_parquet(out / "lin" / TABLES["summary"])
    for col in ("rmse_ratio", "rmse_ratio_lo", "rmse_ratio_hi", "anees", "nees_in_bounds",
                "q_rel_err", "q_rel_err_sd", "r_rel_err", "r_rel_err_sd"):  # fmt: skip
        assert col in summary.columns
    runs = pd.read_parquet(out / "lin" / TABLES["runs"])
    assert {"q_0_1", "r_1_1", "rmse_pos", "anees"} <= set(runs.columns)


@pytest.mark.slow
def test_the_same_seed_gives_the_same_bytes_whatever_the_workers(problem_yaml, tmp_path):
    for jobs in ("1", "2"):
        result = runner.invoke(app, ["run", str(problem_yaml), "--out", str(tmp_path / jobs),
                                     "--jobs", jobs])  # fmt: skip
        assert result.exit_code == 0, result.output
    for key, file in TABLES.items():
        if key != "timing":
            assert (tmp_path / "1" / "lin" / file).read_bytes() == (
                tmp_path / "2" / "lin" / file
            ).read_bytes()
