"""KalmanNet on recorded drives (SPEC 16, issue 26): the unicycle in torch against
models/unicycle.py, the masked loss, the windows and batches of recorded timelines, the numpy
filter against the torch one on a recorded stretch, training per cross-drive fold on the training
drives only, deterministic for a seed."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

pytest.importorskip("torch")
import torch  # noqa: E402

from anfekf_bench.engines.events import run_filter_events  # noqa: E402
from anfekf_bench.filters import kalmannet_train as kt  # noqa: E402
from anfekf_bench.filters.kalmannet import INSTALL_HINT, KalmanNetSpec  # noqa: E402
from anfekf_bench.filters.spec import FilterContext  # noqa: E402
from anfekf_bench.fitting.recorded import fit_on_drives  # noqa: E402
from anfekf_bench.models import Unicycle  # noqa: E402
from anfekf_bench.real_experiment import segment_inputs  # noqa: E402
from anfekf_bench.sources import mrclam as m  # noqa: E402
from anfekf_bench.sources.recorded import Segment, parse_real_scenario  # noqa: E402

T0 = 0.12


TINY = {"name": "kn", "kind": "kalmannet", "epochs": 2, "hidden_size": 6, "window_s": 10,
        "validation_runs": 1, "batch_size": 4, "bptt": 10}  # fmt: skip


def tiny_spec(**change) -> KalmanNetSpec:
    return KalmanNetSpec(**{**TINY, **change})


@pytest.fixture(scope="module")
def logs() -> dict:
    return {d: m.load_drive(d) for d in ("d6-r2", "d7-r1")}


def span(log, t0: float, t1: float):
    """A stretch of a drive as real_experiment's inputs, cold-started from ground truth at t0."""
    pose = np.array(m.interpolate_truth(log, t0))
    rec = SimpleNamespace(log=log, scorable=lambda t: m.scorable(log, t))
    return segment_inputs(rec, Segment(0, t0, t1, t0, pose, t1 - t0), T0)


@pytest.fixture(scope="module")
def stretches(logs) -> dict:
    """30 s of one drive of each of Datasets 6 and 7."""
    return {d: span(lg, lg.t_start + 20, lg.t_start + 50) for d, lg in logs.items()}


# ------------------------------------------------------------------ the motion model


