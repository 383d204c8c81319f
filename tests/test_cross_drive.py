"""The cross-drive protocol (SPEC 15): drives as runs, the compiled grid kernel with branch and
bound, ekf-tuned tuned on other datasets' drives, thinned evaluation times, the scenario file."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from anfekf_bench.config import ScenarioError
from anfekf_bench.engines.events import run_filter_events, timeline
from anfekf_bench.engines.tuning import RESUME_SIZE, GridRuns, score_setting
from anfekf_bench.filters.ekf import RobotEKF, gate_threshold
from anfekf_bench.filters.spec import FilterContext
from anfekf_bench.fitting.recorded import WholeRuns, tune
from anfekf_bench.models import Unicycle
from anfekf_bench.real_experiment import SegmentInputs, segment_inputs, thin_records
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.sources import mrclam as m
from anfekf_bench.sources.recorded import Segment, parse_real_scenario

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "drives" / "mrclam-drives.yaml"
P0 = np.diag([0.05**2, 0.05**2, 0.05**2])


@pytest.fixture(scope="module")
def d6r2() -> m.RobotLog:
    return m.load_drive("d6-r2")


def span_inputs(log: m.RobotLog, t0: float, t1: float, period=None) -> SegmentInputs:
    """A span of a drive as the inputs of one run, cold-started from ground truth at t0."""
    pose = np.array(m.interpolate_truth(log, t0))
    seg = Segment(0, t0, t1, t0, pose, t1 - t0)

    class _Rec:
        pass

    rec = _Rec()
    rec.log = log
    rec.scorable = lambda t: m.scorable(log, t)
    return segment_inputs(rec, seg, period)


def drives_doc(**change) -> dict:
    doc = {
        "name": "drives",
        "protocol": "drives",
        "data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r1", "d7-r1", "d9-r3"]},
        "starts": [1],
        "filters": [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-tuned", "kind": "ekf-tuned"}],
    }
    doc.update(change)
    return doc


# ------------------------------------------------------------------ the kernel


def robot_ekf(x0, sig, gate=None) -> RobotEKF:
    """The reference engine's plain EKF with the sigmas sig = (sv, sw, sr, sb)."""
    sv, sw, sr, sb = sig
    ctx = FilterContext(
        x0=np.array(x0, float), P0=P0, Qu=np.diag([sv * sv, sw * sw]),
        R=np.diag([sr * sr, sb * sb]), model=Unicycle(0.12), dt=0.12, gate=gate,
    )  # fmt: skip
    return RobotEKF(**ctx.kwargs())


def test_compiled_kernel_equals_the_robot_ekf(d6r2):
    """engines.tuning.score_setting (one setting, compiled) against RobotEKF on filterpy, on 60 s
    of 65 Hz odometry, settings that gate and lose lock."""
    inp = span_inputs(d6r2, 100.0, 160.0)
    sig = np.array([[0.1, 0.1, 0.1, 0.05], [0.01, 0.5, 0.05, 0.005], [0.4, 0.02, 0.01, 0.002]])
    gate = gate_threshold(0.999)
    rejected = 0
    for s in sig:
        ref = run_filter_events(robot_ekf(inp.segment.pose, s, gate), inp.timeline)
        e = np.hypot(*(ref["x"][:, :2] - inp.truth[:, :2]).T)[inp.scored]
        sq, mx, nu, nr, fin = score_setting(
            inp.timeline, inp.segment.pose, P0, s, gate, 0.12, inp.truth, inp.scored
        )
        assert fin and not ref["diverged"]
        assert sq == pytest.approx(np.sum(e**2), rel=1e-9)
        assert mx == pytest.approx(e.max(), rel=1e-9)
        assert (nu, nr) == (ref["n_updates"], ref["n_rejected"])
        rejected += nr
    assert rejected > 0  # the gate acted somewhere


def test_kernel_stops_once_the_bound_is_passed(d6r2):
    inp = span_inputs(d6r2, 100.0, 160.0)
    args = (inp.timeline, inp.segment.pose, P0, [0.1, 0.1, 0.1, 0.05], None, 0.12, inp.truth,
            inp.scored)  # fmt: skip
    full = score_setting(*args)
    cut = score_setting(*args, bound=0.5 * full[0])
    assert full[4] and not cut[4]
    assert 0.5 * full[0] < cut[0] < full[0]


