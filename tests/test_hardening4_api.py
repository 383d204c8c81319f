"""Hardening 4 (issue 32): the Python API and the command line check every argument in one place
(`anfekf_bench.arguments`), an output folder is never placed inside another result (nor does
`--force` ever remove a result nested in one), a scenario's every validation error is shown, and
the API's worked example runs from any working directory (docs/HARDENING.md)."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from anfekf_bench import api
from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError, parse_scenario
from anfekf_bench.storage import MANIFEST_FILE, RUNS_DIR, STEPS_FILE, SUMMARY_PARQUET

from .conftest import tiny_scenario

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "api" / "run_scenario.py"

TINY = tiny_scenario()


def scenario_file(folder: Path, name: str, **overrides) -> Path:
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"name": name, **TINY, **overrides}), encoding="utf-8")
    return path


def cli(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def snapshot(root: Path) -> dict[str, str]:
    """Every entry under `root` and a hash of its content: what must not change."""
    found = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            rel = str(path.relative_to(root))
            if path.is_symlink():
                found[rel] = "-> " + os.readlink(path)
            elif path.is_file():
                found[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
            else:
                found[rel] = "folder"
    return found


def assert_one_line(result, *words: str) -> None:
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert "Traceback" not in result.output
    for word in words:
        assert word in lines[0], (word, lines[0])


def assert_names(message: str, field: str) -> None:
    """One line that names the argument first (`runs: ...`), or the path, then the argument
    (`/tmp/x: out must be a folder, ...`)."""
    assert "\n" not in message, message
    assert re.match(rf"(\S+: )?{re.escape(field)}\b", message), (field, message)


@pytest.fixture
def box(tmp_path: Path) -> Path:
    """out/sib: a complete result of the scenario `sib`; its scenario file; small.yaml."""
    scenario_file(tmp_path, "sib")
    scenario_file(tmp_path, "small")
    done = cli("run", tmp_path / "sib.yaml", "--out", tmp_path / "out")
    assert done.exit_code == 0, done.output
    return tmp_path


# ---------------------------------------------------------------------------------------------
# 1. Data loss: an output folder inside another result, and --force over a nested result


def _plant_store(box: Path) -> None:
    """out/sib as a batch in progress leaves it: a stamped run store (no result yet)."""
    sib = box / "out" / "sib"
    (sib / RUNS_DIR).mkdir()
    (sib / RUNS_DIR / "fingerprint").write_text("0123456789abcdef\n")


NESTED_OUT = {
    "inside-a-run-store": ("out/sib/.runs", None),
    "inside-an-unfinished-run-store": ("out/sib/.runs", _plant_store),
    "deep-inside-a-run-store": ("out/sib/.runs/a/b", None),
    "inside-a-result-folder": ("out/sib", None),
    "inside-a-result-through-a-symlink": (
        "link/.runs",
        lambda box: (box / "link").symlink_to(box / "out" / "sib", target_is_directory=True),
    ),
}


@pytest.mark.parametrize("where", list(NESTED_OUT))
def test_an_output_folder_inside_another_result_is_refused(box, where) -> None:
    out, prepare = NESTED_OUT[where]
    if prepare is not None:
        prepare(box)
    before = snapshot(box)
    assert_one_line(cli("run", box / "small.yaml", "--out", box / out), "inside", "sib")
    assert snapshot(box) == before, "nothing is created or changed"
    with pytest.raises(api.PlanError, match="inside"):
        api.run(box / "small.yaml", out=box / out)
    assert snapshot(box) == before


def test_an_output_folder_inside_a_sweep_folder_is_refused(box) -> None:
    sweep = box / "out" / "sw"
    (sweep / "cells").mkdir(parents=True)
    (sweep / MANIFEST_FILE).write_text(
        '{"kind": "anfekf-bench sweep", "name": "sw", "versions": {"anfekf-bench": "1"}}'
    )
    before = snapshot(box)
    assert_one_line(cli("run", box / "small.yaml", "--out", sweep), "inside", "sweep")
    assert snapshot(box) == before


def _nested_result(box: Path) -> Path:
    """What main allowed: a complete result of `small` inside sib's run store."""
    nested = box / "out" / "sib" / RUNS_DIR / "small"
    done = cli("run", box / "small.yaml", "--out", box / "elsewhere")
    assert done.exit_code == 0, done.output
    shutil.copytree(box / "elsewhere" / "small", nested)
    return nested


