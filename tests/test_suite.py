"""The worst case over a suite of scenarios (analysis/suite.py, report/suite.py): ratios, worst
and geometric mean with intervals, NEES shares, lost lock and inconsistent runs on hand-made
arrays whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from anfekf_bench.analysis.metrics import nees_bounds
from anfekf_bench.analysis.suite import LOST_LOCK_M, FilterRuns, SuiteScenario, suite_table

RUNS, STEPS = 20, 30
rng = np.random.default_rng(5)


def _runs(scale=1.0, nees=3.0, diverged=None, err=None) -> FilterRuns:
    e = np.abs(rng.normal(0.1, 0.03, size=(RUNS, STEPS))) if err is None else err
    return FilterRuns(
        pos_err=scale * e,
        nees=np.full((RUNS, STEPS), nees),
        diverged=np.zeros(RUNS, bool) if diverged is None else diverged,
    )


def _scenario(name, filters: dict, changing=False) -> SuiteScenario:
    base = np.abs(rng.normal(0.1, 0.03, size=(RUNS, STEPS)))
    made = {"oracle": _runs(err=base)}
    for fname, scale in filters.items():
        made[fname] = scale if isinstance(scale, FilterRuns) else _runs(scale, err=base)
    return SuiteScenario(name, "oracle", changing, made, {n: n for n in made})


def test_worst_and_geometric_mean_of_known_ratios():
    suite = [
        _scenario("a", {"good": 1.0, "bad": 2.0}),
        _scenario("b", {"good": 1.1, "bad": 1.0}),
    ]
    df = suite_table(suite, resamples=200).set_index("filter")
    assert list(df.index) == ["good", "bad"]  # sorted by the worst case
    assert df.loc["bad", "worst"] == pytest.approx(2.0)
    assert df.loc["bad", "worst_scenario"] == "a"
    assert df.loc["bad", "geomean"] == pytest.approx(math.sqrt(2.0))
    assert df.loc["good", "worst"] == pytest.approx(1.1)
    assert df.loc["good", "geomean"] == pytest.approx(math.sqrt(1.1))
    # a constant per-run ratio on the same runs: every resample gives the same ratios
    assert df.loc["bad", "worst_lo"] == pytest.approx(2.0)
    assert df.loc["bad", "worst_hi"] == pytest.approx(2.0)
    assert "oracle" not in df.index


def test_intervals_cover_the_estimate_when_the_ratio_varies_over_runs():
    base = np.abs(rng.normal(0.1, 0.03, size=(RUNS, STEPS)))
    noisy = FilterRuns(base * rng.uniform(0.8, 1.6, size=(RUNS, 1)), np.ones((RUNS, STEPS)),
                       np.zeros(RUNS, bool))  # fmt: skip
    suite = [
        SuiteScenario("a", "oracle", False, {"oracle": _runs(err=base), "f": noisy}),
        _scenario("b", {"f": 1.0}),
    ]
    r = suite_table(suite, resamples=500).iloc[0]
    assert r.worst_lo < r.worst < r.worst_hi
    assert r.geomean_lo < r.geomean < r.geomean_hi


def test_nees_shares_lost_lock_and_inconsistent_runs():
    lo, hi = nees_bounds(RUNS)
    div = np.zeros(RUNS, bool)
    div[:2] = True
    err = np.abs(rng.normal(0.1, 0.03, size=(RUNS, STEPS)))
    err[5, 10] = 3 * LOST_LOCK_M  # lost lock in run 5 (the oracle stays below)
    nees = np.full((RUNS, STEPS), 3.0)
    nees[7] = 1e6  # an inconsistent run
    shaky = FilterRuns(err, nees, div)
    suite = [
        _scenario("const", {"f": shaky}),
        _scenario("changing", {"f": _runs(nees=(lo + hi) / 2)}, changing=True),
    ]
    r = suite_table(suite, resamples=50).set_index("filter").loc["f"]
    assert r.lost_lock == 3  # two diverged, one above LOST_LOCK_M
    assert r.diverged == 2
    assert r.inconsistent == 1
    assert r.runs == 2 * RUNS
    assert r.nees_in_bounds_min == 0.0  # the constant scenario: run 7 pulls every step out
    assert r.nees_in_bounds_min_constant == 0.0


def test_a_filter_with_no_common_run_ranks_worst_and_fewer_scenarios_last():
    dead = _runs(diverged=np.ones(RUNS, bool))
    suite = [
        _scenario("a", {"dead": dead, "ok": 1.2, "partial": 1.0}),
        _scenario("b", {"dead": 1.0, "ok": 1.0}),
    ]
    df = suite_table(suite, resamples=50, drives={"ok": 0.9})
    assert list(df["filter"]) == ["ok", "dead", "partial"]
    assert df.set_index("filter").loc["dead", "worst"] == math.inf
    assert df.set_index("filter").loc["partial", "scenarios"] == 1
    assert df.set_index("filter").loc["ok", "drives_vs_tuned"] == 0.9
    assert list(df["rank"]) == [1, 2, 3]


class _DriveResult:
    """The parts of a recorded drives result (report.real.RealData) the drives column reads."""

    def __init__(self, errors: dict[str, list[float]], bases: dict[str, str]):
        drives = ["d6-r1", "d7-r1"]
        self.manifest = {"protocol": "drives", "data": {"drives": [{"drive": d} for d in drives]}}
        self.reference = "ekf-tuned"
        rows = [
            (name, run, err)
            for name, per_drive in errors.items()
            for run, err in enumerate(per_drive)
            for _ in range(4)  # four scored steps of the same error on each drive
        ]
        self.steps = pd.DataFrame(rows, columns=["filter", "run", "pos_err"])
        self._instances = [{"name": n, "base": bases.get(n, n)} for n in errors]

    def instances(self) -> list[dict]:
        return self._instances


def test_the_drives_column_is_the_worst_start_of_each_filter_over_ekf_tuned():
    from anfekf_bench.report import suite as suite_report

    drives = _DriveResult(
        {
            "ekf-tuned": [1.0, 2.0],
            "vb-imm-x1": [2.0, 2.0],  # ratios 2, 1: geometric mean sqrt(2)
            "vb-imm-x4": [3.0, 2.0],  # ratios 3, 1: sqrt(3), the worse start
            "imm-x1": [1.0, math.nan],  # lost on a drive: no ratio, ranked as n/a
        },
        {"vb-imm-x1": "vb-imm", "vb-imm-x4": "vb-imm", "imm-x1": "imm"},
    )
    ratios = suite_report.drive_ratios([drives])
    assert ratios == {"vb-imm": pytest.approx(math.sqrt(3.0)), "imm": math.inf}
    suite = [_scenario("a", {"vb-imm": 1.0, "imm": 2.0}), _scenario("b", {"vb-imm": 1.1})]
    df = suite_table(suite, drives=ratios, resamples=50)
    assert df.set_index("filter").loc["vb-imm", "drives_vs_tuned"] == pytest.approx(3**0.5)
    table = suite_report.blocks(df, total=2)[-1]
    assert table.header[-1] == "drives / ekf-tuned"
    cells = {row[1].text: row[-1].text for row in table.rows}
    assert cells["vb-imm"] == "1.73x" and cells["imm (1/2)"] == "n/a"