def test_branch_and_bound_finds_the_full_grids_best(d6r2):
    """tune on whole drives (branch and bound) picks the setting an exhaustive scoring picks."""
    parts = [span_inputs(d6r2, 50.0, 80.0, 0.12), span_inputs(d6r2, 400.0, 430.0, 0.12)]
    sc = parse_real_scenario(
        drives_doc(
            tuning={
                "sigma_v": [-2, 0],
                "sigma_w": [0, 2],
                "sigma_range": [-1, 0],
                "sigma_bearing": [-2, -1],
                "refine": False,
            }
        )  # fmt: skip
    )
    found = tune(sc, parts, jobs=1, whole=True)
    exps = np.stack(np.meshgrid(*sc.tuning.axes(), indexing="ij"), -1).reshape(-1, 4)
    sig = sc.naive.sigmas() * np.exp2(exps)
    total = np.zeros(len(exps))
    for p in parts:  # every setting scored in full (no bound)
        total += [
            score_setting(p.timeline, p.segment.pose, P0, s, gate_threshold(0.999), 0.12,
                          p.truth, p.scored)[0]
            for s in sig
        ]  # fmt: skip
    best = exps[int(np.argmin(total))]
    assert list(found["log2_multipliers"].values()) == best.tolist()
    n = sum(int(p.scored.sum()) for p in parts)
    assert found["train_rmse_pos"] == pytest.approx(math.sqrt(total.min() / n), rel=1e-9)
    assert found["stages"][0]["stopped_early"] > 0  # the bound did cut work
    assert json.dumps(found)
    # every setting the bound stopped is worse than the winner; the ones it let finish are exact
    runs = GridRuns.of([(p.timeline, p.segment.pose, p.truth, p.scored) for p in parts])
    chunk, _ = runs.score(sig, P0, gate_threshold(0.999), 0.12, math.inf, branch_and_bound=True)
    stopped = chunk[:, 4] == 0
    assert stopped.any() and not stopped.all()
    assert np.all(total[stopped] > total.min())
    assert np.allclose(chunk[~stopped, 0], total[~stopped], rtol=1e-9)


def test_folds_sharing_drives_read_their_whole_runs_and_find_the_same(d6r2, monkeypatch):
    """tune_drives' folds share drives (WholeRuns): a search that reads the runs an earlier
    search scored whole finds the same setting, sums and stopped share as one that runs them."""
    parts = [span_inputs(d6r2, 100.0, 130.0, 0.12), span_inputs(d6r2, 400.0, 430.0, 0.12)]
    grid = {"sigma_v": [-2, 0], "sigma_w": [0, 2], "sigma_range": [-1, 1],
            "sigma_bearing": [-2, -1], "refine": True}  # fmt: skip
    sc = parse_real_scenario(drives_doc(tuning=grid))
    ran = []
    score = GridRuns.score

    def counted(self, sig, *args):
        out, done = score(self, sig, *args)
        ran.append(int(np.sum(~np.isnan(done[:, :, 0]))))
        return out, done

    monkeypatch.setattr(GridRuns, "score", counted)
    alone = tune(sc, parts, jobs=2, whole=True)
    ran_alone = sum(ran)
    memo = WholeRuns()
    tune(sc, parts[1:], jobs=2, whole=True, memo=memo)  # an earlier fold on the second run
    ran.clear()
    shared = tune(sc, parts, jobs=2, whole=True, memo=memo)
    for found in (alone, shared):
        found.pop("seconds")
    assert shared == alone
    assert sum(ran) < ran_alone  # runs read, not run again


