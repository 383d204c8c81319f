"""Filters trained on recorded data (`kalmannet`, filters.kalmannet): on the training drives of
the cross-drive protocol (`fit_on_drives`), or on the training segments of one log (protocol
segments, `fit_on_segments`: one fit, on the segments that tune `ekf-tuned`).

The recorded counterpart of anfekf_bench.training: a drive is scored by weights trained on the
drives of the datasets that tune its `ekf-tuned` (`RecordedScenario.tuning_sources`: tune on Dataset
6, test on 7, and the reverse; Dataset 9 on both), never on its own dataset's drives. Per fold
(one set of training drives) and fitted filter:

1. **Fit** on the training drives' timelines and their ground truth at the evaluation times,
   NaN where not scored (`KalmanNetSpec.fit_recorded`): nothing of a test drive is read.
2. **Cache** what the fit returns as `<out>/<name>/.runs/fit-<fingerprint>.json` (the format of
   anfekf_bench.training), keyed by `fold_fingerprint`: the filter's parameters, the training
   drives and their logs' content, what shapes their timelines and truth, the code version. A
   resumed batch reads it (no retraining).
3. **Hand out** to each drive a copy of the scenario whose fitted filter carries its fold's
   weights (`with_fit`); the manifest's `training` key records, per filter and fold, the
   training drives, the fingerprint, whether it came from the cache, and the fit's record
   (weights' SHA-256, training time, losses).
"""

from __future__ import annotations

import hashlib
import json
from functools import partial
from pathlib import Path
from typing import Any

from .outputs import FIT_FILE, PlanError, code_version, read_cached_fit, write_fit
from .sources.recorded import DriveSet, RecordedScenario, log_digest

# The scenario fields a drive's timeline and scored truth depend on (real_experiment.segment_inputs)
_INPUT_FIELDS = {"eval_period_s", "odometry_period_s", "max_gap_s", "misfit_detection"}


def trained_filters(scenario: RecordedScenario) -> list:
    """The filters trained on training drives or segments (kalmannet); ekf-ml is fitted on each
    run's own innovations instead (real_experiment.fit_on_own_innovations)."""
    return [f for f in scenario.filters if f.role == "trained"]


def fold_fingerprint(scenario: RecordedScenario, spec, drives: list) -> str:
    """Hash of what a fold's fit depends on (see the module doc); not the test drives."""
    doc = {
        "filter": spec.model_dump(mode="json", exclude={"name"}),
        "scenario": scenario.model_dump(mode="json", include=_INPUT_FIELDS),
        "drives": [[d.id, log_digest(d.log)] for d in drives],
        "code": code_version(),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def _fit_or_read(spec, fingerprint: str, cache_dir: Path | None, fit) -> tuple[dict, bool]:
    """`fit()` (what `spec.fit_recorded` returns), or the cached fit of `fingerprint`; written
    to the cache when fitted. Returns (fitted, cached)."""
    path = None if cache_dir is None else cache_dir / FIT_FILE.format(fingerprint=fingerprint)
    fitted = None if path is None else read_cached_fit(path, fingerprint, spec.fit_problem)
    if fitted is not None:
        return fitted, True
    try:
        fitted = fit()
    except ValueError as exc:
        raise PlanError(f"filters: {spec.name}: {exc}") from None
    if path is not None:
        write_fit(path, fingerprint, fitted)
    return fitted, False


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
    from .models import Unicycle

    todo = trained_filters(scenario)
    if not todo:
        return {d.id: scenario for d in world.drives}, {}
    model = Unicycle(scenario.odometry_period_s)
    folds = {tuple(scenario.tuning_sources(d.dataset)) for d in world.drives}
    fitted_for: dict[tuple, dict[str, Any]] = {}
    records: dict[str, dict] = {spec.name: {} for spec in todo}
    for sources in sorted(folds, key=lambda k: (len(k), k)):
        train = [d for d in world.drives if d.dataset in sources]
        if not train:
            raise PlanError(
                f"filters: {todo[0].name}: no training drive for the drives tuned on dataset(s)"
                f" {', '.join(map(str, sources))}"
            )
        label = "+".join(map(str, sources))
        fitted_for[sources] = {}
        for spec in todo:
            fingerprint = fold_fingerprint(scenario, spec, train)
            drives = [(inputs[d.id].timeline, inputs[d.id].truth) for d in train]
            fitted, cached = _fit_or_read(
                spec, fingerprint, cache_dir,
                partial(spec.fit_recorded, drives, model, progress,
                        f"training {spec.name} on dataset(s) {label}"),
            )  # fmt: skip
            fitted_for[sources][spec.name] = spec.with_fit(fitted)
            records[spec.name][label] = {
                "kind": spec.kind,
                "fingerprint": fingerprint,
                "cached": cached,
                "train_drives": [d.id for d in train],
                "fitted": spec.fit_record(fitted),
            }
    out = {}
    for d in world.drives:
        specs = fitted_for[tuple(scenario.tuning_sources(d.dataset))]
        filters = [specs.get(f.name, f) for f in scenario.filters]
        out[d.id] = scenario.model_copy(update={"filters": filters})
    return out, records


# The scenario fields that decide a log's training segments (sources.recorded.cut_segments)
_SEGMENT_FIELDS = _INPUT_FIELDS | {"split_fraction", "split_at_s", "segment_s", "min_scorable_s"}


def fit_on_segments(
    scenario: RecordedScenario, rec, segments: list, cache_dir: Path | None, progress: Any = None
) -> tuple[RecordedScenario, dict]:
    """Protocol segments: every trained filter fitted once on the log's training segments
    (`segments`: their real_experiment.SegmentInputs, each cold-started from ground truth, as
    `ekf-tuned`'s tuning sees them; never a held-out one), or read from the cache. Returns the
    scenario carrying the fits and the manifest's account (per filter, one fold keyed "train")."""
    from .models import Unicycle

    todo = trained_filters(scenario)
    if not todo:
        return scenario, {}
    model = Unicycle(scenario.odometry_period_s)
    specs, records = {}, {}
    for spec in todo:
        doc = {
            "filter": spec.model_dump(mode="json", exclude={"name"}),
            "scenario": scenario.model_dump(mode="json", include=_SEGMENT_FIELDS),
            "log": rec.digest,
            "code": code_version(),
        }
        fingerprint = hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]
        fitted, cached = _fit_or_read(
            spec, fingerprint, cache_dir,
            partial(spec.fit_recorded, [(s.timeline, s.truth) for s in segments], model,
                    progress, f"training {spec.name} on {len(segments)} training segments"),
        )  # fmt: skip
        specs[spec.name] = spec.with_fit(fitted)
        records[spec.name] = {
            "train": {
                "kind": spec.kind,
                "fingerprint": fingerprint,
                "cached": cached,
                "train_segments": [s.index for s in rec.train_segments],
                "fitted": spec.fit_record(fitted),
            }
        }
    filters = [specs.get(f.name, f) for f in scenario.filters]
    return scenario.model_copy(update={"filters": filters}), records
