"""Hardening 2 (issue 11): confine, validate first, never unpickle.

Every bad input of docs/HARDENING.md, by class. Each must end in ONE line `error: ...` on stderr
with exit code 2 and no traceback, and must change NOTHING on disk: the sandbox (a previous
complete result in OUT/small, sentinel files beside it, above it and in a sibling result) is
compared entry by entry, content by content, before and after. Files planted in the run store are
refused or redone, never executed. A property test (hypothesis) runs `anfekf run` over scenario
names and --out layouts: nothing outside the scenario's own folder ever changes.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import pickle
import shutil
import socket
import stat
import tempfile
import threading
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from anfekf_bench import experiment
from anfekf_bench.analysis.metrics import NEES_EXPLODED, summarize_filter
from anfekf_bench.cli import app
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.storage import (
    MANIFEST_FILE,
    RUNS_DIR,
    STEPS_FILE,
    SUMMARY_PARQUET,
    parquet_provenance,
    read_run_file,
    write_json,
    write_parquet,
)

from .conftest import cluster_with_one_worker, small_scenario, tiny_scenario, write_scenario

EXIT_USAGE = 2
PWNED_NAME = "PWNED"  # a planted file's code would create this file in the sandbox


def cli(*args: str | Path):
    return CliRunner().invoke(app, [str(a) for a in args])


def assert_one_line_error(result, *fragments: str) -> str:
    assert result.exit_code == EXIT_USAGE, (result.exit_code, result.output, result.exception)
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert "Traceback" not in result.output
    assert "\x1b" not in result.stderr, "control characters are escaped"
    return lines[0]


def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under `root` (symlinks not followed, special files never opened)."""
    found: dict[str, tuple] = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(folder) / name
            rel = path.relative_to(root).as_posix()
            mode = path.lstat().st_mode
            if stat.S_ISLNK(mode):
                found[rel] = ("link", os.readlink(path))
            elif stat.S_ISDIR(mode):
                found[rel] = ("dir",)
            elif stat.S_ISREG(mode):
                found[rel] = ("file", hashlib.sha256(path.read_bytes()).hexdigest())
            else:
                found[rel] = ("special", stat.S_IFMT(mode))
    return found


# --- The sandbox -------------------------------------------------------------------------------

SMALL = {"runs": 2, "record_every": 8}


@pytest.fixture(scope="module")
def previous(tmp_path_factory) -> Path:
    """A complete result of the small scenario (made once; every test copies it)."""
    root = tmp_path_factory.mktemp("previous")
    path = write_scenario(root / "small.yaml", small_scenario(**SMALL))
    _, target = execute(make_plan(*load_scenario(path), None, None, 1), root / "out")
    return target


@dataclass
class Sandbox:
    """root/ holds s.yaml, sentinel.txt and out/ (the --out), where out/small is a previous
    complete result, out/other/keep.txt a sibling and out/sentinel.txt a file beside them."""

    root: Path
    out: Path
    scenario: Path
    monkeypatch: pytest.MonkeyPatch
    extra: dict = field(default_factory=dict)

    @property
    def result(self) -> Path:
        return self.out / "small"

    def yaml(self, text: str, name: str = "bad.yaml") -> Path:
        path = self.root / name
        path.write_text(text, encoding="utf-8")
        return path

    def doc(self, file: str = "bad.yaml", **overrides) -> Path:
        return write_scenario(self.root / file, small_scenario(**{**SMALL, **overrides}))

    def world(self, **overrides) -> Path:
        return self.doc(world={**small_scenario()["world"], **overrides})

    def run(self, scenario: Path, *flags: str) -> list:
        return ["run", scenario, "--out", self.out, *flags]


@pytest.fixture
def sandbox(tmp_path, previous, monkeypatch) -> Sandbox:
    root = tmp_path / "box"
    out = root / "out"
    shutil.copytree(previous, out / "small")
    (root / "sentinel.txt").write_text("above")
    (out / "sentinel.txt").write_text("beside")
    (out / "other").mkdir()
    (out / "other" / "keep.txt").write_text("sibling")
    scenario = write_scenario(root / "s.yaml", small_scenario(**SMALL))
    return Sandbox(root, out, scenario, monkeypatch)


# --- Bad inputs: one line, exit 2, nothing changed --------------------------------------------

# id -> (class, setup returning the command line, fragments of the one-line error)
CASES: dict[str, tuple[str, Callable[[Sandbox], list], tuple[str, ...]]] = {}


def case(klass: str, case_id: str, *fragments: str):
    def register(setup: Callable[[Sandbox], list]):
        assert case_id not in CASES, case_id
        CASES[case_id] = (klass, setup, fragments)
        return setup

    return register


def _name_case(case_id: str, name: str, *fragments: str) -> None:
    case("names", case_id, "name", *fragments)(lambda sb: sb.run(sb.doc(name=name), "--force"))


# Names: the result folder is a direct child of --out with a safe name.
_name_case("name-dot", ".", "letters, digits")
_name_case("name-dotdot", "..", "letters, digits")
_name_case("name-report", "report", "reserved")
_name_case("name-report-upper", "REPORT", "reserved")
_name_case("name-runs-store", ".runs", "letters, digits")
_name_case("name-steps-file", "steps.parquet", "reserved")
_name_case("name-manifest-file", "manifest.json", "reserved")
_name_case("name-baselines", "baselines", "reserved")
_name_case("name-hidden", ".hidden", "letters, digits")
_name_case("name-temporary", "small.tmp", "reserved")
_name_case("name-slash", "a/b", "letters, digits")
_name_case("name-parent-path", "../escape", "letters, digits")
_name_case("name-newline", "a\nb", "letters, digits")
_name_case("name-over-long", "a" * 300, "at most 64")


