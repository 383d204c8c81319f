"""Hardening (issue 7): bad scenario files, bad output paths, divergence, corrupt results.

Every bad input must end in ONE line `error: <file>: <field>: <what is allowed>` on stderr, exit
code 2 and no traceback; a diverged run is counted and kept out of the means.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from anfekf_bench import runner
from anfekf_bench.analysis import tables
from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.filters import RobotEKF, build_filter
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.sources.simulator import simulate_run, simulate_truth
from anfekf_bench.storage import (
    MANIFEST_FILE,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    ResultsError,
    read_parquet,
    scenario_dirs,
)

from .conftest import small_scenario, write_scenario

EXIT_USAGE = 2


def cli(*args: str):
    """Invoke `anfekf` in-process; stdout and stderr are kept apart."""
    return CliRunner().invoke(app, list(args))


def assert_one_line_error(result, *fragments: str) -> str:
    """Exit 2, exactly one stderr line `error: ...` holding every fragment, no traceback."""
    assert result.exit_code == EXIT_USAGE, (result.exit_code, result.output, result.exception)
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    line = lines[0]
    assert line.startswith("error: "), line
    for fragment in fragments:
        assert fragment in line, (fragment, line)
    assert "Traceback" not in result.output
    return line


# --- Scenario files ----------------------------------------------------------------------------

OK = small_scenario()


def _doc(**overrides) -> str:
    return yaml.safe_dump(small_scenario(**overrides), sort_keys=False)


def _world(**overrides) -> str:
    return _doc(world={**OK["world"], **overrides})


# id -> (scenario text or None for "do not create", extra files {name: text}, field, fragments)
BAD_SCENARIOS = {
    "yaml-syntax": ("name: x\nruns: [1,\n", {}, "", ["YAML syntax error", "line 3"]),
    "yaml-tab-indent": ("name: x\n\truns: 2\n", {}, "", ["YAML syntax error", "line 2"]),
    "empty-file": ("", {}, "", ["empty file", "mapping"]),
    "only-comments": ("# nothing here\n", {}, "", ["empty file"]),
    "list-not-mapping": ("- name: x\n- runs: 2\n", {}, "", ["found a list", "mapping"]),
    "scalar-not-mapping": ("just text\n", {}, "", ["found a str", "mapping"]),
    "unknown-key": (_doc(colour="red"), {}, "colour", ["unknown key", "allowed:", "runs"]),
    "unknown-key-with-newline": (
        _doc(**{"bad\nkey": 1}),
        {},
        "bad\\nkey",
        ["unknown key"],
    ),
    "unknown-nested-key": (_world(colour="red"), {}, "world.colour", ["unknown key", "loops"]),
    "unknown-filter-key": (
        _doc(filters=[{"name": "a", "kind": "anfekf", "windw": 5}]),
        {},
        "filters.0.windw",
        ["unknown key", "window"],
    ),
    "wrong-type-text": (_doc(runs="many"), {}, "runs", ["valid integer", "'many'"]),
    "wrong-type-bool": (_doc(runs=True), {}, "runs", ["not true/false"]),
    "wrong-type-mapping": (_doc(world=3), {}, "world", ["dictionary"]),
    "wrong-type-filters": (_doc(filters={"a": 1}), {}, "filters", ["valid list"]),
    "fraction-runs": (_doc(runs=2.5), {}, "runs", ["fractional"]),
    "zero-sigma": (_doc(true_noise={"sigma_v": 0}), {}, "true_noise.sigma_v", ["greater than 0"]),
    "negative-sigma": (
        _doc(filter_noise={"sigma_bearing_deg": -1.0}),
        {},
        "filter_noise.sigma_bearing_deg",
        ["greater than 0", "-1.0"],
    ),
    "nan-sigma": (
        "name: x\ntrue_noise: {sigma_range: .nan}\n",
        {},
        "true_noise.sigma_range",
        ["finite"],
    ),
    "runs-zero": (_doc(runs=0), {}, "runs", ["greater than or equal to 1"]),
    "runs-negative": (_doc(runs=-3), {}, "runs", ["greater than or equal to 1"]),
    "jobs-zero": (_doc(jobs=0), {}, "jobs", ["greater than or equal to 1"]),
    "waypoints-empty-inline": (_world(waypoints=[]), {}, "world.waypoints", ["at least one"]),
    "waypoints-empty-csv": (
        _world(waypoints="route.csv"),
        {"route.csv": "# x,y\n"},
        "world.waypoints",
        ["route.csv", "no points"],
    ),
    "waypoints-csv-bad-row": (
        _world(waypoints="route.csv"),
        {"route.csv": "20,0\nforty,8\n"},
        "world.waypoints",
        ["route.csv", "line 2", "x,y"],  # names the line, never quotes the file's content
    ),
    "waypoints-csv-3-columns": (
        _world(waypoints="route.csv"),
        {"route.csv": "20,0,1\n40,8,1\n"},
        "world.waypoints",
        ["route.csv", "2 columns"],
    ),
    "waypoints-malformed-inline": (
        _world(waypoints=[[20, 0, 5]]),
        {},
        "world.waypoints",
        ["list of [x, y]"],
    ),
    "landmarks-csv-missing": (
        _world(landmarks="nowhere.csv"),
        {},
        "world.landmarks",
        ["nowhere.csv", "not found"],
    ),
    "landmarks-csv-malformed": (
        _world(landmarks="map.csv"),
        {"map.csv": "10,8\n25\n"},
        "world.landmarks",
        ["map.csv", "x,y"],
    ),
    "landmarks-csv-infinite": (
        _world(landmarks="map.csv"),
        {"map.csv": "10,8\ninf,3\n"},
        "world.landmarks",
        ["map.csv", "finite"],
    ),
    "duplicate-filter-names": (
        _doc(filters=[{"name": "a", "kind": "ekf"}, {"name": "a", "kind": "anfekf"}]),
        {},
        "filters",
        ["unique", "repeated: a"],
    ),
    "unknown-filter-kind": (
        _doc(filters=[{"name": "u", "kind": "ukf"}]),
        {},
        "filters.0",
        ["'ukf'", "'anfekf'"],
    ),
    "bad-name": (_doc(name="a b/c"), {}, "name", ["letters, digits"]),
    "not-utf8": (None, {}, "", ["cannot read"]),
    "does-not-exist": (None, {}, "", ["does not exist"]),
}


def _write_case(case: str, tmp_path: Path) -> Path:
    text, files, _, _ = BAD_SCENARIOS[case]
    path = tmp_path / "scenario.yaml"
    for name, content in files.items():
        (tmp_path / name).write_text(content, encoding="utf-8")
    if case == "not-utf8":
        path.write_bytes(b"name: \xff\xfe\n")
    elif text is not None:
        path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("case", list(BAD_SCENARIOS))
def test_bad_scenario_is_one_clean_line(case: str, tmp_path: Path) -> None:
    path = _write_case(case, tmp_path)
    _, _, field, fragments = BAD_SCENARIOS[case]
    out = tmp_path / "out"
    result = cli("run", str(path), "--out", str(out))
    named = f"{path}: {field}: " if field else f"{path}: "
    assert_one_line_error(result, named, *fragments)
    assert not out.exists(), "nothing is written for a bad scenario"


@pytest.mark.parametrize("case", ["yaml-syntax", "unknown-key", "waypoints-empty-csv"])
def test_loader_raises_the_same_message(case: str, tmp_path: Path) -> None:
    path = _write_case(case, tmp_path)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    line = assert_one_line_error(cli("run", str(path), "--out", str(tmp_path / "o")))
    assert line == f"error: {info.value}"
    assert "\n" not in str(info.value)


def test_debug_shows_the_exception(tmp_path: Path) -> None:
    path = _write_case("unknown-key", tmp_path)
    result = cli("run", str(path), "--out", str(tmp_path / "out"), "--debug")
    assert result.exit_code not in (0, EXIT_USAGE)
    assert isinstance(result.exception, ScenarioError)
    assert result.exception.field == "colour"


def _anfekf_process(*args: str) -> subprocess.CompletedProcess:
    code = "from anfekf_bench.cli import main; main()"
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120
    )


def test_real_process_prints_one_line(tmp_path: Path) -> None:
    """Outside CliRunner too: nothing else (warnings, tracebacks) reaches stderr."""
    path = _write_case("waypoints-empty-csv", tmp_path)
    plain = _anfekf_process("run", str(path), "--out", str(tmp_path / "out"))
    assert plain.returncode == EXIT_USAGE
    assert plain.stderr.count("\n") == 1 and plain.stderr.startswith("error: "), plain.stderr
    assert "world.waypoints" in plain.stderr


def test_folder_with_one_bad_scenario_runs_nothing(tmp_path: Path) -> None:
    write_scenario(tmp_path / "a.yaml", small_scenario(name="a"))
    (tmp_path / "b.yaml").write_text("name: b\nruns: 0\n", encoding="utf-8")
    out = tmp_path / "out"
    assert_one_line_error(cli("run", str(tmp_path), "--out", str(out)), "b.yaml: runs: ")
    assert not out.exists()


@pytest.mark.parametrize("flag", ["--runs", "--jobs"])
@pytest.mark.parametrize("value", ["0", "-1", "two"])
def test_bad_count_flags_are_rejected(flag: str, value: str, small_yaml: Path) -> None:
    """Exit 2, names the option, no traceback; a number out of range gets our one-line error,
    a word typer's own usage error."""
    result = cli("run", str(small_yaml), flag, value, "--out", str(small_yaml.parent / "out"))
    assert result.exit_code == EXIT_USAGE
    if value == "two":
        assert f"Invalid value for '{flag}'" in result.output
    else:
        assert result.stderr.strip() == f"error: {flag}: must be an integer >= 1 (got {value})"
    assert "Traceback" not in result.output
    assert not (small_yaml.parent / "out").exists()


