"""KalmanNet (filters/kalmannet.py, kalmannet_train.py): the linear-Gaussian acceptance test,
determinism, a tiny training on the robot model, the missing-extra error, and the NEES that is
"not available" (NaN) through the metrics."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from anfekf_bench.analysis.metrics import add_trace_metrics, format_number, summarize_filter
from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError, parse_scenario, resolve_world
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters.context import build_filter, filter_context
from anfekf_bench.filters.kalmannet import INSTALL_HINT, KalmanNetSpec, KalmanNetWeights
from anfekf_bench.filters.registry import KINDS
from anfekf_bench.fitting.simulated import training_seeds
from anfekf_bench.runner import simulate
from anfekf_bench.sources.simulator import world_path

from .conftest import small_scenario, write_scenario

torch = pytest.importorskip("torch")
kt = pytest.importorskip("anfekf_bench.filters.kalmannet_train")


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---------------------------------------------------------------------------------------------
# A linear-Gaussian model: 2-D constant velocity, position measurements


def cv_model(dt=1.0, q=0.1, r=1.0):
    F1 = np.array([[1.0, dt], [0.0, 1.0]])
    Q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    H1 = np.array([[1.0, 0.0]])
    return np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1), np.kron(np.eye(2), H1), r * np.eye(2)


def simulate_linear(F, Q, H, R, n_seq, T, rng):
    """x (n_seq, T + 1, n) from x0 ~ N(0, I); z (n_seq, T, m) of x[:, 1:]."""
    n, m = F.shape[0], H.shape[0]
    LQ, LR = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    x = np.zeros((n_seq, T + 1, n))
    x[:, 0] = rng.standard_normal((n_seq, n))
    z = np.zeros((n_seq, T, m))
    for t in range(T):
        x[:, t + 1] = x[:, t] @ F.T + rng.standard_normal((n_seq, n)) @ LQ.T
        z[:, t] = x[:, t + 1] @ H.T + rng.standard_normal((n_seq, m)) @ LR.T
    return x, z


def kalman_filter(F, Q, H, R, x, z):
    """The Kalman filter from the known x0 (P0 = 0): the optimal estimates (n_seq, T, n)."""
    x_est, P, out = x[:, 0].copy(), np.zeros((F.shape[0],) * 2), []
    for t in range(z.shape[1]):
        x_est, P = x_est @ F.T, F @ P @ F.T + Q
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x_est = x_est + (z[:, t] - x_est @ H.T) @ K.T
        P = (np.eye(len(P)) - K @ H) @ P
        out.append(x_est.copy())
    return np.stack(out, axis=1)


def train_linear(seed=0, epochs=6, T=30):
    F, Q, H, R = cv_model()
    rng = np.random.default_rng(0)
    system = kt.LinearSystem(F, H)
    batches = [kt.linear_batch(*simulate_linear(F, Q, H, R, 20, T, rng)) for _ in range(5)]
    result = kt.fit(
        system, batches, epochs=epochs, learning_rate=1e-2, hidden_size=16, bptt=T, seed=seed
    )
    return result, system, (F, Q, H, R), rng


def test_on_a_linear_gaussian_model_its_mse_is_within_10_percent_of_the_kalman_filter():
    result, system, (F, Q, H, R), rng = train_linear()
    x, z = simulate_linear(F, Q, H, R, 500, 30, rng)  # held-out sequences
    mse_kf = np.mean((kalman_filter(F, Q, H, R, x, z) - x[:, 1:]) ** 2)
    est = kt.estimate(result.weights, system, kt.linear_batch(x, z)).transpose(1, 0, 2)
    mse_kn = np.mean((est - x[:, 1:]) ** 2)
    # The Kalman filter is optimal here: the network cannot beat it beyond sampling noise.
    assert 0.97 * mse_kf < mse_kn < 1.10 * mse_kf, (mse_kn, mse_kf)
    # Dead reckoning (the untrained network's zero gain) is far worse: the bound is not loose.
    untrained = kt.to_weights(kt.GainNet(12, 16, 4, 2), (np.ones(2), np.ones(4)), 1.0)
    dead = kt.estimate(untrained, system, kt.linear_batch(x, z))
    assert np.mean((dead.transpose(1, 0, 2) - x[:, 1:]) ** 2) > 1.5 * mse_kf
    assert result.training_time_s > 0 and len(result.epoch_loss) == 6
    assert 0 < result.training_cpu_s


def test_held_out_runs_keep_the_epoch_that_does_best_on_them():
    F, Q, H, R = cv_model()
    rng = np.random.default_rng(5)
    system = kt.LinearSystem(F, H)
    batches = [kt.linear_batch(*simulate_linear(F, Q, H, R, 20, 30, rng)) for _ in range(2)]
    held_out = [kt.linear_batch(*simulate_linear(F, Q, H, R, 20, 30, rng))]
    settings = dict(epochs=4, learning_rate=5e-2, hidden_size=8, bptt=30, seed=0)
    result = kt.fit(system, batches, validation=held_out, **settings)
    assert len(result.validation_loss) == 4
    kept = kt.from_weights(result.weights, system)
    scales = (result.weights.obs_scale, result.weights.state_scale)
    with torch.no_grad():
        loss = kt.run_pass(kept, system, held_out[0], scales, 30)[0]
    assert loss == min(result.validation_loss)
    assert result.best_epoch == 1 + int(np.argmin(result.validation_loss))
    last = kt.fit(system, batches, **settings)  # without held-out runs: the last epoch's
    assert last.best_epoch == 4 and not last.validation_loss
    if result.best_epoch != 4:
        assert last.weights.to_bytes() != result.weights.to_bytes()


def test_same_seed_same_weights_bytes_and_another_seed_others():
    a = train_linear(seed=3, epochs=2)[0].weights.to_bytes()
    b = train_linear(seed=3, epochs=2)[0].weights.to_bytes()
    c = train_linear(seed=4, epochs=2)[0].weights.to_bytes()
    assert a == b and a != c


def test_weights_round_trip_through_bytes():
    w = train_linear(epochs=1)[0].weights
    back = KalmanNetWeights.from_bytes(w.to_bytes())
    assert back.to_bytes() == w.to_bytes() and back.hidden_size == 16
    for name, array in w.arrays.items():
        np.testing.assert_array_equal(back.arrays[name], array)
    with pytest.raises(ValueError, match="size"):
        KalmanNetWeights.from_bytes(w.to_bytes()[:-8])


# ---------------------------------------------------------------------------------------------
# The robot model: a tiny training on short simulated runs, then an evaluation run


def small_kalmannet_scenario(**spec):
    doc = small_scenario(record_every=8)
    kn = {"name": "kn", "kind": "kalmannet", "epochs": 2, "hidden_size": 8, "validation_runs": 1}
    doc["filters"] = [{"name": "ekf", "kind": "ekf"}, {**kn, **spec}]
    doc["training"] = {"runs": 3}
    scenario = parse_scenario(doc)
    return scenario, resolve_world(scenario.world, Path("small.yaml"))


@pytest.fixture(scope="module")
def tiny_robot():
    scenario, world = small_kalmannet_scenario()
    spec = scenario.filters[1]
    path = world_path(world)
    runs = [simulate(scenario, world, s, path) for s in training_seeds(scenario.seed, 3)]
    result = spec.train(runs, world, filter_context(spec, scenario, world))
    evaluation = simulate(scenario, world, np.random.SeedSequence(scenario.seed).spawn(1)[0], path)
    return scenario, world, spec, result, evaluation


def test_a_tiny_robot_training_runs_an_evaluation_run_with_finite_estimates(tiny_robot):
    scenario, world, spec, result, data = tiny_robot
    assert result.training_time_s < 30 and all(map(math.isfinite, result.epoch_loss))
    # 2 runs fitted, 1 held out: one validation loss per epoch, the best epoch's weights kept.
    assert len(result.validation_loss) == 2 and 1 <= result.best_epoch <= 2
    trained = spec.with_weights(result.weights)
    out = run_filter(build_filter(trained, scenario, world), data, world, scenario.record_every)
    assert not out["diverged"] and np.isfinite(out["x"]).all()
    assert np.isnan(out["P"]).all() and math.isnan(out["nis_sum"])
    seen = sum(len(s.ids) for s in data.scans)
    assert seen > 0 and out["n_updates"] == seen and out["n_rejected"] == 0
    # It corrects: far closer to the truth than its own dead reckoning would stay.
    x_true = data.truth.x[scenario.record_every :: scenario.record_every]
    err = np.hypot(*(out["x"][:, :2] - x_true[:, :2]).T)
    assert np.sqrt(np.mean(err**2)) < 5.0


def test_the_numpy_filter_is_the_trained_torch_filter(tiny_robot):
    """The filter the engine runs (numpy) and the one training optimised (torch) are the same
    maths: the same estimates at every scan step."""
    scenario, world, spec, result, data = tiny_robot
    trained = spec.with_weights(result.weights)
    out = run_filter(build_filter(trained, scenario, world), data, world, world.sensor_every)
    ctx = filter_context(spec, scenario, world)
    system = kt.RobotSystem(ctx.dt, ctx.model.B, result.weights.range_scale)
    est = kt.estimate(result.weights, system, kt.robot_batch(system, [data], world))[:, 0]
    np.testing.assert_allclose(out["x"][: len(est)], est, rtol=0, atol=1e-9)


def test_its_nees_is_not_available_through_the_metrics(tiny_robot):
    scenario, world, spec, result, data = tiny_robot
    trained = spec.with_weights(result.weights)
    trace = run_filter(build_filter(trained, scenario, world), data, world, scenario.record_every)
    x_true = data.truth.x[scenario.record_every :: scenario.record_every][: len(trace["x"])]
    trace = add_trace_metrics(trace, x_true)
    assert np.isnan(trace["nees"]).all() and np.isfinite(trace["pos_err"]).all()
    runs = 3
    rec = summarize_filter(
        np.tile(trace["pos_err"], (runs, 1)),
        np.tile(trace["heading_err"], (runs, 1)),
        np.tile(trace["nees"], (runs, 1)),
        np.zeros(runs, dtype=bool),
    )
    assert math.isfinite(rec["rmse_pos"]) and rec["diverged"] == 0 and rec["inconsistent"] == 0
    assert math.isnan(rec["anees"]) and math.isnan(rec["nees_in_bounds"])
    assert format_number(rec["anees"], 2) == "-"


def test_a_spec_without_weights_does_not_build():
    scenario, world = small_kalmannet_scenario()
    with pytest.raises(RuntimeError, match="no trained weights"):
        build_filter(scenario.filters[1], scenario, world)


# ---------------------------------------------------------------------------------------------
# Without the extra


def test_registered_with_documented_defaults():
    assert "kalmannet" in KINDS and KalmanNetSpec.fitted_on_training
    fields = KalmanNetSpec.model_fields
    assert "train_runs" not in fields, "training.runs is the one training-set size"
    for name in ("epochs", "learning_rate", "hidden_size", "bptt", "validation_runs", "seed"):
        assert fields[name].description, name


def test_without_torch_a_scenario_naming_kalmannet_is_one_line_exit_2(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)  # what `import torch` sees when not installed
    doc = small_scenario()
    doc["filters"] = [{"name": "ekf", "kind": "ekf"}, {"name": "kn", "kind": "kalmannet"}]
    with pytest.raises(ScenarioError, match=r"filters\.1: .*\.\[learned\]"):
        parse_scenario(doc, "x.yaml")
    path = write_scenario(tmp_path / "kn.yaml", doc)
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0] == f"error: {path}: filters.1: {INSTALL_HINT}"
    assert not (tmp_path / "out").exists(), "nothing is written before the error"


@pytest.mark.slow
def test_the_report_says_a_filter_without_covariance_has_no_nees(tmp_path):
    """What the report does with a filter whose P (so NEES) is NaN at every step: the NEES
    figure's legend and the summary table say "not available"; its RMSE is still reported."""
    from anfekf_bench.report import plots
    from anfekf_bench.report.report import load_scenario_data, markdown_table, summary_rows
    from anfekf_bench.storage import parquet_provenance, read_steps, write_parquet

    filters = [{"name": "ekf", "kind": "ekf"}, {"name": "ekf-oracle", "kind": "ekf-oracle"}]
    doc = small_scenario(runs=3, record_every=8, filters=filters)
    path = write_scenario(tmp_path / "s.yaml", doc)
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    folder = tmp_path / "out" / "small"
    steps = read_steps(folder)
    nan_columns = ["nees"] + [c for c in steps.columns if c.startswith("P_")]
    steps.loc[steps["filter"] == "ekf", nan_columns] = np.nan  # as KalmanNet records them
    provenance = parquet_provenance(folder / "steps.parquet")
    write_parquet(folder / "steps.parquet", steps, provenance)  # the batch's own file, edited
    sc = load_scenario_data(folder)
    fig = plots.nees_figure(sc)
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend())]
    legend = [t.get_text() for leg in legends for t in leg.get_texts()]
    assert "ekf: NEES not available (no covariance)" in legend
    assert any(t.startswith("ekf-oracle: ANEES") for t in legend)
    rows = {r.filter: r for r in summary_rows([sc])}
    assert math.isnan(rows["ekf"].anees) and math.isfinite(rows["ekf"].rmse_pos)
    assert math.isfinite(rows["ekf-oracle"].anees)
    assert "NEES not available (-) for ekf: no covariance" in markdown_table(list(rows.values()))