def test_torch_unicycle_is_models_unicycle_to_1e_12():
    rng = np.random.default_rng(3)
    model, system = Unicycle(T0), kt.UnicycleSystem(1.0)
    x = np.column_stack([rng.normal(0, 3, 50), rng.normal(0, 3, 50), rng.uniform(-3.14, 3.14, 50)])
    x[0, 2] = math.pi  # the wrap's edge
    u = np.column_stack([rng.normal(0.2, 0.3, 50), rng.normal(0, 1.5, 50), rng.uniform(0, 0.3, 50)])
    got = system.f(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    want = np.array([model.f(xi, ui[:2], ui[2]) for xi, ui in zip(x, u, strict=True)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_a_span_of_steps_is_that_many_model_steps_and_zero_steps_add_nothing():
    rng = np.random.default_rng(4)
    model, system = Unicycle(T0), kt.UnicycleSystem(1.0)
    S, B = 40, 6
    u = np.stack([rng.normal(0.2, 0.3, (S, B)), rng.normal(0, 1.0, (S, B)),
                  rng.uniform(0.005, 0.2, (S, B))], axis=-1)  # fmt: skip
    x0 = np.column_stack([rng.normal(0, 2, B), rng.normal(0, 2, B), rng.uniform(-3, 3, B)])
    got = system.f_span(torch.as_tensor(x0), system.prepare_span(torch.as_tensor(u))).numpy()
    for b in range(B):
        x = x0[b]
        for s in range(S):
            x = model.f(x, u[s, b, :2], u[s, b, 2])
        np.testing.assert_allclose(got[b], x, rtol=0, atol=1e-12)
    padded = np.concatenate([u, np.zeros((7, B, 3))])  # recorded_batch's padding
    A, C, D = (t.numpy() for t in system.prepare_span(torch.as_tensor(padded)))
    A0, C0, D0 = (t.numpy() for t in system.prepare_span(torch.as_tensor(u)))
    assert np.array_equal(A, A0) and np.array_equal(C, C0) and np.array_equal(D, D0)


# ------------------------------------------------------------------ windows, batches, the loss


def test_windows_cover_the_drive_from_scored_truth_without_overlap(stretches):
    inp = stretches["d6-r2"]
    windows = kt.windows_of_drive(inp.timeline, inp.truth, 10.0)
    assert len(windows) == 3
    for w in windows:
        assert np.all(np.isfinite(w.x0)) and w.timeline.t[0] > w.timeline.t_start
        assert len(w.truth) == int(w.timeline.record.sum())
    # Consecutive and disjoint: every stamp after the first window's start is in exactly one.
    t = np.concatenate([w.timeline.t for w in windows])
    assert np.all(np.diff(t) > 0)
    assert len(np.concatenate([w.timeline.z for w in windows])) == sum(
        int(w.timeline.lm[-1]) for w in windows
    )


def test_the_masked_loss_leaves_unscored_truth_out(stretches):
    """NaN truth (not scored) is no target: the loss is the mean over the scored ones only, the
    same whatever the unscored rows hold, and training on it stays finite."""
    inp = stretches["d6-r2"]
    truth = inp.truth.copy()
    truth[40:120] = np.nan  # a Vicon gap
    windows = kt.windows_of_drive(inp.timeline, truth, 10.0)
    system = kt.UnicycleSystem(3.0)
    batch = kt.recorded_batch(system, windows)
    spec = tiny_spec()
    torch.manual_seed(0)
    net = kt.GainNet(11, spec.hidden_size, 3, 2)
    scales = (np.ones(2), np.ones(3))
    loss, est = kt.run_pass(net, system, batch, scales, bptt=10**6)
    targets = [ev for ev in batch.events if ev[0] == "target"]
    errs = []
    for e, ev in zip(est.numpy(), targets, strict=True):
        mask = ev[2].numpy()
        d = e[mask] - ev[1].numpy()[mask]
        d[:, 2] = (d[:, 2] + math.pi) % (2 * math.pi) - math.pi
        errs.append(np.sum(d**2, axis=1))
    # Every scored time is a target but the first window's start (a window's start is the
    # previous window's last target).
    assert sum(len(v) for v in errs) == int(np.isfinite(truth[:, 0]).sum()) - 1
    assert loss == pytest.approx(float(np.mean(np.concatenate(errs))), rel=1e-12)
    result = kt.train_recorded(tiny_spec(epochs=1), [(inp.timeline, truth)], Unicycle(T0))
    assert all(map(math.isfinite, result.epoch_loss + result.validation_loss))
    assert all(np.isfinite(a).all() for a in result.weights.arrays.values())


def test_the_numpy_filter_is_the_torch_filter_on_a_recorded_stretch(stretches):
    """The filter the engine runs (numpy, `predict(u, dt)` on the unicycle) and the one training
    optimises (torch, aligned windows of several lengths in one batch) are the same maths."""
    inp = stretches["d6-r2"]
    spec = tiny_spec(epochs=1)
    result = kt.train_recorded(spec, [(inp.timeline, inp.truth)], Unicycle(T0))
    system = kt.UnicycleSystem(result.weights.range_scale)
    windows = kt.windows_of_drive(inp.timeline, inp.truth, 10.0)
    batch = kt.recorded_batch(system, windows)
    est = kt.estimate(result.weights, system, batch)  # (targets, B, 3)
    targets = [ev[2].numpy() for ev in batch.events if ev[0] == "target"]
    trained = spec.with_weights(result.weights)
    for b, w in enumerate(windows):
        ctx = FilterContext(x0=w.x0, P0=np.eye(3) * 1e-3, Qu=np.eye(2), R=np.eye(2),
                            model=Unicycle(T0), dt=T0, gate=None)  # fmt: skip
        out = run_filter_events(trained.build(ctx), w.timeline)
        scored = out["x"][np.all(np.isfinite(w.truth), axis=1)]
        mine = np.array([e[b] for e, mask in zip(est, targets, strict=True) if mask[b]])
        assert len(mine) == len(scored) > 0
        np.testing.assert_allclose(mine, scored, rtol=0, atol=1e-9)


# ------------------------------------------------------------------ folds of the drives protocol


def two_drive_world(stretches):
    drives = [
        SimpleNamespace(id=d, dataset=m.drive_dataset(d), log=inp.segment, segment=inp.segment)
        for d, inp in stretches.items()
    ]
    return SimpleNamespace(drives=drives)


def fold_scenario(**spec):
    doc = {"name": "kn-drives", "protocol": "drives",
           "data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r2", "d7-r1"]},
           "filters": [{"name": "ekf", "kind": "ekf"},
                       {**TINY, **spec}]}  # fmt: skip
    return parse_real_scenario(doc)


def learned(fitted: dict) -> dict:
    """A fold's fit without its cost (times differ from one training to the next)."""
    return {k: v for k, v in fitted.items() if k not in ("training_time_s", "training_cpu_s")}


def fit_folds(scenario, stretches, monkeypatch):
    monkeypatch.setattr("anfekf_bench.fitting.recorded.log_digest", lambda log: "fixed")
    return fit_on_drives(scenario, two_drive_world(stretches), stretches, None)


def test_each_fold_trains_on_the_other_datasets_drive_only_and_deterministically(
    stretches, monkeypatch
):
    scenario = fold_scenario()
    runs, records = fit_folds(scenario, stretches, monkeypatch)
    rec = records["kn"]  # keyed by the datasets trained on
    assert rec["6"]["train_drives"] == ["d6-r2"] and rec["7"]["train_drives"] == ["d7-r1"]
    assert rec["6"]["fitted"]["weights_sha256"] != rec["7"]["fitted"]["weights_sha256"]
    assert rec["6"]["fitted"]["training_time_s"] > 0 and not rec["6"]["cached"]
    assert "weights_base64" not in rec["6"]["fitted"]
    kn = {d: next(f for f in s.filters if f.name == "kn") for d, s in runs.items()}
    assert kn["d6-r2"].trained and kn["d7-r1"].trained
    # Same seed, same bytes; Dataset 7's drive changed (truth and measurements): the weights
    # that score it (trained on Dataset 6) are the same, those trained on it are not.
    _, again = fit_folds(scenario, stretches, monkeypatch)
    for k in ("6", "7"):
        assert learned(again["kn"][k]["fitted"]) == learned(rec[k]["fitted"])
    changed = dict(stretches)
    inp = stretches["d7-r1"]
    changed["d7-r1"] = replace(
        inp, truth=inp.truth + 0.5, timeline=replace(inp.timeline, z=inp.timeline.z * 1.1)
    )
    _, other = fit_on_drives(scenario, two_drive_world(stretches), changed, None)
    assert learned(other["kn"]["6"]["fitted"]) == learned(rec["6"]["fitted"])
    assert other["kn"]["7"]["fitted"]["weights_sha256"] != rec["7"]["fitted"]["weights_sha256"]
    scoring_d7 = next(f for f in runs["d7-r1"].filters if f.name == "kn").fitted
    assert scoring_d7["weights_sha256"] == rec["6"]["fitted"]["weights_sha256"]


def test_a_fold_is_read_from_the_cache(stretches, monkeypatch, tmp_path):
    scenario = fold_scenario(epochs=1)
    monkeypatch.setattr("anfekf_bench.fitting.recorded.log_digest", lambda log: "fixed")
    world = two_drive_world(stretches)
    _, first = fit_on_drives(scenario, world, stretches, tmp_path)
    assert len(list(tmp_path.glob("fit-*.json"))) == 2

    def refuse(*a, **k):
        raise AssertionError("a cached fold was trained again")

    monkeypatch.setattr(KalmanNetSpec, "fit", refuse)
    _, second = fit_on_drives(scenario, world, stretches, tmp_path)
    assert all(second["kn"][k]["cached"] for k in ("6", "7"))
    assert [second["kn"][k]["fitted"] for k in ("6", "7")] == [
        first["kn"][k]["fitted"] for k in ("6", "7")
    ]


def test_more_held_out_windows_than_windows_is_a_one_line_plan_error(stretches, monkeypatch):
    from anfekf_bench.outputs import PlanError

    with pytest.raises(PlanError, match=r"^filters: kn: validation_runs: 50 must be fewer"):
        fit_folds(fold_scenario(validation_runs=50), stretches, monkeypatch)


# ------------------------------------------------------------------ the scenario file


def test_kalmannet_is_one_instance():
    scenario = fold_scenario()
    assert scenario.instance_names() == ["ekf x0.25", "ekf x1", "ekf x4", "kn"]


def test_on_protocol_segments_it_trains_on_the_training_segments_only(tmp_path):
    """A user's log, protocol segments: one fit on the training segments, cached, recorded."""
    from typer.testing import CliRunner

    from anfekf_bench.cli import app

    from .test_real_data import user_scenario

    path = user_scenario(tmp_path)
    doc = yaml.safe_load(path.read_text())
    doc["filters"] = [doc["filters"][1], {**TINY, "epochs": 1, "window_s": 5}]
    doc["claims"] = []
    path.write_text(yaml.safe_dump(doc))
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    manifest = json.loads((tmp_path / "out" / "my-robot" / "manifest.json").read_text())
    fold = manifest["training"]["kn"]["train"]
    train = [s["index"] for s in manifest["data"]["train_segments"]]
    assert fold["train_segments"] == train and not fold["cached"]
    assert fold["fitted"]["weights_sha256"] and fold["fitted"]["training_time_s"] > 0
    assert "kn" in [f["name"] for f in manifest["filters"]]


def test_without_torch_a_drives_scenario_naming_kalmannet_is_one_line(monkeypatch):
    from anfekf_bench.config import ScenarioError

    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(ScenarioError) as err:
        fold_scenario()
    assert str(err.value).endswith(INSTALL_HINT) and "\n" not in str(err.value)


def test_the_shipped_config_matches_the_main_drives_config():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "configs"
    learned = yaml.safe_load((root / "learned-drives" / "mrclam-drives-kalmannet.yaml").read_text())
    main = yaml.safe_load((root / "drives" / "mrclam-drives.yaml").read_text())
    for key in ("data", "tune_on", "eval_period_s", "naive", "gate_probability", "seed"):
        assert learned[key] == main[key], key
    scenario = parse_real_scenario(learned)
    assert "kalmannet" in scenario.instance_names() and scenario.reference() == "ekf-tuned"


@pytest.mark.slow
def test_two_drives_end_to_end_record_the_training_per_fold(tmp_path):
    from typer.testing import CliRunner

    from anfekf_bench.cli import app

    doc = {"name": "kn-e2e", "protocol": "drives", "eval_period_s": 0.12, "starts": [1],
           "data": {"kind": "mrclam", "path": "builtin", "drives": ["d6-r1", "d7-r1"]},
           "tuning": {"sigma_v": [-1, 0], "sigma_w": [0, 1], "sigma_range": [-1, 0],
                      "sigma_bearing": [-2, -1], "refine": False},
           "filters": [{"name": "ekf-tuned", "kind": "ekf-tuned"},
                       {"name": "kalmannet", "kind": "kalmannet", "epochs": 1, "hidden_size": 4,
                        "window_s": 300, "validation_runs": 0}]}  # fmt: skip
    path = tmp_path / "kn.yaml"
    path.write_text(yaml.safe_dump(doc))
    res = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    manifest = json.loads((tmp_path / "out" / "kn-e2e" / "manifest.json").read_text())
    folds = manifest["training"]["kalmannet"]
    assert folds["6"]["train_drives"] == ["d6-r1"] and folds["7"]["train_drives"] == ["d7-r1"]
    assert all(f["fitted"]["training_time_s"] > 0 for f in folds.values())
    assert [f["name"] for f in manifest["filters"]] == ["ekf-tuned", "kalmannet"]


def test_each_folds_trained_weights_run_on_the_fast_engine_as_on_filterpy(stretches, monkeypatch):
    """The drives protocol hands each drive its fold's weights (`with_fit`); `runner.run_spec`
    runs them on the fast engine's kernel (the unicycle) with filterpy's results."""
    from anfekf_bench.runner import engine_of, run_spec

    from .test_fast_engine import assert_same_run

    runs, _ = fit_folds(fold_scenario(epochs=1), stretches, monkeypatch)
    updates = 0
    for drive, scenario in runs.items():
        spec = next(f for f in scenario.filters if f.name == "kn")
        inp = stretches[drive]
        ctx = FilterContext(x0=inp.segment.pose, P0=np.eye(3) * 1e-3, Qu=np.eye(2), R=np.eye(2),
                            model=Unicycle(T0), dt=T0, gate=None)  # fmt: skip
        assert engine_of("fast", spec, model=ctx.model) == "fast"
        ref = run_spec("filterpy", spec, ctx, inp.timeline)
        out = run_spec("fast", spec, ctx, inp.timeline)
        assert not ref["diverged"] and np.isfinite(ref["x"]).all()
        assert_same_run(ref, out, what=drive)
        updates += ref["n_updates"]
    assert updates > 0  # (d7-r1's stretch sees no landmark)