@pytest.mark.parametrize("stamped", [False, True], ids=["complete", "other-batch-runs"])
def test_force_never_removes_a_result_nested_in_the_run_store(box, stamped) -> None:
    nested = _nested_result(box)
    if stamped:  # --force would discard another batch's run store, whole
        (nested.parent / "fingerprint").write_text("0123456789abcdef\n")
    before = snapshot(box)
    result = cli("run", box / "sib.yaml", "--out", box / "out", "--force", "--seed", "9")
    assert_one_line(result, "small")
    assert snapshot(box) == before
    assert (nested / MANIFEST_FILE).is_file()


def test_resuming_never_removes_a_result_nested_in_the_run_store(box) -> None:
    """Without --force, a batch in progress removes its run store when it completes."""
    shutil.rmtree(box / "out" / "sib")
    nested = _nested_result(box)
    before = snapshot(box)
    assert_one_line(cli("run", box / "sib.yaml", "--out", box / "out"), "small")
    assert snapshot(box) == before
    assert (nested / MANIFEST_FILE).is_file()


def test_finishing_a_batch_leaves_what_it_did_not_write_in_the_run_store(tmp_path) -> None:
    """Behind the check above: the run store is removed entry by entry, never wholesale."""
    from anfekf_bench.outputs import finish_result

    target = tmp_path / "sib"
    staging = target / RUNS_DIR / "result"
    staging.mkdir(parents=True)
    (staging / MANIFEST_FILE).write_text("{}")
    (target / RUNS_DIR / "run-000000.npz").write_bytes(b"run")
    (target / RUNS_DIR / "small").mkdir()
    (target / RUNS_DIR / "small" / MANIFEST_FILE).write_text('{"precious": 1}')
    finish_result(target, staging)
    assert (target / MANIFEST_FILE).is_file()
    assert (target / RUNS_DIR / "small" / MANIFEST_FILE).read_text() == '{"precious": 1}'
    assert not (target / RUNS_DIR / "run-000000.npz").exists()


# ---------------------------------------------------------------------------------------------
# 2. One validation layer: the API's arguments typed and range-checked as the command line's


BAD_RUN_ARGUMENTS = {
    "runs-true": ({"runs": True}, "runs"),
    "runs-negative": ({"runs": -1}, "runs"),
    "runs-float": ({"runs": 2.5}, "runs"),
    "runs-too-many": ({"runs": 100_001}, "runs"),
    "runs-text": ({"runs": "4"}, "runs"),
    "seed-negative": ({"seed": -1}, "seed"),
    "seed-2-63": ({"seed": 2**63}, "seed"),
    "seed-false": ({"seed": False}, "seed"),
    "jobs-million": ({"jobs": 10**6}, "jobs"),
    "jobs-zero": ({"jobs": 0}, "jobs"),
    "engine-bogus": ({"engine": "bogus"}, "engine"),
    "engine-not-text": ({"engine": 1}, "engine"),
    "backend-bogus": ({"backend": "gpu"}, "backend"),
    "scheduler-not-text": ({"scheduler": 5}, "scheduler"),
    "force-no": ({"force": "no"}, "force"),
    "force-one": ({"force": 1}, "force"),
    "out-number": ({"out": 5}, "out"),
    "out-a-file": ({"out": "FILE"}, "out"),
    "out-nul": ({"out": "a\0b"}, "out"),
    "on-result-not-callable": ({"on_result": "print"}, "on_result"),
}


@pytest.mark.parametrize("case", list(BAD_RUN_ARGUMENTS))
def test_api_run_refuses_bad_arguments_in_one_line(box, case) -> None:
    kwargs, field = BAD_RUN_ARGUMENTS[case]
    if kwargs.get("out") == "FILE":
        (box / "a-file").write_text("mine")
        kwargs = {"out": box / "a-file"}
    kwargs = {"out": box / "out", **kwargs}
    before = snapshot(box)
    with pytest.raises(api.PlanError) as raised:
        api.run(box / "sib.yaml", **kwargs)
    assert_names(str(raised.value), field)
    assert snapshot(box) == before, "the previous result stays; nothing is written"


@pytest.mark.parametrize(
    ("flag", "value"), [("--runs", "0"), ("--jobs", "1025"), ("--seed", str(2**63))]
)
def test_the_command_line_refuses_the_same_values(box, flag, value) -> None:
    assert_one_line(cli("run", box / "sib.yaml", "--out", box / "out", flag, value), flag)


def test_api_run_records_what_the_command_line_records(box) -> None:
    """Good arguments still run: an int subclass that is not a bool (numpy's int64) is a count."""
    import numpy as np

    result = api.run(box / "sib.yaml", out=box / "api", runs=np.int64(2), seed=np.uint8(5))
    manifest = result.manifest()
    assert manifest["runs"] == 2 and manifest["seed"] == 5
    assert type(manifest["runs"]) is int