def test_grid_kernel_sums_the_settings_of_one_call_as_one_by_one(d6r2):
    """GridRuns.score (every setting over every run, one compiled call) gives the bits of
    score_setting run by run and summed in order, a diverging setting (inf) included."""
    parts = [span_inputs(d6r2, 100.0, 120.0, 0.12), span_inputs(d6r2, 400.0, 415.0)]
    sig = np.array([[0.1, 0.1, 0.1, 0.05], [0.01, 0.5, 0.05, 0.005], [1e-9, 1e-9, 1e-9, 1e-9],
                    [0.4, 0.02, 0.01, 0.002]])  # fmt: skip
    gate = gate_threshold(0.999)
    runs = GridRuns.of([(p.timeline, p.segment.pose, p.truth[:, :2], p.scored) for p in parts])
    got, done = runs.score(sig, P0, gate, 0.12)
    for s, row in zip(sig, got, strict=True):
        total, worst, upd, rej = 0.0, 0.0, 0, 0
        for p in parts:
            sq, mx, nu, nr, fin = score_setting(
                p.timeline, p.segment.pose, P0, s, gate, 0.12, p.truth, p.scored
            )
            total, worst, upd, rej = total + sq, max(worst, mx), upd + nu, rej + nr
        assert row.tolist() == [total, worst, upd, rej, 1.0]
    assert np.isinf(got[:, 0]).any() and np.isfinite(got[:, 0]).any()


def test_a_run_the_bound_stopped_goes_on_from_there_with_the_same_bits(d6r2):
    """grid_kernel's `partial`: a run stopped by the bound keeps its state (stamp, x, P, sums),
    and a later call goes on from there: the sums of scoring every run from its start, bit for
    bit, and the same settings stopped under a bound in between."""
    parts = [span_inputs(d6r2, 100.0, 130.0, 0.12), span_inputs(d6r2, 400.0, 430.0, 0.12)]
    sig = np.array([[0.1, 0.1, 0.1, 0.05], [0.01, 0.5, 0.05, 0.005], [0.4, 0.02, 0.01, 0.002],
                    [0.05, 0.2, 0.2, 0.01]])  # fmt: skip
    gate = gate_threshold(0.999)
    runs = GridRuns.of([(p.timeline, p.segment.pose, p.truth, p.scored) for p in parts])
    fresh, fresh_done = runs.score(sig, P0, gate, 0.12)
    low = 0.2 * np.min(fresh[:, 0])
    partial = np.full((len(sig), len(parts), RESUME_SIZE), np.nan)
    stopped, _ = runs.score(sig, P0, gate, 0.12, low, True, None, partial)
    kept = ~np.isnan(partial[:, :, 0])
    assert np.all(stopped[:, 4] == 0) and kept.sum(axis=1).tolist() == [1] * len(sig)
    middle = float(np.median(fresh[:, 0]))
    again = partial.copy()
    resumed_mid, _ = runs.score(sig, P0, gate, 0.12, middle, True, None, again)
    alone_mid, _ = runs.score(sig, P0, gate, 0.12, middle, True)
    assert resumed_mid[:, 4].tolist() == alone_mid[:, 4].tolist()
    finished = resumed_mid[:, 4] == 1
    assert finished.any() and not finished.all()
    assert resumed_mid[finished].tolist() == alone_mid[finished].tolist()
    resumed, done = runs.score(sig, P0, gate, 0.12, math.inf, False, None, partial)
    assert resumed.tolist() == fresh.tolist()
    assert np.array_equal(done, fresh_done, equal_nan=True) and np.isnan(partial[:, :, 0]).all()


# ------------------------------------------------------------------ evaluation times


def test_thinned_evaluation_times_keep_every_command_and_landmark(d6r2):
    tl = timeline(m.events(d6r2, 100.0, 130.0))
    thin = thin_records(tl, 0.12)
    kept = thin.t[thin.record]
    assert kept[0] == tl.record_t[0]
    assert np.all(np.diff(kept) >= 0.12 - 1e-12)
    assert set(kept) <= set(tl.record_t)
    assert 6.0 <= len(kept) / 30.0 <= 8.4  # about 8 Hz out of 65 Hz
    assert len(thin) < 0.6 * len(tl)  # held commands merged
    assert np.array_equal(thin.z, tl.z) and thin.lm[-1] == tl.lm[-1]  # every landmark
    assert thin.dt.sum() == pytest.approx(tl.dt.sum()) and np.all(thin.dt > 0)
    for k in range(len(thin)):  # each merged interval holds the command the original held
        inside = (tl.t > thin.t[k] - thin.dt[k]) & (tl.t <= thin.t[k])
        assert np.all(tl.u[inside] == thin.u[k])
        a, b = thin.lm[k], thin.lm[k + 1]
        if b > a:
            j = int(np.searchsorted(tl.t, thin.t[k]))
            assert (tl.lm[j], tl.lm[j + 1]) == (a, b)
    assert thin_records(tl, None) is tl


