"""The regression gate `anfekf check`: baseline comparison, the paper's claims, exit codes.

Most tests write small synthetic result folders (summary.parquet, summary.json, manifest.json)
with the storage helpers, so they run in milliseconds; one runs a tiny real scenario end to end.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.analysis.gate import DEFAULT_TOLERANCES, Tolerance, judge, shown_metric
from anfekf_bench.cli import app
from anfekf_bench.storage import (
    CLAIMS_FILE,
    MANIFEST_FILE,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    write_json,
    write_parquet,
)

from .conftest import small_scenario, write_scenario

runner = CliRunner()

SEEDS = {"correct": 1001, "wrong_r": 1002, "wrong_q": 1003, "consistency": 1004}


def _metrics(rmse_pos: float, nees_in_bounds: float = 0.9, anees: float = 3.2) -> dict:
    return {
        "rmse_pos": rmse_pos,
        "rmse_heading": 0.012,
        "anees": anees,
        "nees_in_bounds": nees_in_bounds,
        "diverged": 0,
        "anis": 2.1,
        "gate_rejected": 0.001,
    }


def paper_like() -> dict[str, dict[str, dict]]:
    """Four scenarios whose numbers satisfy every claim, like the real reduced CI run."""
    return {
        "correct": {
            "ekf": _metrics(0.206),
            "anfekf": _metrics(0.207),
            "ekf-oracle": _metrics(0.206),
        },
        "wrong_r": {
            "ekf": _metrics(0.418, 0.02, 26.4),
            "anfekf": _metrics(0.207, 0.89, 4.3),
            "ekf-oracle": _metrics(0.197, 0.96, 3.1),
        },
        "wrong_q": {
            "ekf": _metrics(3.34, 0.0, 117.0),
            "anfekf": _metrics(0.225, 0.36, 13.3),
            "ekf-oracle": _metrics(0.197, 0.94, 3.2),
        },
        "consistency": {
            "ekf": _metrics(0.294, 0.46, 4.7),
            "anfekf": _metrics(0.206, 0.87, 3.4),
            "ekf-oracle": _metrics(0.198, 0.92, 3.2),
        },
    }


def claim(text: str, verdict: str, estimate=0.5, lo=0.4, hi=0.6, warning: str = "") -> dict:
    """One claims.json record as `anfekf run` writes it."""
    return {"claim": text, "filter": "anfekf", "vs": "ekf", "metric": "rmse_pos",
            "at_most": 0.6, "at_least": None, "source": "", "runs_used": 20,
            "estimate": estimate, "lo": lo, "hi": hi, "method": "BCa", "verdict": verdict,
            "warning": warning}  # fmt: skip


def write_results(
    root: Path,
    scenarios: dict[str, dict[str, dict]],
    runs: int = 20,
    claims: dict[str, list[dict]] | None = None,
) -> Path:
    """Result folders as `anfekf run` writes them (steps.parquet is a stand-in: never read).

    Each scenario declares one claim that holds unless `claims` says otherwise."""
    for name, filters in scenarios.items():
        folder = root / name
        write_parquet(folder / STEPS_FILE, pd.DataFrame({"scenario": [name]}))
        records = [
            {
                "scenario": name,
                "filter": fname,
                "runs": runs,
                "runs_used": runs - m["diverged"],
                "nees_lo": 2.02,
                "nees_hi": 4.17,
                **m,
            }
            for fname, m in filters.items()
        ]
        write_parquet(folder / SUMMARY_PARQUET, pd.DataFrame(records))
        write_json(folder / SUMMARY_JSON, records)
        stored = (claims or {}).get(name, [claim("anfekf rmse_pos <= 0.6 x ekf", "holds")])
        write_json(folder / CLAIMS_FILE, stored)
        # The scenario declares the claims whose records claims.json holds (check decides them
        # again from the declaration and the interval).
        keys = ("filter", "vs", "metric", "at_most", "at_least")
        declared = [{k: record[k] for k in keys} for record in stored]
        manifest = {"seed": SEEDS.get(name, 7), "runs": runs, "fingerprint": "0" * 16,
                    "scenario": {"name": name, "claims": declared}}  # fmt: skip
        write_json(folder / MANIFEST_FILE, manifest)
    return root


def check(*args: str | Path):
    return runner.invoke(app, ["check", *map(str, args)])


@pytest.fixture
def gate(tmp_path: Path) -> tuple[Path, Path]:
    """(results folder, baseline file written from it by --update)."""
    results = write_results(tmp_path / "res", paper_like())
    baseline = tmp_path / "baselines" / "ci.json"
    done = check(results, "--baseline", baseline, "--update")
    assert done.exit_code == 0, done.output
    return results, baseline


def _fail_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("FAIL ")]


def test_update_writes_a_baseline_that_then_passes(gate):
    results, baseline = gate
    doc = json.loads(baseline.read_text())
    assert doc["tolerances"] == DEFAULT_TOLERANCES
    assert doc["scenarios"]["wrong_r"]["seed"] == 1002 and doc["scenarios"]["wrong_r"]["runs"] == 20
    assert doc["scenarios"]["wrong_r"]["filters"]["anfekf"]["rmse_pos"] == 0.207
    assert doc["rules"], "the verdict rules are written into the file"
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 0, result.output
    assert _fail_lines(result.output) == []
    assert "regression gate passed: 60 metrics within tolerance, 4 claims hold" in result.output


CHANGES = {
    # id: (filter, metric, new value, expected verdict or None when within tolerance)
    "rmse-worse": ("ekf-oracle", "rmse_pos", 0.197 * 1.10, "worse"),
    "rmse-better": ("ekf-oracle", "rmse_pos", 0.197 * 0.90, "better (refresh the baseline)"),
    "rmse-within": ("ekf-oracle", "rmse_pos", 0.197 * 1.02, None),
    "heading-worse": ("ekf-oracle", "rmse_heading", 0.013, "worse"),
    "anees-away-from-3": ("ekf-oracle", "anees", 3.5, "worse"),
    "anees-below-3-is-worse-too": ("ekf-oracle", "anees", 2.5, "worse"),
    "anees-towards-3": ("anfekf", "anees", 3.5, "better (refresh the baseline)"),
    "in-bounds-drop": ("ekf-oracle", "nees_in_bounds", 0.90, "worse"),
    "in-bounds-within": ("ekf-oracle", "nees_in_bounds", 0.94, None),
    "one-more-diverged": ("ekf-oracle", "diverged", 1, "worse"),
    "became-undefined": ("ekf-oracle", "rmse_pos", math.nan, "worse"),
}


@pytest.mark.parametrize("filt, metric, value, verdict", CHANGES.values(), ids=CHANGES.keys())
def test_a_metric_beyond_tolerance_fails_with_its_row(gate, filt, metric, value, verdict):
    results, baseline = gate
    scenarios = paper_like()
    scenarios["wrong_r"][filt][metric] = value
    write_results(results, scenarios)
    result = check(results, "--baseline", baseline)
    fails = _fail_lines(result.output)
    if verdict is None:
        assert result.exit_code == 0, result.output
        assert fails == []
        return
    assert result.exit_code == 1, result.output
    assert len(fails) == 1, fails
    assert fails[0].startswith(f"FAIL wrong_r / {filt} / {shown_metric(metric)}: ")
    assert fails[0].endswith(f": {verdict}")
    assert "tolerance ±" in fails[0]
    assert "regression gate FAILED: 1 of" in result.output
    assert "--update" in result.output, "a failure says how to refresh on purpose"


def test_angles_are_shown_in_degrees_with_their_unit(gate):
    """One angle unit per surface: the check table and its FAIL lines show the heading RMSE in
    degrees, labelled, like every other table (the files keep radians)."""
    results, baseline = gate
    scenarios = paper_like()
    scenarios["wrong_r"]["ekf-oracle"]["rmse_heading"] = 0.013  # rad; the baseline has 0.012
    write_results(results, scenarios)
    result = runner.invoke(app, ["check", str(results), "--baseline", str(baseline)],
                           env={"COLUMNS": "200"})  # fmt: skip
    fails = _fail_lines(result.output)
    assert fails == [
        "FAIL wrong_r / ekf-oracle / rmse_heading [deg]: 0.6875 -> 0.7448 (+8.3 %;"
        " tolerance ±3 % relative): worse"
    ]
    assert "rmse_heading [deg]" in result.output and "rmse_pos [m]" in result.output
    assert re.search(r"rmse_heading \[deg\]\s+│\s+0\.6875\s+│\s+0\.6875", result.output)
    assert not re.search(r"│ rmse_heading\s+│", result.output)  # never a bare (radian) row
    assert json.loads(baseline.read_text())["scenarios"]["wrong_r"]["filters"]["anfekf"][
        "rmse_heading"
    ] == pytest.approx(0.012)  # stored in radians, as summary.parquet


def test_a_missing_filter_fails(gate):
    results, baseline = gate
    scenarios = paper_like()
    del scenarios["wrong_r"]["ekf-oracle"]
    shutil.rmtree(results / "wrong_r")
    write_results(results, scenarios)
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1
    assert _fail_lines(result.output) == [
        "FAIL wrong_r / filter ekf-oracle: in the baseline but not in the results"
    ]


def test_a_missing_scenario_fails(gate):
    results, baseline = gate
    shutil.rmtree(results / "consistency")
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1
    assert _fail_lines(result.output) == [
        "FAIL scenario consistency: in the baseline but not in the results",
    ]


def test_a_scenario_or_filter_the_baseline_does_not_guard_fails(gate):
    results, baseline = gate
    scenarios = paper_like()
    scenarios["correct"]["anfekf-q"] = _metrics(0.29)
    scenarios["extra"] = {"ekf": _metrics(0.3)}
    write_results(results, scenarios)
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1
    assert _fail_lines(result.output) == [
        "FAIL correct / filter anfekf-q: in the results but not guarded by the baseline"
        " (refresh it)",
        "FAIL scenario extra: in the results but not guarded by the baseline (refresh it)",
    ]


def test_other_seed_or_runs_are_not_comparable(gate):
    results, baseline = gate
    write_results(results, paper_like(), runs=12)
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1
    fails = _fail_lines(result.output)
    assert len(fails) == 4
    assert fails[0].startswith("FAIL consistency: results made with runs 12, the baseline with 20")


CLAIM_VERDICTS = {
    # id: (verdict, its interval against at_most 0.6, fails the gate, fails it with --strict)
    "holds": ("holds", (0.5, 0.45, 0.55), False, False),
    "fails": ("fails", (0.7, 0.65, 0.8), True, True),
    "inconclusive": ("inconclusive", (0.6, 0.5, 0.7), False, True),
}


@pytest.mark.parametrize(
    "verdict, interval, fails, fails_strict", CLAIM_VERDICTS.values(), ids=CLAIM_VERDICTS
)
def test_declared_claims_are_checked_even_when_the_baseline_agrees(
    tmp_path, verdict, interval, fails, fails_strict
):
    claims = {"wrong_r": [claim("anfekf rmse_pos <= 0.6 x ekf", verdict, *interval)]}
    results = write_results(tmp_path / "res", paper_like(), claims=claims)
    baseline = tmp_path / "ci.json"
    # The baseline is written from these very results, so every metric row passes.
    written = check(results, "--baseline", baseline, "--update")
    assert baseline.is_file()
    for done, should_fail in (
        (written, fails),
        (check(results, "--baseline", baseline), fails),
        (check(results, "--baseline", baseline, "--strict"), fails_strict),
    ):
        assert done.exit_code == int(should_fail), done.output
        fails_ = _fail_lines(done.output)
        if should_fail:
            shown = f"{interval[0]:g} [{interval[1]:g}, {interval[2]:g}]"
            assert fails_ == [
                f"FAIL claim wrong_r: anfekf rmse_pos <= 0.6 x ekf: {verdict} ({shown})"
            ]
        else:
            assert fails_ == []


def test_without_a_baseline_only_the_claims_are_checked(tmp_path):
    scenarios = {"wrong_r": paper_like()["wrong_r"], "mine": {"ekf": _metrics(1.0)}}
    results = write_results(tmp_path / "res", scenarios, claims={"mine": []})
    result = check(results)
    assert result.exit_code == 0, result.output
    assert "1 claims hold" in result.output
    write_results(results, scenarios, claims={"mine": [], "wrong_r": [claim("anfekf x", "fails")]})
    result = check(results)
    assert result.exit_code == 1
    assert _fail_lines(result.output)[0].startswith("FAIL claim wrong_r: ")


def test_nothing_to_check_is_not_a_pass(tmp_path):
    """No baseline and no claims: the gate says it checked nothing and exits 1."""
    results = write_results(tmp_path / "res", {"mine": {"ekf": _metrics(1.0)}}, claims={"mine": []})
    result = check(results)
    assert result.exit_code == 1
    assert "regression gate checked NOTHING" in result.output
    assert "passed" not in result.output


def test_a_damaged_claims_file_is_unusable_input(tmp_path):
    results = write_results(tmp_path / "res", {"mine": {"ekf": _metrics(1.0)}})
    (results / "mine" / CLAIMS_FILE).write_text('[{"claim": "x", "verdict": "maybe"}]')
    result = check(results)
    assert result.exit_code == 2
    assert "not a claims file written by anfekf run" in result.output


def test_update_keeps_hand_tuned_tolerances_and_follows_the_results(gate):
    results, baseline = gate
    doc = json.loads(baseline.read_text())
    doc["tolerances"] = {"rmse_pos": {"relative": 0.2}, "anis": {"relative": 0.01}}
    baseline.write_text(json.dumps(doc))
    scenarios = paper_like()
    scenarios["wrong_r"]["ekf-oracle"]["rmse_pos"] = 0.197 * 1.10  # inside 20 %
    scenarios["wrong_r"]["ekf-oracle"]["anis"] = 2.2  # outside 1 %: further from 2
    write_results(results, scenarios)
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 1
    assert _fail_lines(result.output) == [
        "FAIL wrong_r / ekf-oracle / anis: 2.1 -> 2.2 (+4.8 %; tolerance ±1 % relative): worse"
    ]
    updated = check(results, "--baseline", baseline, "--update")
    assert updated.exit_code == 0, updated.output
    assert "baseline written to" in updated.output
    assert json.loads(baseline.read_text())["tolerances"] == doc["tolerances"]
    assert check(results, "--baseline", baseline).exit_code == 0


def test_update_shows_what_it_accepts_and_says_what_it_drops(gate):
    results, baseline = gate
    scenarios = paper_like()
    scenarios["wrong_r"]["ekf"]["rmse_pos"] = 0.5
    write_results(results, scenarios)
    shutil.rmtree(results / "consistency")
    result = check(results, "--baseline", baseline, "--update")
    assert result.exit_code == 0, result.output
    assert "worse" in result.output and "missing" in result.output  # the accepted comparison
    assert "dropped from the baseline (not in the results): consistency" in result.output
    doc = json.loads(baseline.read_text())
    assert list(doc["scenarios"]) == ["correct", "wrong_q", "wrong_r"]
    assert doc["scenarios"]["wrong_r"]["filters"]["ekf"]["rmse_pos"] == 0.5


def _edit(doc: dict, path: str, value) -> dict:
    keys = path.split(".")
    node = doc
    for key in keys[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return doc


_DELETE = object()
BAD_BASELINES = {
    # id: (edit of a valid baseline, or raw text; expected fragment of the one-line error)
    "not-json": ("{ nope", "not readable JSON"),
    "a-list": ("[1, 2]", "expected a JSON object"),
    "other-format": (("format", "something else"), "not an anfekf-bench baseline"),
    "unknown-kind": (("tolerances.rmse_pos", {"percent": 5}), "tolerances.rmse_pos: unknown kind"),
    "negative-limit": (("tolerances.anees", {"relative": -0.1}), "tolerances.anees.relative: must"),
    "unknown-metric": (("tolerances.speed", {"relative": 0.1}), "tolerances.speed: unknown metric"),
    "no-scenarios": (("scenarios", {}), "scenarios: expected a mapping"),
    "seed-not-int": (("scenarios.wrong_r.seed", "1002"), "scenarios.wrong_r.seed: must be an"),
    "value-missing": (
        ("scenarios.wrong_r.filters.ekf.rmse_pos", _DELETE),
        "scenarios.wrong_r.filters.ekf: no value for rmse_pos",
    ),
    "value-not-number": (
        ("scenarios.wrong_r.filters.ekf.anees", "high"),
        "scenarios.wrong_r.filters.ekf.anees: must be a finite number or null",
    ),
}


@pytest.mark.parametrize("edit, expected", BAD_BASELINES.values(), ids=BAD_BASELINES.keys())
def test_a_malformed_baseline_is_one_line_and_exit_2(gate, edit, expected):
    results, baseline = gate
    if isinstance(edit, str):
        baseline.write_text(edit)
    else:
        baseline.write_text(json.dumps(_edit(json.loads(baseline.read_text()), *edit)))
    for args in ((), ("--update",)):
        result = check(results, "--baseline", baseline, *args)
        assert result.exit_code == 2, result.output
        err = result.stderr.strip()
        assert len(err.splitlines()) == 1 and err.startswith(f"error: {baseline}: "), err
        assert expected in err, err
        assert "Traceback" not in result.output


def _no_folder(results: Path, baseline: Path) -> tuple[Path, Path]:
    return results / "nowhere", baseline


def _no_manifest(results: Path, baseline: Path) -> tuple[Path, Path]:
    (results / "wrong_r" / MANIFEST_FILE).unlink()
    return results, baseline


def _corrupt_summary(results: Path, baseline: Path) -> tuple[Path, Path]:
    (results / "correct" / SUMMARY_PARQUET).write_bytes(b"not parquet")
    return results, baseline


def _no_baseline(results: Path, baseline: Path) -> tuple[Path, Path]:
    return results, baseline.with_name("none.json")


BAD_INPUTS = {
    "no-results-folder": (_no_folder, "results folder does not exist"),
    "no-manifest": (_no_manifest, "incomplete result"),
    "corrupt-summary": (_corrupt_summary, "not a readable Parquet"),
    "no-baseline-file": (_no_baseline, "baseline file not found"),
}


@pytest.mark.parametrize("breaker, expected", BAD_INPUTS.values(), ids=BAD_INPUTS.keys())
def test_unusable_results_are_one_line_and_exit_2(gate, breaker, expected):
    results, baseline = breaker(*gate)
    result = check(results, "--baseline", baseline)
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and expected in err, err


def test_update_needs_a_baseline_path(gate):
    results, _ = gate
    result = check(results, "--update")
    assert result.exit_code == 2 and "--update needs --baseline" in result.stderr


JUDGEMENTS = {
    # id: (metric, tolerance, baseline, now, verdict)
    "rmse-up": ("rmse_pos", Tolerance("relative", 0.05), 1.0, 1.06, "worse"),
    "rmse-down": (
        "rmse_pos",
        Tolerance("relative", 0.05),
        1.0,
        0.94,
        "better (refresh the baseline)",
    ),
    "rmse-edge-inside": ("rmse_pos", Tolerance("relative", 0.05), 1.0, 1.05, "ok"),
    "anees-crosses-3-further": ("anees", Tolerance("relative", 0.05), 2.9, 3.2, "worse"),
    "anees-crosses-3-closer": (
        "anees",
        Tolerance("relative", 0.05),
        3.6,
        2.8,
        "better (refresh the baseline)",
    ),
    "anees-same-distance": ("anees", Tolerance("relative", 0.05), 2.0, 4.5, "changed"),
    "in-bounds-up": (
        "nees_in_bounds",
        Tolerance("absolute", 0.05),
        0.5,
        0.6,
        "better (refresh the baseline)",
    ),
    "gate-share-has-no-side": ("gate_rejected", Tolerance("absolute", 0.01), 0.1, 0.2, "changed"),
    "diverged-exact": ("diverged", Tolerance("absolute", 0), 0, 0, "ok"),
    "both-undefined": ("rmse_pos", Tolerance("relative", 0.05), math.nan, math.nan, "ok"),
    "defined-again": ("rmse_pos", Tolerance("relative", 0.05), math.nan, 1.0, "changed"),
    "zero-baseline": ("rmse_pos", Tolerance("relative", 0.05), 0.0, 0.1, "worse"),
}


@pytest.mark.parametrize("metric, tol, base, now, verdict", JUDGEMENTS.values(), ids=JUDGEMENTS)
def test_judge(metric, tol, base, now, verdict):
    assert judge(metric, tol, base, now) == verdict


def test_a_real_run_passes_against_its_own_baseline(tmp_path):
    path = write_scenario(tmp_path / "s.yaml", small_scenario(name="wrong_r", runs=2, jobs=1))
    out = tmp_path / "out"
    assert runner.invoke(app, ["run", str(path), "--out", str(out)]).exit_code == 0
    baseline = tmp_path / "b.json"
    written = check(out, "--baseline", baseline, "--update")
    assert written.exit_code == 0, written.output
    doc = json.loads(baseline.read_text())
    assert doc["scenarios"]["wrong_r"]["seed"] == 7 and doc["scenarios"]["wrong_r"]["runs"] == 2
    assert list(doc["scenarios"]["wrong_r"]["filters"]) == ["ekf", "anfekf", "ekf-oracle"]
    result = check(out / "wrong_r", "--baseline", baseline)
    assert result.exit_code == 0, result.output
    assert "0 claims hold" in result.output
