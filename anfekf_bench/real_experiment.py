"""A real-data scenario end to end (SPEC 9): tune the reference, run the held-out segments, write.

1. **Tune** (`tune`): the `ekf-tuned` reference's noise by a grid search on the training part
   (`sources.recorded.TuningConfig`): every training segment is cold-started from ground truth
   and the plain EKF is run for every noise setting (`engines.tuning.score_setting`, the compiled
   tuning kernel, the settings split over `jobs` processes); the criterion is the pooled position
   RMSE over the scorable evaluation times of all training segments.
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

import hashlib
import json
import math
import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from .engines.tuning import TimelineLikelihood, fit_noise, score_setting, unicycle_terms
from .filters.context import recorded_context, recorded_p0
from .filters.ekf import gate_threshold
from .filters.fitted import EKFMLSpec, sigmas_problem
from .filters.spec import FilterContext
from .models import Unicycle
from .outputs import FIT_FILE, PlanError, code_version, read_cached_fit, write_fit
from .real_training import fit_on_drives, fit_on_segments, trained_filters
from .runner import Prepared, RunInputs, engine_of, pad_to, run_one
from .sources import mrclam
from .sources.recorded import (
    DriveSet,
    RecordedScenario,
    Recording,
    Segment,
)
from .timeline import Timeline, timeline
from .workers import local_workers

LOST_LOCK_M = 1.0  # a run whose position error exceeds this at a scored time has lost lock


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
# 1. Tuning


AXES = ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing")


def _score_chunk(exps: np.ndarray, naive: np.ndarray, segs, P0, gate, T0) -> np.ndarray:
    """(G, 5): sq_sum, count, max_err, n_updates, n_rejected of each setting over every training
    segment (the tuning kernel, one setting at a time)."""
    out = np.zeros((len(exps), 5))
    terms = [unicycle_terms(s.timeline) for s in segs]
    for g, e in enumerate(exps):
        sig = naive * np.exp2(e)
        for s, tk in zip(segs, terms, strict=True):
            sq, mx, nu, nr, _ = score_setting(
                s.timeline, s.segment.pose, P0, sig, gate, T0, s.truth, s.scored, terms=tk
            )
            out[g] += (sq, int(s.scored.sum()), 0.0, nu, nr)
            out[g, 2] = max(out[g, 2], mx)
    return out


def _score(exps: np.ndarray, naive, segs, P0, gate, T0, jobs: int) -> np.ndarray:
    """`_score_chunk` with the settings dealt round-robin to `jobs` threads (the compiled kernel
    releases the GIL: no worker processes to start, nothing to pickle)."""
    parts = max(1, min(jobs, len(exps)))
    if parts == 1:
        return _score_chunk(exps, naive, segs, P0, gate, T0)
    found = Parallel(n_jobs=parts, backend="threading")(
        delayed(_score_chunk)(exps[i::parts], naive, segs, P0, gate, T0) for i in range(parts)
    )
    out = np.zeros((len(exps), 5))
    for i, f in enumerate(found):
        out[i::parts] = f
    return out


def _criterion(scores: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        rmse = np.sqrt(scores[:, 0] / scores[:, 1])
    return np.where(np.isfinite(rmse), rmse, np.inf)


def tune(scenario: RecordedScenario, rec: Recording, jobs: int = 1) -> dict:
    """The grid search of `ekf-tuned` on the training segments (see the module doc).

    Returns the chosen standard deviations (sigma_v, sigma_w_rad, sigma_range,
    sigma_bearing_rad), their log2 multipliers of the naive values, the criterion there, the
    stages (settings and best value of each), the share of coarse settings that lost lock (a
    position error above 1 m) and the time it took.
    """
    started = time.perf_counter()
    segs = [segment_inputs(rec, s) for s in rec.train_segments]
    naive = scenario.naive.sigmas()
    P0 = recorded_p0(scenario)
    gate = gate_threshold(scenario.gate_probability)
    T0 = scenario.odometry_period_s
    axes = scenario.tuning.axes()
    coarse = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)
    scores = _score(coarse, naive, segs, P0, gate, T0, jobs)
    crit = _criterion(scores)
    all_exps, all_scores, all_crit = [coarse], [scores], [crit]
    best = int(np.argmin(crit))
    stages = [{"stage": "coarse (step 2^1)", "settings": len(coarse), "best": float(crit[best])}]
    best_exp = coarse[best]
    if scenario.tuning.refine:
        offsets = np.stack(np.meshgrid(*[[-1.0, 0.0, 1.0]] * 4, indexing="ij"), -1).reshape(-1, 4)
        for step, label in ((0.5, "2^(1/2)"), (0.25, "2^(1/4)")):
            exps = best_exp + step * offsets
            s = _score(exps, naive, segs, P0, gate, T0, jobs)
            c = _criterion(s)
            all_exps.append(exps)
            all_scores.append(s)
            all_crit.append(c)
            stages.append({"stage": f"refine (step {label})", "settings": len(exps),
                           "best": float(c.min())})  # fmt: skip
            best_exp = np.vstack(all_exps)[int(np.argmin(np.concatenate(all_crit)))]
    exps = np.vstack(all_exps)
    crit = np.concatenate(all_crit)
    scores = np.vstack(all_scores)
    i = int(np.argmin(crit))
    best_exp = exps[i]
    sig = naive * np.exp2(best_exp)
    seen = scores[i, 3] + scores[i, 4]
    return {
        "criterion": "pooled position RMSE over the scorable evaluation times of the training"
        " segments [m]",
        "sigma_v": float(sig[0]),
        "sigma_w_rad": float(sig[1]),
        "sigma_range": float(sig[2]),
        "sigma_bearing_rad": float(sig[3]),
        "log2_multipliers": {a: float(e) for a, e in zip(AXES, best_exp, strict=True)},
        "train_rmse_pos": float(crit[i]),
        "train_max_pos_err": float(scores[i, 2]),
        "train_gate_rejected": float(scores[i, 4] / seen) if seen else math.nan,
        "train_segments": len(segs),
        "settings": int(len(exps)),
        "coarse_lost_lock_share": float(np.mean(scores[: len(coarse), 2] > LOST_LOCK_M)),
        "stages": stages,
        "seconds": round(time.perf_counter() - started, 3),
    }


# --------------------------------------------------------------------------------------------
# 1b. Tuning across drives (protocol drives, SPEC 15): the same grid and refinement as `tune`,
# on whole drives, by branch and bound on the compiled tuning kernel (engines.tuning)


def _bnb_chunk(exps: np.ndarray, naive, inputs, P0, gate, T0, bound: float) -> np.ndarray:
    """(G, 5): sq_sum, max_err, n_updates, n_rejected, finished of each setting over all
    `inputs`, stopping a setting once its sum passes the best complete sum seen (or `bound`)."""
    out = np.zeros((len(exps), 5))
    best = bound
    terms = [unicycle_terms(s.timeline) for s in inputs]
    for g, e in enumerate(exps):
        sig = naive * np.exp2(e)
        total, worst, upd, rej, finished = 0.0, 0.0, 0, 0, True
        for s, tk in zip(inputs, terms, strict=True):
            sq, mx, nu, nr, fin = score_setting(
                s.timeline, s.segment.pose, P0, sig, gate, T0, s.truth, s.scored,
                best - total, terms=tk,
            )  # fmt: skip
            total, worst, upd, rej = total + sq, max(worst, mx), upd + nu, rej + nr
            if not fin or not math.isfinite(total):
                finished = finished and math.isfinite(total) and fin
                break
        out[g] = (total, worst, upd, rej, float(finished))
        if finished and total < best:
            best = total
    return out


def _bnb(exps: np.ndarray, naive, inputs, P0, gate, T0, jobs: int, bound: float) -> np.ndarray:
    """`_bnb_chunk` with the settings dealt round-robin to `jobs` threads (as `_score`)."""
    parts = max(1, min(jobs, len(exps)))
    if parts == 1:
        return _bnb_chunk(exps, naive, inputs, P0, gate, T0, bound)
    found = Parallel(n_jobs=parts, backend="threading")(
        delayed(_bnb_chunk)(exps[i::parts], naive, inputs, P0, gate, T0, bound)
        for i in range(parts)
    )
    out = np.zeros((len(exps), 5))
    for i, f in enumerate(found):
        out[i::parts] = f
    return out


def _bnb_best(scores: np.ndarray) -> int:
    """The setting with the smallest complete sum (every setting is scored at the same times)."""
    crit = np.where(scores[:, 4] > 0, scores[:, 0], np.inf)
    crit = np.where(np.isfinite(crit), crit, np.inf)
    return int(np.argmin(crit))


def tune_on_drives(
    scenario: RecordedScenario, inputs: list[SegmentInputs], jobs: int = 1, seeds=()
) -> dict:
    """`tune`'s grid search (coarse grid, then 3^4 around the best with steps 2^(1/2) and
    2^(1/4)) on whole drives. The criterion, the pooled position RMSE over every scored time of
    `inputs`, has the same denominator for every setting, so the smallest sum of squares wins
    and a setting stops once its partial sum passes the best complete one (branch and bound:
    the same winner as scoring every setting in full). `seeds` (log2 multipliers) are scored
    first, to start with a tight bound; the coarse grid then runs nearest the seeds first."""
    started = time.perf_counter()
    naive = scenario.naive.sigmas()
    P0 = recorded_p0(scenario)
    gate = gate_threshold(scenario.gate_probability)
    T0 = scenario.odometry_period_s
    count = int(sum(int(s.scored.sum()) for s in inputs))
    coarse = np.stack(np.meshgrid(*scenario.tuning.axes(), indexing="ij"), -1).reshape(-1, 4)
    seeds = np.array(seeds, dtype=float).reshape(-1, 4)
    anchor = seeds[0] if len(seeds) else coarse.mean(axis=0)
    coarse = coarse[np.argsort(np.abs(coarse - anchor).sum(axis=1), kind="stable")]
    bound = math.inf
    all_exps, all_scores, stages = [], [], []
    if len(seeds):
        sc = _bnb_chunk(seeds, naive, inputs, P0, gate, T0, bound)
        all_exps.append(seeds)
        all_scores.append(sc)
        bound = float(sc[_bnb_best(sc), 0]) if np.any(sc[:, 4] > 0) else bound
    sc = _bnb(coarse, naive, inputs, P0, gate, T0, jobs, bound)
    all_exps.append(coarse)
    all_scores.append(sc)
    stopped = float(np.mean(sc[:, 4] == 0))
    stages.append({"stage": "coarse (step 2^1)", "settings": len(coarse), "stopped_early": stopped})
    if scenario.tuning.refine:
        offsets = np.stack(np.meshgrid(*[[-1.0, 0.0, 1.0]] * 4, indexing="ij"), -1).reshape(-1, 4)
        for step, label in ((0.5, "2^(1/2)"), (0.25, "2^(1/4)")):
            exps, scores = np.vstack(all_exps), np.vstack(all_scores)
            i = _bnb_best(scores)
            sc = _bnb(exps[i] + step * offsets, naive, inputs, P0, gate, T0, jobs,
                      float(scores[i, 0]))  # fmt: skip
            all_exps.append(exps[i] + step * offsets)
            all_scores.append(sc)
            stages.append({"stage": f"refine (step {label})", "settings": len(offsets),
                           "stopped_early": float(np.mean(sc[:, 4] == 0))})  # fmt: skip
    exps, scores = np.vstack(all_exps), np.vstack(all_scores)
    i = _bnb_best(scores)
    sig = naive * np.exp2(exps[i])
    seen = scores[i, 2] + scores[i, 3]
    return {
        "criterion": "pooled position RMSE over the scored evaluation times of the training"
        " drives, whole [m]",
        "sigma_v": float(sig[0]),
        "sigma_w_rad": float(sig[1]),
        "sigma_range": float(sig[2]),
        "sigma_bearing_rad": float(sig[3]),
        "log2_multipliers": {a: float(e) for a, e in zip(AXES, exps[i], strict=True)},
        "train_rmse_pos": float(math.sqrt(scores[i, 0] / count)) if count else math.nan,
        "train_max_pos_err": float(scores[i, 1]),
        "train_gate_rejected": float(scores[i, 3] / seen) if seen else math.nan,
        "settings": int(len(exps)),
        "search": "branch and bound (engines.tuning): a setting stops once its sum of squared"
        " errors passes the best complete one; the winner is the full grid's",
        "stages": stages,
        "seconds": round(time.perf_counter() - started, 3),
    }


def drive_rmse(scenario: RecordedScenario, inputs: SegmentInputs, tuned: dict) -> float:
    """The position RMSE of the plain EKF with `tuned` noise on one drive (engines.tuning)."""
    sig = [tuned[k] for k in ("sigma_v", "sigma_w_rad", "sigma_range", "sigma_bearing_rad")]
    sq, *_ = score_setting(
        inputs.timeline, inputs.segment.pose, recorded_p0(scenario), sig,
        gate_threshold(scenario.gate_probability), scenario.odometry_period_s,
        inputs.truth, inputs.scored,
    )  # fmt: skip
    n = int(inputs.scored.sum())
    return float(math.sqrt(sq / n)) if n else math.nan


def tune_drives(scenario: RecordedScenario, inputs: dict[str, SegmentInputs], world: DriveSet,
                jobs: int = 1) -> tuple[dict[str, dict], dict]:  # fmt: skip
    """ekf-tuned's noise for every drive (tuned on the drives of `scenario.tuning_sources` of
    its dataset, never its own), and the manifest's account: each tuning, and per drive the
    RMSE of the cross-dataset values against values tuned on its own dataset's drives (which
    include the drive itself: in-sample, the most tuning can give on that map)."""
    by_dataset: dict[int, list[str]] = {}
    for d in world.drives:
        by_dataset.setdefault(d.dataset, []).append(d.id)
    keys = {tuple(scenario.tuning_sources(ds)) for ds in by_dataset}
    keys |= {(ds,) for ds in by_dataset}
    tunings: dict[tuple, dict] = {}
    for key in sorted(keys, key=lambda k: (len(k), k)):  # single datasets first: they seed
        drives = [d for ds in key for d in by_dataset[ds]]
        seeds = [list(tunings[(ds,)]["log2_multipliers"].values()) for ds in key
                 if (ds,) in tunings]  # fmt: skip
        tunings[key] = tune_on_drives(scenario, [inputs[d] for d in drives], jobs, seeds)
        tunings[key]["train_drives"] = drives
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


# --------------------------------------------------------------------------------------------
# 1c. ekf-ml: each run's noise fitted on that run's own innovations, never its ground truth

NOISE_KEYS = ("sigma_v", "sigma_w_rad", "sigma_range", "sigma_bearing_rad")


@dataclass(frozen=True, eq=False)
class OwnInnovations:
    """What `EKFMLSpec.fit` gets on recorded data (in place of the simulated training runs): one
    run's landmark innovations under the unicycle EKF (`engines.tuning.TimelineLikelihood`, which
    holds no ground truth) and the naive sigmas its Nelder-Mead starts multiply."""

    problem: TimelineLikelihood
    naive: np.ndarray

    def fit_noise(self, criterion: str, starts: list[float], max_evaluations: int) -> dict:
        if criterion != "likelihood":  # only the likelihood needs no truth
            raise ValueError(f"a recorded run's own data fits the likelihood, not {criterion!r}")
        found = fit_noise(self.problem, criterion, self.naive, starts, max_evaluations)
        sigmas = found.pop("sigmas")
        found["at_fit"] = found.pop("training")
        return {**dict(zip(NOISE_KEYS, sigmas, strict=True)), **found}


def own_fit_problem(fitted: dict) -> str | None:
    """Why a cached fit of one run's own innovations (what `OwnInnovations.fit_noise` returns)
    cannot be used: its four sigmas, each a number whose square is finite and positive."""
    return sigmas_problem(fitted, NOISE_KEYS, "")


def own_innovations(scenario: RecordedScenario, inputs: SegmentInputs) -> OwnInnovations:
    """The objective of `ekf-ml` on one run: its timeline from its cold start (the start pose,
    as every filter's), with the scenario's P0, gate and T0; `inputs.truth` is not passed on."""
    problem = TimelineLikelihood.of(
        inputs.timeline, inputs.segment.pose, recorded_p0(scenario),
        gate_threshold(scenario.gate_probability), scenario.odometry_period_s,
    )  # fmt: skip
    return OwnInnovations(problem, scenario.naive.sigmas())


def own_fit_fingerprint(spec, own: OwnInnovations) -> str:
    """Hash of what one run's fit depends on: the filter's parameters, the run's timeline and
    start, P0, the gate, T0, the naive sigmas and the code (not the ground truth)."""
    pr = own.problem
    h = hashlib.sha256()
    doc = {
        "filter": spec.model_dump(mode="json", exclude={"name"}),
        "P0": pr.P0.tolist(), "gate": pr.gate, "T0": pr.T0, "naive": own.naive.tolist(),
        "x0": pr.x0.tolist(), "code": code_version(),
    }  # fmt: skip
    h.update(json.dumps(doc, sort_keys=True).encode())
    for a in (pr.dt, pr.u, pr.lm, pr.z, pr.xy):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def _fit_own(spec, own: OwnInnovations) -> dict:
    return spec.fit(own)


def fit_on_own_innovations(
    scenario: RecordedScenario, inputs: list[SegmentInputs], labels: list[str],
    cache_dir: Path | None, jobs: int = 1,
) -> tuple[dict[int, dict[str, dict]], dict]:  # fmt: skip
    """Every `ekf-ml` filter of the scenario fitted on each run's own innovations (`inputs`, in
    run order; `labels` name them: drive ids or segment numbers), the fits spread over `jobs`
    processes, each cached in `cache_dir` by its fingerprint (a resumed batch does not refit).
    Returns, per run index, the noise of each ekf-ml instance (instance name -> the sigma keys
    of `noise_sigmas`), and the manifest's account of every fit and its cost."""
    specs = [spec for spec in scenario.filters if isinstance(spec, EKFMLSpec)]
    if not specs:
        return {}, {}
    started = time.perf_counter()
    todo, found = [], {}
    for spec in specs:
        for inp in inputs:
            own = own_innovations(scenario, inp)
            fp = own_fit_fingerprint(spec, own)
            path = None if cache_dir is None else cache_dir / FIT_FILE.format(fingerprint=fp)
            cached = None if path is None else read_cached_fit(path, fp, own_fit_problem)
            found[spec.name, inp.segment.index] = (fp, cached is not None, cached)
            if cached is None:
                todo.append((spec, inp.segment.index, own, fp, path))
    if todo:
        with local_workers():
            fits = Parallel(n_jobs=max(1, min(jobs, len(todo))))(
                delayed(_fit_own)(spec, own) for spec, _, own, _, _ in todo
            )
        for (spec, run, _, fp, path), fitted in zip(todo, fits, strict=True):
            if path is not None:
                write_fit(path, fp, fitted)
            found[spec.name, run] = (fp, False, fitted)
    noise: dict[int, dict[str, dict]] = {}
    record = {}
    for spec in specs:
        runs = []
        for inp, label in zip(inputs, labels, strict=True):
            fp, cached, fitted = found[spec.name, inp.segment.index]
            noise.setdefault(inp.segment.index, {})[spec.name] = fitted
            runs.append({"run": inp.segment.index, "label": label, "fingerprint": fp,
                         "cached": cached, **fitted})  # fmt: skip
        record[spec.name] = {
            "kind": spec.kind,
            "criterion": "innovation negative log-likelihood of the run itself: sum over every"
            " associated landmark measurement (accepted by the gate or not) of log|S| +"
            " nu^T S^-1 nu, per measurement; the filter gates as it runs",
            "uses": "each run's own odometry and landmark measurements; never its ground truth"
            " (the start pose is the run's cold start, as for every filter)",
            "runs": runs,
        }
    seconds = round(time.perf_counter() - started, 3)
    return noise, {"filters": record, "seconds": seconds, "fitted_now": len(todo)}