# --force: only this tool's files of an anfekf result are ever removed.
@case("force", "force-foreign-folder", "small", "did not write", "docs")
def _(sb):
    shutil.rmtree(sb.result)
    (sb.result / "docs").mkdir(parents=True)
    (sb.result / "docs" / "index.md").write_text("# my notes")
    return sb.run(sb.scenario, "--force")


@case("force", "force-package-source", "did not write", "__init__.py")
def _(sb):
    shutil.rmtree(sb.result)
    shutil.copytree(Path(experiment.__file__).parent / "analysis", sb.result)
    return sb.run(sb.scenario, "--force")


@case("force", "force-symlink-to-folder", "symbolic link")
def _(sb):
    elsewhere = sb.root / "elsewhere"
    sb.result.rename(elsewhere)  # a complete result, but reached through a symlink
    sb.result.symlink_to(elsewhere, target_is_directory=True)
    return sb.run(sb.scenario, "--force")


@case("force", "force-symlink-to-file", "symbolic link")
def _(sb):
    shutil.rmtree(sb.result)
    sb.result.symlink_to(sb.root / "sentinel.txt")
    return sb.run(sb.scenario, "--force")


@case("force", "force-a-file", "not a folder")
def _(sb):
    shutil.rmtree(sb.result)
    sb.result.write_text("a file of that name")
    return sb.run(sb.scenario, "--force")


@case("force", "force-result-plus-notes", "did not write", "notes.txt")
def _(sb):
    (sb.result / "notes.txt").write_text("mine")
    return sb.run(sb.scenario, "--force")


@case("force", "force-result-plus-subfolder", "did not write", "figures")
def _(sb):
    (sb.result / "figures").mkdir()
    return sb.run(sb.scenario, "--force")


@case("force", "force-run-store-symlink", "did not write", ".runs")
def _(sb):
    (sb.root / "precious").mkdir()
    (sb.root / "precious" / "data.bin").write_bytes(b"keep me")
    (sb.result / RUNS_DIR).symlink_to(sb.root / "precious", target_is_directory=True)
    return sb.run(sb.scenario, "--force")


@case("force", "force-result-file-symlink", "did not write", STEPS_FILE)
def _(sb):
    (sb.result / STEPS_FILE).unlink()
    (sb.result / STEPS_FILE).symlink_to(sb.root / "sentinel.txt")
    return sb.run(sb.scenario, "--force")


@case("force", "force-manifest-fifo", "did not write", MANIFEST_FILE)
def _(sb):
    (sb.result / MANIFEST_FILE).unlink()
    os.mkfifo(sb.result / MANIFEST_FILE)
    return sb.run(sb.scenario, "--force")


@case("force", "force-no-anfekf-marker", "holds no anfekf result")
def _(sb):
    shutil.rmtree(sb.result)
    sb.result.mkdir()
    (sb.result / "data.json").write_text('{"mine": true}')
    return sb.run(sb.scenario, "--force")


@case("force", "force-foreign-manifest", "holds no anfekf result")
def _(sb):
    shutil.rmtree(sb.result)
    sb.result.mkdir()
    (sb.result / MANIFEST_FILE).write_text('{"name": "a web app", "icons": []}')
    return sb.run(sb.scenario, "--force")


@pytest.mark.parametrize("leftover", ["empty-run-store", "temporary-file", "lock-only"])
@pytest.mark.parametrize("force", [False, True], ids=["plain", "force"])
def test_what_a_killed_first_attempt_leaves_is_taken_over(sandbox, leftover, force) -> None:
    """A first attempt killed right after creating its folder leaves only our own leftovers: a
    rerun (with --force or not) takes the folder over instead of calling it foreign."""
    shutil.rmtree(sandbox.result)
    sandbox.result.mkdir()
    (sandbox.result / ".lock").write_text("12345\n")
    if leftover == "empty-run-store":
        (sandbox.result / RUNS_DIR).mkdir()
    elif leftover == "temporary-file":
        (sandbox.result / ".steps.parquet.x1y2.tmp").write_bytes(b"half")
    result = cli(*sandbox.run(sandbox.scenario, *(["--force"] if force else [])))
    assert result.exit_code == 0, result.output
    assert (sandbox.result / MANIFEST_FILE).is_file()
    assert not list(sandbox.result.glob(".*.tmp"))


# Validate first: a forced rerun that cannot run leaves the previous result as it was.
@case("validate-first", "route-shorter-than-record-every", "record_every", "longer than the route")
def _(sb):
    return sb.run(sb.doc(record_every=100_000), "--force")


@case("validate-first", "route-of-zero-steps", "world.waypoints", "no control steps")
def _(sb):
    return sb.run(sb.world(waypoints=[[0.2, 0.0]]), "--force")


@case("validate-first", "route-never-completed", "world.max_steps", "not completed")
def _(sb):
    return sb.run(sb.world(max_steps=10), "--force")


@case("validate-first", "memory-exhausted", "runs", "memory", "fewer runs")
def _(sb):
    sb.monkeypatch.setattr(experiment, "machine_memory", lambda: 2 * 2**30)
    return sb.run(sb.doc(runs=50_000, record_every=1), "--force")


@case("validate-first", "runs-flag-absurd", "--runs", "<= 100000")
def _(sb):
    return sb.run(sb.scenario, "--force", "--runs", "1000000000000")


@case("validate-first", "jobs-flag-absurd", "--jobs", "<= 1024")
def _(sb):
    return sb.run(sb.scenario, "--force", "--jobs", "100000")


@case("validate-first", "seed-flag-beyond-64-bits", "--seed", "<=")
def _(sb):
    return sb.run(sb.scenario, "--force", "--seed", str(2**70))


