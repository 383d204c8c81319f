"""Training runs for the filters fitted before the batch (filters.fitted: `ekf-ml`, `ekf-tuned`;
filters.kalmannet: `kalmannet`, trained on them).

1. **Seeds.** Evaluation run i draws from `SeedSequence(seed).spawn(runs)[i]`, whose spawn key is
   (i,) with i < MAX_RUNS. Training run j draws from `training_seeds(seed, n)[j]`: the children
   of `SeedSequence(seed, spawn_key=(TRAINING_BRANCH,))`, spawn key (TRAINING_BRANCH, j). No
   evaluation run can have that key (a key of length 2; and TRAINING_BRANCH itself is beyond any
   run index), so the two sets of streams are disjoint by construction, whatever `runs` is.
2. **Fit.** The training runs are simulated in this process (the scenario's world and true
   noise, `training.runs` of them) once per batch, and each fitted filter's `fit` is called on
   them (the fitting code decides its engine; the built-in kinds use the fast engine's kernels).
3. **Cache.** What a fit returns is saved as `<out>/<name>/.runs/fit-<fingerprint>.json`, keyed
   by `SimulatedSource.training_fingerprint` (the filter's parameters, the scenario fields a fit
   depends on, the seed, the training settings, the code version): a resumed batch reuses it
   (no refit); --force and a completed batch remove it with the rest of the run store.
4. **Hand out.** Every evaluation run gets a copy of the spec carrying the fitted values
   (`FittedSpec.with_fit`): the workers never fit.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from ..config import SimulatedScenario, World
from ..filters.ekf import gate_threshold
from ..filters.spec import FilterSpec
from ..outputs import FIT_FILE, read_cached_fit, write_fit
from ..runner import simulate
from ..sources.simulator import RunData, world_path

TRAINING_BRANCH = 2**32 - 1  # spawn key of the training branch of the root seed


def training_seeds(seed: int, runs: int) -> list[np.random.SeedSequence]:
    """The training runs' seeds: the training branch's children (never an evaluation run's)."""
    return np.random.SeedSequence(seed, spawn_key=(TRAINING_BRANCH,)).spawn(runs)


@dataclass
class TrainingSet:
    """What a fitted filter's `fit` gets: the scenario, its world, the simulated training runs,
    their seeds, the filters' start covariance and gate, and the worker processes it may use."""

    scenario: SimulatedScenario
    world: World
    runs: list[RunData]
    seeds: list[np.random.SeedSequence]
    jobs: int = 1
    progress: Any = None  # the CLI's rich Progress, for a long fit's bar (kalmannet); None: quiet
    P0: np.ndarray = field(init=False)
    gate: float | None = field(init=False)
    # (criterion, starts, max_evaluations) -> (its starts' results, seconds), computed together
    # for several fits by `prepare_noise_fits`
    _starts_found: dict = field(init=False, default_factory=dict)

    def __post_init__(self):
        self.P0 = np.eye(3) * self.scenario.p0
        self.gate = gate_threshold(self.scenario.gate_probability)

    @cached_property
    def problem(self):
        """The training runs as the tuning kernel reads them (`engines.tuning.TrainingProblem`),
        built once for every fit of this set."""
        from ..engines.tuning import TrainingProblem

        return TrainingProblem.of(
            self.runs, self.world, self.P0, self.gate, self.scenario.record_every
        )

    def prepare_noise_fits(self, requests: list[tuple[str, list[float], int]]) -> None:
        """Run the Nelder-Mead starts of several `fit_noise` calls (criterion, starts,
        max_evaluations) in one batch of workers; each call then finds its starts done, and
        counts an equal share of the batch's wall time in its "seconds"."""
        from ..engines.tuning import start_results

        todo = list(dict.fromkeys((c, tuple(s), n) for c, s, n in requests))
        if self.jobs < 2 or len(todo) < 2:
            return
        started = time.perf_counter()
        sigmas = np.array(self.scenario.filter_noise.radians())
        found = start_results(
            self.problem, [(c, sigmas, list(s), n) for c, s, n in todo], self.jobs
        )
        share = (time.perf_counter() - started) / len(todo)
        self._starts_found.update((key, (f, share)) for key, f in zip(todo, found, strict=True))

    def fit_noise(self, criterion: str, starts: list[float], max_evaluations: int) -> dict:
        """The four sigmas of a fixed EKF that optimise `criterion` ("likelihood": innovations
        only; "rmse": the truth) over these runs, from `starts` x the assumed sigmas
        (`engines.tuning.fit_noise`); a service of the training layer, so that a filter spec
        asks for it here and never imports an engine."""
        from ..engines.tuning import SIGMA_NAMES, fit_noise

        done, seconds = self._starts_found.get((criterion, tuple(starts), max_evaluations),
                                               (None, 0.0))  # fmt: skip
        found = fit_noise(
            self.problem, criterion, np.array(self.scenario.filter_noise.radians()), starts,
            max_evaluations, jobs=self.jobs, found=done, found_seconds=seconds,
        )  # fmt: skip
        found["sigmas_rad"] = dict(zip(SIGMA_NAMES, found.pop("sigmas"), strict=True))
        return found


def simulate_training(
    scenario: SimulatedScenario, world: World, seed: int, jobs: int = 1, progress: Any = None
) -> TrainingSet:
    """The scenario's training runs (see the module doc)."""
    seeds = training_seeds(seed, scenario.training.runs)
    path = world_path(world)
    runs = [simulate(scenario, world, s, path) for s in seeds]
    return TrainingSet(
        scenario=scenario, world=world, runs=runs, seeds=seeds, jobs=jobs, progress=progress
    )


def fitted_filters(scenario: SimulatedScenario) -> list[FilterSpec]:
    return [f for f in scenario.filters if f.fitted_on_training]


@dataclass
class Fits:
    """The scenario whose fitted filters carry their values, and what the manifest records."""

    scenario: SimulatedScenario
    records: dict  # filter name -> {kind, fingerprint, cached, training_runs, fitted}
    fitted_now: int  # fits computed by this call (not read from the cache)


def fit_filters(plan, cache_dir: Path | None, progress: Any = None) -> Fits:
    """Fit every fitted filter of `plan` (an experiment.Plan) once, or read its fit from
    `cache_dir` (None: no cache); see the module doc. `progress`: a rich Progress a long fit
    adds its bar to (None: quiet)."""
    scenario = plan.scenario
    todo = fitted_filters(scenario)
    if not todo:
        return Fits(scenario=scenario, records={}, fitted_now=0)
    training: TrainingSet | None = None
    records, specs, fitted_now = {}, {}, 0
    # Each fit's (fingerprint, cache file, cached values or None), the cache read once
    stored = {}
    for spec in todo:
        fingerprint = plan.source.training_fingerprint(plan, spec)
        path = None if cache_dir is None else cache_dir / FIT_FILE.format(fingerprint=fingerprint)
        cached = None if path is None else read_cached_fit(path, fingerprint, spec.fit_problem)
        stored[spec.name] = (fingerprint, path, cached)
    if plan.jobs > 1:
        # The noise fits not in the cache: their starts in one batch of workers
        # (`prepare_noise_fits`); each fit below then finds its starts done, the same numbers.
        fresh = [
            r for spec in todo
            if stored[spec.name][2] is None and (r := spec.noise_fit_request()) is not None
        ]  # fmt: skip
        if len(fresh) > 1:
            training = simulate_training(scenario, plan.world, plan.seed, plan.jobs, progress)
            training.prepare_noise_fits(fresh)
    for spec in todo:
        fingerprint, path, fitted = stored[spec.name]
        cached = fitted is not None
        if fitted is None:
            if training is None:
                training = simulate_training(scenario, plan.world, plan.seed, plan.jobs, progress)
            fitted = spec.fit(training)
            fitted_now += 1
            if path is not None:
                write_fit(path, fingerprint, fitted)
        specs[spec.name] = spec.with_fit(fitted)
        records[spec.name] = {
            "kind": spec.kind,
            "fingerprint": fingerprint,
            "cached": cached,
            "training_runs": scenario.training.runs,
            "training_seed_branch": [plan.seed, TRAINING_BRANCH],
            "fitted": spec.fit_record(fitted),
        }
    filters = [specs.get(f.name, f) for f in scenario.filters]
    return Fits(
        scenario=scenario.model_copy(update={"filters": filters}),
        records=records,
        fitted_now=fitted_now,
    )
