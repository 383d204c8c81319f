"""The report's one loader of results (report/results.py, issue 33): every kind of result folder
loads into one `LoadedResult` (its kind, its tables, its manifest, its filters and their roles);
a folder without a table its kind needs is a one-line error naming the file."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from anfekf_bench.problems.experiment import PROBLEM_FORMAT
from anfekf_bench.problems.experiment import TABLES as PROBLEM_TABLES
from anfekf_bench.report.results import (
    PROBLEM,
    RECORDED,
    SIMULATED,
    SWEEP,
    find_results,
    load_result,
)
from anfekf_bench.storage import (
    CLAIMS_FILE,
    COMPARISONS_FILE,
    RESULT_FORMAT,
    RUNS_FILE,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    SWEEP_FILE,
    SWEEP_KIND,
    ResultsError,
    write_json,
    write_parquet,
)

BATCH = {"seed": "3", "fingerprint": "f" * 16}
TABLE = pd.DataFrame({"filter": ["ekf"], "value": [1.0]})


def _folder(root: Path, name: str, manifest: dict, tables: tuple[str, ...]) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    for table in tables:
        if table.endswith(".json"):
            write_json(folder / table, [])
        else:
            write_parquet(folder / table, TABLE, BATCH)
    write_json(folder / "manifest.json", manifest)
    return folder


SIMULATED_TABLES = (STEPS_FILE, RUNS_FILE, SUMMARY_PARQUET, COMPARISONS_FILE, CLAIMS_FILE)
RECORDED_TABLES = (STEPS_FILE, RUNS_FILE, SUMMARY_PARQUET, SUMMARY_JSON, COMPARISONS_FILE)


def simulated(root: Path, tables=SIMULATED_TABLES, **scenario) -> Path:
    filters = [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-oracle", "kind": "ekf-oracle"},
               {"name": "anfekf", "kind": "anfekf"}]  # fmt: skip
    manifest = {"format": RESULT_FORMAT, "seed": 3, "fingerprint": "f" * 16,
                "scenario": {"name": "sim", "filters": filters, **scenario}}  # fmt: skip
    return _folder(root, "sim", manifest, tables)


def recorded(root: Path, protocol: str, tables=RECORDED_TABLES) -> Path:
    instances = [
        {"name": "ekf x1", "base": "ekf", "kind": "ekf", "start": 1.0},
        {"name": "ekf-tuned", "base": "ekf-tuned", "kind": "ekf-tuned", "start": None},
        {"name": "sage-husa x4", "base": "sage-husa", "kind": "sage-husa", "start": 4},
    ]
    manifest = {
        "format": RESULT_FORMAT,
        "kind": "recorded",
        "protocol": protocol,
        "seed": 3,
        "fingerprint": "f" * 16,
        "filters": instances,
        "scenario": {"name": protocol, "filters": [{"name": "ekf", "kind": "ekf"}]},
    }
    return _folder(root, protocol, manifest, tables)  # fmt: skip


def sweep(root: Path) -> Path:
    manifest = {"kind": SWEEP_KIND, "name": "sw", "runs": 2, "axes": []}
    return _folder(root, "sw", manifest, (SWEEP_FILE,))


def problem(root: Path) -> Path:
    manifest = {"format": PROBLEM_FORMAT, "scenario": {"name": "lin", "filters": [
        {"name": "kf", "kind": "ekf"}]}}  # fmt: skip
    return _folder(root, "lin", manifest, tuple(PROBLEM_TABLES.values()))


def test_each_kind_of_result_loads(tmp_path):
    sim = load_result(simulated(tmp_path))
    assert sim.kind == SIMULATED and sim.name == "sim" and sim.protocol is None
    assert sim.tables == (STEPS_FILE, RUNS_FILE, SUMMARY_PARQUET, COMPARISONS_FILE, CLAIMS_FILE)
    assert sim.roles() == {"ekf": "reference", "ekf-oracle": "oracle", "anfekf": "adaptive"}
    assert list(sim.read(SUMMARY_PARQUET)["filter"]) == ["ekf"]
    for protocol in ("segments", "drives"):
        rec = load_result(recorded(tmp_path, protocol))
        assert rec.kind == RECORDED and rec.protocol == protocol and rec.name == protocol
        # the instances, as the tables name them, with the filter each was made from
        assert [(f.name, f.base, f.start, f.role) for f in rec.filters] == [
            ("ekf x1", "ekf", 1.0, "reference"), ("ekf-tuned", "ekf-tuned", None, "fitted"),
            ("sage-husa x4", "sage-husa", 4.0, "adaptive")]  # fmt: skip
        assert rec.read(SUMMARY_JSON) == []
    sw = load_result(sweep(tmp_path))
    assert sw.kind == SWEEP and sw.name == "sw" and sw.tables == (SWEEP_FILE,)
    pr = load_result(problem(tmp_path))
    assert pr.kind == PROBLEM and pr.name == "lin" and pr.has("problem_noise.parquet")


def test_find_results_lists_every_kind_under_a_parent(tmp_path):
    simulated(tmp_path)
    recorded(tmp_path, "drives")
    sweep(tmp_path)
    problem(tmp_path)
    found = find_results([tmp_path])
    assert [(r.kind, r.folder.name) for r in found] == [
        ("recorded", "drives"),
        ("simulated", "sim"),
        ("sweep", "sw"),
        ("problem", "lin"),
    ]
    # the report folder is left out
    assert [r.folder.name for r in find_results([tmp_path], out_dir=tmp_path / "sim")] == [
        "drives", "sw", "lin"]  # fmt: skip


@pytest.mark.parametrize(
    "make, missing",
    [
        (lambda root: simulated(root, tables=(SUMMARY_PARQUET,), steps_table=False), None),
        (lambda root: recorded(root, "segments", tables=(STEPS_FILE, SUMMARY_JSON)),
         COMPARISONS_FILE),
        (lambda root: recorded(root, "drives", tables=(STEPS_FILE, COMPARISONS_FILE)),
         SUMMARY_JSON),
        (lambda root: _folder(root, "sw", {"kind": SWEEP_KIND}, ()), SWEEP_FILE),
        (lambda root: _folder(root, "lin", {"format": PROBLEM_FORMAT},
                              (PROBLEM_TABLES["summary"],)), PROBLEM_TABLES["runs"]),
    ],
)  # fmt: skip
def test_a_missing_table_is_one_line_naming_it(tmp_path, make, missing):
    folder = make(tmp_path)
    if missing is None:  # steps_table: false, summary.parquet present: it loads
        assert load_result(folder).tables == (SUMMARY_PARQUET,)
        return
    with pytest.raises(ResultsError) as err:
        load_result(folder)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{folder / missing}: missing")


def test_a_damaged_simulated_result_says_steps_are_missing(tmp_path):
    folder = simulated(tmp_path, tables=(SUMMARY_PARQUET,))
    with pytest.raises(ResultsError, match=r"steps.parquet: missing, though .* says the scenario"):
        load_result(folder)


def test_a_folder_without_a_manifest_is_one_line(tmp_path):
    (tmp_path / "half").mkdir()
    with pytest.raises(ResultsError, match="incomplete result"):
        load_result(tmp_path / "half")


def test_a_table_of_another_batch_is_refused_on_read(tmp_path):
    folder = simulated(tmp_path)
    write_parquet(folder / RUNS_FILE, TABLE, {"seed": "4", "fingerprint": "f" * 16})
    result = load_result(folder)
    with pytest.raises(ResultsError, match="different batches"):
        result.read(SUMMARY_PARQUET)
    with pytest.raises(ResultsError, match="phases.parquet: missing"):
        result.read("phases.parquet")


def _steps_of_a_batch(runs: int = 3, steps: int = 4) -> pd.DataFrame:
    rows = [
        {"scenario": "s", "filter": f, "run": r, "step": 8 * (k + 1)}
        for f in ("ekf", "anfekf") for r in range(runs) for k in range(steps)
    ]  # fmt: skip
    df = pd.DataFrame(rows)
    df["filter"] = pd.Categorical(df["filter"], categories=["ekf", "anfekf"])
    return df


@pytest.mark.parametrize("shuffled", [False, True])
def test_a_batch_table_passes_the_saved_result_checks_in_any_row_order(tmp_path, shuffled):
    from anfekf_bench.report.consistency import check_saved_result

    manifest = {"scenario": {"name": "s"}, "runs": 3, "filters": [{"name": "ekf"}]}
    steps = _steps_of_a_batch()
    if shuffled:  # not as a batch writes it: the check sorts before comparing the steps
        steps = steps.sample(frac=1.0, random_state=3).reset_index(drop=True)
    check_saved_result(tmp_path, steps, manifest)
    ragged = steps.copy()
    ragged.loc[(ragged["run"] == 2) & (ragged["filter"] == "anfekf"), "step"] += 1
    with pytest.raises(ResultsError, match="recorded at different steps"):
        check_saved_result(tmp_path, ragged, manifest)
    one = (steps["filter"] == "ekf") & (steps["run"] == 1) & (steps["step"] == 16)
    dup = pd.concat([steps, steps[one]], ignore_index=True)
    with pytest.raises(ResultsError, match=r"duplicated rows \(filter 'ekf', run 1, step 16"):
        check_saved_result(tmp_path, dup, manifest)
    # the repeated row next to its twin (a table otherwise in the order a batch writes)
    beside = pd.concat([steps, steps[one]]).sort_index(kind="stable").reset_index(drop=True)
    with pytest.raises(ResultsError, match=r"duplicated rows \(filter 'ekf', run 1, step 16"):
        check_saved_result(tmp_path, beside, manifest)