@case("validate-first", "sigma-overflows", "true_noise.sigma_range", "less than or equal")
def _(sb):
    return sb.run(sb.doc(true_noise={"sigma_range": 1e154}), "--force")


@case("validate-first", "p0-overflows", "p0", "less than or equal")
def _(sb):
    return sb.run(sb.doc(p0=1e300), "--force")


@case("validate-first", "start-far-away", "world.x0", "less than or equal")
def _(sb):
    return sb.run(sb.world(x0=[1e300, 0, 0]), "--force")


@case("validate-first", "dt-absurd", "world.dt", "less than or equal")
def _(sb):
    return sb.run(sb.world(dt=1e9), "--force")


@case("validate-first", "max-steps-absurd", "world.max_steps", "less than or equal")
def _(sb):
    return sb.run(sb.world(max_steps=10**12), "--force")


@case("validate-first", "dask-unreachable", "cannot reach Dask scheduler", "no answer")
def _(sb):
    doc = sb.doc(backend={"kind": "dask", "scheduler": f"tcp://127.0.0.1:{_unused_port()}",
                          "connect_timeout_s": 1})  # fmt: skip
    return sb.run(doc, "--force")


@case("validate-first", "dask-address-not-dask", "did not answer as a Dask scheduler")
def _(sb):
    address = _silent_server(sb)
    doc = sb.doc(backend={"kind": "dask", "scheduler": address, "connect_timeout_s": 1})
    return sb.run(doc, "--force")


# Strict YAML.
@case("yaml", "duplicate-top-key", "line 3", "'runs' appears twice")
def _(sb):
    return sb.run(sb.yaml("name: small\nruns: 2\nruns: 3\n"))


@case("yaml", "duplicate-nested-key", "'loops' appears twice")
def _(sb):
    return sb.run(sb.yaml("name: small\nworld:\n  loops: 1\n  loops: 2\n"))


@case("yaml", "duplicate-filter-key", "'kind' appears twice")
def _(sb):
    return sb.run(sb.yaml("name: small\nfilters:\n  - {name: a, kind: ekf, kind: anfekf}\n"))


ALIAS_BOMB = "".join(
    f"{x}: &{x} [{', '.join([f'*{p}'] * 9) if p else ', '.join(['lol'] * 9)}]\n"
    for p, x in zip(["", "a", "b", "c", "d", "e", "f", "g"], "abcdefgh", strict=True)
)


@case("yaml", "alias-bomb", "holds more than")
def _(sb):
    assert len(ALIAS_BOMB) < 600, len(ALIAS_BOMB)  # 9^8 = 43 million values in ~500 bytes
    return sb.run(sb.yaml(ALIAS_BOMB))


@case("yaml", "recursive-alias", "refers to the node that holds it")
def _(sb):
    return sb.run(sb.yaml("name: small\nrec: &r [1, *r]\n"))


@case("yaml", "lists-nested-deep", "nested")
def _(sb):
    return sb.run(sb.yaml("name: small\nruns: " + "[" * 200 + "1" + "]" * 200 + "\n"))


@case("yaml", "mappings-nested-deep", "nested deeper than")
def _(sb):
    return sb.run(sb.yaml("name: small\nworld: " + "{a: " * 40 + "1" + "}" * 40 + "\n"))


@case("yaml", "python-tag", "YAML syntax error", "python/object")
def _(sb):
    marker = sb.root / PWNED_NAME
    return sb.run(sb.yaml(f"name: !!python/object/apply:os.system ['touch {marker}']\n"))


@case("yaml", "scenario-too-large", "at most 1 MB")
def _(sb):
    return sb.run(sb.yaml("name: small\n" + "# padding\n" * 120_000))


@case("yaml", "scenario-is-a-fifo", "FIFO")
def _(sb):
    os.mkfifo(sb.root / "fifo.yaml")
    return sb.run(sb.root / "fifo.yaml")


@case("yaml", "scenario-is-a-device", "device")
def _(sb):
    return sb.run(Path("/dev/zero"))


# Files a scenario names: regular files only, content never echoed, control characters escaped.
def _map_case(case_id: str, setup: Callable[[Sandbox], str], *fragments: str) -> None:
    def make(sb: Sandbox) -> list:
        return sb.run(sb.world(landmarks=setup(sb)))

    case("files", case_id, "world.landmarks", *fragments)(make)


def _fifo(sb: Sandbox) -> str:
    os.mkfifo(sb.root / "map.csv")
    return "map.csv"


def _write(name: str, data: bytes) -> Callable[[Sandbox], str]:
    def setup(sb: Sandbox) -> str:
        (sb.root / name).write_bytes(data)
        return name

    return setup


_map_case("map-is-a-fifo", _fifo, "FIFO")
_map_case("map-is-a-folder", lambda sb: str(sb.out / "other"), "folder")
_map_case("map-is-a-device", lambda sb: "/dev/zero", "device")
_map_case("map-binary", _write("map.bin", bytes(range(256)) * 4), "not a text file")
_map_case("map-secret-first-line", _write("secret.csv", b"TOPSECRET,hunter2\n"), "line 1", "x,y")
_map_case(
    "map-too-many-points",
    _write("big.csv", b"1,2\n" * 100_001),
    "more than 100000 points",
)
_map_case("map-huge-coordinates", _write("far.csv", b"1e300,0\n"), "within")
_map_case("map-too-large-file", _write("huge.csv", b"# pad\n" * 3_000_000), "at most 16 MB")


@case("files", "map-name-control-characters", "map file not found", "\\x1b[2J")
def _(sb):
    return sb.run(sb.world(landmarks="\x1b[2Jgone.csv"))


