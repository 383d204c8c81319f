"""Per-phase metrics, recovery times and noise-tracking errors (analysis/phases, SPEC 14),
recomputed by hand on a made-up trace, and the tables a scheduled batch writes."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2

from anfekf_bench.analysis.phases import (
    RECOVERY_HOLD_S,
    phase_bounds,
    phases_frame,
    recovery_time,
    summary_tracking,
)
from anfekf_bench.schedule import NoiseSchedule

SIGMAS = (0.3, math.radians(3.0), 0.1, math.radians(1.0))
SCHEDULE = NoiseSchedule.model_validate(
    {"changes": [{"channels": ["R"], "factor": 4, "start_s": 4, "end_s": 7}]}
)
STEPS = np.arange(1, 51) * 8  # recorded every 8th control step of 25 ms: t = 0.2 .. 10 s
T = STEPS * 0.025
RUNS = 3
PHASE_OF = np.where(STEPS < 160, 0, np.where(STEPS < 280, 1, 2))  # by integer step: 4 s, 7 s


def filter_error(t: float) -> float:
    """The made-up filter's error over the oracle's (whose error is 1 m times a run factor)."""
    if t < 4 - 1e-9:
        return 1.0
    if t < 5.4 - 1e-9:
        return 2.0  # out of the 1.2 band after the change
    if abs(t - 6.0) < 1e-9:
        return 1.5  # one excursion at 6.0 s: recovered from 6.2 s (to the phase's end)
    if t < 7 - 1e-9:
        return 1.1
    return 1.3  # never back in the last phase: censored


def made_up_steps() -> tuple[pd.DataFrame, dict]:
    rng = np.random.default_rng(0)
    run_factor = [1.0, 1.1, 0.9]
    true_r = SIGMAS[2] ** 2 * np.where(PHASE_OF == 1, 4.0, 1.0)
    rows, raw = [], {}
    for name in ("f", "oracle"):
        for run in range(RUNS):
            diverged = name == "f" and run == 2
            nees = rng.uniform(0.5, 6.0, len(T))
            pos = np.array([run_factor[run] * (filter_error(t) if name == "f" else 1.0) for t in T])
            heading = rng.uniform(0.0, 0.1, len(T))
            log_ratio = np.where(PHASE_OF == 0, 0.5, -1.0) if name == "f" else np.zeros(len(T))
            r_rr = true_r * np.exp(log_ratio)
            if diverged:
                pos[:] = heading[:] = nees[:] = r_rr[:] = np.nan
            raw[name, run] = {"pos": pos, "heading": heading, "nees": nees, "R_rr": r_rr}
            for i in range(len(T)):
                rows.append({
                    "scenario": "hand", "filter": name, "run": run, "step": STEPS[i], "t": T[i],
                    "pos_err": pos[i], "heading_err": heading[i], "nees": nees[i],
                    "R_rr": r_rr[i], "R_bb": SIGMAS[3] ** 2, "Q_vv": SIGMAS[0] ** 2 * 2.0,
                    "Q_gg": SIGMAS[1] ** 2, "diverged": diverged,
                })  # fmt: skip
    return pd.DataFrame(rows), raw


def test_phase_bounds_follow_the_change_points():
    assert phase_bounds(SCHEDULE, 10.0) == [(0.0, 4.0), (4.0, 7.0), (7.0, 10.0)]
    assert (T[PHASE_OF == 1] >= 4).all() and (T[PHASE_OF == 2] >= 7).all()  # float products


def test_phases_table_recomputed_by_hand():
    steps, raw = made_up_steps()
    table = phases_frame(steps, SCHEDULE, SIGMAS, "oracle")
    assert list(table["filter"]) == ["f"] * 3 + ["oracle"] * 3
    kept = {"f": [0, 1], "oracle": [0, 1, 2]}
    for (name, phase), row in table.set_index(["filter", "phase"]).iterrows():
        at = np.flatnonzero(PHASE_OF == phase)
        runs = kept[name]
        rmse = [math.sqrt(sum(raw[name, r]["pos"][i] ** 2 for r in runs) / len(runs)) for i in at]
        assert row["rmse_pos"] == pytest.approx(sum(rmse) / len(rmse), rel=1e-12)
        head = [math.sqrt(sum(raw[name, r]["heading"][i] ** 2 for r in runs) / len(runs))
                for i in at]  # fmt: skip
        assert row["rmse_heading"] == pytest.approx(sum(head) / len(head), rel=1e-12)
        avg = [sum(raw[name, r]["nees"][i] for r in runs) / len(runs) for i in at]
        assert row["anees"] == pytest.approx(sum(avg) / len(avg), rel=1e-12)
        lo = chi2.ppf(0.025, 3 * len(runs)) / len(runs)
        hi = chi2.ppf(0.975, 3 * len(runs)) / len(runs)
        assert row["nees_in_bounds"] == pytest.approx(sum(lo < a < hi for a in avg) / len(avg))
        assert row["runs_used"] == len(runs) and row["diverged"] == 3 - len(runs)
        assert row["t_start"] == [0.0, 4.0, 7.0][phase]
        # tracking: |ln ratio| of R_rr is 0.5 in phase 0 and 1 after it for f, 0 for the oracle
        expected_r = (0.5 if phase == 0 else 1.0) if name == "f" else 0.0
        assert row["track_R_rr"] == pytest.approx(expected_r, abs=1e-12)
        # R_bb stays nominal while the schedule makes the true one 4x in phase 1
        assert row["track_R_bb"] == pytest.approx(math.log(4.0) if phase == 1 else 0.0)
        assert row["track_Q_vv"] == pytest.approx(math.log(2.0), abs=1e-12)
    f = table[table["filter"] == "f"].set_index("phase")
    for phase in range(3):  # over the runs both kept (0 and 1), the phase's RMSE ratio
        at = np.flatnonzero(PHASE_OF == phase)
        curve = {name: [math.sqrt(sum(raw[name, r]["pos"][i] ** 2 for r in (0, 1)) / 2)
                        for i in at] for name in ("f", "oracle")}  # fmt: skip
        expected = sum(curve["f"]) / sum(curve["oracle"])
        row = f.loc[phase]
        assert row["rmse_vs_oracle"] == pytest.approx(expected, rel=1e-12)
        assert row["rmse_vs_oracle_lo"] <= row["rmse_vs_oracle"] <= row["rmse_vs_oracle_hi"]
    assert table[table["filter"] == "oracle"]["rmse_vs_oracle"].isna().all()
    assert math.isnan(f.loc[0, "recovery_s"])  # no change before the first phase
    assert f.loc[1, "recovery_s"] == pytest.approx(6.2 - 4.0)
    assert not f.loc[1, "recovery_censored"]
    assert f.loc[2, "recovery_s"] == pytest.approx(3.0) and f.loc[2, "recovery_censored"]
    oracle = table[table["filter"] == "oracle"].set_index("phase")
    assert oracle.loc[1, "recovery_s"] == pytest.approx(0.0)  # t = 4.0 is recorded


def test_whole_run_tracking_errors():
    steps, _ = made_up_steps()
    tracking = summary_tracking(steps, SCHEDULE, SIGMAS)
    n0 = int((PHASE_OF == 0).sum())
    assert tracking["f"]["track_R_rr"] == pytest.approx((0.5 * n0 + (50 - n0)) / 50)
    assert tracking["oracle"]["track_R_rr"] == pytest.approx(0.0, abs=1e-12)


def test_no_oracle_no_recovery_time():
    steps, _ = made_up_steps()
    table = phases_frame(steps, SCHEDULE, SIGMAS, None)
    assert table["recovery_s"].isna().all() and not table["recovery_censored"].any()


def test_recovery_holds_for_the_hold_time_only():
    """Out of the band at 2 s and at 20 s of a 30 s phase: from 2.5 s the filter stays in the
    band for more than RECOVERY_HOLD_S, so the late excursion does not undo the recovery; an
    excursion within the hold does."""
    t = np.arange(0.0, 30.0, 0.5)
    oracle = np.ones(len(t))
    f = np.where(np.isin(t, [2.0, 20.0]), 1.5, 1.0)
    assert recovery_time(t, f, oracle, 0.0, 30.0) == (2.5, False)
    close = np.where(np.isin(t, [2.0, 2.0 + RECOVERY_HOLD_S - 1]), 1.5, 1.0)
    assert recovery_time(t, close, oracle, 0.0, 30.0) == (RECOVERY_HOLD_S + 1.5, False)
    # in the band only in the last 3 s: recovered (the hold is cut at the phase's end)
    late = np.where(t < 27.0, 1.5, 1.0)
    assert recovery_time(t, late, oracle, 0.0, 30.0) == (27.0, False)
    # exactly 1.2x is inside the band; never inside: censored at the phase's length
    assert recovery_time(t, 1.2 * oracle, oracle, 0.0, 30.0) == (0.0, False)
    assert recovery_time(t, 1.3 * oracle, oracle, 0.0, 30.0) == (30.0, True)


# ---------------------------------------------------------------------------------------------
# A scheduled batch end to end: its tables, manifest and report


@pytest.mark.slow
def test_scheduled_batch_writes_phases_and_the_report(tmp_path):
    import json

    import pyarrow.parquet as pq

    from anfekf_bench.experiment import execute, make_plan
    from anfekf_bench.report.report import write_report
    from anfekf_bench.scenarios import load_scenario

    from .conftest import small_scenario, write_scenario

    doc = small_scenario(
        name="sched",
        runs=3, record_every=8, engine="fast",
        filter_noise={"sigma_range": 0.1, "sigma_bearing_deg": 1.0},
        filters=[
            {"name": "ekf", "kind": "ekf"},
            {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
            {"name": "sage-husa", "kind": "sage-husa", "adapt": "R"},
            {"name": "ekf-oracle", "kind": "ekf-oracle"},
        ],
        noise_schedule={
            "changes": [{"channels": ["R"], "factor": 25, "start_s": 6, "end_s": 12}],
            "blackouts": [{"start_s": 15, "end_s": 17}],
        },
    )  # fmt: skip
    path = write_scenario(tmp_path / "sched.yaml", doc)
    records, target = execute(make_plan(*load_scenario(path), None, None, 1), tmp_path / "out")
    phases = pd.read_parquet(target / "phases.parquet")
    assert list(phases["t_start"].unique()) == [0.0, 6.0, 12.0, 15.0, 17.0]
    assert len(phases) == 4 * 5
    units = json.loads(pq.read_metadata(target / "phases.parquet").metadata[b"anfekf.units"])
    assert units["recovery_s"] == "s" and units["rmse_pos"] == "m"
    assert all("track_R_rr" in r for r in records)
    oracle = next(r for r in records if r["filter"] == "ekf-oracle")
    assert oracle["track_R_rr"] == pytest.approx(0.0, abs=1e-12)
    manifest = json.loads((target / "manifest.json").read_text())
    assert manifest["engines"] == {
        "ekf": "fast", "anfekf": "fast", "sage-husa": "fast", "ekf-oracle": "filterpy",
    }  # fmt: skip
    report = write_report([tmp_path / "out"], tmp_path / "report", html=False)
    names = {p.name for p in report.files}
    assert {"sched_changes.png", "sched_variances.png"} <= names
    text = (tmp_path / "report" / "report.md").read_text()
    assert "**Per phase**" in text and "recovery [s]" in text


def test_constant_noise_batch_has_no_phases(tmp_path):
    from anfekf_bench.experiment import execute, make_plan
    from anfekf_bench.scenarios import load_scenario

    from .conftest import small_scenario, write_scenario

    path = write_scenario(tmp_path / "plain.yaml", small_scenario(runs=2, record_every=8))
    records, target = execute(make_plan(*load_scenario(path), None, None, 1), tmp_path / "out")
    assert not (target / "phases.parquet").exists()
    assert not any(k.startswith("track_") for r in records for k in r)


def test_a_phase_without_recorded_steps_has_no_metrics():
    """Changes 0.1 s apart, recorded every 0.2 s: the phase between them holds no step."""
    schedule = NoiseSchedule.model_validate(
        {"changes": [{"channels": ["R"], "factor": 4, "start_s": 5.01, "end_s": 5.11}]}
    )
    steps, _ = made_up_steps()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        table = phases_frame(steps, schedule, SIGMAS, "oracle")
    empty = table[table["t_start"] == 5.01]
    assert len(empty) == 2 and empty["rmse_pos"].isna().all() and empty["runs"].isna().all()
    assert table[table["t_start"] == 5.11]["rmse_pos"].notna().all()