def _two_batches(box: Path) -> tuple[Path, Path]:
    other = cli("run", box / "sib.yaml", "--out", box / "other", "--seed", "4")
    assert other.exit_code == 0, other.output
    return box / "out" / "sib", box / "other" / "sib"


@pytest.mark.parametrize("table", ["steps", "summary", "runs"])
def test_a_result_table_of_another_batch_is_refused(box, table) -> None:
    ours, theirs = _two_batches(box)
    name = {"steps": STEPS_FILE, "summary": SUMMARY_PARQUET, "runs": "runs.parquet"}[table]
    shutil.copyfile(theirs / name, ours / name)
    with pytest.raises(api.ResultsError, match="different batches"):
        getattr(api.open_result(ours), table)()


def test_report_takes_one_path_as_one_result(box) -> None:
    report = api.report(str(box / "out" / "sib"), out=box / "report")
    assert report == box / "report" / "report.md" and report.is_file()


BAD_CALLS = {
    "load-a-number": (lambda box: api.load(5), "source"),
    "load-base-a-number": (lambda box: api.load({"name": "x"}, base=5), "base"),
    "load-file-base-a-number": (lambda box: api.load(box / "sib.yaml", base=5), "base"),
    "run-experiment-a-number": (lambda box: api.run(5, out=box / "out"), "experiment"),
    "open-result-a-number": (lambda box: api.open_result(5), "folder"),
    "open-result-a-list": (lambda box: api.open_result([box]), "folder"),
    "result-a-number": (lambda box: api.Result(5).summary(), "folder"),
    "report-results-a-number": (lambda box: api.report(5, out=box / "r"), "results"),
    "report-results-a-bad-item": (
        lambda box: api.report([box / "out", 5], out=box / "r"),
        "results",
    ),
    "report-out-a-number": (lambda box: api.report([box / "out"], out=5), "out"),
    "report-out-a-file": (lambda box: api.report([box / "out"], out=box / "small.yaml"), "out"),
    "report-no-results": (lambda box: api.report([], out=box / "r"), "results"),
}


@pytest.mark.parametrize("case", list(BAD_CALLS))
def test_every_api_function_checks_its_arguments(box, case) -> None:
    call, field = BAD_CALLS[case]
    before = snapshot(box)
    with pytest.raises(api.PlanError) as raised:
        call(box)
    assert_names(str(raised.value), field)
    assert snapshot(box) == before


# ---------------------------------------------------------------------------------------------
# 3. Every validation error of a scenario is shown (up to a limit, then the count of the rest)


def test_every_scenario_error_is_shown_in_the_one_line() -> None:
    with pytest.raises(ScenarioError) as raised:
        parse_scenario({"name": "x", "runs": 0, "seed": -1, "record_every": 0}, "s.yaml")
    message = str(raised.value)
    assert "\n" not in message
    for field in ("runs", "seed", "record_every"):
        assert field in message, message
    assert "more error" not in message or "seed" in message


def test_errors_past_the_limit_are_counted() -> None:
    from anfekf_bench.config import SHOWN_ERRORS

    noise = {k: -1 for k in ("sigma_v", "sigma_gamma_deg", "sigma_range", "sigma_bearing_deg")}
    doc = {
        "name": "x",
        "runs": 0,
        "seed": -1,
        "record_every": 0,
        "jobs": 0,
        "true_noise": noise,
        "filter_noise": noise,
    }
    with pytest.raises(ScenarioError) as raised:
        parse_scenario(doc, "s.yaml")
    message = str(raised.value)
    total = 12
    assert message.count("Input should be") == 1 + SHOWN_ERRORS, message
    assert f"and {total - 1 - SHOWN_ERRORS} more" in message, message


def test_the_command_line_shows_the_second_error(tmp_path) -> None:
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump({"name": "two", **TINY, "runs": 0, "seed": -1}))
    result = cli("run", path, "--out", tmp_path / "out")
    assert_one_line(result, "runs", "seed")


# ---------------------------------------------------------------------------------------------
# 4. The API's worked example runs from any working directory


@pytest.mark.slow
def test_the_api_example_runs_from_another_working_directory(tmp_path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    done = subprocess.run(
        [sys.executable, str(EXAMPLE), "results"],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr
    assert (elsewhere / "results" / "wrong_r" / MANIFEST_FILE).is_file()
    assert (elsewhere / "results" / "report" / "report.md").is_file()