def test_merged_predicts_change_the_estimate_by_round_off_only(d6r2):
    """The EKF on the merged timeline against the EKF on every odometry stamp, at the same
    evaluation times: the joined midpoint-Euler steps differ by far less than the filter's
    error (sub-millimetre over 60 s)."""
    from anfekf_bench.engines.events import run_filter_events
    from anfekf_bench.filters.ekf import RobotEKF
    from anfekf_bench.filters.spec import FilterContext
    from anfekf_bench.models import Unicycle

    tl = timeline(m.events(d6r2, 200.0, 260.0))
    thin = thin_records(tl, 0.12)
    full = replace(tl, record=np.isin(tl.t, thin.t[thin.record]))
    x0 = np.array(m.interpolate_truth(d6r2, 200.0))

    def run(t):
        ctx = FilterContext(x0=x0, P0=P0, Qu=np.diag([0.01, 0.04]), R=np.diag([0.01, 1e-4]),
                            model=Unicycle(0.12), dt=0.12, gate=gate_threshold(0.999))  # fmt: skip
        return run_filter_events(RobotEKF(**ctx.kwargs()), t)["x"]

    a, b = run(thin), run(full)
    assert a.shape == b.shape and len(a) > 400
    assert np.max(np.hypot(a[:, 0] - b[:, 0], a[:, 1] - b[:, 1])) < 1e-3


def test_no_scored_time_outside_ground_truth():
    """Every drive is scored from its first Vicon stamp to its last, never after (Dataset 6
    Robot 1: 128 s of odometry after the last Vicon stamp are not run), nor inside a gap."""
    sc, world = load_scenario(CONFIG)
    assert [d.id for d in world.drives] == sc.data.drives and len(world.drives) == 11
    for d in world.drives:
        inp = segment_inputs(d, d.segment, sc.eval_period_s)
        assert d.segment.t0 == d.log.t_start == 0.0 and d.segment.end == d.log.t_end
        assert inp.t.max() <= d.log.t_end
        assert np.all(d.exclusions.scorable(inp.t[inp.scored]))
        assert np.all(np.isnan(inp.truth[~inp.scored]))
        for a, b in d.exclusions.gaps:
            assert not np.any(inp.scored & (inp.t > a) & (inp.t < b))
        if d.id == "d6-r1":
            assert d.log.odo_t[-1] - inp.t.max() > 128.0
        if d.id == "d6-r4":
            assert (~inp.scored).sum() >= 15  # the 2 s gap at 8 Hz
        else:
            assert inp.scored.mean() > 0.999 or d.id == "d9-r3"


# ------------------------------------------------------------------ the scenario file


def test_shipped_cross_drive_config_tunes_each_dataset_on_the_others():
    sc, world = load_scenario(CONFIG)
    assert sc.protocol == "drives" and world.digest
    assert sc.tuning_sources(6) == [7] and sc.tuning_sources(7) == [6]
    assert sc.tuning_sources(9) == [6, 7]
    d9 = yaml.safe_load((CONFIG.parent.parent / "real" / "mrclam-d9.yaml").read_text())
    # the segment protocol's filters, and ekf-ml fitted on each drive's own innovations
    assert [f["name"] for f in d9["filters"]] + ["ekf-ml"] == [f.name for f in sc.filters]
    names = sc.instance_names()
    assert "ekf-tuned" in names and "anfekf-rq x0.25" in names and "vbakf x4" in names
    assert "ekf-ml" in names and not any(n.startswith("ekf-ml x") for n in names)
    maps = {d.dataset: d.log.landmark_x.tolist() for d in world.drives}
    assert len({tuple(v) for v in maps.values()}) == 3  # three maps, never mixed
    assert world.summary()["drives"][0]["drive"] == "d6-r1"