@case("files", "filter-name-escape-sequence", "filters", "\\x1b[31m")
def _(sb):
    return sb.run(sb.doc(filters=[{"name": "\x1b[31mred", "kind": "ekf"}]))


@case("files", "filter-name-markup", "filters", "letters, digits")
def _(sb):
    return sb.run(sb.doc(filters=[{"name": "[bold]x[/bold]", "kind": "ekf"}]))


@case("files", "filter-name-mathtext", "filters", "letters, digits")
def _(sb):
    return sb.run(sb.doc(filters=[{"name": "$\\alpha^$", "kind": "ekf"}]))


@case("files", "out-component-too-long", "--out", "longer than")
def _(sb):
    return ["run", sb.scenario, "--out", sb.root / ("x" * 300)]


# The regression gate's baseline: non-finite or non-numeric values never pass.
def _baseline_case(case_id: str, value_json: str, *fragments: str) -> None:
    def make(sb: Sandbox) -> list:
        baseline = _baseline(sb)
        text = baseline.read_text()
        doc = json.loads(text)
        metrics = doc["scenarios"]["small"]["filters"]["ekf"]
        marker = 987654.321
        metrics["rmse_pos"] = marker
        baseline.write_text(json.dumps(doc).replace(str(marker), value_json))
        return ["check", sb.out, "--baseline", baseline]

    case("baseline", case_id, *fragments)(make)


def _baseline(sb: Sandbox) -> Path:
    path = sb.root / "baseline.json"
    for folder in ("other",):  # check reads every scenario folder: keep only the result
        shutil.rmtree(sb.out / folder)
    (sb.out / "sentinel.txt").unlink()
    written = cli("check", sb.out, "--baseline", path, "--update")
    assert path.is_file(), written.output
    return path


_baseline_case("baseline-1e400", "1e400", "out of range")
_baseline_case("baseline-infinity", "Infinity", "Infinity")
_baseline_case("baseline-minus-infinity", "-Infinity", "Infinity")
_baseline_case("baseline-nan", "NaN", "NaN")
_baseline_case("baseline-text", '"0.2"', "rmse_pos", "finite number or null")
_baseline_case("baseline-boolean", "true", "rmse_pos", "finite number or null")
_baseline_case("baseline-list", "[0.2]", "rmse_pos", "finite number or null")
_baseline_case("baseline-mapping", '{"v": 1}', "rmse_pos", "finite number or null")
_baseline_case("baseline-duplicate-key", '0.2, "rmse_pos": 0.3', "appears twice")


@case("baseline", "baseline-tolerance-1e400", "out of range")
def _(sb):
    baseline = _baseline(sb)
    doc = json.loads(baseline.read_text())
    doc["tolerances"]["rmse_pos"] = {"relative": 123.456}
    baseline.write_text(json.dumps(doc).replace("123.456", "1e400"))
    return ["check", sb.out, "--baseline", baseline]


@case("baseline", "baseline-negative-runs", "runs", ">= 1")
def _(sb):
    baseline = _baseline(sb)
    doc = json.loads(baseline.read_text())
    doc["scenarios"]["small"]["runs"] = -1
    baseline.write_text(json.dumps(doc))
    return ["check", sb.out, "--baseline", baseline]


@case("baseline", "baseline-is-a-fifo", "FIFO")
def _(sb):
    _baseline(sb).unlink()
    os.mkfifo(sb.root / "baseline.json")
    return ["check", sb.out, "--baseline", sb.root / "baseline.json"]


@case("baseline", "results-summary-infinite", "summary.parquet", "infinite")
def _(sb):
    baseline = _baseline(sb)
    summary = pd.read_parquet(sb.result / SUMMARY_PARQUET)
    summary.loc[0, "rmse_pos"] = np.inf
    path = sb.result / SUMMARY_PARQUET
    write_parquet(path, summary, parquet_provenance(path))
    return ["check", sb.out, "--baseline", baseline]


# report: saved results that are not one batch's.
def _report_case(case_id: str, edit: Callable[[Sandbox, pd.DataFrame], pd.DataFrame], *frags):
    def make(sb: Sandbox) -> list:
        steps = pd.read_parquet(sb.result / STEPS_FILE)
        # The edit keeps the batch's metadata (else it is refused as another batch's file).
        kept = parquet_provenance(sb.result / STEPS_FILE)
        write_parquet(sb.result / STEPS_FILE, edit(sb, steps), kept)
        return ["report", sb.out / "small", "--out", sb.root / "report"]

    case("report", case_id, STEPS_FILE, *frags)(make)


def _other_scenario(sb, steps):
    steps["scenario"] = pd.Categorical(["wrong_r"] * len(steps))
    return steps


def _drop_run(sb, steps):
    return steps[steps["run"] != 1].reset_index(drop=True)


def _extra_run(sb, steps):
    extra = steps[steps["run"] == 1].copy()
    extra["run"] = 7
    return pd.concat([steps, extra], ignore_index=True)


def _drop_filter(sb, steps):
    return steps[steps["filter"] != "ekf-oracle"].reset_index(drop=True)


def _shift_steps(sb, steps):
    one = (steps["run"] == 1) & (steps["filter"] == "ekf")
    steps.loc[one, "step"] = steps.loc[one, "step"] + 1
    return steps


_report_case("report-steps-of-another-scenario", _other_scenario, "holds scenario 'wrong_r'")
_report_case(
    "report-duplicated-rows",
    lambda sb, s: pd.concat([s, s.iloc[:5]], ignore_index=True),
    "duplicated rows",
)
_report_case("report-run-missing", _drop_run, "runs 1 missing")
_report_case("report-extra-run", _extra_run, "not in the batch")
_report_case("report-filter-without-rows", _drop_filter, "'ekf-oracle'", "has no rows")
_report_case("report-ragged-steps", _shift_steps, "different steps")