# --------------------------------------------------------------------------------------------
# 2. The held-out segments


def noise_sigmas(noise: dict) -> tuple[float, float, float, float]:
    """(sv, sw, sr, sb) of a tuned or fitted noise record (`tune`, `fit_on_own_innovations`)."""
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
    (an error above LOST_LOCK_M at a scored time)."""
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
        rec = dict(rec)
        rec.update(
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
    learns = bool(trained_filters(scenario))
    training = [segment_inputs(rec, s) for s in rec.train_segments] if learns else []
    run_scenario, trained = fit_on_segments(scenario, rec, training, store, progress)
    action = ""
    for name in trained:
        how = "read from the cache" if trained[name]["train"]["cached"] else "trained"
        action += f"; {name} {how} on the training segments"
    tuned = None
    if scenario.reference() is not None:
        tuned = tune(scenario, rec, plan.jobs)
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
    tuned_for, tuning = {}, None
    if scenario.reference() is not None:
        tuned_for, tuning = tune_drives(scenario, inputs, world, plan.jobs)
        action += f"; ekf-tuned tuned per dataset on the others' drives ({tuning['seconds']:.1f} s)"
    n_steps = max(len(i.t) for i in inputs.values())
    fitted, fits = fit_on_own_innovations(
        scenario, [inputs[d.id] for d in world.drives], [d.id for d in world.drives], store,
        plan.jobs,
    )  # fmt: skip
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
    return Prepared(items, action + _fits_action(fits), manifest, n_steps)


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
