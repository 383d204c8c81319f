"""The "recorded" training runs (fitting.fit): a recorded log's training segments (protocol
segments) or, per cross-drive fold, the drives of the datasets that tune a test dataset
(protocol drives), each cold-started from ground truth (`RecordedTraining`); and the fits on them,
each through `fitting.fit.fit_specs`:

- `ekf-tuned` (filters.fitted.EKFTunedSpec, the simulated scenarios' spec: these runs' `fit_noise`
  chooses the fit): the grid search (`tune`, one compiled call per thread:
  engines.tuning.GridRuns) on the training segments (via `tune_segments`) or, per fold, by
  branch and bound over whole drives (via `tune_drives`); not cached (it is the batch's
  reference, as before);
- `kalmannet` (filters.kalmannet): trained once on the training segments (`fit_on_segments`) or
  once per fold (`fit_on_drives`).

A drive is scored by values fitted on the drives of the datasets that tune its `ekf-tuned`
(`RecordedScenario.tuning_sources`: tune on Dataset 6, test on 7, and the reverse; Dataset 9 on
both), never on its own dataset's drives. Per fold and fitted filter:

1. **Fit** on the training drives' timelines and their ground truth at the evaluation times,
   NaN where not scored (`RecordedTraining.pairs`, `grid_search`): nothing of a test drive is
   read.
2. **Cache** what a trained filter's fit returns as `<out>/<name>/.runs/fit-<fingerprint>.json`
   (as fitting.simulated), keyed by `RecordedTraining.fingerprint`: the filter's parameters, the
   training drives and their logs' content (or the log and the fields that cut its segments),
   what shapes their timelines and truth, the code version. A resumed batch reads it.
3. **Hand out** to each drive a copy of the scenario whose fitted filter carries its fold's
   weights (`with_fit`); the manifest's `training` key records, per filter and fold, the
   training drives, the fingerprint, whether it came from the cache, and the fit's record
   (weights' SHA-256, training time, losses). ekf-tuned's noise reaches each run as its
   `tuned` record (real_experiment.recorded_run); the manifest's `tuning` key records it.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from joblib import Parallel, delayed

from ..analysis.suite import LOST_LOCK_M
from ..engines.tuning import RESUME_SIZE, GridRuns, score_setting
from ..filters.context import recorded_p0
from ..filters.ekf import gate_threshold
from ..filters.fitted import sigmas_problem
from ..models import Unicycle
from ..outputs import PlanError, code_version
from ..sources.recorded import NOISE_KEYS, DriveSet, RecordedScenario, log_digest
from .fit import TrainingRuns, fit_specs

# The scenario fields a drive's timeline and scored truth depend on (real_experiment.segment_inputs)
_INPUT_FIELDS = {"eval_period_s", "odometry_period_s", "max_gap_s", "misfit_detection"}
# The scenario fields that decide a log's training segments (sources.recorded.cut_segments)
_SEGMENT_FIELDS = _INPUT_FIELDS | {"split_fraction", "split_at_s", "segment_s", "min_scorable_s"}


@dataclass(eq=False)
class RecordedTraining(TrainingRuns):
    """The "recorded" training runs (fitting.fit): a log's training segments (protocol
    segments), or the drives of one cross-drive fold (protocol drives: the drives of the datasets
    that tune a test dataset, never one of its own), each cold-started from ground truth. What a
    spec's `fit` reads: `pairs()` (kalmannet) or `fit_noise` (ekf-tuned: `grid_search()`)."""

    source: ClassVar[str] = "recorded"
    scenario: RecordedScenario
    inputs: list  # real_experiment.SegmentInputs of the training segments or drives
    what: str  # what they are, for a progress bar ("dataset(s) 6", "3 training segments")
    account: dict  # the manifest's account of them ({"train_drives": [...]}, ...)
    data_doc: dict  # what they depend on, for the fingerprint (not the filter, not the code)
    drives: bool = False  # whole drives (grid search by branch and bound) or segments
    jobs: int = 1
    progress: Any = None
    seeds: list | tuple = ()  # drives: log2 multipliers scored first (tune)
    memo: Any = None  # drives: WholeRuns shared by the folds of one tune_drives

    @property
    def model(self):
        return Unicycle(self.scenario.odometry_period_s)

    def pairs(self) -> list[tuple]:
        """(Timeline, truth at its evaluation times, NaN where not scored) of each run."""
        return [(s.timeline, s.truth) for s in self.inputs]

    def progress_label(self, spec) -> str:
        return f"training {spec.name} on {self.what}"

    def fit_noise(self, criterion: str, starts, max_evaluations: int) -> dict:
        """A fixed EKF's noise fitted on these runs (filters.fitted.FittedNoiseSpec.fit): the
        position RMSE (ekf-tuned) by the grid search of the scenario's `tuning:`, whatever
        Nelder-Mead's starts and evaluations (a recorded scenario refuses them)."""
        if criterion != "rmse":
            raise ValueError(f"a recorded log's training runs fit no {criterion!r} noise")
        return self.grid_search()

    def fit_problem(self, spec):
        """A noise fit here is a noise record (`tune`: sigma_v, sigma_w_rad, sigma_range,
        sigma_bearing_rad), as a run's own innovations give (fitting.own); a trained filter's
        fit is checked by its spec."""
        if spec.noise_fit_request() is None:
            return spec.fit_problem
        return lambda fitted: sigmas_problem(fitted, NOISE_KEYS, "")

    def grid_search(self) -> dict:
        """ekf-tuned's grid search on these runs (`tune`: by branch and bound on whole drives)."""
        return tune(self.scenario, self.inputs, self.jobs, self.seeds, self.drives, self.memo)

    def fingerprint(self, spec) -> str:
        """Hash of what a fit on these runs depends on (see the module doc); not the test
        drives or segments."""
        doc = {
            "filter": spec.model_dump(mode="json", exclude={"name"}),
            **self.data_doc,
            "code": code_version(),
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]

    def describe(self) -> dict:
        return self.account


