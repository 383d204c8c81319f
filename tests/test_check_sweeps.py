"""`anfekf check` over sweeps (each cell a scenario `<sweep>/<cell>`), and sweep.parquet written
as every result file is: a scenario column, plain column names, the Parquet metadata."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import LOCK_FILE, PARQUET_KEY_PREFIX
from anfekf_bench.sweeps import CELLS_DIR, SWEEP_FILE, cell_plans, expand, run_sweep

from .conftest import small_scenario, write_scenario

runner = CliRunner()


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """A folder with a 2-cell sweep over a dotted field and an ordinary scenario beside it."""
    root = tmp_path_factory.mktemp("checksweep")
    out = root / "out"
    doc = small_scenario(name="sw", runs=2, jobs=1, record_every=8)
    doc["sweep"] = {"axes": [{"field": "filter_noise.sigma_range", "values": [0.5, 2.0]}]}
    path = write_scenario(root / "sw.yaml", doc)
    scenario, _ = load_scenario(path)
    cells = expand(scenario, path)
    run_sweep(scenario.name, scenario.sweep.axes, cells,
              cell_plans(cells, runs=None, seed=None, jobs=None), out)  # fmt: skip
    plain = small_scenario(name="plain", runs=2, jobs=1, record_every=8)
    scenario, world = load_scenario(write_scenario(root / "plain.yaml", plain))
    execute(make_plan(scenario, world, None, None, 1), out)
    return out


def test_sweep_parquet_has_the_scenario_column_plain_names_and_the_metadata(results):
    path = results / "sw" / SWEEP_FILE
    table = pq.read_table(path)
    names = table.column_names
    assert names[0] == "scenario" and set(table.column("scenario").to_pylist()) == {"sw"}
    assert "filter_noise_sigma_range" in names
    assert not any("." in n for n in names), names
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    for key in ("scenario", "seed", "fingerprint", "units", "version", "git_commit"):
        assert PARQUET_KEY_PREFIX + key in meta, key
    assert meta[PARQUET_KEY_PREFIX + "scenario"] == "sw"
    assert json.loads(meta[PARQUET_KEY_PREFIX + "units"])["rmse_pos"] == "m"
    # the same keys as every other result file
    summary = pq.read_metadata(results / "plain" / "summary.parquet").metadata
    assert {k.decode() for k in summary if k.startswith(b"anfekf.")} <= set(meta)
    # filter as plain text, as in summary.parquet (not a dictionary/categorical column)
    plain = pq.read_schema(results / "plain" / "summary.parquet").field("filter").type
    assert table.schema.field("filter").type == plain


def test_no_lock_is_left_in_finished_cells(results):
    cells = sorted((results / "sw" / CELLS_DIR).iterdir())
    assert len(cells) == 2
    assert not any((c / LOCK_FILE).exists() for c in cells)


def test_check_reads_a_sweep_folder_and_a_parent_with_sweeps(results, tmp_path):
    baseline = tmp_path / "b.json"
    made = runner.invoke(app, ["check", str(results), "--baseline", str(baseline), "--update"])
    assert made.exit_code == 0, made.output
    scenarios = json.loads(baseline.read_text())["scenarios"]
    assert set(scenarios) == {"plain", "sw/cell-000", "sw/cell-001"}
    again = runner.invoke(app, ["check", str(results), "--baseline", str(baseline)])
    assert again.exit_code == 0, again.output
    # the sweep folder alone: its cells
    only = tmp_path / "only.json"
    sweep = results / "sw"
    assert (
        runner.invoke(app, ["check", str(sweep), "--baseline", str(only), "--update"]).exit_code
        == 0
    )
    assert set(json.loads(only.read_text())["scenarios"]) == {"sw/cell-000", "sw/cell-001"}
    assert runner.invoke(app, ["check", str(sweep), "--baseline", str(only)]).exit_code == 0


def test_check_fails_when_a_cell_baseline_is_20_percent_better(results, tmp_path):
    baseline = tmp_path / "b.json"
    sweep = results / "sw"
    runner.invoke(app, ["check", str(sweep), "--baseline", str(baseline), "--update"])
    doc = json.loads(baseline.read_text())
    cell = doc["scenarios"]["sw/cell-001"]["filters"]["anfekf"]
    assert math.isfinite(cell["rmse_pos"])
    cell["rmse_pos"] *= 0.8
    baseline.write_text(json.dumps(doc))
    result = runner.invoke(app, ["check", str(sweep), "--baseline", str(baseline)])
    assert result.exit_code == 1, result.output
    assert "worse" in result.output and "sw/cell-001" in result.output
