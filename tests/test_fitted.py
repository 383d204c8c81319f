"""Filters fitted on training runs (anfekf_bench.fitting.simulated, filters.fitted, engines.tuning):
`ekf-ml` (innovation likelihood, no truth) and `ekf-tuned` (position RMSE, truth) on simulated
scenarios; training seeds disjoint from evaluation; the fit cached in the run store, recorded in
the manifest, handed to the workers."""

from __future__ import annotations

import json
import math
import pickle

import numpy as np
import pytest

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines import fast
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.engines.tuning import TrainingProblem
from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.filters.context import build_filter, filter_context
from anfekf_bench.filters.ekf import RobotEKF
from anfekf_bench.filters.fitted import EKFMLSpec, EKFTunedSpec, FilterNotFitted
from anfekf_bench.filters.registry import SPEC_BY_KIND
from anfekf_bench.fitting.simulated import (
    TRAINING_BRANCH,
    fit_filters,
    simulate_training,
    training_seeds,
)
from anfekf_bench.runner import run_tasks, simulate
from anfekf_bench.storage import MANIFEST_FILE, RUNS_DIR

from .conftest import small_scenario

TRUE = {"sigma_v": 0.3, "sigma_gamma_deg": 3.0, "sigma_range": 0.1, "sigma_bearing_deg": 1.0}
WRONG = {"sigma_v": 0.1, "sigma_gamma_deg": 1.0, "sigma_range": 0.3, "sigma_bearing_deg": 3.0}


def _scenario(training_runs: int = 4, **overrides):
    doc = small_scenario(
        record_every=4,
        true_noise=TRUE,
        filter_noise=WRONG,
        training={"runs": training_runs},
        filters=[
            {"name": "ekf", "kind": "ekf"},
            {"name": "ml", "kind": "ekf-ml", "max_evaluations": 60},
            {"name": "tuned", "kind": "ekf-tuned", "starts": [1.0], "max_evaluations": 60},
            {"name": "ekf-oracle", "kind": "ekf-oracle"},
        ],
    )
    doc.update(overrides)
    scenario = parse_scenario(doc)
    return scenario, resolve_world(scenario.world, ".")


# ---------------------------------------------------------------------------------------------
# The objective kernel against the reference engine


class _LikelihoodEKF(RobotEKF):
    """filterpy's EKF that sums log|S| + nu^T S^-1 nu over every associated innovation."""

    nll = 0.0

    def update_landmark(self, z, landmark):
        inn = self.innovation(z, landmark)
        S = inn.HPHt + self.R
        self.nll += math.log(np.linalg.det(S)) + float(inn.nu @ np.linalg.solve(S, inn.nu))
        return super().update_landmark(z, landmark)


def test_objective_kernel_equals_the_reference_engine():
    scenario, world = _scenario()
    data = simulate(scenario, world, np.random.SeedSequence(11))
    ctx = filter_context(scenario.filters[0], scenario, world)
    flt = _LikelihoodEKF(**ctx.kwargs())
    trace = run_filter(flt, data, world, scenario.record_every)
    problem = TrainingProblem.of([data], world, ctx.P0, ctx.gate, scenario.record_every)
    got = problem.evaluate(np.array(scenario.filter_noise.radians()))
    steps = np.arange(scenario.record_every, len(data.u_odo) + 1, scenario.record_every)
    e = data.truth.x[steps] - trace["x"]
    e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
    rmse = float(np.mean(np.sqrt(np.sum(e[:, :2] ** 2, axis=1))))
    nees = np.einsum("ki,ki->k", e, np.linalg.solve(trace["P"], e[..., None])[..., 0])
    n_inn = trace["n_updates"] + trace["n_rejected"]
    assert got["rmse_pos"] == pytest.approx(rmse, rel=1e-9)
    assert got["nll_per_innovation"] == pytest.approx(flt.nll / n_inn, rel=1e-9)
    assert got["anees"] == pytest.approx(float(np.mean(nees)), rel=1e-7)
    assert got["gate_rejected"] == pytest.approx(trace["n_rejected"] / n_inn)


# ---------------------------------------------------------------------------------------------
# Seeds


def test_training_seeds_are_disjoint_from_every_evaluation_run():
    seed, runs = 1003, 2000
    evaluation = [t["seed"] for t in run_tasks(None, None, runs, seed)]
    training = training_seeds(seed, 50)
    # by construction: keys of another length, under a branch no run index reaches
    assert all(len(s.spawn_key) == 1 and s.spawn_key[0] < TRAINING_BRANCH for s in evaluation)
    assert all(s.spawn_key[:1] == (TRAINING_BRANCH,) and len(s.spawn_key) == 2 for s in training)
    # and in fact: no two streams share their state
    states = {tuple(s.generate_state(8)) for s in evaluation}
    assert len(states) == runs
    assert not states & {tuple(s.generate_state(8)) for s in training}
    # the same seed gives the same training runs
    again = training_seeds(seed, 50)
    assert [tuple(s.generate_state(4)) for s in again] == [
        tuple(s.generate_state(4)) for s in training
    ]