def test_default_tuning_sources_leave_one_dataset_out():
    sc = parse_real_scenario(drives_doc())
    assert sc.tuning_sources(6) == [7, 9] and sc.tuning_sources(9) == [6, 7]


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r1", "d8-r1"]}},
         "unknown drive 'd8-r1'"),
        ({"data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r1", "d6-r1"]}},
         "a drive is listed twice"),
        ({"tune_on": {6: [6]}}, "a dataset is never tuned on its own drives"),
        ({"tune_on": {6: [8]}}, "tune_on: 6: datasets must be among"),
        ({"data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r1", "d6-r2"]}},
         "ekf-tuned needs drives of another dataset"),
        ({"protocol": "segments"}, "data.drives and tune_on belong to protocol drives"),
        ({"data": {"kind": "mrclam", "path": "builtin"}}, "protocol drives needs data.drives"),
        ({"data": {"kind": "mrclam", "path": "x", "drives": ["d6-r1", "d7-r1"]}},
         "drive and drives name built-in drives"),
    ],
)  # fmt: skip
def test_cross_drive_scenario_errors_are_one_line(tmp_path, change, expected):
    path = tmp_path / "drives.yaml"
    path.write_text(yaml.safe_dump(drives_doc(**change)))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    text = str(err.value)
    assert expected in text and "\n" not in text


def test_segment_protocol_on_any_builtin_drive(tmp_path):
    path = tmp_path / "d6r2.yaml"
    doc = {"name": "d6r2", "data": {"kind": "mrclam", "path": "builtin", "drive": "d6-r2"},
           "segment_s": 90, "filters": [{"name": "ekf", "kind": "ekf"}]}  # fmt: skip
    path.write_text(yaml.safe_dump(doc))
    sc, rec = load_scenario(path)
    assert rec.log.name == "mrclam-dataset6-robot2" and len(rec.test_segments) == 5


# ------------------------------------------------------------------ the report over drives


def synthetic_drives_result(tmp_path) -> object:
    """A RealData of protocol drives with hand-made errors: 'a x1' has exactly half ekf-tuned's
    error on every drive, 'b x1' twice, and loses lock (2 m) on drive 2."""
    import pandas as pd

    from anfekf_bench.report.real import RealData

    ids = ["d6-r1", "d7-r1", "d9-r3"]
    rows = []
    rng = np.random.default_rng(1)
    for run, _ in enumerate(ids):
        base = 0.1 + 0.05 * run + 0.01 * rng.random(20)
        for name, scale in (("ekf-tuned", 1.0), ("a x1", 0.5), ("b x1", 2.0)):
            err = base * scale
            if name == "b x1" and run == 2:
                err = np.r_[err[:-1], 2.0]
            for k, e in enumerate(err):
                rows.append({"filter": name, "run": run, "step": k + 1, "t": 0.12 * k,
                             "pos_err": e})  # fmt: skip
    steps = pd.DataFrame(rows)
    manifest = {
        "protocol": "drives", "seed": 0, "runs": 3,
        "filters": [{"name": "ekf-tuned", "base": "ekf-tuned", "kind": "ekf-tuned", "start": None},
                    {"name": "a x1", "base": "a", "kind": "ekf", "start": 1.0},
                    {"name": "b x1", "base": "b", "kind": "sage-husa", "start": 1.0}],
        "data": {"drives": [{"drive": d} for d in ids]},
        "scenario": {"name": "syn"},
    }  # fmt: skip
    summary = [{"filter": n, "rmse_pos": float(steps[steps["filter"] == n]["pos_err"].mean())}
               for n in ("ekf-tuned", "a x1", "b x1")]  # fmt: skip
    return RealData("syn", "", tmp_path, manifest, steps, summary, pd.DataFrame())


def test_drive_ratios_are_paired_over_drives(tmp_path):
    from anfekf_bench.report.real import drive_lost_lock, drive_ratio_rows, drive_rmse

    rd = synthetic_drives_result(tmp_path)
    rm = drive_rmse(rd)
    assert list(rm.columns) == ["d6-r1", "d7-r1", "d9-r3"]
    assert np.allclose(rm.loc["a x1"] / rm.loc["ekf-tuned"], 0.5)
    lost = drive_lost_lock(rd)
    assert lost.loc["b x1"].tolist() == [False, False, True] and not lost.loc["a x1"].any()
    rows = {r["filter"]: r for r in drive_ratio_rows(rd, resamples=999)}
    assert rows["a x1"]["ratio"] == pytest.approx(0.5)
    assert rows["a x1"]["better"] == 3 and rows["a x1"]["lost_lock"] == 0
    assert math.isnan(rows["a x1"]["lo"])  # every drive the same ratio: no spread to resample
    b = rows["b x1"]
    assert b["ratio"] > 2.0 and b["lo"] <= b["ratio"] <= b["hi"] and b["lost_lock"] == 1
    assert rows["ekf-tuned"]["ratio"] == 1.0