def trained_filters(scenario: RecordedScenario) -> list:
    """The filters trained on training drives or segments (kalmannet); ekf-ml is fitted on each
    run's own innovations instead (fitting.own.fit_on_own_innovations)."""
    return [f for f in scenario.filters if f.role == "trained"]


def drive_fold(
    scenario: RecordedScenario, train: list, inputs: dict, jobs: int = 1, progress: Any = None,
    seeds: list | tuple = (), memo: Any = None,
) -> RecordedTraining:  # fmt: skip
    """The training runs of one cross-drive fold: the drives `train` (whole), their inputs."""
    label = "+".join(map(str, sorted({d.dataset for d in train})))
    return RecordedTraining(
        scenario=scenario,
        inputs=[inputs[d.id] for d in train],
        what=f"dataset(s) {label}",
        account={"train_drives": [d.id for d in train]},
        data_doc={
            "scenario": scenario.model_dump(mode="json", include=_INPUT_FIELDS),
            "drives": [[d.id, log_digest(d.log)] for d in train],
        },
        drives=True,
        jobs=jobs,
        progress=progress,
        seeds=seeds,
        memo=memo,
    )


def segment_training(
    scenario: RecordedScenario, rec, segments: list, jobs: int = 1, progress: Any = None
) -> RecordedTraining:
    """The training runs of protocol segments: the log's training segments (`segments`: their
    real_experiment.SegmentInputs, each cold-started from ground truth; never a held-out one)."""
    return RecordedTraining(
        scenario=scenario,
        inputs=segments,
        what=f"{len(segments)} training segments",
        account={"train_segments": [s.index for s in rec.train_segments]},
        data_doc={
            "scenario": scenario.model_dump(mode="json", include=_SEGMENT_FIELDS),
            "log": rec.digest,
        },
        jobs=jobs,
        progress=progress,
    )