def test_training_runs_are_not_evaluation_runs():
    scenario, world = _scenario(training_runs=3)
    training = simulate_training(scenario, world, scenario.seed)
    evaluation = [simulate(scenario, world, t["seed"]) for t in run_tasks(scenario, world, 5, 7)]
    for a in training.runs:
        for b in evaluation:
            assert not np.array_equal(a.u_odo, b.u_odo)


# ---------------------------------------------------------------------------------------------
# The fits move toward the truth


@pytest.mark.slow
def test_ekf_ml_recovers_the_true_sigmas_without_truth():
    scenario, world = _scenario(training_runs=40)
    training = simulate_training(scenario, world, scenario.seed)
    spec = EKFMLSpec(name="ml", kind="ekf-ml", starts=[1.0, 3.0], max_evaluations=400)
    fitted = spec.fit(training)
    got = np.array(spec.with_fit(fitted).fitted_sigmas())
    true = np.array(scenario.true_noise.radians())
    start = np.array(scenario.filter_noise.radians())
    np.testing.assert_allclose(got, true, rtol=0.15)
    assert np.all(np.abs(np.log(got / true)) < np.abs(np.log(start / true)))
    assert fitted["training"]["nll_per_innovation"] < fitted["start"]["nll_per_innovation"]


def test_ekf_ml_moves_toward_the_truth_on_a_short_budget():
    scenario, world = _scenario(training_runs=8)
    training = simulate_training(scenario, world, scenario.seed)
    fitted = EKFMLSpec(name="ml", kind="ekf-ml", starts=[1.0], max_evaluations=80).fit(training)
    got = np.array([fitted["sigmas_rad"][k] for k in fitted["sigmas_rad"]])
    true = np.array(scenario.true_noise.radians())
    start = np.array(scenario.filter_noise.radians())
    # each sigma of the wrong guess is 3x off: the fit is closer in the log on the whole
    assert np.sum(np.log(got / true) ** 2) < 0.25 * np.sum(np.log(start / true) ** 2)
    assert fitted["evaluations"] <= 80 + 2


def test_ekf_tuned_is_no_worse_than_its_start_on_the_training_runs():
    scenario, world = _scenario(training_runs=6)
    training = simulate_training(scenario, world, scenario.seed)
    fitted = EKFTunedSpec(name="t", kind="ekf-tuned", starts=[1.0], max_evaluations=60).fit(
        training
    )
    assert fitted["criterion"] == "rmse" and fitted["consistency_scale"] > 0
    assert fitted["training"]["rmse_pos"] <= fitted["start"]["rmse_pos"]
    assert fitted["training"]["rmse_pos"] < 0.9 * fitted["start"]["rmse_pos"]
    # NEES is reported beside the RMSE it was tuned for
    assert {"anees", "nees_in_bounds"} <= set(fitted["training"])


# ---------------------------------------------------------------------------------------------
# The mechanism: hand-out, cache, manifest, resume, --force


def test_a_fitted_filter_is_built_from_its_fit_and_never_unfitted():
    scenario, world = _scenario()
    spec = scenario.filters[1]
    with pytest.raises(FilterNotFitted):
        build_filter(spec, scenario, world)
    sig = {"sigma_v": 0.2, "sigma_gamma": 0.04, "sigma_range": 0.5, "sigma_bearing": 0.01}
    fitted = spec.with_fit({"sigmas_rad": sig})
    assert spec._fit is None  # the scenario's own spec is not changed
    # what a worker receives (pickled by joblib or Dask) still carries the fit
    flt = build_filter(pickle.loads(pickle.dumps(fitted)), scenario, world)
    np.testing.assert_allclose(np.diag(flt.Qu), [0.04, 0.0016])
    np.testing.assert_allclose(np.diag(flt.R), [0.25, 1e-4])
    assert fast.supports(fitted)