def _text_column(sb, steps):
    steps["R_rr"] = steps["R_rr"].astype(str)
    return steps


def _truth_infinite(sb, steps):
    steps.loc[3, "x_true"] = np.inf
    return steps


def _filter_empty(sb, steps):
    steps["filter"] = steps["filter"].astype(object)
    steps.loc[2, "filter"] = None
    return steps


_report_case("report-column-of-text", _text_column, "R_rr", "expected numbers")
_report_case("report-truth-not-finite", _truth_infinite, "x_true", "finite")
_report_case("report-filter-empty-cells", _filter_empty, "filter", "empty cells")


@case("report", "report-filter-name-markup", "not plain text")
def _(sb):
    steps = pd.read_parquet(sb.result / STEPS_FILE)
    steps["filter"] = steps["filter"].astype(str).replace("ekf", "[red]ekf[/]")
    write_parquet(sb.result / STEPS_FILE, steps, parquet_provenance(sb.result / STEPS_FILE))
    manifest = json.loads((sb.result / MANIFEST_FILE).read_text())
    manifest["scenario"]["filters"][0]["name"] = "[red]ekf[/]"
    write_json(sb.result / MANIFEST_FILE, manifest)
    return ["report", sb.out / "small", "--out", sb.root / "report"]


@case("report", "report-steps-fifo", STEPS_FILE, "FIFO")
def _(sb):
    (sb.result / STEPS_FILE).unlink()
    os.mkfifo(sb.result / STEPS_FILE)
    return ["report", sb.out / "small", "--out", sb.root / "report"]


@case("report", "report-manifest-fifo", MANIFEST_FILE, "not a regular file")
def _(sb):
    (sb.result / MANIFEST_FILE).unlink()
    os.mkfifo(sb.result / MANIFEST_FILE)
    return ["report", sb.out / "small", "--out", sb.root / "report"]


@case("report", "report-manifest-duplicate-key", MANIFEST_FILE, "appears twice")
def _(sb):
    text = (sb.result / MANIFEST_FILE).read_text()
    (sb.result / MANIFEST_FILE).write_text(text.replace('"runs": 2,', '"runs": 2, "runs": 3,', 1))
    return ["report", sb.out / "small", "--out", sb.root / "report"]


@case("report", "report-manifest-nan", MANIFEST_FILE, "NaN")
def _(sb):
    text = (sb.result / MANIFEST_FILE).read_text()
    (sb.result / MANIFEST_FILE).write_text(text.replace('"runs": 2,', '"runs": NaN,', 1))
    return ["report", sb.out / "small", "--out", sb.root / "report"]


# Command-line usage: one line, not click's box.
for _id, _flags, _frag in (
    ("flag-runs-not-a-number", ["--runs", "two"], "Invalid value for '--runs'"),
    ("flag-misspelt", ["--rusn", "3"], "No such option: --rusn"),
    ("flag-backend-unknown", ["--backend", "slurm"], "'slurm'"),
):
    case("flags", _id, _frag)(lambda sb, flags=_flags: sb.run(sb.scenario, *flags))


@case("flags", "command-unknown", "No such command")
def _(sb):
    return ["runn", sb.scenario]


@case("flags", "argument-missing", "Missing argument")
def _(sb):
    return ["run"]


def _unused_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _silent_server(sb: Sandbox) -> str:
    """A TCP server that accepts connections and never says a word (not a Dask scheduler)."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held: list[socket.socket] = []

    def accept() -> None:
        with contextlib.suppress(OSError):
            while True:
                held.append(server.accept()[0])

    threading.Thread(target=accept, daemon=True).start()
    sb.extra["server"] = (server, held)
    return f"tcp://127.0.0.1:{server.getsockname()[1]}"


@pytest.mark.parametrize("case_id", list(CASES))
def test_bad_input_is_one_line_and_changes_nothing(case_id: str, sandbox: Sandbox) -> None:
    klass, setup, fragments = CASES[case_id]
    if klass == "validate-first" and case_id.startswith("dask"):
        pytest.importorskip("distributed")
    argv = setup(sandbox)
    before = snapshot(sandbox.root)
    try:
        result = cli(*argv)
    finally:
        server = sandbox.extra.get("server")
        if server is not None:
            for conn in [server[0], *server[1]]:
                conn.close()
    assert_one_line_error(result, *fragments)
    assert snapshot(sandbox.root) == before, "nothing may change, the previous result included"
    assert not (sandbox.root / PWNED_NAME).exists()


def test_at_least_sixty_distinct_bad_inputs_are_listed_in_the_docs() -> None:
    doc = (Path(__file__).parents[1] / "docs" / "HARDENING.md").read_text(encoding="utf-8")
    ids = [*CASES, *STORE_CASES, *DASK_CASES]
    assert len(ids) >= 60, len(ids)
    missing = [i for i in ids if f"`{i}`" not in doc]
    assert missing == [], f"docs/HARDENING.md does not list {missing}"


# --- The run store: planted or foreign files are refused (and redone), never executed ---------


class _Pwn:
    """Unpickling this creates the PWNED marker: proof that a file was executed."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _npz(members: dict[str, bytes], compress: bool = False) -> bytes:
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", compression=method) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buf.getvalue()


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _pickled(marker: Path) -> bytes:
    return pickle.dumps(_Pwn(marker))


def _object_array(marker: Path) -> bytes:
    return _npz({"header.npy": _npy(np.array([_Pwn(marker)], dtype=object))})