def fit_on_drives(
    scenario: RecordedScenario,
    world: DriveSet,
    inputs: dict,
    cache_dir: Path | None,
    progress: Any = None,
) -> tuple[dict[str, RecordedScenario], dict]:
    """Fit every trained filter of `scenario` once per fold (see the module doc). `inputs`: drive
    id -> real_experiment.SegmentInputs. Returns the scenario each drive runs with (its fold's
    weights; every drive when there is no trained filter) and the manifest's account. PlanError
    (one line) when a filter cannot be trained on a fold's drives."""
    todo = trained_filters(scenario)
    if not todo:
        return {d.id: scenario for d in world.drives}, {}
    folds = {tuple(scenario.tuning_sources(d.dataset)) for d in world.drives}
    requests, labels = [], []
    for sources in sorted(folds, key=lambda k: (len(k), k)):
        train = [d for d in world.drives if d.dataset in sources]
        if not train:
            raise PlanError(
                f"filters: {todo[0].name}: no training drive for the drives tuned on dataset(s)"
                f" {', '.join(map(str, sources))}"
            )
        fold = drive_fold(scenario, train, inputs, progress=progress)
        for spec in todo:
            requests.append((spec, fold))
            labels.append((sources, "+".join(map(str, sources))))
    found = fit_specs(requests, cache_dir)
    fitted_for: dict[tuple, dict[str, Any]] = {}
    records: dict[str, dict] = {spec.name: {} for spec in todo}
    for (spec, fold), (sources, label), fit in zip(requests, labels, found, strict=True):
        fitted_for.setdefault(sources, {})[spec.name] = spec.with_fit(fit.fitted)
        records[spec.name][label] = fit.record(spec, fold)
    out = {}
    for d in world.drives:
        specs = fitted_for[tuple(scenario.tuning_sources(d.dataset))]
        filters = [specs.get(f.name, f) for f in scenario.filters]
        out[d.id] = scenario.model_copy(update={"filters": filters})
    return out, records


def fit_on_segments(
    scenario: RecordedScenario, rec, segments: list, cache_dir: Path | None, progress: Any = None
) -> tuple[RecordedScenario, dict]:
    """Protocol segments: every trained filter fitted once on the log's training segments
    (`segment_training`), or read from the cache. Returns the scenario carrying the fits and the
    manifest's account (per filter, one fold keyed "train")."""
    todo = trained_filters(scenario)
    if not todo:
        return scenario, {}
    training = segment_training(scenario, rec, segments, progress=progress)
    found = fit_specs([(spec, training) for spec in todo], cache_dir)
    specs = {spec.name: spec.with_fit(fit.fitted) for spec, fit in zip(todo, found, strict=True)}
    records = {
        spec.name: {"train": fit.record(spec, training)}
        for spec, fit in zip(todo, found, strict=True)
    }
    filters = [specs.get(f.name, f) for f in scenario.filters]
    return scenario.model_copy(update={"filters": filters}), records


def tuned_reference(scenario: RecordedScenario):
    """The scenario's ekf-tuned spec (its reference), or None."""
    name = scenario.reference()
    return next((f for f in scenario.filters if f.name == name), None)


def tune_segments(scenario: RecordedScenario, rec, segments: list, jobs: int = 1) -> dict:
    """ekf-tuned's noise on the log's training segments (`segments`, as `segment_training`),
    through fitting.fit (not cached: the grid search is the reference of the batch)."""
    training = segment_training(scenario, rec, segments, jobs)
    return fit_specs([(tuned_reference(scenario), training)], None)[0].fitted


# --------------------------------------------------------------------------------------------
# ekf-tuned: the grid search, on training segments or (protocol drives, SPEC 15) whole drives


AXES = ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing")
_CRITERION = {
    False: "pooled position RMSE over the scorable evaluation times of the training segments [m]",
    True: "pooled position RMSE over the scored evaluation times of the training drives, whole [m]",
}
_BRANCH_AND_BOUND = (
    "branch and bound (engines.tuning): a setting stops once its sum of squared errors passes"
    " the best complete one; the winner is the full grid's"
)