# --- Output paths ------------------------------------------------------------------------------


def test_out_is_a_file(small_yaml: Path) -> None:
    out = small_yaml.parent / "results.txt"
    out.write_text("not a folder")
    assert_one_line_error(cli("run", str(small_yaml), "--out", str(out)), str(out), "--out")
    assert out.read_text() == "not a folder"


def test_out_below_a_file_cannot_be_created(small_yaml: Path) -> None:
    """As root nothing is unwritable by permission; a path below a file is, for anyone."""
    blocker = small_yaml.parent / "somefile"
    blocker.write_text("x")
    out = blocker / "sub"
    assert_one_line_error(cli("run", str(small_yaml), "--out", str(out)), str(out), "--out")


def test_scenario_folder_name_taken_by_a_file(small_yaml: Path) -> None:
    out = small_yaml.parent / "out"
    out.mkdir()
    (out / "small").write_text("in the way")
    assert_one_line_error(cli("run", str(small_yaml), "--out", str(out)), "small", "not a folder")


# --- Hypothesis: any document loads or fails with ScenarioError --------------------------------

KNOWN_KEYS = sorted(
    {
        *OK,
        *OK["world"],
        "sigma_v",
        "sigma_range",
        "kind",
        "adapt",
        "window",
        "x0",
        "p0",
        "gate_probability",
        "description",
    }
)
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**20), max_value=10**20),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["bailey-webmap", "ekf", "anfekf", "ekf-oracle", "R", "Q", "x.csv", ""]),
)
keys = st.one_of(
    st.sampled_from([*KNOWN_KEYS, "a\nb", "\r", "\t\x00"]), st.text(max_size=8), st.integers(-3, 3)
)
documents = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(keys, inner, max_size=5)),
    max_leaves=20,
)