def _members(good: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(good)) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _tampered(good: bytes) -> bytes:
    """One number changed, the zip rebuilt with valid CRCs: only our checksum can notice."""
    members = _members(good)
    data = bytearray(members["data.npy"])
    data[-1] ^= 0x01
    members["data.npy"] = bytes(data)
    return _npz(members)


def _huge_shape(good: bytes) -> bytes:
    header = b"{'descr': '|u1', 'fortran_order': False, 'shape': (1000000000000,), }"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + b"\0" * 64
    members = _members(good)
    members["data.npy"] = npy
    return _npz(members)


def _compressed(good: bytes) -> bytes:
    return _npz(_members(good), compress=True)


def _other_run(runs: Path) -> bytes:
    return (runs / "run-000000.npz").read_bytes()  # run 0's file under run 1's name


# id -> how to plant run 1's file (bytes, or a callable that makes the entry itself)
STORE_CASES: dict[str, Callable] = {
    "store-pickle-as-npz": lambda m, good, runs: _pickled(m),
    "store-object-array": lambda m, good, runs: _object_array(m),
    "store-tampered-bytes": lambda m, good, runs: _tampered(good),
    "store-truncated": lambda m, good, runs: good[: len(good) // 2],
    "store-compressed-member": lambda m, good, runs: _compressed(good),
    "store-huge-declared-shape": lambda m, good, runs: _huge_shape(good),
    "store-other-run-under-this-name": lambda m, good, runs: _other_run(runs),
    "store-empty-file": lambda m, good, runs: b"",
    "store-fifo": "fifo",
    "store-folder": "folder",
    "store-symlink-to-a-file": "symlink",
    "store-joblib-pickle-beside": "joblib",
}


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory) -> tuple[Path, Path, pd.DataFrame]:
    """An interrupted batch (runs 0 and 1 saved of 3) and the uninterrupted steps."""
    root = tmp_path_factory.mktemp("store")
    path = write_scenario(root / "s.yaml", small_scenario(runs=3, record_every=8))
    _, reference = execute(make_plan(*load_scenario(path), None, None, 1), root / "reference")

    def stop_after_two(result: dict, seen: list = []) -> None:  # noqa: B006
        seen.append(result)
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        execute(
            make_plan(*load_scenario(path), None, None, 1), root / "out", on_result=stop_after_two
        )
    return path, root / "out" / "small", pd.read_parquet(reference / STEPS_FILE)


