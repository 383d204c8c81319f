"""The Python API on problem scenarios (SPEC 17): `api.load` / `api.run` take them, and a
problem result's `Result` (from `api.run` or `api.open_result`) gives its own tables, the same
as `anfekf run` writes for the same scenario and seed."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench import api
from anfekf_bench.cli import app
from anfekf_bench.problems.experiment import TABLES, read_problem_result

from .conftest import write_scenario

runner = CliRunner()
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "custom_problem" / "scenario.yaml"
FILTERS = [{"name": "kf", "kind": "ekf"}, {"name": "oracle", "kind": "ekf-oracle"},
           {"name": "sh", "kind": "sage-husa"}]  # fmt: skip
LINEAR = {"name": "lin", "problem": "linear", "seed": 3, "runs": 2, "system": {"steps": 60},
          "filters": FILTERS}  # fmt: skip
TRACKING = {"name": "trk", "problem": "tracking", "seed": 4, "runs": 2,
            "system": {"steps": 40}, "filter_noise": {"Q_scale": 0.1, "R_scale": 1.0},
            "filters": [*FILTERS, {"name": "vb", "kind": "vb-r"}]}  # fmt: skip


def check_tables(result: api.Result, runs: int, filters: list[str]) -> None:
    """Its tables are the problem result's, read by the API as the problems' reader reads them."""
    stored = read_problem_result(result.folder)
    summary, per_run = result.summary(), result.runs()
    assert list(summary["filter"]) == filters
    assert {"rmse_ratio", "q_rel_err", "r_rel_err"} <= set(summary.columns)
    assert len(per_run) == runs * len(filters)
    pd.testing.assert_frame_equal(summary, stored["summary"])
    pd.testing.assert_frame_equal(per_run, stored["runs"])
    pd.testing.assert_frame_equal(result.noise(), stored["noise"])
    pd.testing.assert_frame_equal(result.timing(), stored["timing"])
    assert result.manifest()["format"] == stored["manifest"]["format"]
    assert result.loaded().kind == "problem"
    with pytest.raises(FileNotFoundError, match="steps.parquet"):
        result.steps()


def test_a_linear_problem_runs_from_python_as_from_the_command_line(tmp_path):
    result = api.run(api.load(LINEAR), out=tmp_path / "api")
    check_tables(result, 2, ["kf", "oracle", "sh"])
    opened = api.open_result(tmp_path / "api" / "lin")
    pd.testing.assert_frame_equal(opened.summary(), result.summary())
    path = write_scenario(tmp_path / "lin.yaml", LINEAR)
    cli = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "cli")])
    assert cli.exit_code == 0, cli.output
    for key, file in TABLES.items():
        if key != "timing":  # seconds: the one table that differs between identical runs
            assert (tmp_path / "api" / "lin" / file).read_bytes() == (
                tmp_path / "cli" / "lin" / file
            ).read_bytes()
    with pytest.raises(api.OutputExists, match="force=True"):
        api.run(LINEAR, out=tmp_path / "api")
    again = api.run(LINEAR, out=tmp_path / "api", runs=3, force=True)
    assert len(again.runs()) == 9
    with pytest.raises(api.PlanError, match="local processes only"):
        api.run(LINEAR, out=tmp_path / "other", backend="dask")


def test_tracking_and_a_module_from_python_on_the_fast_engine(tmp_path):
    pytest.importorskip("numba")
    tracking = api.run(TRACKING, out=tmp_path, engine="fast")
    check_tables(tracking, 2, ["kf", "oracle", "sh", "vb"])
    assert tracking.manifest()["engine"] == "fast"
    assert "gated" in tracking.summary().columns
    module = api.run(api.load(EXAMPLE), out=tmp_path, runs=1, engine="fast")
    check_tables(module, 1, ["ekf", "oracle", "sage-husa", "vb-r"])
    assert api.open_result(module.folder).noise().equals(module.noise())