def _paths(doc, prefix=()):
    """Every (key path) inside nested dicts and lists of a document."""
    if isinstance(doc, dict):
        items = doc.items()
    elif isinstance(doc, list):
        items = enumerate(doc)
    else:
        return
    for key, value in items:
        yield (*prefix, key)
        yield from _paths(value, (*prefix, key))


@st.composite
def mutated_scenarios(draw):
    """A valid scenario with one to three edits: a value replaced, a key dropped or added."""
    doc = json.loads(json.dumps(small_scenario()))
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(doc))
        path = draw(st.sampled_from(paths))
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["replace", "drop", "add", "negate"]))
        if action == "replace":
            parent[path[-1]] = draw(documents)
        elif action == "drop":
            del parent[path[-1]]
        elif action == "add" and isinstance(parent, dict):
            parent[draw(keys)] = draw(documents)
        elif action == "negate" and isinstance(parent[path[-1]], (int, float)):
            parent[path[-1]] = -parent[path[-1]]
    return doc


yaml_texts = st.one_of(
    documents.map(lambda d: yaml.safe_dump(d, allow_unicode=True)),
    mutated_scenarios().map(lambda d: yaml.safe_dump(d, allow_unicode=True)),
    st.text(alphabet=st.sampled_from(list("name: runs\n-[]{},'\"#&*!|>?%@`\t 0.1e")), max_size=60),
)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    """One folder for every generated document (module scope: hypothesis reuses it)."""
    return tmp_path_factory.mktemp("hypothesis")