def test_a_trained_spec_pickles_with_its_weights(tiny_robot):
    """Workers receive the spec pickled: the weights travel with it."""
    import pickle

    scenario, world, spec, result, data = tiny_robot
    back = pickle.loads(pickle.dumps(spec.with_weights(result.weights)))
    assert back._weights.to_bytes() == result.weights.to_bytes() and spec._weights is None


def test_a_non_finite_gain_marks_the_run_diverged(tiny_robot):
    scenario, world, spec, result, data = tiny_robot
    arrays = {k: v.copy() for k, v in result.weights.arrays.items()}
    arrays["fc_out2.bias"][0] = np.nan
    broken = KalmanNetWeights(
        arrays, result.weights.obs_scale, result.weights.state_scale,
        result.weights.range_scale, result.weights.hidden_size,
    )  # fmt: skip
    flt = build_filter(spec.with_weights(broken), scenario, world)
    out = run_filter(flt, data, world, scenario.record_every)
    assert out["diverged"] and np.isnan(out["x"][-1]).all()


# ---------------------------------------------------------------------------------------------
# Trained by `anfekf run` itself: the training-runs mechanism (anfekf_bench.fitting.simulated)


class _Stop(Exception):
    pass


def tiny_run_scenario(tmp_path, **training):
    doc = small_scenario(runs=2, jobs=1, record_every=8)
    doc["filters"] = [
        {"name": "ekf", "kind": "ekf"},
        {"name": "kn", "kind": "kalmannet", "epochs": 2, "hidden_size": 8, "validation_runs": 1},
    ]
    doc["training"] = {"runs": 3, **training}
    return write_scenario(tmp_path / "kn.yaml", doc)


