"""Result files as other tools read them: scenario and filter join across steps, runs, summary and
comparisons (polars), and every Parquet file says where it came from (pyarrow metadata)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from anfekf_bench.config import ScenarioError, read_points_csv
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.provenance import git_commit, package_version
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import parquet_provenance

from .conftest import small_scenario, write_scenario

PARQUET_FILES = ("steps.parquet", "runs.parquet", "summary.parquet", "comparisons.parquet")


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> tuple[Path, str]:
    """A tiny finished result (2 runs) and its fingerprint."""
    root = tmp_path_factory.mktemp("files")
    doc = small_scenario(name="joined", runs=2, record_every=8, seed=11)
    scenario, world = load_scenario(write_scenario(root / "joined.yaml", doc))
    plan = make_plan(scenario, world, None, None, 1)
    _, target = execute(plan, root / "results")
    return target, plan.fingerprint()


@pytest.mark.parametrize("name", PARQUET_FILES)
def test_parquet_metadata_says_where_the_file_came_from(result, name):
    target, fingerprint = result
    meta = pq.read_metadata(target / name).metadata
    assert meta[b"anfekf.scenario"] == b"joined"
    assert meta[b"anfekf.seed"] == b"11"
    assert meta[b"anfekf.fingerprint"] == fingerprint.encode()
    assert meta[b"anfekf.version"] == package_version().encode()
    assert meta[b"anfekf.git_commit"] == (git_commit() or "unknown").encode()
    units = json.loads(meta[b"anfekf.units"])
    columns = pq.read_schema(target / name).names
    assert set(units) <= set(columns)
    # The same through storage's reader, without the prefix.
    assert parquet_provenance(target / name)["fingerprint"] == fingerprint


def test_units_name_every_physical_column(result):
    target, _ = result
    steps = json.loads(pq.read_metadata(target / "steps.parquet").metadata[b"anfekf.units"])
    assert steps["t"] == "s" and steps["pos_err"] == "m" and steps["heading_err"] == "rad"
    assert steps["R_rr"] == "m^2" and steps["Q_gg"] == "rad^2" and steps["nees"] == "1"
    runs = json.loads(pq.read_metadata(target / "runs.parquet").metadata[b"anfekf.units"])
    assert runs["rmse_pos"] == "m" and runs["rmse_heading"] == "rad"
    summary = json.loads(pq.read_metadata(target / "summary.parquet").metadata[b"anfekf.units"])
    assert summary["rmse_pos"] == "m" and summary["nees_in_bounds"] == "share (0..1)"


def test_a_copied_file_keeps_its_metadata(result, tmp_path):
    target, fingerprint = result
    copy = tmp_path / "elsewhere.parquet"
    copy.write_bytes((target / "summary.parquet").read_bytes())
    assert parquet_provenance(copy)["fingerprint"] == fingerprint


def test_scenario_and_filter_have_one_type_in_every_file(result):
    target, _ = result
    for name in PARQUET_FILES:
        schema = pq.read_schema(target / name)
        for col in ("scenario", "filter", "vs"):
            if col in schema.names:
                assert str(schema.field(col).type) in ("string", "large_string"), (name, col)


def test_polars_joins_steps_runs_summary_and_comparisons(result):
    pl = pytest.importorskip("polars")
    target, _ = result
    steps = pl.read_parquet(target / "steps.parquet")
    runs = pl.read_parquet(target / "runs.parquet")
    summary = pl.read_parquet(target / "summary.parquet")
    comparisons = pl.read_parquet(target / "comparisons.parquet")
    joined = steps.join(summary, on=["scenario", "filter"], how="inner", suffix="_summary")
    assert joined.height == steps.height
    with_runs = steps.join(runs, on=["scenario", "filter", "run"], how="inner", suffix="_run")
    assert with_runs.height == steps.height
    ratios = comparisons.join(summary, on=["scenario", "filter"], how="inner")
    assert ratios.height == comparisons.height > 0
    # The join agrees with the files: each run's own RMSE recomputed from its steps.
    per_run = steps.group_by(["filter", "run"]).agg((pl.col("pos_err") ** 2).mean().sqrt())
    check = per_run.join(runs.select(["filter", "run", "rmse_pos"]), on=["filter", "run"])
    np.testing.assert_allclose(check["pos_err"].to_numpy(), check["rmse_pos"].to_numpy())


# --------------------------------------------------------------------------- map CSV files


@pytest.mark.parametrize(
    "text",
    [
        "x,y\n1,2\n3,4\n",
        "X, Y\n1,2\n3,4\n",
        "# landmarks\nx,y\n1,2\n3,4\n",
        "1,2\n3,4\n",
    ],
    ids=["header", "header-spaces-caps", "comment-then-header", "no-header"],
)
def test_map_csv_may_start_with_an_x_y_header(tmp_path, text):
    path = tmp_path / "map.csv"
    path.write_text(text, encoding="utf-8")
    pts = read_points_csv(path, scenario_path="s.yaml", field="world.landmarks")
    np.testing.assert_array_equal(pts, [[1, 2], [3, 4]])


@pytest.mark.parametrize(
    ("text", "message"),
    [("1,2\nx,y\n", "line 2"), ("a,b\n1,2\n", "line 1"), ("x,y\n", "no points")],
    ids=["header-not-first", "other-names", "header-only"],
)
def test_only_a_first_x_y_line_is_a_header(tmp_path, text, message):
    path = tmp_path / "map.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ScenarioError, match=message):
        read_points_csv(path, scenario_path="s.yaml", field="world.landmarks")


def test_a_scenario_reads_a_map_with_a_header(tmp_path):
    (tmp_path / "lm.csv").write_text("x,y\n10,8\n25,-6\n40,10\n", encoding="utf-8")
    (tmp_path / "wp.csv").write_text("x,y\n20,0\n40,8\n", encoding="utf-8")
    doc = small_scenario(world={"landmarks": "lm.csv", "waypoints": "wp.csv"})
    _, world = load_scenario(write_scenario(tmp_path / "s.yaml", doc))
    np.testing.assert_array_equal(world.landmarks, [[10, 8], [25, -6], [40, 10]])
    np.testing.assert_array_equal(world.waypoints, [[20, 0], [40, 8]])