def _load_or_error(text: str, folder: Path) -> ScenarioError | None:
    path = folder / "scenario.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        load_scenario(path)
    except ScenarioError as exc:
        message = str(exc)
        assert message.startswith(f"{path}: ") and "\n" not in message, message
        return exc
    return None


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(yaml_texts)
def test_any_document_loads_or_fails_cleanly(scratch: Path, text: str) -> None:
    _load_or_error(text, scratch)  # any other exception fails the test


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated_scenarios())
def test_cli_error_line_equals_loader_error(scratch: Path, doc) -> None:
    """Through the command line (only for documents that fail: no simulation is run)."""
    text = yaml.safe_dump(doc, allow_unicode=True)
    error = _load_or_error(text, scratch)
    assume(error is not None)
    result = cli("run", str(scratch / "scenario.yaml"), "--out", str(scratch / "out"))
    assert assert_one_line_error(result) == f"error: {error}"


# --- Divergence --------------------------------------------------------------------------------


class PoisonedEKF(RobotEKF):
    """An EKF that breaks in a chosen way at its `after`-th landmark update."""

    mode = "nan-P"
    after = 30

    def update_landmark(self, z, landmark):
        accepted = super().update_landmark(z, landmark)
        self.poison_count = getattr(self, "poison_count", 0) + 1
        if self.poison_count == self.after:
            if self.mode == "nan-P":
                self.P[0, 0] = np.nan
            elif self.mode == "inf-x":
                self.x[1] = np.inf
            elif self.mode == "indefinite-P":
                self.P = self.P - 10.0 * np.eye(3)  # finite and symmetric, not PD
            elif self.mode == "singular-solve":
                raise np.linalg.LinAlgError("Singular matrix")
            elif self.mode == "zero-R":
                self.R = np.zeros((2, 2))
        return accepted


class LateNaNEKF(RobotEKF):
    """NaN in a prediction after the last scan: only the end-of-run check can see it."""

    def predict(self, u=0, dt=None):
        super().predict(u, dt)
        self.n_predict = getattr(self, "n_predict", 0) + 1
        if self.n_predict == self.last_step:
            self.x = np.full(3, np.nan)


def _poisoned(flt: RobotEKF, cls: type, **attrs) -> RobotEKF:
    flt.__class__ = cls
    for name, value in attrs.items():
        setattr(flt, name, value)
    return flt


