"""Your own filter through the extension point: a class path or an entry point in the scenario."""

from __future__ import annotations

import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import custom
from anfekf_bench.filters.context import build_filter
from anfekf_bench.runner import simulate
from anfekf_bench.scenarios import load_scenario

from .conftest import small_scenario, write_scenario

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "custom_filter"
runner = CliRunner()


def _restart_workers() -> None:
    """End joblib's reusable loky workers: the next batch starts new ones, which see the
    current sys.path and PYTHONPATH (workers started by an earlier test would not)."""
    from joblib.externals.loky import get_reusable_executor

    get_reusable_executor().shutdown(wait=True)


@pytest.fixture
def example_on_path(monkeypatch):
    # As a user does it (docs/CUSTOM_FILTERS.md): the module on PYTHONPATH, for the workers too.
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.setenv("PYTHONPATH", str(EXAMPLE))
    _restart_workers()
    yield
    _restart_workers()
    sys.modules.pop("nis_scaled", None)


def scenario_with(tmp_path: Path, entry: dict, **extra) -> Path:
    doc = small_scenario(runs=2, **extra)
    doc["filters"] = [{"name": "ekf", "kind": "ekf"}, entry]
    return write_scenario(tmp_path / "s.yaml", doc)


def test_the_worked_example_runs_through_the_extension_point(example_on_path, tmp_path):
    doc = yaml.safe_load((EXAMPLE / "scenario.yaml").read_text())
    small = small_scenario(runs=2)
    doc.update(runs=2, world=small["world"], record_every=small["record_every"])
    path = write_scenario(tmp_path / "example.yaml", doc)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "nis-scaled" in result.output
    assert (tmp_path / "out" / "custom_filter_example" / "comparisons.parquet").is_file()


def test_the_example_adapts_R_and_equals_the_ekf_with_adaptation_off(example_on_path, tmp_path):
    entry = {"name": "mine", "kind": "custom", "class": "nis_scaled:NisScaledR"}
    scenario, world = load_scenario(scenario_with(tmp_path, entry))
    ekf_spec, mine_spec = scenario.filters
    data = simulate(scenario, world, np.random.SeedSequence(1))
    off = mine_spec.model_copy(update={"params": {"adaptation": False}})
    ekf = run_filter(build_filter(ekf_spec, scenario, world), data, world, scenario.record_every)
    frozen = run_filter(build_filter(off, scenario, world), data, world, scenario.record_every)
    np.testing.assert_allclose(frozen["x"], ekf["x"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(frozen["P"], ekf["P"], rtol=0, atol=1e-12)
    adapted = run_filter(build_filter(mine_spec, scenario, world), data, world, 1)
    assert not np.allclose(adapted["R_diag"][-1], ekf["R_diag"][-1]), "R must move"
    assert (adapted["R_diag"] > 0).all()


NIS = "nis_scaled:NisScaledR"
BAD = {
    # id: (the custom entry's extra keys, expected message part)
    "not-importable": ({"class": "no_such_xyz:F"}, "cannot import module 'no_such_xyz'"),
    "no-such-class": ({"class": "nis_scaled:Nope"}, "module 'nis_scaled' has no 'Nope'"),
    "not-a-filter": ({"class": "nis_scaled:Field"}, "is not a subclass of anfekf_bench.filters"),
    "not-a-path": ({"class": "bad path"}, "expected module:Class"),
    "param-out-of-range": ({"class": NIS, "params": {"gain": 7}}, "params.gain"),
    "unknown-param": ({"class": NIS, "params": {"bogus": 1}}, "params.bogus"),
    "params-without-schema": (
        {"class": "anfekf_bench.filters:RobotEKF", "params": {"a": 1}},
        "declares no Params",
    ),
}


@pytest.mark.parametrize("extra, message", BAD.values(), ids=BAD.keys())
def test_an_unusable_class_is_one_line_naming_file_and_field(
    example_on_path, tmp_path, extra, message
):
    path = scenario_with(tmp_path, {"name": "mine", "kind": "custom", **extra})
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"error: {path}: filters.1")
    assert message in lines[0]
    assert not (tmp_path / "out").exists(), "nothing is written for a bad scenario"


def test_an_entry_point_kind_names_a_filter(example_on_path, tmp_path, monkeypatch):
    ep = EntryPoint("nis-r", "nis_scaled:NisScaledR", custom.ENTRY_POINT_GROUP)
    monkeypatch.setattr(custom, "entry_points", lambda group: [ep] if group == ep.group else [])
    path = scenario_with(tmp_path, {"name": "mine", "kind": "nis-r", "gain": 0.3})
    scenario, world = load_scenario(path)
    spec = scenario.filters[1]
    assert spec.kind == "custom" and spec.class_path == "nis_scaled:NisScaledR"
    flt = build_filter(spec, scenario, resolve_world(scenario.world, path))
    assert type(flt).__name__ == "NisScaledR" and flt.params.gain == 0.3
    unknown = scenario_with(tmp_path, {"name": "mine", "kind": "nis-q"})
    result = runner.invoke(app, ["run", str(unknown), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2 and "filters.1" in result.stderr