def test_anfekf_run_trains_kalmannet_and_records_the_weights_and_time(tmp_path):
    """The CLI trains it on the training runs (no second mechanism), records the weights' hash
    and the training time in the manifest, and a second identical run trains the same weights
    and scores the same results."""
    import json

    import pandas as pd

    path = tiny_run_scenario(tmp_path)
    shas, summaries = [], []
    for out in ("a", "b"):
        result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / out)])
        assert result.exit_code == 0, result.output
        assert "kn fitted (3 training runs)" in result.output
        folder = tmp_path / out / "small"
        manifest = json.loads((folder / "manifest.json").read_text())
        rec = manifest["training"]["kn"]
        assert rec["kind"] == "kalmannet" and rec["cached"] is False and rec["training_runs"] == 3
        fitted = rec["fitted"]
        assert len(fitted["weights_sha256"]) == 64 and "weights_base64" not in fitted
        assert fitted["training_time_s"] > 0 and fitted["epochs"] == 2
        assert 1 <= fitted["best_epoch"] <= 2 and len(fitted["validation_loss"]) == 2
        shas.append(fitted["weights_sha256"])
        summary = pd.read_parquet(folder / "summary.parquet")
        kn = summary[summary["filter"] == "kn"].iloc[0]
        assert math.isfinite(kn["rmse_pos"]) and math.isnan(kn["anees"])
        summaries.append(summary.drop(columns=[c for c in summary if "time" in c]))
    assert shas[0] == shas[1], "deterministic on CPU for a seed"
    pd.testing.assert_frame_equal(summaries[0], summaries[1])


