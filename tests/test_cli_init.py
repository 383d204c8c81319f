"""`anfekf init` (a starter scenario), "did you mean" on typos, the usage line, plurals."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from anfekf_bench.cli import app, plural
from anfekf_bench.config import ScenarioError
from anfekf_bench.filters.registry import KINDS
from anfekf_bench.scenarios import load_scenario

from .conftest import small_scenario, write_scenario

runner = CliRunner()


def test_init_writes_a_commented_scenario_that_run_accepts(tmp_path):
    path = tmp_path / "my_first.yaml"
    result = runner.invoke(app, ["init", str(path)])
    assert result.exit_code == 0, result.output
    text = path.read_text()
    assert text.count("\n#") >= 3  # commented
    scenario, _ = load_scenario(path)  # what `anfekf run` validates before any work
    assert scenario.name == "my_first"
    kinds = {f.kind for f in scenario.filters}
    assert {"ekf", "anfekf", "ekf-oracle"} <= kinds <= set(KINDS)
    assert scenario.claims


def test_init_never_overwrites(tmp_path):
    path = tmp_path / "scenario.yaml"
    path.write_text("mine\n")
    result = runner.invoke(app, ["init", str(path)])
    assert result.exit_code == 2
    assert "already exists" in result.output and "\n" not in result.output.strip()
    assert path.read_text() == "mine\n"
    missing = runner.invoke(app, ["init", str(tmp_path / "no" / "such.yaml")])
    assert missing.exit_code == 2 and "no such folder" in missing.output


def test_init_writes_scenario_yaml_by_default(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert runner.invoke(app, ["init"]).exit_code == 0
    assert load_scenario(tmp_path / "scenario.yaml")[0].name == "scenario"


@pytest.mark.parametrize(
    ("entry", "suggestion"),
    [
        ({"name": "s", "kind": "sage-husas"}, "did you mean 'sage-husa'?"),
        ({"name": "a", "kind": "anfkf"}, "did you mean 'anfekf'?"),
        ({"name": "a", "kind": "anfekf", "windwo": 5}, "did you mean 'window'?"),
    ],
)
def test_a_mistyped_kind_or_key_gets_a_suggestion(tmp_path, entry, suggestion):
    doc = small_scenario()
    doc["filters"] = [{"name": "ekf", "kind": "ekf"}, entry]
    with pytest.raises(ScenarioError, match=suggestion.replace("?", r"\?")):
        load_scenario(write_scenario(tmp_path / "s.yaml", doc))


def test_a_far_off_key_gets_no_wild_guess(tmp_path):
    doc = small_scenario()
    doc["filters"] = [{"name": "a", "kind": "anfekf", "zzzzzz": 1}]
    with pytest.raises(ScenarioError) as err:
        load_scenario(write_scenario(tmp_path / "s.yaml", doc))
    assert "did you mean" not in str(err.value)


def test_usage_lines_have_no_braces():
    for command in ("run", "check", "init"):
        usage = runner.invoke(app, [command, "--help"]).output
        line = next(x for x in usage.splitlines() if "Usage:" in x)
        assert "{" not in line and "}" not in line, line
    usage = runner.invoke(app, ["run", "--help"]).output
    line = next(x for x in usage.splitlines() if "Usage" in x)
    assert line.split()[-1] == "SCENARIO"


def test_counts_are_singular_for_one():
    assert plural(1, "scenario") == "1 scenario"
    assert plural(2, "scenario") == "2 scenarios"
    assert plural(0, "figure") == "0 figures"


def test_the_yaml_is_plain_yaml(tmp_path):
    path = tmp_path / "s.yaml"
    runner.invoke(app, ["init", str(path)])
    doc = yaml.safe_load(path.read_text())
    assert isinstance(doc, dict) and isinstance(doc["filters"], list)
    assert Path(path).stat().st_size < 4000


def test_fast_without_numba_says_so_once_and_the_manifest_records_it(tmp_path, monkeypatch):
    from anfekf_bench.engines import fast
    from anfekf_bench.storage import read_manifest

    monkeypatch.setattr(fast, "JIT", False)  # as if numba were not installed
    docs = [small_scenario(name=n, runs=1, record_every=8, engine="fast") for n in ("a", "b")]
    folder = tmp_path / "scenarios"
    folder.mkdir()
    for doc in docs:
        write_scenario(folder / f"{doc['name']}.yaml", doc)
    result = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert result.output.count("without numba") == 1  # two scenarios, one warning
    assert read_manifest(tmp_path / "out" / "a")["fast_compiled"] is False
    monkeypatch.setattr(fast, "JIT", True)
    again = runner.invoke(app, ["run", str(folder / "a.yaml"), "--out", str(tmp_path / "o2")])
    assert "without numba" not in again.output
    assert read_manifest(tmp_path / "o2" / "a")["fast_compiled"] is True


@pytest.mark.slow
def test_a_sweep_ends_with_one_summary_table_not_lines_per_cell(tmp_path):
    doc = small_scenario(name="sw", runs=2, jobs=1, record_every=8)
    doc["sweep"] = {"axes": [{"scale": "R", "values": [0.5, 2.0]}]}
    path = write_scenario(tmp_path / "sw.yaml", doc)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "running" not in result.output and "cell-000" not in result.output
    table = result.output.split("sweep sw: 2 cells x 2 runs")[1]
    assert "RMSE / oracle" in table and "cells <= 1.5x" in table
    for name in ("ekf", "anfekf", "ekf-oracle"):
        assert name in table
    assert "eta" in result.output  # the progress line: rate, elapsed, time left
    again = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert again.exit_code == 0 and "(2 complete already: reused)" in again.output