class WholeRuns:
    """The runs the grid kernel scored, per (training run, setting): the folds of one
    `tune_drives` share drives (Datasets 6 and 7 tune 9 on the drives that tune 7 and 6), so a
    fold reads what an earlier fold ran whole (engines.tuning.grid_kernel's `known`) and goes on
    from where an earlier fold's bound stopped a run (its `partial`): the same sums and winners
    as running them again."""

    def __init__(self) -> None:
        self._found: dict[tuple, np.ndarray] = {}
        self._stopped: dict[tuple, np.ndarray] = {}

    def known(self, inputs: list, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What is known of each setting of `sig` on each of `inputs`: (G, runs, 4) whole runs
        and (G, runs, RESUME_SIZE) stopped ones, NaN where nothing is."""
        out = np.full((len(sig), len(inputs), 4), np.nan)
        partial = np.full((len(sig), len(inputs), RESUME_SIZE), np.nan)
        for g, row in enumerate(sig):
            key = row.tobytes()
            for r, s in enumerate(inputs):
                found = self._found.get((s, key))  # SegmentInputs hash by identity
                if found is not None:
                    out[g, r] = found
                elif (stopped := self._stopped.get((s, key))) is not None:
                    partial[g, r] = stopped
        return out, partial

    def keep(self, inputs: list, sig: np.ndarray, done: np.ndarray, partial: np.ndarray) -> None:
        for g, row in enumerate(sig):
            key = row.tobytes()
            for r, s in enumerate(inputs):
                if not np.isnan(done[g, r, 0]):
                    self._found[(s, key)] = done[g, r].copy()
                    self._stopped.pop((s, key), None)
                elif not np.isnan(partial[g, r, 0]):
                    self._stopped[(s, key)] = partial[g, r].copy()


def _score(runs: GridRuns, exps: np.ndarray, naive, P0, gate, T0, jobs: int, bound: float,
           whole: bool, memo: WholeRuns | None = None, inputs=()) -> np.ndarray:  # fmt: skip
    """`GridRuns.score` of the settings naive * 2^exps (G, 5: sq_sum, max_err, n_updates,
    n_rejected, finished), the settings dealt round-robin to `jobs` threads, one compiled call
    each (the kernel releases the GIL: no worker processes to start, nothing to pickle). With
    `whole` (branch and bound), each thread's call keeps its own best complete sum as bound.
    `memo`: the runs of `inputs` scored before, read instead of run where whole, gone on with
    from where a bound stopped them otherwise, and kept."""
    sig = np.array([naive * np.exp2(e) for e in exps]).reshape(-1, 4)
    known, partial = memo.known(inputs, sig) if memo is not None else (None, None)
    parts = max(1, min(jobs, len(exps)))
    if parts == 1:
        out, done = runs.score(sig, P0, gate, T0, bound, whole, known, partial)
    else:
        chunks = [(None, None) if known is None else
                  (known[i::parts], np.ascontiguousarray(partial[i::parts]))
                  for i in range(parts)]  # fmt: skip
        found = Parallel(n_jobs=parts, backend="threading")(
            delayed(runs.score)(sig[i::parts], P0, gate, T0, bound, whole, *chunks[i])
            for i in range(parts)
        )
        out = np.zeros((len(exps), 5))
        done = np.full((len(exps), len(runs.stamps) - 1, 4), np.nan)
        for i, (o, d) in enumerate(found):
            out[i::parts] = o
            done[i::parts] = d
            if partial is not None:
                partial[i::parts] = chunks[i][1]  # updated by the call
    if memo is not None:
        memo.keep(inputs, sig, done, partial)
    return out


def _best(scores: np.ndarray) -> int:
    """The setting with the smallest complete sum of squared errors (every setting is scored at
    the same times, so it has the smallest pooled RMSE); a setting that diverged scores inf."""
    crit = np.where(scores[:, 4] > 0, scores[:, 0], np.inf)
    crit = np.where(np.isfinite(crit), crit, np.inf)
    return int(np.argmin(crit))


def tune(
    scenario: RecordedScenario, inputs: list, jobs: int = 1, seeds=(), whole: bool = False,
    memo: WholeRuns | None = None,
) -> dict:  # fmt: skip
    """The grid search of `ekf-tuned` (sources.recorded.TuningConfig) on the training runs
    `inputs` (real_experiment.SegmentInputs, each cold-started from ground truth): the coarse
    grid, then 3^4 settings around the best so far with steps 2^(1/2) and 2^(1/4). The
    criterion, the pooled position RMSE over every scored time of `inputs`, has the same
    denominator for every setting, so the smallest sum of squares wins.

    Training segments (`whole` False): every setting scored in full; the record says which
    share of the coarse settings lost lock (a position error above 1 m). Whole drives (`whole`
    True): branch and bound, a setting stops once its partial sum passes the best complete one
    (the same winner as scoring every setting in full); `seeds` (log2 multipliers) are scored
    first, to start with a tight bound, and the coarse grid runs nearest the first seed first.
    `memo`: the runs earlier searches scored on some of `inputs`, whole or up to where their
    bound stopped them (`WholeRuns`).

    Returns the chosen standard deviations (sigma_v, sigma_w_rad, sigma_range,
    sigma_bearing_rad), their log2 multipliers of the naive values, the criterion there, the
    stages and the time it took.
    """
    started = time.perf_counter()
    naive = scenario.naive.sigmas()
    runs = GridRuns.of([(s.timeline, s.segment.pose, s.truth, s.scored) for s in inputs])
    count = int(sum(int(s.scored.sum()) for s in inputs))
    fixed = (naive, recorded_p0(scenario), gate_threshold(scenario.gate_probability),
             scenario.odometry_period_s)  # fmt: skip
    shared = (memo, inputs)

    def rmse(sq: float) -> float:
        return float(math.sqrt(sq / count)) if count else math.nan

    def stage(label: str, sc: np.ndarray) -> dict:
        doc = {"stage": label, "settings": len(sc)}
        if whole:
            doc["stopped_early"] = float(np.mean(sc[:, 4] == 0))
        else:
            doc["best"] = rmse(sc[_best(sc), 0])
        return doc

    coarse = np.stack(np.meshgrid(*scenario.tuning.axes(), indexing="ij"), -1).reshape(-1, 4)
    all_exps, all_scores, bound = [], [], math.inf
    if whole:
        seeds = np.array(seeds, dtype=float).reshape(-1, 4)
        anchor = seeds[0] if len(seeds) else coarse.mean(axis=0)
        coarse = coarse[np.argsort(np.abs(coarse - anchor).sum(axis=1), kind="stable")]
        if len(seeds):
            sc = _score(runs, seeds, *fixed, 1, bound, whole, *shared)
            all_exps.append(seeds)
            all_scores.append(sc)
            bound = float(sc[_best(sc), 0]) if np.any(sc[:, 4] > 0) else bound
    sc = _score(runs, coarse, *fixed, jobs, bound, whole, *shared)
    all_exps.append(coarse)
    all_scores.append(sc)
    coarse_scores = sc
    stages = [stage("coarse (step 2^1)", sc)]
    if scenario.tuning.refine:
        offsets = np.stack(np.meshgrid(*[[-1.0, 0.0, 1.0]] * 4, indexing="ij"), -1).reshape(-1, 4)
        for step, label in ((0.5, "2^(1/2)"), (0.25, "2^(1/4)")):
            exps, scores = np.vstack(all_exps), np.vstack(all_scores)
            i = _best(scores)
            around = exps[i] + step * offsets
            sc = _score(runs, around, *fixed, jobs, float(scores[i, 0]) if whole else bound,
                        whole, *shared)  # fmt: skip
            all_exps.append(around)
            all_scores.append(sc)
            stages.append(stage(f"refine (step {label})", sc))
    exps, scores = np.vstack(all_exps), np.vstack(all_scores)
    i = _best(scores)
    sig = naive * np.exp2(exps[i])
    seen = scores[i, 2] + scores[i, 3]
    out = {
        "criterion": _CRITERION[whole],
        "sigma_v": float(sig[0]),
        "sigma_w_rad": float(sig[1]),
        "sigma_range": float(sig[2]),
        "sigma_bearing_rad": float(sig[3]),
        "log2_multipliers": {a: float(e) for a, e in zip(AXES, exps[i], strict=True)},
        "train_rmse_pos": rmse(scores[i, 0]),
        "train_max_pos_err": float(scores[i, 1]),
        "train_gate_rejected": float(scores[i, 3] / seen) if seen else math.nan,
    }
    if whole:
        out |= {"settings": int(len(exps)), "search": _BRANCH_AND_BOUND}
    else:
        out |= {
            "train_segments": len(inputs),
            "settings": int(len(exps)),
            "coarse_lost_lock_share": float(np.mean(coarse_scores[:, 1] > LOST_LOCK_M)),
        }
    return out | {"stages": stages, "seconds": round(time.perf_counter() - started, 3)}


def drive_rmse(scenario: RecordedScenario, inputs, tuned: dict) -> float:
    """The position RMSE of the plain EKF with `tuned` noise on one drive (engines.tuning)."""
    sig = [tuned[k] for k in ("sigma_v", "sigma_w_rad", "sigma_range", "sigma_bearing_rad")]
    sq, *_ = score_setting(
        inputs.timeline, inputs.segment.pose, recorded_p0(scenario), sig,
        gate_threshold(scenario.gate_probability), scenario.odometry_period_s,
        inputs.truth, inputs.scored,
    )  # fmt: skip
    n = int(inputs.scored.sum())
    return float(math.sqrt(sq / n)) if n else math.nan


def tune_drives(scenario: RecordedScenario, inputs: dict, world: DriveSet,
                jobs: int = 1) -> tuple[dict[str, dict], dict]:  # fmt: skip
    """ekf-tuned's noise for every drive (tuned on the drives of `scenario.tuning_sources` of
    its dataset, never its own), and the manifest's account: each tuning, and per drive the
    RMSE of the cross-dataset values against values tuned on its own dataset's drives (which
    include the drive itself: in-sample, the most tuning can give on that map)."""
    by_dataset: dict[int, list] = {}
    for d in world.drives:
        by_dataset.setdefault(d.dataset, []).append(d)
    keys = {tuple(scenario.tuning_sources(ds)) for ds in by_dataset}
    keys |= {(ds,) for ds in by_dataset}
    reference = tuned_reference(scenario)
    tunings: dict[tuple, dict] = {}
    memo = WholeRuns()  # the folds share drives
    for key in sorted(keys, key=lambda k: (len(k), k)):  # single datasets first: they seed
        drives = [d for ds in key for d in by_dataset[ds]]
        seeds = [list(tunings[(ds,)]["log2_multipliers"].values()) for ds in key
                 if (ds,) in tunings]  # fmt: skip
        fold = drive_fold(scenario, drives, inputs, jobs, seeds=seeds, memo=memo)
        tunings[key] = fit_specs([(reference, fold)], None)[0].fitted
        tunings[key]["train_drives"] = [d.id for d in drives]
    tuned_for, per_drive = {}, []
    for d in world.drives:
        cross = tunings[tuple(scenario.tuning_sources(d.dataset))]
        tuned_for[d.id] = cross
        per_drive.append(
            {
                "drive": d.id,
                "dataset": d.dataset,
                "tuned_on": cross["train_drives"],
                "cross_rmse_pos": drive_rmse(scenario, inputs[d.id], cross),
                "in_dataset_rmse_pos": drive_rmse(scenario, inputs[d.id], tunings[(d.dataset,)]),
            }
        )
    doc = {
        "protocol": "drives",
        "tunings": {"+".join(map(str, k)): v for k, v in tunings.items()},
        "per_drive": per_drive,
        "seconds": round(sum(t["seconds"] for t in tunings.values()), 3),
    }
    return tuned_for, doc
