"""Training runs for the filters fitted before the batch (filters.fitted: `ekf-ml`, `ekf-tuned`;
filters.kalmannet: `kalmannet`, trained on them; filters.augmented: `ekf-aug-calibrated`, its error
states chosen and started on them).

1. **Seeds.** Evaluation run i draws from `SeedSequence(seed).spawn(runs)[i]`, whose spawn key is
   (i,) with i < MAX_RUNS. Training run j draws from `training_seeds(seed, n)[j]`: the children
   of `SeedSequence(seed, spawn_key=(TRAINING_BRANCH,))`, spawn key (TRAINING_BRANCH, j). No
   evaluation run can have that key (a key of length 2; and TRAINING_BRANCH itself is beyond any
   run index), so the two sets of streams are disjoint by construction, whatever `runs` is.
2. **Fit.** The training runs (a `TrainingSet`, the "simulated" training runs of fitting.fit)
   are simulated in this process (the scenario's world and true noise, `training.runs` of them)
   once per batch, when a fit is not in the cache, and each fitted filter's `fit` is called on
   them through `fitting.fit.fit_specs` (the fitting code decides its engine; the built-in kinds
   use the fast engine's kernels).
3. **Cache.** What a fit returns is saved as `<out>/<name>/.runs/fit-<fingerprint>.json`, keyed
   by `TrainingSet.fingerprint` (the filter's parameters, the scenario fields a fit
   depends on, the seed, the training settings, the code version): a resumed batch reuses it
   (no refit); --force and a completed batch remove it with the rest of the run store.
4. **Hand out.** Every evaluation run gets a copy of the spec carrying the fitted values
   (`FittedSpec.with_fit`): the workers never fit.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

from ..analysis.metrics import recorded_steps
from ..config import SimulatedScenario, World
from ..engines.tuning import SIGMA_NAMES, TrainingProblem, fit_noise, start_results
from ..filters.ekf import gate_threshold
from ..filters.spec import FilterSpec
from ..outputs import code_version
from ..runner import simulate
from ..sources.simulator import RunData, world_path
from .fit import TrainingRuns, fit_specs

TRAINING_BRANCH = 2**32 - 1  # spawn key of the training branch of the root seed
# The scenario fields a simulated fit depends on (besides the filter, the seed and the map)
FINGERPRINT_FIELDS = {"world", "true_noise", "filter_noise", "p0", "gate_probability", "training",
                      "record_every"}  # fmt: skip


def training_seeds(seed: int, runs: int) -> list[np.random.SeedSequence]:
    """The training runs' seeds: the training branch's children (never an evaluation run's)."""
    return np.random.SeedSequence(seed, spawn_key=(TRAINING_BRANCH,)).spawn(runs)


@dataclass(eq=False)
class TrainingSet(TrainingRuns):
    """The "simulated" training runs (fitting.fit): what a fitted filter's `fit` gets: the
    scenario, its world, the training runs (simulated when first read), their seeds, the
    filters' start covariance and gate, and the jobs it may use (threads for the noise fits'
    starts)."""

    source: ClassVar[str] = "simulated"
    scenario: SimulatedScenario
    world: World
    seed: int
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
    def seeds(self) -> list[np.random.SeedSequence]:
        return training_seeds(self.seed, self.scenario.training.runs)

    @cached_property
    def runs(self) -> list[RunData]:
        """The training runs, simulated here on first use (see the module doc)."""
        path = world_path(self.world)
        return [simulate(self.scenario, self.world, s, path) for s in self.seeds]

    def fingerprint(self, spec) -> str:
        """Hash of everything a fitted filter's fit depends on: its own parameters, the
        scenario's world, noise, start, gate, recording and training settings, the seed and the
        code; not the evaluation runs, the other filters or the engine."""
        doc = {
            "filter": spec.model_dump(mode="json", exclude={"name"}),
            "scenario": self.scenario.model_dump(mode="json", include=FINGERPRINT_FIELDS),
            "seed": self.seed,
            "landmarks": self.world.landmarks.tolist(),
            "waypoints": self.world.waypoints.tolist(),
            "code": code_version(),
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]

    def describe(self) -> dict:
        return {
            "training_runs": self.scenario.training.runs,
            "training_seed_branch": [self.seed, TRAINING_BRANCH],
        }

    def prepare(self, specs: list) -> None:
        """With jobs > 1, the noise fits about to run start together (`prepare_noise_fits`)."""
        requests = [r for spec in specs if (r := spec.noise_fit_request()) is not None]
        if self.jobs > 1 and len(requests) > 1:
            self.prepare_noise_fits(requests)

    @cached_property
    def problem(self):
        """The training runs as the tuning kernel reads them (`engines.tuning.TrainingProblem`),
        built once for every fit of this set."""
        return TrainingProblem.of(
            self.runs, self.world, self.P0, self.gate, self.scenario.record_every
        )

    def prepare_noise_fits(self, requests: list[tuple[str, list[float], int]]) -> None:
        """Run the Nelder-Mead starts of several `fit_noise` calls (criterion, starts,
        max_evaluations) in one batch of workers; each call then finds its starts done, and
        counts an equal share of the batch's wall time in its "seconds"."""
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
        done, seconds = self._starts_found.get((criterion, tuple(starts), max_evaluations),
                                               (None, 0.0))  # fmt: skip
        found = fit_noise(
            self.problem, criterion, np.array(self.scenario.filter_noise.radians()), starts,
            max_evaluations, jobs=self.jobs, found=done, found_seconds=seconds,
        )  # fmt: skip
        found["sigmas_rad"] = dict(zip(SIGMA_NAMES, found.pop("sigmas"), strict=True))
        return found

    def augmented_runs(self, spec) -> tuple[np.ndarray, np.ndarray]:
        """Each training run by `spec` (an `ekf-aug`) on the fast engine's kernel: its
        error-parameter estimates at its last record, runs x 4 (filters.augmented.PARAMETERS'
        order), and its position RMSE against the truth at the recorded steps (as the scorer
        takes it); NaN for a run that lost its covariance. What `ekf-aug-calibrated` is fitted
        on."""
        from ..engines.fast import augmented_run
        from ..filters.context import filter_context
        from ..timeline import from_run

        ctx = filter_context(spec, self.scenario, self.world)
        every = self.scenario.record_every
        ends, rmse = [], []
        for run in self.runs:
            out, theta = augmented_run(spec, ctx, from_run(run, self.world, every))
            truth = run.truth.x[recorded_steps(len(run.u_odo), every)]
            err = out["x"][:, :2] - truth[:, :2]
            ends.append(theta[-1])
            rmse.append(math.sqrt(np.mean(np.sum(err**2, axis=1))) if len(err) else math.nan)
        return np.array(ends), np.array(rmse)


def simulate_training(
    scenario: SimulatedScenario, world: World, seed: int, jobs: int = 1, progress: Any = None
) -> TrainingSet:
    """The scenario's training runs (see the module doc), simulated now."""
    training = TrainingSet(scenario=scenario, world=world, seed=seed, jobs=jobs, progress=progress)
    _ = training.runs
    return training


def fitted_filters(scenario: SimulatedScenario) -> list[FilterSpec]:
    return [f for f in scenario.filters if f.fitted_on_training]


@dataclass
class Fits:
    """The scenario whose fitted filters carry their values, and what the manifest records."""

    scenario: SimulatedScenario
    records: dict  # filter name -> {kind, fingerprint, cached, training_runs, fitted}
    fitted_now: int  # fits computed by this call (not read from the cache)


def fit_filters(plan, cache_dir, progress: Any = None) -> Fits:
    """Fit every fitted filter of `plan` (an experiment.Plan) once on its simulated training
    runs, or read its fit from `cache_dir` (None: no cache), through `fitting.fit.fit_specs`;
    see the module doc. `progress`: a rich Progress a long fit adds its bar to (None: quiet)."""
    scenario = plan.scenario
    todo = fitted_filters(scenario)
    if not todo:
        return Fits(scenario=scenario, records={}, fitted_now=0)
    training = TrainingSet(
        scenario=scenario, world=plan.world, seed=plan.seed, jobs=plan.jobs, progress=progress
    )
    found = fit_specs([(spec, training) for spec in todo], cache_dir, plan.jobs)
    pairs = list(zip(todo, found, strict=True))
    specs = {spec.name: spec.with_fit(fit.fitted) for spec, fit in pairs}
    filters = [specs.get(f.name, f) for f in scenario.filters]
    return Fits(
        scenario=scenario.model_copy(update={"filters": filters}),
        records={spec.name: fit.record(spec, training) for spec, fit in pairs},
        fitted_now=sum(not fit.cached for fit in found),
    )