@pytest.fixture(scope="module")
def small_run():
    """One simulated run on the small world: (scenario, world, data)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = write_scenario(Path(tmp) / "s.yaml", small_scenario(record_every=8))
        scenario, world = load_scenario(path)
    truth = simulate_truth(world)
    data = simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(3))
    return scenario, world, data


def _fresh_ekf(scenario, world) -> RobotEKF:
    return build_filter(scenario.filters[0], scenario, world)


@pytest.mark.parametrize("mode", ["nan-P", "inf-x", "indefinite-P", "singular-solve", "zero-R"])
def test_run_filter_marks_divergence(mode: str, small_run) -> None:
    scenario, world, data = small_run
    flt = _poisoned(_fresh_ekf(scenario, world), PoisonedEKF, mode=mode, after=30)
    trace = runner.run_filter(flt, data, world, record_every=8)
    assert trace["diverged"] is True
    assert np.isnan(trace["x"][-1]).all() and np.isnan(trace["P"][-1]).all()


def test_blow_up_after_the_last_scan_is_caught(small_run) -> None:
    scenario, world, data = small_run
    K = len(data.u_odo)
    last = K if K % world.sensor_every else K - 1  # a step without a scan (no health check)
    flt = _poisoned(_fresh_ekf(scenario, world), LateNaNEKF, last_step=last)
    assert runner.run_filter(flt, data, world, record_every=1)["diverged"] is True


def test_healthy_run_is_not_diverged(small_run) -> None:
    scenario, world, data = small_run
    trace = runner.run_filter(_fresh_ekf(scenario, world), data, world, record_every=8)
    assert trace["diverged"] is False
    assert np.isfinite(trace["x"]).all()


@pytest.mark.parametrize("kind", ["ekf", "anfekf-R", "anfekf-Q"])
def test_covariance_stays_symmetric_and_positive_definite(kind: str, small_run) -> None:
    scenario, world, data = small_run
    spec = {"ekf": scenario.filters[0], "anfekf-R": scenario.filters[1]}.get(kind)
    if spec is None:
        spec = scenario.filters[1].model_copy(update={"adapt": "Q"})
    flt = build_filter(spec, scenario, world)
    update = flt.update_landmark
    checked = []

    def checked_update(z, landmark):
        accepted = update(z, landmark)
        if accepted:  # a gated-out measurement leaves P as the prediction made it
            assert np.array_equal(flt.P, flt.P.T), "P exactly symmetric after every update"
        checked.append(accepted)
        return accepted

    flt.update_landmark = checked_update
    trace = runner.run_filter(flt, data, world, record_every=1)
    assert trace["diverged"] is False
    assert sum(checked) > 50, "the run fused measurements"
    P = trace["P"]
    assert np.allclose(P, np.swapaxes(P, 1, 2), rtol=1e-12, atol=0), "symmetric at every step"
    assert (np.linalg.eigvalsh(P) > 0).all(), "P positive definite at every step"


@pytest.fixture
def one_run_diverges(monkeypatch):
    """Filter `ekf` diverges in run 2 only (jobs 1: runs in order, in this process)."""
    real_run = runner.run_filter
    calls = {"n": 0}
    n_filters = len(small_scenario()["filters"])  # ekf first: runner runs them in order

    def run(flt, *args):
        calls["n"] += 1
        if calls["n"] == 2 * n_filters + 1:  # run 2's ekf
            flt = _poisoned(flt, PoisonedEKF, mode="nan-P", after=20)
        return real_run(flt, *args)

    monkeypatch.setattr(runner, "run_filter", run)
    return 2


def test_diverged_run_is_counted_and_kept_out_of_the_means(one_run_diverges, tmp_path) -> None:
    bad = one_run_diverges
    doc = small_scenario(runs=5, record_every=8)
    path = write_scenario(tmp_path / "s.yaml", doc)
    plan = make_plan(*load_scenario(path), None, None, 1)
    records, target = execute(plan, tmp_path / "out")

    steps = pd.read_parquet(target / STEPS_FILE)
    div = steps.groupby(["filter", "run"], observed=True)["diverged"].agg(["all", "any"])
    assert (div["all"] == div["any"]).all(), "one value per (filter, run)"
    flagged = sorted(map(tuple, div.index[div["all"]].tolist()))
    assert flagged == [("ekf", bad)]

    summary = {r["filter"]: r for r in json.loads((target / SUMMARY_JSON).read_text())}
    assert summary["ekf"]["diverged"] == 1 and summary["ekf"]["runs_used"] == 4
    assert summary["anfekf"]["diverged"] == 0 and summary["anfekf"]["runs_used"] == 5
    assert pd.read_parquet(target / SUMMARY_PARQUET).set_index("filter").loc["ekf", "diverged"] == 1

    # The means are the means over the healthy runs: as if run 2 had never been there.
    healthy = steps[~((steps["filter"] == "ekf") & (steps["run"] == bad))].copy()
    ekf_healthy = tables.summary_records(healthy[healthy["filter"] == "ekf"].copy())[0]
    for key in ("rmse_pos", "rmse_heading", "anees", "nees_in_bounds"):
        assert math.isfinite(summary["ekf"][key]), key
        assert summary["ekf"][key] == pytest.approx(ekf_healthy[key], rel=1e-12), key
    assert {r["filter"]: r["diverged"] for r in records} == {
        "ekf": 1,
        "anfekf": 0,
        "ekf-oracle": 0,
    }

    # report.md shows the count as runs used / runs.
    report = cli("report", str(target.parent), "--out", str(tmp_path / "report"))
    assert report.exit_code == 0, report.output
    md = (tmp_path / "report" / "report.md").read_text(encoding="utf-8")
    rows = {line.split("|")[2].strip(): line for line in md.splitlines() if line.startswith("| s")}
    assert "| 4/5 |" in rows["ekf"] and "| 5/5 |" in rows["anfekf"]


def test_cli_table_shows_the_diverged_count(one_run_diverges, tmp_path) -> None:
    path = write_scenario(tmp_path / "s.yaml", small_scenario(runs=3, record_every=8))
    result = cli("run", str(path), "--out", str(tmp_path / "out"), "--jobs", "1")
    assert result.exit_code == 0, result.output
    rows = [
        [cell.strip() for cell in line.replace("┃", "│").split("│")[1:-1]]
        for line in result.stdout.splitlines()
        if line.count("│") + line.count("┃") >= 3
    ]
    header = next(row for row in rows if "diverged" in row)
    by_filter: dict[str, list[str]] = {}
    for row in rows:  # the summary table comes first (other tables follow it)
        by_filter.setdefault(row[0], row)
    column = header.index("diverged")
    assert by_filter["ekf"][column] == "1"
    assert by_filter["anfekf"][column] == "0"
    assert by_filter["ekf"][header.index("inconsistent")] == "0"


# --- Saved results that are corrupt, truncated or incomplete -----------------------------------


@pytest.fixture(scope="module")
def finished_result(tmp_path_factory) -> Path:
    """A complete tiny result folder (2 runs), made once; tests copy it before damaging it."""
    root = tmp_path_factory.mktemp("finished")
    path = write_scenario(root / "s.yaml", small_scenario(runs=2, record_every=8))
    plan = make_plan(*load_scenario(path), None, None, 1)
    _, target = execute(plan, root / "results")
    return target


def _damaged_copy(finished: Path, tmp_path: Path, name: str, how: str) -> Path:
    import shutil

    results = tmp_path / "results"
    shutil.copytree(finished.parent, results)
    victim = results / finished.name / name
    data = victim.read_bytes()
    if how == "truncated":
        victim.write_bytes(data[: len(data) // 2])
    elif how == "garbage":
        victim.write_bytes(b"this is not parquet\n" * 10)
    elif how == "empty":
        victim.write_bytes(b"")
    elif how == "missing":
        victim.unlink()
    return results


DAMAGE = [
    (name, how)
    for name in (STEPS_FILE, SUMMARY_PARQUET)
    for how in ("truncated", "garbage", "empty", "missing")
]


@pytest.mark.parametrize(("name", "how"), DAMAGE, ids=[f"{n}-{h}" for n, h in DAMAGE])
def test_read_parquet_raises_results_error(finished_result, tmp_path, name, how) -> None:
    results = _damaged_copy(finished_result, tmp_path, name, how)
    with pytest.raises(ResultsError) as info:
        read_parquet(results / finished_result.name / name)
    assert name in str(info.value) and "\n" not in str(info.value)


# Each command on every damaged file (both refuse a folder holding a corrupt Parquet file), and
# on the missing file it needs (report reads steps.parquet, check reads summary.parquet).
COMMAND_DAMAGE = [
    (command, name, how)
    for command in ("report", "check")
    for name, how in DAMAGE
    if how != "missing" or (command, name) in {("report", STEPS_FILE), ("check", SUMMARY_PARQUET)}
]


@pytest.mark.parametrize(
    ("command", "name", "how"), COMMAND_DAMAGE, ids=["-".join(c) for c in COMMAND_DAMAGE]
)
def test_report_and_check_on_damaged_parquet(finished_result, tmp_path, command, name, how):
    results = _damaged_copy(finished_result, tmp_path, name, how)
    args = [command, str(results)]
    if command == "report":
        args += ["--out", str(tmp_path / "report")]
    result = cli(*args)
    assert_one_line_error(result, name)
    assert not (tmp_path / "report" / "report.md").exists()


@pytest.mark.parametrize("command", ["report", "check"])
def test_report_and_check_refuse_an_incomplete_result(finished_result, tmp_path, command):
    """Without manifest.json (written last) a folder is an interrupted run, not a result."""
    results = _damaged_copy(finished_result, tmp_path, MANIFEST_FILE, "missing")
    with pytest.raises(ResultsError, match="incomplete"):
        scenario_dirs(results)
    args = [command, str(results)]
    if command == "report":
        args += ["--out", str(tmp_path / "report")]
    assert_one_line_error(cli(*args), "incomplete", "anfekf run")
