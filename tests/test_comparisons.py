"""Paired comparisons and claims of a scenario (analysis.comparisons), on hand-made steps tables."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from anfekf_bench.analysis.comparisons import (
    claim_text,
    comparison_pairs,
    comparisons_frame,
    evaluate_claims,
)
from anfekf_bench.analysis.tables import runs_frame
from anfekf_bench.config import ClaimSpec, ScenarioError, parse_scenario

RUNS, STEPS = 20, 30


def steps_table(pos_err: dict[str, np.ndarray], nees: dict[str, np.ndarray] | None = None):
    """A steps table with the columns the comparisons read, from (runs, steps) arrays."""
    blocks = []
    for name, err in pos_err.items():
        runs, steps = err.shape
        nn = np.full_like(err, 3.0) if nees is None else nees[name]
        blocks.append(
            pd.DataFrame(
                {
                    "scenario": "s",
                    "filter": name,
                    "run": np.repeat(np.arange(runs), steps),
                    "step": np.tile(np.arange(1, steps + 1), runs),
                    "t": np.tile(np.arange(1, steps + 1) * 0.2, runs),
                    "pos_err": err.ravel(),
                    "heading_err": err.ravel() / 10,
                    "nees": nn.ravel(),
                    "R_rr": 1.0,
                    "R_bb": 1.0,
                    "Q_vv": 1.0,
                    "Q_gg": 1.0,
                    "diverged": False,
                }  # fmt: skip
            )
        )
    df = pd.concat(blocks, ignore_index=True)
    df["filter"] = pd.Categorical(df["filter"], categories=list(pos_err))
    return df


@pytest.fixture
def errors() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    ekf = np.abs(rng.normal(0.4, 0.1, (RUNS, STEPS)))
    return {"ekf": ekf, "half": ekf * 0.5, "same": ekf.copy(), "oracle": ekf * 0.45}


def test_pairs_compare_every_filter_with_each_reference_then_the_users():
    filters = [("ekf", "reference"), ("a", "adaptive"), ("o", "oracle"), ("b", "adaptive")]
    assert comparison_pairs(filters, [("a", "b"), ("a", "ekf")]) == [
        ("a", "ekf"), ("o", "ekf"), ("b", "ekf"), ("ekf", "o"), ("a", "o"), ("b", "o"), ("a", "b"),
    ]  # fmt: skip
    assert comparison_pairs([("x", "adaptive")]) == []


def test_a_constant_ratio_is_that_ratio_with_a_zero_width_interval(errors):
    table = comparisons_frame(steps_table(errors), [("half", "ekf"), ("same", "ekf")])
    by = table.set_index(["filter", "metric"])
    half = by.loc[("half", "rmse_pos")]
    assert half.estimate == pytest.approx(0.5, abs=1e-12)
    assert half.lo == half.hi == half.estimate
    same = by.loc[("same", "rmse_pos")]
    assert same.estimate == 1.0 and same.lo == same.hi == 1.0
    assert same.p_value == 1.0
    assert by.loc[("half", "anees")].estimate == 1.0  # nees identical in both
    assert set(table["runs_used"]) == {RUNS}


def test_a_diverged_run_is_left_out_for_both_filters(errors):
    steps = steps_table(errors)
    steps.loc[(steps["filter"] == "ekf") & (steps["run"] == 4), "diverged"] = True
    steps.loc[(steps["filter"] == "half") & (steps["run"] == 4), "pos_err"] = 1e6
    table = comparisons_frame(steps, [("half", "ekf")])
    row = table[table["metric"] == "rmse_pos"].iloc[0]
    assert row.runs_used == RUNS - 1
    assert row.estimate == pytest.approx(0.5, abs=1e-12), "run 4 of `half` must not count"


@pytest.mark.slow  # starts two worker processes
def test_a_large_table_on_workers_is_the_table_computed_here(errors, monkeypatch):
    """The comparisons shared out over workers (each filter's pairs in one chunk) give the same
    rows, bit for bit and in the same order, as computed in this process; a small table stays
    here."""
    from anfekf_bench.analysis import comparisons

    rng = np.random.default_rng(11)
    many = dict(errors)
    for i in range(3):
        many[f"f{i}"] = errors["ekf"] * rng.uniform(0.5, 1.5, (RUNS, STEPS))
    steps = steps_table(many)
    pairs = comparison_pairs([(n, "oracle" if n == "oracle" else "reference" if n == "ekf"
                               else "adaptive") for n in many])  # fmt: skip
    here = comparisons_frame(steps, pairs, seed=5, resamples=200)
    arrays = {n: {"pos_err": np.zeros((RUNS, STEPS))} for n in many}
    assert len(comparisons._chunks(pairs, 2, 2, arrays)) == 1, "a small table stays here"
    monkeypatch.setattr(comparisons, "PARALLEL_MIN_CELLS", 0)
    chunks = comparisons._chunks(pairs, 2, 2, arrays)
    assert len(chunks) == 2 and sorted(sum(chunks, [])) == sorted(pairs)
    on_threads = comparisons_frame(steps, pairs, seed=5, resamples=200, jobs=2)
    pd.testing.assert_frame_equal(on_threads, here, check_exact=True)


def _claims(*specs: dict) -> list[ClaimSpec]:
    return [ClaimSpec(**s) for s in specs]


def test_claim_verdicts_on_the_interval(errors):
    noisy = dict(errors)
    rng = np.random.default_rng(9)
    noisy["noisy"] = errors["ekf"] * rng.uniform(0.4, 0.8, (RUNS, 1))  # ratio ~0.6 +- spread
    steps = steps_table(noisy)
    claims = _claims(
        {"filter": "half", "vs": "ekf", "metric": "rmse_pos", "at_most": 0.6},  # holds
        {"filter": "half", "vs": "ekf", "metric": "rmse_pos", "at_most": 0.4},  # fails
        {"filter": "noisy", "vs": "ekf", "metric": "rmse_pos", "at_most": 0.6},  # straddles
        {"filter": "half", "vs": "ekf", "metric": "rmse_pos", "at_least": 0.45},  # holds
    )
    found = evaluate_claims(steps, claims, resamples=500)
    assert [c["verdict"] for c in found] == ["holds", "fails", "inconclusive", "holds"]
    straddle = found[2]
    assert straddle["lo"] < 0.6 < straddle["hi"]
    assert "straddles" in straddle["warning"]
    assert found[0]["claim"] == "half rmse_pos <= 0.6 x ekf"


def test_share_claims_are_decided_on_the_point_estimate(errors):
    nees = {name: np.full((RUNS, STEPS), 3.0) for name in errors}
    nees["ekf"][:, : STEPS // 2] = 30.0  # half the steps out of bounds
    steps = steps_table(errors, nees)
    found = evaluate_claims(
        steps,
        _claims(
            {"filter": "half", "metric": "nees_in_bounds", "at_least": 0.85},
            {"filter": "ekf", "metric": "nees_in_bounds", "at_least": 0.85},
            {"filter": "half", "vs": "ekf", "metric": "nees_in_bounds", "at_least": 0.0},
        ),
    )
    assert [c["verdict"] for c in found] == ["holds", "fails", "holds"]
    assert found[1]["estimate"] == pytest.approx(0.5)
    assert found[2]["estimate"] == pytest.approx(0.5)
    assert all(c["method"] == "point" and math.isnan(c["lo"]) for c in found)
    assert "point estimate" in found[0]["warning"]


def test_few_runs_are_flagged(errors):
    few = {k: v[:5] for k, v in errors.items()}
    found = evaluate_claims(
        steps_table(few), _claims({"filter": "half", "vs": "ekf", "metric": "anees", "at_most": 2})
    )
    assert "only 5 runs" in found[0]["warning"]


def test_claim_text_and_validation():
    assert claim_text(ClaimSpec(filter="a", metric="anees", at_most=4)) == "a anees <= 4"
    with pytest.raises(ValueError, match="exactly one of at_most or at_least"):
        ClaimSpec(filter="a", metric="anees", at_most=4, at_least=1)
    doc = {"name": "s", "filters": [{"name": "ekf", "kind": "ekf"}], "claims": [{"filter": "nope",
           "metric": "rmse_pos", "at_most": 1}]}  # fmt: skip
    with pytest.raises(ScenarioError, match="claims: entry 0: no filter named .nope."):
        parse_scenario(doc)


def test_runs_table_holds_each_runs_own_metrics():
    err = np.array([[3.0, 4.0], [0.0, 0.0]])
    result = {
        "run": 0,
        "filters": {
            "ekf": {
                "pos_err": err[0], "heading_err": err[0], "nees": np.array([1.0, 5.0]),
                "diverged": False, "nis_sum": 6.0, "n_updates": 3, "n_rejected": 1,
            }
        },
    }  # fmt: skip
    row = runs_frame("s", ["ekf"], [result]).iloc[0]
    assert row.rmse_pos == pytest.approx(math.sqrt(12.5))
    assert row.mean_nees == 3.0 and row.max_nees == 5.0 and row.anis == 2.0
    assert (row.n_updates, row.n_rejected, bool(row.diverged)) == (3, 1, False)