def test_a_resumed_batch_reads_the_trained_weights_from_the_cache(tmp_path, monkeypatch):
    from anfekf_bench.experiment import execute, make_plan
    from anfekf_bench.scenarios import load_scenario

    scenario, world = load_scenario(tiny_run_scenario(tmp_path))
    plan = make_plan(scenario, world, None, None, None)

    def stop(result):
        raise _Stop

    with pytest.raises(_Stop):
        execute(plan, tmp_path / "out", on_result=stop)
    cached = list((tmp_path / "out" / "small" / ".runs").glob("fit-*.json"))
    assert len(cached) == 1
    import json

    doc = json.loads(cached[0].read_text())

    def train_again(*args, **kwargs):
        raise AssertionError("trained again although the fit is cached")

    monkeypatch.setattr(kt, "train", train_again)
    records, folder = execute(plan, tmp_path / "out")
    rec = json.loads((folder / "manifest.json").read_text())["training"]["kn"]
    assert rec["cached"] is True
    assert rec["fitted"]["weights_sha256"] == doc["fitted"]["weights_sha256"]
    assert any(r["filter"] == "kn" and math.isfinite(r["rmse_pos"]) for r in records)


def test_a_fit_restores_the_exact_weights_and_refuses_a_tampered_one(tiny_robot):
    import base64
    import hashlib

    scenario, world, spec, result, data = tiny_robot
    raw = result.weights.to_bytes()
    fitted = {"weights_sha256": hashlib.sha256(raw).hexdigest(),
              "weights_base64": base64.b64encode(raw).decode()}  # fmt: skip
    assert spec.with_fit(fitted)._weights.to_bytes() == raw
    fitted["weights_sha256"] = "0" * 64
    with pytest.raises(ValueError, match="do not match their hash"):
        spec.with_fit(fitted)


