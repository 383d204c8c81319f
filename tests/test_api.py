"""The Python API (docs/API.md): its worked example runs, and gives the same tables as the
command line on the same scenario."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from anfekf_bench import api
from anfekf_bench.cli import app

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "api" / "run_scenario.py"


def test_docs_show_the_example_verbatim():
    assert EXAMPLE.read_text(encoding="utf-8") in (ROOT / "docs" / "API.md").read_text("utf-8")


@pytest.mark.slow
def test_example_gives_the_command_lines_tables(tmp_path):
    from typer.testing import CliRunner

    done = subprocess.run(
        [sys.executable, str(EXAMPLE), str(tmp_path / "api")], cwd=ROOT, capture_output=True,
        text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "report:" in done.stdout
    assert (tmp_path / "api" / "report" / "report.md").is_file()
    cli = CliRunner().invoke(
        app, ["run", str(ROOT / "configs" / "wrong_r.yaml"), "--runs", "4", "--engine", "fast",
              "--out", str(tmp_path / "cli")],
    )  # fmt: skip
    assert cli.exit_code == 0, cli.output
    ours, theirs = (
        api.open_result(tmp_path / "api" / "wrong_r"),
        api.open_result(tmp_path / "cli" / "wrong_r"),
    )
    for table in ("summary", "runs", "steps", "comparisons"):
        pd.testing.assert_frame_equal(getattr(ours, table)(), getattr(theirs, table)())
    assert ours.claims() == theirs.claims()
    assert ours.manifest()["fingerprint"] == theirs.manifest()["fingerprint"]


def test_load_from_a_dict_equals_the_file(tmp_path):
    import yaml

    data = yaml.safe_load((ROOT / "configs" / "correct.yaml").read_text("utf-8"))
    from_dict = api.load(data, base=ROOT / "configs")
    from_file = api.load(ROOT / "configs" / "correct.yaml")
    assert from_dict.scenario == from_file.scenario
    assert from_dict.name == "correct"


def test_bad_input_raises_the_one_line_errors(tmp_path):
    with pytest.raises(api.ScenarioError, match="runs"):
        api.load({"name": "x", "runs": 0})
    with pytest.raises(api.ScenarioError, match="does not exist"):
        api.load(tmp_path / "missing.yaml")


def test_a_run_from_python_reads_back(tmp_path):
    result = api.run(ROOT / "configs" / "correct.yaml", out=tmp_path, runs=2, engine="fast")
    assert result.folder == tmp_path / "correct"
    summary = result.summary()
    assert list(summary["filter"]) == [f.name for f in api.load(
        ROOT / "configs" / "correct.yaml").scenario.filters]  # fmt: skip
    assert result.manifest()["runs"] == 2
    with pytest.raises(FileNotFoundError):
        api.Result(tmp_path / "nowhere").summary()