@pytest.mark.parametrize("case_id", list(STORE_CASES))
def test_planted_run_files_are_refused_never_executed(case_id, interrupted, tmp_path) -> None:
    path, saved, reference = interrupted
    target = tmp_path / "out" / "small"
    shutil.copytree(saved, target)
    runs = target / RUNS_DIR
    victim = runs / "run-000001.npz"
    good = victim.read_bytes()
    marker = tmp_path / PWNED_NAME
    plant = STORE_CASES[case_id]
    victim.unlink()
    if plant == "fifo":
        os.mkfifo(victim)
    elif plant == "folder":
        victim.mkdir()
        (victim / "x").write_bytes(_pickled(marker))
    elif plant == "symlink":
        victim.symlink_to(tmp_path / "outside.bin")
        (tmp_path / "outside.bin").write_bytes(_pickled(marker))
    elif plant == "joblib":
        victim.write_bytes(good)
        (runs / "run-000002.joblib").write_bytes(_pickled(marker))
    else:
        victim.write_bytes(plant(marker, good, runs))
    result = cli("run", path, "--out", tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert not marker.exists(), "a planted file was executed"
    if plant != "joblib":
        assert (
            "resuming: 1 of 3 runs" in result.stdout
            and "1 saved run files refused" in result.stdout
        )
    pd.testing.assert_frame_equal(pd.read_parquet(target / STEPS_FILE), reference)
    if plant == "symlink":
        assert (tmp_path / "outside.bin").read_bytes() == _pickled(marker), "never written through"


def test_run_file_roundtrip_is_exact_and_generic(tmp_path) -> None:
    """Any nested dict of arrays and scalars (fields others add later included) comes back with
    the same types, dtypes and bytes; another fingerprint is refused."""
    from anfekf_bench.storage import RunFileRefused, write_run_file

    result = {
        "run": 3,
        "step": np.arange(4, dtype=np.int32),
        "filters": {
            "a b/c": {
                "x": np.ones((4, 3)),
                "P": np.eye(3)[None].repeat(4, 0),
                "diverged": False,
                "nis_sum": float("nan"),
                "n": 2**70,
                "flag": np.bool_(True),
                "s": np.float32(0.5),
                "none": None,
                "per_update": [np.zeros(2), (1, "two")],
            }
        },  # fmt: skip
        7: "an int key",
    }
    path = tmp_path / "run-000003.npz"
    write_run_file(path, result, "f" * 16)
    back = read_run_file(path, "f" * 16)
    assert back.keys() == result.keys()
    got, want = back["filters"]["a b/c"], result["filters"]["a b/c"]
    for key in ("x", "P"):
        assert got[key].dtype == want[key].dtype and np.array_equal(got[key], want[key])
    assert got["diverged"] is False and np.isnan(got["nis_sum"]) and got["n"] == 2**70
    assert isinstance(got["flag"], np.bool_) and isinstance(got["s"], np.float32)
    assert got["none"] is None and isinstance(got["per_update"][1], tuple)
    assert back[7] == "an int key" and back["step"].dtype == np.int32
    with pytest.raises(RunFileRefused, match="another scenario"):
        read_run_file(path, "0" * 16)
    with pytest.raises(TypeError, match="object"):
        write_run_file(tmp_path / "bad.npz", {"x": np.array([object()])}, "f" * 16)


def _forged_run_file(tree: dict, data: bytes, fingerprint: str) -> bytes:
    """A run file whose header and checksum are consistent (anyone can compute a SHA-256), so
    that only the reader's own checks of the tree against the data can refuse it."""
    import json

    from anfekf_bench.storage import RUN_FORMAT, _checksum

    tree_json = json.dumps(tree, separators=(",", ":"))
    header = {"format": RUN_FORMAT, "fingerprint": fingerprint, "tree": tree_json,
              "sha256": _checksum(fingerprint, tree_json, data)}  # fmt: skip
    return _npz({"header.npy": _npy(np.frombuffer(json.dumps(header).encode(), np.uint8)),
                 "data.npy": _npy(np.frombuffer(data, np.uint8))})  # fmt: skip


@pytest.mark.parametrize(
    ("case", "array", "data", "why"),
    [
        ("data-shorter-than-declared", ["<f8", [4], "C"], bytes(24), "shorter"),
        ("data-left-over", ["<f8", [2], "C"], bytes(24), "malformed"),
        ("object-dtype", ["|O", [1], "C"], bytes(8), "malformed"),
        ("negative-shape", ["<f8", [-1], "C"], bytes(8), "malformed"),
        ("unknown-order", ["<f8", [1], "X"], bytes(8), "malformed"),
    ],
)
def test_run_file_whose_tree_and_data_disagree_is_refused(tmp_path, case, array, data, why):
    from anfekf_bench.storage import RunFileRefused, read_run_file

    path = tmp_path / "run-000000.npz"
    tree = {"dict": [["run", {"int": 0}], ["x", {"array": array}]]}
    path.write_bytes(_forged_run_file(tree, data, "f" * 16))
    with pytest.raises(RunFileRefused, match=why):
        read_run_file(path, "f" * 16)


def test_run_file_is_two_members_whatever_the_arrays(tmp_path) -> None:
    """The header and one data member (v2): the write cost does not grow with the arrays' count."""
    from anfekf_bench.storage import write_run_file

    result = {"run": 0, "filters": {f"f{i}": {"x": np.ones((5, 3)), "P": np.eye(3)} for i in
                                    range(8)}}  # fmt: skip
    write_run_file(tmp_path / "run-000000.npz", result, "f" * 16)
    with zipfile.ZipFile(tmp_path / "run-000000.npz") as archive:
        assert sorted(archive.namelist()) == ["data.npy", "header.npy"]


# --- Dask: dead workers and a non-Dask address end in one line, in bounded time ---------------

DASK_CASES = ("dask-all-workers-died",)


@pytest.mark.slow
def test_dask_batch_whose_workers_all_die_ends_in_one_line(tmp_path) -> None:
    """The only worker (no nanny to restart it) is killed mid-batch: the command ends within
    about the connect timeout with one line, finished runs saved, nothing else on stderr."""
    import signal
    import subprocess
    import sys
    import time

    with cluster_with_one_worker() as (address, worker):
        doc = small_scenario(runs=40, record_every=8)
        doc["backend"] = {"kind": "dask", "scheduler": address, "connect_timeout_s": 2}
        path = write_scenario(tmp_path / "s.yaml", doc)
        out = tmp_path / "out"
        command = [sys.executable, "-c", "from anfekf_bench.cli import main; main()"]
        proc = subprocess.Popen(
            [*command, "run", str(path), "--out", str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 120
            while not list((out / "small" / RUNS_DIR).glob("run-*.npz")):
                assert proc.poll() is None, proc.communicate()
                assert time.monotonic() < deadline, "no run finished within 120 s"
                time.sleep(0.05)
            os.kill(worker.pid, signal.SIGKILL)
            killed = time.monotonic()
            _, stderr = proc.communicate(timeout=60)
            took = time.monotonic() - killed
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == EXIT_USAGE, stderr
    assert stderr.splitlines() == [
        f"error: Dask cluster at {address} has had no workers for 2 s during the batch (they"
        " died or left); finished runs are saved: run the same command again to resume"
    ]
    assert took < 30, f"took {took:.1f} s"
    assert list((out / "small" / RUNS_DIR).glob("run-*.npz")), "finished runs stay saved"


# --- Divergence: a filter whose NEES explodes while staying finite is counted -----------------


def test_inconsistent_runs_are_counted_apart_from_diverged() -> None:
    steps = 10
    nees = np.full((4, steps), 3.0)
    nees[1] = 1e16  # ANEES 1e16: finite, not diverged, absurd
    nees[2, 3] = np.inf  # one infinite step (a finite P, an enormous error)
    nees[3] = NEES_EXPLODED * 0.999  # just below the threshold
    err = np.ones((4, steps))
    record = summarize_filter(err, err, nees, np.array([False, False, False, False]))
    assert record["inconsistent"] == 2 and record["diverged"] == 0 and record["runs_used"] == 4
    diverged = summarize_filter(err, err, nees, np.array([False, True, False, False]))
    assert diverged["inconsistent"] == 1, "a diverged run is counted as diverged only"


def test_a_singular_covariance_gives_a_nees_not_a_traceback(tmp_path) -> None:
    """p0: 0 leaves P singular before the first updates: NEES over the directions P has
    (pseudo-inverse) there, the ordinary solve everywhere else; the run completes."""
    from anfekf_bench.analysis.metrics import nees

    P = np.stack([np.diag([1.0, 4.0, 0.0]), np.diag([1.0, 4.0, 9.0])])
    e = np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 3.0]])
    assert nees(e, P).tolist() == [2.0, 3.0]
    path = write_scenario(tmp_path / "p0.yaml", small_scenario(runs=1, record_every=1, p0=0))
    result = cli("run", path, "--out", tmp_path / "out")
    assert result.exit_code == 0, result.output