def test_fit_is_cached_by_fingerprint(tmp_path, monkeypatch):
    scenario, world = _scenario()
    plan = make_plan(scenario, world, None, None, None)
    first = fit_filters(plan, tmp_path)
    assert first.fitted_now == 2 and not any(r["cached"] for r in first.records.values())
    assert len(list(tmp_path.glob("fit-*.json"))) == 2

    def refit(*args, **kwargs):
        raise AssertionError("refitted although cached")

    monkeypatch.setattr(EKFMLSpec, "fit", refit)
    monkeypatch.setattr(EKFTunedSpec, "fit", refit)
    second = fit_filters(plan, tmp_path)
    assert second.fitted_now == 0 and all(r["cached"] for r in second.records.values())
    for name in ("ml", "tuned"):
        assert second.records[name]["fitted"] == first.records[name]["fitted"]
    spec = next(f for f in second.scenario.filters if f.name == "ml")
    assert spec.fitted_sigmas() == tuple(first.records["ml"]["fitted"]["sigmas_rad"].values())
    # another training set is another fingerprint: no cache hit
    other, _ = _scenario(training_runs=5)
    plan5 = make_plan(other, world, None, None, None)
    fingerprint = plan.source.training_fingerprint(plan, scenario.filters[1])
    assert plan5.source.training_fingerprint(plan5, other.filters[1]) != fingerprint
    # the evaluation runs are not part of it
    plan9 = make_plan(scenario, world, 9, None, None)
    assert plan9.source.training_fingerprint(plan9, scenario.filters[1]) == fingerprint


class _Stop(Exception):
    pass


def test_manifest_records_the_fit_and_resume_reuses_it(tmp_path):
    scenario, world = _scenario()
    plan = make_plan(scenario, world, 3, None, 1)
    seen = []

    def stop_after_one(result):
        seen.append(result["run"])
        raise _Stop

    with pytest.raises(_Stop):
        execute(plan, tmp_path, on_result=stop_after_one)
    runs_dir = tmp_path / scenario.name / RUNS_DIR
    assert len(list(runs_dir.glob("fit-*.json"))) == 2
    records, _ = execute(plan, tmp_path)  # resumes: the fits come from the cache
    manifest = json.loads((tmp_path / scenario.name / MANIFEST_FILE).read_text())
    assert manifest["resumed_runs"] == seen
    training = manifest["training"]
    assert set(training) == {"ml", "tuned"}
    for rec in training.values():
        assert rec["cached"] is True
        assert rec["training_runs"] == 4
        fitted = rec["fitted"]
        assert set(fitted["sigmas_rad"]) == {
            "sigma_v", "sigma_gamma", "sigma_range", "sigma_bearing",
        }  # fmt: skip
        assert fitted["evaluations"] > 0 and fitted["seconds"] >= 0
    assert {r["filter"] for r in records} == {"ekf", "ml", "tuned", "ekf-oracle"}
    # --force starts over: a fresh fit, the same values (deterministic)
    execute(plan, tmp_path, force=True)
    again = json.loads((tmp_path / scenario.name / MANIFEST_FILE).read_text())["training"]
    assert not any(r["cached"] for r in again.values())
    for name in training:
        assert again[name]["fitted"]["sigmas_rad"] == training[name]["fitted"]["sigmas_rad"]


@pytest.mark.slow
def test_results_do_not_depend_on_the_worker_count(tmp_path):
    scenario, world = _scenario(engine="fast")
    out = {}
    for jobs in (1, 2):
        plan = make_plan(scenario, world, 2, None, jobs)
        records, _ = execute(plan, tmp_path / f"j{jobs}")
        out[jobs] = {r["filter"]: r["rmse_pos"] for r in records}
    assert out[1] == out[2]


def test_a_recorded_log_fits_the_one_ekf_tuned_spec_by_its_grid_and_ekf_ml_on_its_own_runs():
    from anfekf_bench.sources.recorded import REAL_KINDS, REAL_SPECS, RecordedScenario

    # ekf-ml is fitted on each recorded run's own innovations (tests/test_ekf_ml_real.py); the
    # one ekf-tuned spec on the recorded training runs (fitting.recorded.RecordedTraining)
    assert REAL_KINDS.count("ekf-tuned") == 1 and REAL_KINDS.count("ekf-ml") == 1
    assert EKFTunedSpec in REAL_SPECS and EKFMLSpec in REAL_SPECS
    assert RecordedScenario.spec_by_kind["ekf-tuned"] is SPEC_BY_KIND["ekf-tuned"]
    assert {"simulated", "recorded"} <= EKFTunedSpec.fit_sources


