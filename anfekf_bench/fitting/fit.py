"""The one entry point of every fit before the batch (`fit_specs`), and what a source's training
runs offer it (`TrainingRuns`).

A filter spec declares its fit on its class (filters/): `fit_sources`, the training runs it can
be fitted on (FIT_SOURCES), and `fit(training)`, which returns a JSON-able dict. A source
supplies its training runs as `TrainingRuns`, one object per set of runs a fit reads (a fold):

- "simulated" (`fitting.simulated.TrainingSet`): training runs of the scenario's world, from
  seeds of a branch that no evaluation run draws from; one set for every fitted filter;
- "recorded" (`fitting.recorded.RecordedTraining`): a recorded log's training segments (one set),
  or, per cross-drive fold, the drives of the other datasets (never a drive of the fold's own);
- "own" (`fitting.own.OwnInnovations`): one recorded run's own landmark innovations (one set
  per run), never its ground truth.

`fit_specs` then does the same for every (spec, training runs) pair: refuse a source the spec
does not declare, read the fit from the run store's cache by the training runs' fingerprint of
the spec (when given a cache folder), fit what is not cached (`spec.fit(training)`; on threads
where the training runs say their fits are independent, `fits_in_threads`), write it
to the cache, and return each fit with its fingerprint and whether it came from the cache. How
the fitted values reach the runs stays with the source (`with_fit` copies of the specs, or a
noise record per run).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from joblib import Parallel, delayed

from ..filters.spec import FIT_SOURCES
from ..outputs import FIT_FILE, PlanError, read_cached_fit, write_fit


class TrainingRuns:
    """What a source hands `fit_specs`: one set of training runs (see the module doc). A
    subclass sets `source` and gives its fingerprint of a spec's fit and the manifest's
    description of the runs; it adds the services its specs' `fit` asks for (`fit_noise`,
    `grid_search`, the runs themselves)."""

    source: ClassVar[str]  # one of FIT_SOURCES
    # True: each fit reads only this set and spends its time in compiled kernels that release
    # the GIL: fits of several sets may run at once on threads (a recorded run's own innovations)
    fits_in_threads: ClassVar[bool] = False

    def fingerprint(self, spec) -> str:
        """Hash of everything `spec`'s fit on these runs depends on (its cache key)."""
        raise NotImplementedError

    def describe(self) -> dict:
        """The manifest's account of these runs (how many, which seeds, drives or segments)."""
        return {}

    def fit_problem(self, spec):
        """The check a cached fit must pass before `with_fit` gets it (`spec.fit_problem`)."""
        return spec.fit_problem

    def prepare(self, specs: list) -> None:
        """Called with the specs about to be fitted on these runs, before the first fit (work
        several fits share, computed together: the simulated noise fits' starts)."""


@dataclass(frozen=True)
class FitResult:
    """One spec's fit on one set of training runs."""

    fitted: dict
    fingerprint: str  # the training runs' hash of what the fit depends on (its cache key)
    cached: bool  # read from the run store's cache (not computed by this call)

    def record(self, spec, training: TrainingRuns) -> dict:
        """The manifest's record of the fit: {kind, fingerprint, cached, <the runs>, fitted}."""
        return {
            "kind": spec.kind,
            "fingerprint": self.fingerprint,
            "cached": self.cached,
            **training.describe(),
            "fitted": spec.fit_record(self.fitted),
        }


class FitNotDeclared(ValueError):
    """A spec asked to fit on training runs of a source it does not declare (a bug)."""


def _fit(spec, training: TrainingRuns) -> dict:
    try:
        return spec.fit(training)
    except ValueError as exc:  # training runs that cannot fit this filter: the user's data
        raise PlanError(f"filters: {spec.name}: {exc}") from None


def fit_specs(
    requests: list[tuple[Any, TrainingRuns]], cache_dir: Path | None, jobs: int = 1
) -> list[FitResult]:
    """Fit each (spec, training runs) pair of `requests`, or read its fit from `cache_dir` (None:
    no cache), in order (see the module doc). `jobs`: the threads the fits of
    `fits_in_threads` training runs may use. FitNotDeclared when a spec does not declare the
    source of its training runs; PlanError (one line) when the runs cannot fit it."""
    found: list[FitResult | None] = []
    todo: list[tuple[int, str, Path | None]] = []  # (request, fingerprint, cache file)
    for i, (spec, training) in enumerate(requests):
        if training.source not in FIT_SOURCES or training.source not in spec.fit_sources:
            declared = ", ".join(sorted(spec.fit_sources)) or "none"
            raise FitNotDeclared(
                f"filter {spec.name!r} ({spec.kind}) declares no fit on {training.source!r}"
                f" training runs (it declares: {declared})"
            )
        fingerprint, path, cached = training.fingerprint(spec), None, None
        if cache_dir is not None:
            path = cache_dir / FIT_FILE.format(fingerprint=fingerprint)
            cached = read_cached_fit(path, fingerprint, training.fit_problem(spec))
        found.append(None if cached is None else FitResult(cached, fingerprint, True))
        if cached is None:
            todo.append((i, fingerprint, path))
    computed: dict[int, dict] = {}
    in_threads = [i for i, _, _ in todo if requests[i][1].fits_in_threads]
    if len(in_threads) > 1 and jobs > 1:
        fits = Parallel(n_jobs=min(jobs, len(in_threads)), backend="threading")(
            delayed(_fit)(*requests[i]) for i in in_threads
        )
        computed.update(zip(in_threads, fits, strict=True))
    prepared: set[int] = set()
    for i, fingerprint, path in todo:
        spec, training = requests[i]
        if i not in computed:
            if id(training) not in prepared:  # once per set, with every spec it is to fit
                prepared.add(id(training))
                training.prepare([requests[j][0] for j, _, _ in todo if requests[j][1] is training])
            computed[i] = _fit(spec, training)
        if path is not None:
            write_fit(path, fingerprint, computed[i])
        found[i] = FitResult(computed[i], fingerprint, False)
    return found  # type: ignore[return-value]