def test_drives_report_figures_draw(tmp_path):
    from anfekf_bench.report.real import drives_errors_figure, drives_heatmap_figure

    rd = synthetic_drives_result(tmp_path)
    fig = drives_heatmap_figure(rd)
    assert fig.axes[0].images[0].get_array().shape == (2, 3)
    fig = drives_errors_figure(rd)
    assert any(line.get_gid() == "pos/d9-r3/ekf-tuned" for line in fig.axes[2].lines)


@pytest.mark.slow
def test_two_drives_end_to_end_with_report(tmp_path):
    """protocol drives through `anfekf run` and `anfekf report`: one run per drive, ekf-tuned of
    each drive tuned on the other dataset's drive, the kernel's RMSE equal to the filterpy run's."""
    from typer.testing import CliRunner

    from anfekf_bench.cli import app
    from anfekf_bench.report.real import drive_rmse, load_real

    doc = drives_doc(
        data={"kind": "mrclam", "path": "builtin", "drives": ["d6-r1", "d7-r1"]},
        eval_period_s=0.12,
        tuning={"sigma_v": [-1, 0], "sigma_w": [0, 1], "sigma_range": [-1, 0],
                "sigma_bearing": [-2, -1], "refine": False},
        filters=[{"name": "ekf", "kind": "ekf"}, {"name": "ekf-tuned", "kind": "ekf-tuned"},
                 {"name": "ekf-ml", "kind": "ekf-ml", "starts": [1.0], "max_evaluations": 40}],
    )  # fmt: skip
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(doc))
    runner = CliRunner()
    res = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    folder = tmp_path / "out" / "drives"
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["protocol"] == "drives" and manifest["runs"] == 2
    per_drive = {d["drive"]: d for d in manifest["tuning"]["per_drive"]}
    assert per_drive["d6-r1"]["tuned_on"] == ["d7-r1"]
    assert per_drive["d7-r1"]["tuned_on"] == ["d6-r1"]
    rm = drive_rmse(load_real(folder))
    for d in ("d6-r1", "d7-r1"):
        assert rm.loc["ekf-tuned", d] == pytest.approx(per_drive[d]["cross_rmse_pos"], rel=1e-6)
    # ekf-ml: one instance, fitted on each drive's own innovations, recorded with its cost
    fits = manifest["fits"]["filters"]["ekf-ml"]["runs"]
    assert [f["label"] for f in fits] == ["d6-r1", "d7-r1"] and not any(f["cached"] for f in fits)
    assert all(f["evaluations"] <= 42 and f["seconds"] > 0 for f in fits)
    assert "ekf-ml" in rm.index and not any(n.startswith("ekf-ml x") for n in rm.index)
    res = runner.invoke(app, ["report", str(folder), "--out", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "cross / in-dataset" in text and "drives_heatmap.png" in text
    # the audit against Vicon (issue 35): its tables, and the report shows them
    from anfekf_bench.storage import AUDIT_FILES

    for name in AUDIT_FILES.values():
        assert (folder / name).is_file(), name
    audited = pd.read_parquet(folder / AUDIT_FILES["drives"])
    assert audited["drive"].tolist() == ["d6-r1", "d7-r1"]
    assert "audited against Vicon" in text and "w scale [95 %]" in text
    # consistency run by run: the summary's share pools every scored step of both drives
    steps = pd.read_parquet(folder / "steps.parquet")
    nees = steps[steps["filter"] == "ekf-tuned"]["nees"].to_numpy()
    nees = nees[np.isfinite(nees)]
    summary = {r["filter"]: r for r in json.loads((folder / "summary.json").read_text())}
    assert summary["ekf-tuned"]["nees_in_bounds"] == pytest.approx(
        np.mean((nees > 0.2158) & (nees < 9.348)), abs=1e-3
    )
    runs = pd.read_parquet(folder / "runs.parquet")
    assert runs["nees_in_bounds"].between(0, 1).all()