@pytest.mark.parametrize("key", ["starts", "max_evaluations"])
def test_a_recorded_ekf_tuned_refuses_the_simulated_fits_fields(key):
    """Nelder-Mead's starts and evaluations mean nothing to the grid search: refused, not
    ignored (one line naming the field)."""
    from anfekf_bench.config import ScenarioError
    from anfekf_bench.sources.recorded import parse_real_scenario

    value = [1.0] if key == "starts" else 50
    doc = {"name": "r", "data": {"kind": "mrclam", "path": "builtin"},
           "filters": [{"name": "ekf", "kind": "ekf"},
                       {"name": "t", "kind": "ekf-tuned", key: value}]}  # fmt: skip
    with pytest.raises(ScenarioError, match=rf"filters\.1\.{key}: not for a recorded log"):
        parse_real_scenario(doc)
    del doc["filters"][1][key]
    assert parse_real_scenario(doc).reference() == "t"


def test_recorded_training_runs_fit_ekf_tuned_by_their_grid_search(monkeypatch):
    """The one spec's fit on "recorded" training runs is their grid search, whatever its
    Nelder-Mead fields; a likelihood fit on them is refused."""
    from anfekf_bench.fitting.recorded import RecordedTraining

    training = RecordedTraining.__new__(RecordedTraining)
    monkeypatch.setattr(RecordedTraining, "grid_search", lambda self: {"sigma_v": 1.0})
    spec = EKFTunedSpec(name="t", kind="ekf-tuned")
    assert spec.fit(training) == {"sigma_v": 1.0}
    with pytest.raises(ValueError, match="fit no 'likelihood' noise"):
        EKFMLSpec(name="m", kind="ekf-ml").fit(training)
    check = training.fit_problem(spec)
    assert check({"sigma_v": 1, "sigma_w_rad": 1, "sigma_range": 1, "sigma_bearing_rad": 1}) is None
    assert "sigma_range" in check({"sigma_v": 1, "sigma_w_rad": 1, "sigma_bearing_rad": 1})


def test_two_noise_fits_run_their_starts_in_one_batch_with_the_same_fits(monkeypatch):
    """With workers, ekf-ml's and ekf-tuned's Nelder-Mead starts run in one batch
    (TrainingSet.prepare_noise_fits): the fits are those of one process, start by start."""
    from anfekf_bench.fitting.simulated import TrainingSet, fit_filters

    scenario, world = _scenario(training_runs=2)
    batches = []
    prepare = TrainingSet.prepare_noise_fits
    monkeypatch.setattr(
        TrainingSet, "prepare_noise_fits",
        lambda self, requests: batches.append(len(requests)) or prepare(self, requests),
    )  # fmt: skip
    fits = {jobs: fit_filters(make_plan(scenario, world, 2, None, jobs), None) for jobs in (1, 2)}
    assert batches == [2]  # jobs 2 only, both fits at once
    for name in ("ml", "tuned"):
        one, two = fits[1].records[name]["fitted"], fits[2].records[name]["fitted"]
        assert one["sigmas_rad"] == two["sigmas_rad"]
        assert one["starts"] == two["starts"] and one["evaluations"] == two["evaluations"]
        assert two["seconds"] > 0.1 * one["seconds"]  # counts its share of the batch (~1/4)


@pytest.mark.parametrize("motion", ["bicycle", "unicycle"])
def test_the_fit_kernels_table_of_step_terms_gives_predicts_bits(motion: str) -> None:
    """The tuning kernel reads each stamp's heading-free terms from `step_terms_table` (computed
    once per run, not at each of a fit's hundreds of passes): its predict is kernels.predict's,
    bit for bit, on both motion models, a stamp of no length included."""
    from anfekf_bench.engines.kernels import (
        MOTION_BICYCLE,
        MOTION_UNICYCLE,
        jacobians_at,
        noise_scale,
        predict,
        predict_from,
    )
    from anfekf_bench.engines.tuning import step_terms_table

    rng = np.random.default_rng(7)
    n = 300
    u = np.column_stack([rng.uniform(0.0, 3.0, n), rng.uniform(-0.6, 0.6, n)])
    dt = rng.uniform(0.001, 0.2, n)
    dt[5] = 0.0
    code, B, T0 = (
        (MOTION_BICYCLE, 4.0, 0.0) if motion == "bicycle" else (MOTION_UNICYCLE, 0.0, 0.12)
    )
    table = step_terms_table(u, dt, code, B)
    x, P, Qu = (1.0, -2.0, 3.0), tuple(np.diag([0.1, 0.2, 0.01]).ravel()), (0.09, 0.0, 0.0, 0.003)
    for k in range(n):
        expected = predict(x, P, u[k, 0], u[k, 1], dt[k], code, B, T0, Qu)
        terms = tuple(table[k])
        f02, f12, G = jacobians_at(x[2], terms)
        got = predict_from(x, P, f02, f12, G, terms[8], noise_scale(dt[k], code, T0), Qu)
        assert got == expected, k
        x, P = expected[0], expected[1]