def test_more_validation_runs_than_training_runs_is_one_line_exit_2(tmp_path):
    path = tiny_run_scenario(tmp_path, runs=1)
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    want = "filters.kn.validation_runs: 1 must be fewer than training.runs (1)"
    assert len(lines) == 1 and want in lines[0]
    assert not (tmp_path / "out" / "small").exists()


@pytest.mark.parametrize(
    "name, source",
    [("correct", "correct"), ("wrong_r", "wrong_r"), ("wrong_q", "wrong_q"),
     ("consistency", "consistency"), ("r_small", "zoo/r_small"), ("q_large", "zoo/q_large")],
)  # fmt: skip
def test_make_learned_scores_the_runs_of_the_scenario_it_mirrors(name, source):
    """configs/learned/<name>.yaml: the source scenario's seed and noise (so its 20 runs are the
    first 20 of the source's), the four filters, and KalmanNet compared with the ANFEKF."""
    from anfekf_bench.scenarios import load_scenario

    configs = Path(__file__).resolve().parents[1] / "configs"
    learned, _ = load_scenario(configs / "learned" / f"{name}.yaml")
    original, _ = load_scenario(configs / f"{source}.yaml")
    assert learned.seed == original.seed and learned.runs == 20 and learned.training.runs == 50
    assert learned.true_noise == original.true_noise
    assert learned.filter_noise == original.filter_noise
    assert [f.kind for f in learned.filters] == ["ekf", "anfekf", "ekf-oracle", "kalmannet"]
    assert ("kalmannet", "anfekf") in [tuple(p) for p in learned.compare]


@pytest.mark.slow
def test_anfekf_run_engine_fast_scores_kalmannet_as_the_filterpy_engine(tmp_path):
    """The trained network end to end on the fast engine: `anfekf run --engine fast` trains the
    same weights (cached in the run store, handed to the workers) and scores the same summary
    as the filterpy engine, and the manifest says kalmannet ran on the fast engine."""
    import json

    import pandas as pd

    path = tiny_run_scenario(tmp_path)
    summaries, shas = {}, set()
    for engine in ("filterpy", "fast"):
        out = tmp_path / engine
        args = ["run", str(path), "--out", str(out), "--engine", engine]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
        manifest = json.loads((out / "small" / "manifest.json").read_text())
        assert manifest["engines"] == {"ekf": engine, "kn": engine}
        shas.add(manifest["training"]["kn"]["fitted"]["weights_sha256"])
        summary = pd.read_parquet(out / "small" / "summary.parquet")
        summaries[engine] = summary.drop(columns=[c for c in summary if "time" in c])
    assert len(shas) == 1
    a, b = summaries["filterpy"], summaries["fast"]
    assert list(a["filter"]) == list(b["filter"]) == ["ekf", "kn"]
    numeric = a.select_dtypes("number").columns
    pd.testing.assert_frame_equal(a[numeric], b[numeric], rtol=1e-9, atol=0)