# --- Property: nothing outside the scenario folder ever changes -------------------------------

TINY = tiny_scenario()
NAMES = st.one_of(
    st.sampled_from(
        [
            ".",
            "..",
            "report",
            "REPORT",
            ".runs",
            "steps.parquet",
            "manifest.json",
            "small",
            "other",
            "a/b",
            "../up",
            "x" * 70,
            "-x",
            "ok-1",
            "v1.2",
            "",
            " ",
            "a\nb",
            "bench.json",
            "sentinel.txt",
            ".lock",
        ]
    ),  # fmt: skip
    st.text(alphabet=st.sampled_from(list("ab./\\-_ \n\x1b0")), min_size=1, max_size=8),
    # Safe names, twice as likely: those runs write, and must write only in their own folder.
    st.from_regex(r"[a-z0-9][a-z0-9._-]{0,6}", fullmatch=True),
    st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,6}", fullmatch=True),
)
OUT_LAYOUTS = st.sampled_from(["missing", "existing", "nested-missing", "dot", "symlinked"])
TARGET_STATES = st.sampled_from(
    ["absent", "absent", "result", "foreign", "symlink", "file", "other-seed-runs", "empty"]
)


def _prepare_layout(box: Path, layout: str) -> tuple[Path, Path]:
    """(the --out argument, the folder it really is), with sentinels around."""
    (box / "work").mkdir()
    (box / "work" / "sentinel.txt").write_text("cwd")
    (box / "elsewhere").mkdir()
    (box / "elsewhere" / "keep.txt").write_text("keep")
    if layout == "missing":
        return box / "out", box / "out"
    if layout == "nested-missing":
        return box / "a" / "b" / "out", box / "a" / "b" / "out"
    if layout == "dot":
        return Path("."), box / "work"
    real = box / "real-out"
    real.mkdir()
    (real / "sentinel.txt").write_text("beside")
    (real / "other").mkdir()
    (real / "other" / "keep.txt").write_text("sibling")
    if layout == "symlinked":
        (box / "out").symlink_to(real, target_is_directory=True)
        return box / "out", real
    return real, real


def _prepare_target(box: Path, real_out: Path, name: str, state: str, previous: Path) -> None:
    from anfekf_bench.storage import scenario_name_problem

    target = real_out / name
    if state == "absent" or scenario_name_problem(name) or os.path.lexists(target):
        return  # an unsafe name is refused whatever is there; an existing entry stays as it is
    real_out.mkdir(parents=True, exist_ok=True)
    if state == "result":
        shutil.copytree(previous, target)
    elif state == "foreign":
        (target / "docs").mkdir(parents=True)
        (target / "docs" / "notes.md").write_text("mine")
    elif state == "symlink":
        target.symlink_to(box / "elsewhere", target_is_directory=True)
    elif state == "file":
        target.write_text("a file")
    elif state == "other-seed-runs":
        (target / RUNS_DIR).mkdir(parents=True)
        (target / RUNS_DIR / "fingerprint").write_text("0123456789abcdef\n")
    elif state == "empty":
        target.mkdir()


@pytest.fixture(scope="module")
def tiny_previous(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tiny")
    path = write_scenario(root / "t.yaml", {"name": "prev", **TINY})
    _, target = execute(make_plan(*load_scenario(path), None, None, 1), root / "out")
    return target


@contextlib.contextmanager
def _cwd(path: Path):
    before = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=NAMES, layout=OUT_LAYOUTS, state=TARGET_STATES, force=st.booleans())
def test_nothing_outside_the_scenario_folder_ever_changes(
    tiny_previous, tmp_path_factory, name, layout, state, force
) -> None:
    from anfekf_bench.storage import scenario_name_problem

    box = Path(tempfile.mkdtemp(dir=tmp_path_factory.getbasetemp()))
    out_arg, real_out = _prepare_layout(box, layout)
    _prepare_target(box, real_out, name, state, tiny_previous)
    scenario = box / "s.yaml"
    scenario.write_text(yaml.safe_dump({"name": name, **TINY}), encoding="utf-8")
    # The scenario's own folder, by this test's own reckoning: a direct child of --out.
    child = name not in ("", ".", "..") and "/" not in name and "\0" not in name
    mine = (real_out / name).relative_to(box).as_posix() if child else None
    before = snapshot(box)
    with _cwd(box / "work"):
        result = cli("run", scenario, "--out", out_arg, *(["--force"] if force else []))
    after = snapshot(box)
    assert result.exit_code in (0, EXIT_USAGE), (result.output, result.exception)
    event(f"exit {result.exit_code}")
    assert "Traceback" not in result.output
    if result.exit_code == EXIT_USAGE:
        assert len(result.stderr.splitlines()) == 1, result.stderr
    target_was_symlink = before.get(mine, ("",))[0] == "link" if mine else False

    def inside(rel: str) -> bool:
        return (
            mine is not None
            and not target_was_symlink
            and (rel == mine or rel.startswith(mine + "/"))
        )

    for rel, entry in before.items():
        if not inside(rel):
            assert after.get(rel) == entry, f"{rel} changed ({name!r}, {layout}, {state}, {force})"
    for rel in after.keys() - before.keys():
        # New entries: the scenario folder's own, or the --out folders it had to create.
        creatable = (real_out.relative_to(box).as_posix() + "/").startswith(rel + "/")
        assert inside(rel) or (creatable and after[rel] == ("dir",)), rel
    if result.exit_code == 0:
        assert scenario_name_problem(name) is None
        assert (real_out / name / MANIFEST_FILE).is_file()
