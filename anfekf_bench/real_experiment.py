"""A real-data scenario end to end (SPEC 9): tune the reference, run the held-out segments, write.

1. **Tune** (`tune`): the `ekf-tuned` reference's noise by a grid search on the training part
   (`sources.recorded.TuningConfig`): every training segment is cold-started from ground truth
   and the plain EKF is run for every noise setting (fitting.recorded.tune: the compiled tuning
   kernel over every setting and segment, `engines.tuning.grid_kernel`, the settings dealt to
   `jobs` threads); the criterion is the pooled position RMSE over the scorable evaluation
   times of all training segments.
2. **Run** (`recorded_run`): each held-out segment is one Monte Carlo "run" of the one per-run
   function, `runner.run_one`: every filter instance (each filter from each naive start, and
   ekf-tuned) is cold-started from ground truth at the segment's start
   (`filters.context.recorded_context`) and stepped over its timeline (`timeline.Timeline`) on
   the plan's engine (`runner.run_spec`: the fast engine for the kinds it runs, filterpy for the
   rest).
3. **Align**: a run's per-step arrays are indexed by the evaluation time's rank in its segment
   (step k = the segment's k-th odometry stamp; t = seconds since the segment's cold start).
   Segments differ by a few stamps, so shorter ones are padded with NaN up to the longest.
   Ground truth is NaN wherever it must not be scored (a Vicon gap, a mis-fit, the padding):
   errors and NEES are NaN there and every metric leaves NaN out (analysis.metrics).
4. **Write**: `RecordedSource` is what experiment's one pipeline (`experiment.execute`) asks of
   a recorded log: its runs, its checks, the preparation above (tuning, training, fits) and the
   runs as picklable calls; the pipeline dispatches them (local processes or Dask), saves each
   run as it finishes (resumed segment by segment after an interruption) and writes what a
   simulated scenario writes (steps, runs, summary, comparisons against ekf-tuned, claims,
   manifest) through the same tables and the same run store.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from .analysis.metrics import nees_single_run
from .analysis.suite import LOST_LOCK_M
from .drive_audit import audit_tables
from .filters.context import recorded_context
from .filters.spec import FilterContext
from .fitting.own import fit_on_own_innovations
from .fitting.recorded import (
    fit_on_drives,
    fit_on_segments,
    trained_filters,
    tune_drives,
    tune_segments,
)
from .models import Unicycle
from .outputs import PlanError
from .runner import Prepared, RunInputs, engine_of, pad_to, run_one
from .sources import mrclam
from .sources.recorded import (
    DriveSet,
    RecordedScenario,
    Recording,
    Segment,
)
from .timeline import Timeline, timeline

# --------------------------------------------------------------------------------------------
# Segments as filter inputs


@dataclass(frozen=True, eq=False)
class SegmentInputs:
    """What a filter consumes and is scored against on one segment."""

    segment: Segment
    timeline: Timeline
    t: np.ndarray  # evaluation times (odometry stamps) [s, log time]
    truth: np.ndarray  # (n, 3) ground truth there, NaN where it is not scorable
    scored: np.ndarray  # (n,) bool


def thin_records(tl: Timeline, period_s: float | None) -> Timeline:
    """The timeline with its evaluation times thinned: a record stamp is kept when it lies at
    least `period_s` after the last kept one (the first is kept). The filter still sees every
    command and every landmark; stamps that are then neither an evaluation time nor a landmark
    time nor a change of command are merged into the next stamp (65 Hz odometry, 8 Hz scores)."""
    if period_s is None:
        return tl
    idx = np.flatnonzero(tl.record)
    keep = np.zeros(len(idx), bool)
    last = -math.inf
    for i, t in enumerate(tl.t[idx].tolist()):
        if t - last >= period_s:
            keep[i] = True
            last = t
    record = np.zeros(len(tl.t), bool)
    record[idx[keep]] = True
    # A stamp with no landmark and no evaluation whose command is held on over the next interval
    # only splits one predict in two: merged into the next stamp (midpoint Euler over the joined
    # interval; the rate-consistent Q is the same; 65 Hz odometry repeats its command ~4 times).
    n = len(tl.t)
    empty = tl.lm[:-1] == tl.lm[1:]
    same_next = np.r_[np.all(tl.u[1:] == tl.u[:-1], axis=1), False]
    kept = np.flatnonzero(~(empty & ~record & same_next))
    if len(kept) == n:
        return replace(tl, record=record)
    t = tl.t[kept]
    return replace(
        tl,
        t=t,
        dt=np.diff(np.r_[tl.t_start, t]),
        u=np.ascontiguousarray(tl.u[kept]),
        lm=np.r_[tl.lm[kept], tl.lm[-1]],
        record=record[kept],
    )


def segment_inputs(rec, seg: Segment, eval_period_s: float | None = None) -> SegmentInputs:
    """A segment's timeline, evaluation times and ground truth (NaN where not scorable). `rec`
    is a `Recording` or a `Drive` (what has `log` and `scorable`)."""
    tl = thin_records(timeline(mrclam.events(rec.log, seg.t0, seg.end)), eval_period_s)
    t = tl.record_t
    truth = np.column_stack(mrclam.interpolate_truth(rec.log, t)).reshape(-1, 3)
    scored = rec.scorable(t) & np.all(np.isfinite(truth), axis=1)
    truth[~scored] = np.nan
    return SegmentInputs(seg, tl, t, truth, scored)


# --------------------------------------------------------------------------------------------
# 2. The held-out segments


def noise_sigmas(noise: dict) -> tuple[float, float, float, float]:
    """(sv, sw, sr, sb) of a tuned or fitted noise record (`fitting.recorded.tune`,
    `fitting.own.fit_on_own_innovations`)."""
    return noise["sigma_v"], noise["sigma_w_rad"], noise["sigma_range"], noise["sigma_bearing_rad"]


def recorded_run(
    scenario: RecordedScenario,
    inputs: SegmentInputs,
    tuned: dict | None,
    n_steps: int,
    fitted: dict[str, dict] | None = None,
    engine: str = "filterpy",
) -> dict:
    """One held-out segment or drive as a Monte Carlo run (`runner.run_one`): every filter
    instance from ground truth (`recorded_context`), padded to `n_steps` evaluation times.
    `tuned`: ekf-tuned's noise; `fitted`: each ekf-ml instance's, fitted on this run."""
    seg = inputs.segment
    run = RunInputs(
        seg.index, inputs.timeline, np.arange(1, n_steps + 1),
        pad_to(inputs.t - seg.t0, n_steps), pad_to(inputs.truth, n_steps), len(inputs.t),
    )  # fmt: skip

    def context(name: str, spec, m: float | None) -> FilterContext:
        if m is None and spec.role == "fitted":
            noise = noise_sigmas((fitted or {}).get(name, tuned))
            return recorded_context(scenario, seg.pose, None, noise)
        return recorded_context(scenario, seg.pose, m)

    instances = ((name, spec, context(name, spec, m)) for name, spec, m in scenario.instances())
    return run_one(run, instances, engine)


# --------------------------------------------------------------------------------------------
# 3. Tables


def real_summary(
    records: list[dict], ordered: list[dict], scenario: RecordedScenario
) -> list[dict]:
    """The summary records plus what matters on real data, per filter instance: its base filter
    and start, the pooled RMSE over all scored times, the largest error, the runs that lost lock
    (an error above LOST_LOCK_M at a scored time). Consistency is read run by run: the runs of a
    recorded log are different times (different drives), so a step index pools nothing; nees_lo
    / nees_hi are the single-run 95 % chi-square(3) bounds and nees_in_bounds the share of every
    scored step of every run whose own NEES lies inside them (runs.parquet has each run's)."""
    meta = {name: (spec.name, m) for name, spec, m in scenario.instances()}
    out = []
    for rec in records:
        name = rec["filter"]
        traces = [r["filters"][name] for r in ordered if not r["filters"][name]["diverged"]]
        err = np.concatenate([t["pos_err"] for t in traces]) if traces else np.zeros(0)
        err = err[np.isfinite(err)]
        per_run_max = [
            float(np.nanmax(t["pos_err"])) if np.isfinite(t["pos_err"]).any() else math.nan
            for t in traces
        ]
        base, m = meta[name]
        nees = np.array([t["nees"] for t in traces]) if traces else np.zeros((0, 0))
        consistency = nees_single_run(nees)
        rec = dict(rec)
        rec.update(
            nees_lo=consistency["lo"],
            nees_hi=consistency["hi"],
            nees_in_bounds=consistency["pooled"],
            base_filter=base,
            start=m,
            rmse_pos_pooled=float(np.sqrt(np.mean(err**2))) if len(err) else math.nan,
            max_pos_err=float(np.max(err)) if len(err) else math.nan,
            lost_lock_runs=int(sum(v > LOST_LOCK_M for v in per_run_max)),
        )
        out.append(rec)
    return out


# --------------------------------------------------------------------------------------------
# 4. The source of experiment's one pipeline

SEGMENTS_ALIGNMENT = (
    "step k of a run is the k-th odometry stamp of its segment; t is seconds since the segment's"
    " cold start; shorter segments are padded with NaN"
)
DRIVES_ALIGNMENT = (
    "run r is drive r of data.drives, whole from its ground-truth start; step k is its k-th"
    " evaluation time (odometry stamps at least eval_period_s apart); t is seconds since the"
    " cold start; shorter drives are padded with NaN"
)


@dataclass(frozen=True, eq=False)
class RecordedSource:
    """Runs read from a recorded log (experiment.Plan's source for a `RecordedScenario`): its
    held-out segments (protocol segments, a `Recording`) or its drives (protocol drives, a
    `DriveSet`), each cold-started from ground truth. The plan's seed only seeds the bootstrap
    intervals; ekf-tuned is tuned, kalmannet trained and ekf-ml fitted in `prepare`."""

    world: Recording | DriveSet

    @property
    def runs(self) -> int:
        return len(self.world.test_segments)

    def filter_names(self, scenario: RecordedScenario) -> list[str]:
        """Every filter instance (each filter from each naive start, and the fixed ones)."""
        return scenario.instance_names()

    def fingerprint_doc(self, plan) -> dict:
        """What determines a run's bytes: the scenario, the log's content, the engine."""
        return {
            "scenario": plan.scenario.model_dump(
                mode="json", exclude={"jobs", "backend", "engine"}
            ),
            "data": self.world.digest,
            "engine": plan.engine,
        }

    def check(self, plan) -> int:
        """What can fail before the batch (PlanError); returns the held-out evaluation times."""
        if isinstance(self.world, DriveSet):
            return sum(
                int(np.sum((d.log.odo_t > d.segment.t0) & (d.log.odo_t <= d.segment.end)))
                for d in self.world.drives
            )
        log = self.world.log
        for part, segments in (("training", self.world.train_segments),
                               ("held-out", self.world.test_segments)):  # fmt: skip
            for seg in segments:
                if not np.any((log.odo_t > seg.t0) & (log.odo_t <= seg.end)):
                    odo = (
                        f"{log.odo_t.min():.1f}-{log.odo_t.max():.1f} s" if len(log.odo_t)
                        else "none"
                    )  # fmt: skip
                    raise PlanError(
                        f"data: {part} segment {seg.index} ({seg.t0:.1f}-{seg.end:.1f} s) holds"
                        f" no odometry (the log's odometry: {odo}); odometry and ground truth"
                        " must overlap"
                    )
        return sum(
            int(np.sum((log.odo_t > s.t0) & (log.odo_t <= s.end))) for s in self.world.test_segments
        )

    def engines(self, plan) -> dict[str, str]:
        model = Unicycle(plan.scenario.odometry_period_s)
        return {
            name: engine_of(plan.engine, spec, model=model)
            for name, spec, _ in plan.scenario.instances()
        }

    def comparison_pairs(self, scenario: RecordedScenario) -> list[tuple[str, str]]:
        """Every instance against the ekf-tuned reference, then the scenario's `compare`."""
        ref = scenario.reference()
        pairs = [(n, ref) for n in scenario.instance_names() if ref is not None and n != ref]
        for pair in scenario.compare:
            if tuple(pair) not in pairs:
                pairs.append(tuple(pair))
        return pairs

    def summary(self, plan, records: list[dict], steps, ordered: list[dict]):
        """The summary with real_summary's columns; no phases."""
        return real_summary(records, ordered, plan.scenario), None

    def prepare(self, plan, store: Path, progress=None) -> Prepared:
        """Train (kalmannet, on training segments or per fold), tune ekf-tuned, fit ekf-ml on
        each run's own innovations (all cached in `store` where they can be), and hand out one
        `recorded_run` call per held-out segment or drive."""
        if isinstance(self.world, DriveSet):
            return _prepare_drives(plan, self.world, store, progress)
        return _prepare_segments(plan, self.world, store, progress)


def _prepare_segments(plan, rec: Recording, store: Path, progress) -> Prepared:
    scenario = plan.scenario
    # Trained filters (kalmannet): fitted on the training segments only (or the cache).
    tunes = scenario.reference() is not None
    learns = bool(trained_filters(scenario))
    training = [segment_inputs(rec, s) for s in rec.train_segments] if learns or tunes else []
    run_scenario, trained = fit_on_segments(scenario, rec, training, store, progress)
    action = ""
    for name in trained:
        how = "read from the cache" if trained[name]["train"]["cached"] else "trained"
        action += f"; {name} {how} on the training segments"
    tuned = None
    if tunes:
        tuned = tune_segments(scenario, rec, training, plan.jobs)
        action += (
            f"; ekf-tuned on {tuned['train_segments']} training segments"
            f" ({tuned['settings']} settings, {tuned['seconds']:.1f} s): sigma_v"
            f" {tuned['sigma_v']:.4g} m/s, sigma_w {tuned['sigma_w_rad']:.4g} rad/s,"
            f" sigma_range {tuned['sigma_range']:.4g} m, sigma_bearing"
            f" {tuned['sigma_bearing_rad']:.4g} rad (training RMSE"
            f" {tuned['train_rmse_pos']:.4f} m)"
        )
    inputs = [segment_inputs(rec, s) for s in rec.test_segments]
    n_steps = max(len(i.t) for i in inputs)
    fitted, fits = fit_on_own_innovations(
        scenario, inputs, [str(i.segment.index) for i in inputs], store, plan.jobs
    )
    items = {
        i.segment.index: partial(
            recorded_run, run_scenario, i, tuned, n_steps, fitted.get(i.segment.index), plan.engine
        )
        for i in inputs
    }
    manifest = {
        **_recorded_manifest(plan.scenario, rec.summary(), tuned, SEGMENTS_ALIGNMENT),
        **({"fits": fits} if fits else {}),
        **({"training": trained} if trained else {}),
    }
    return Prepared(items, action + _fits_action(fits), manifest, n_steps)


def _prepare_drives(plan, world: DriveSet, store: Path, progress) -> Prepared:
    """Protocol drives: tune per test dataset, run every drive whole."""
    scenario = plan.scenario
    inputs = {d.id: segment_inputs(d, d.segment, scenario.eval_period_s) for d in world.drives}
    # Trained filters (kalmannet): one fit per fold, on its training drives only (or the cache).
    run_scenario, trained = fit_on_drives(scenario, world, inputs, store, progress)
    action = ""
    for name, folds in trained.items():
        how = "read from the cache" if all(r["cached"] for r in folds.values()) else "trained"
        action += f"; {name} {how} per fold (on dataset(s) {', '.join(folds)})"
    # ekf-ml's fits need nothing of the tuning: with jobs > 1 they run beside it (both on
    # threads, in compiled kernels), so that either fills the cores the other leaves idle
    # between its stages
    fit_own = partial(
        fit_on_own_innovations, scenario, [inputs[d.id] for d in world.drives],
        [d.id for d in world.drives], store, plan.jobs,
    )  # fmt: skip
    with ThreadPoolExecutor(max_workers=1) as beside:
        own = beside.submit(fit_own) if plan.jobs > 1 else None
        tuned_for, tuning = {}, None
        if scenario.reference() is not None:
            tuned_for, tuning = tune_drives(scenario, inputs, world, plan.jobs)
            action += (
                f"; ekf-tuned tuned per dataset on the others' drives ({tuning['seconds']:.1f} s)"
            )
        # The audit against Vicon (SPEC 18): the data's errors and ekf-tuned's lost-lock episodes
        started = time.perf_counter()
        audit = audit_tables(scenario, world.drives, inputs, tuned_for, plan.seed)
        action += f"; drives audited against Vicon ({time.perf_counter() - started:.1f} s)"
        fitted, fits = own.result() if own is not None else fit_own()
    n_steps = max(len(i.t) for i in inputs.values())
    items = {
        d.segment.index: partial(
            recorded_run,
            run_scenario[d.id],
            inputs[d.id],
            tuned_for.get(d.id),
            n_steps,
            fitted.get(d.segment.index),
            plan.engine,
        )  # fmt: skip
        for d in world.drives
    }
    manifest = {
        **_recorded_manifest(scenario, world.summary(), tuning, DRIVES_ALIGNMENT),
        "protocol": "drives",
        "tuning_seconds": tuning["seconds"] if tuning else 0.0,
        **({"fits": fits} if fits else {}),
        **({"training": trained} if trained else {}),
    }
    return Prepared(items, action + _fits_action(fits), manifest, n_steps, tables=audit)


def _recorded_manifest(scenario: RecordedScenario, data: dict, tuning, alignment: str) -> dict:
    """The manifest keys only a recorded result has (report.real reads them)."""
    return {
        "kind": "recorded",
        "data": data,
        "tuning": tuning,
        "alignment": alignment,
    }


def _fits_action(fits: dict) -> str:
    """The start line's account of the ekf-ml fits (empty without ekf-ml)."""
    if not fits:
        return ""
    n = sum(len(f["runs"]) for f in fits["filters"].values())
    return (
        f"; ekf-ml fitted on each run's own innovations ({n} fits, {fits['fitted_now']} computed"
        f" now, {fits['seconds']:.1f} s)"
    )
