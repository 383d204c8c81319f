"""`ekf-ml` on recorded data: each run's noise fitted on that run's own innovations, never its
ground truth (the recorded counterpart of the simulated training runs: a recorded run has no
training runs of its own that share its noise, but its odometry and landmark measurements are
evidence of it without the truth).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..engines.tuning import TimelineLikelihood, fit_noise
from ..filters.context import recorded_p0
from ..filters.ekf import gate_threshold
from ..filters.fitted import sigmas_problem
from ..outputs import code_version
from ..sources.recorded import NOISE_KEYS, RecordedScenario
from .fit import TrainingRuns, fit_specs


@dataclass(frozen=True, eq=False)
class OwnInnovations(TrainingRuns):
    """The "own" training runs (fitting.fit): what `EKFMLSpec.fit` gets on recorded data (in
    place of the simulated training runs): one run's landmark innovations under the unicycle EKF
    (`engines.tuning.TimelineLikelihood`, which holds no ground truth) and the naive sigmas its
    Nelder-Mead starts multiply. Independent of the other runs' fits, and spent in the compiled
    kernel: the fits of several runs share threads (`fits_in_threads`)."""

    source: ClassVar[str] = "own"
    fits_in_threads: ClassVar[bool] = True
    problem: TimelineLikelihood
    naive: np.ndarray

    def fit_noise(self, criterion: str, starts: list[float], max_evaluations: int) -> dict:
        if criterion != "likelihood":  # only the likelihood needs no truth
            raise ValueError(f"a recorded run's own data fits the likelihood, not {criterion!r}")
        found = fit_noise(self.problem, criterion, self.naive, starts, max_evaluations)
        sigmas = found.pop("sigmas")
        found["at_fit"] = found.pop("training")
        return {**dict(zip(NOISE_KEYS, sigmas, strict=True)), **found}

    def fingerprint(self, spec) -> str:
        """Hash of what one run's fit depends on: the filter's parameters, the run's timeline and
        start, P0, the gate, T0, the naive sigmas and the code (not the ground truth)."""
        pr = self.problem
        h = hashlib.sha256()
        doc = {
            "filter": spec.model_dump(mode="json", exclude={"name"}),
            "P0": pr.P0.tolist(), "gate": pr.gate, "T0": pr.T0, "naive": self.naive.tolist(),
            "x0": pr.x0.tolist(), "code": code_version(),
        }  # fmt: skip
        h.update(json.dumps(doc, sort_keys=True).encode())
        for a in (pr.dt, pr.u, pr.lm, pr.z, pr.xy):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]

    def fit_problem(self, spec):
        return own_fit_problem


def own_fit_problem(fitted: dict) -> str | None:
    """Why a cached fit of one run's own innovations (what `OwnInnovations.fit_noise` returns)
    cannot be used: its four sigmas, each a number whose square is finite and positive."""
    return sigmas_problem(fitted, NOISE_KEYS, "")


def own_innovations(scenario: RecordedScenario, inputs) -> OwnInnovations:
    """The objective of `ekf-ml` on one run: its timeline from its cold start (the start pose,
    as every filter's), with the scenario's P0, gate and T0; `inputs.truth` is not passed on."""
    problem = TimelineLikelihood.of(
        inputs.timeline, inputs.segment.pose, recorded_p0(scenario),
        gate_threshold(scenario.gate_probability), scenario.odometry_period_s,
    )  # fmt: skip
    return OwnInnovations(problem, scenario.naive.sigmas())


def fit_on_own_innovations(
    scenario: RecordedScenario, inputs: list, labels: list[str],
    cache_dir: Path | None, jobs: int = 1,
) -> tuple[dict[int, dict[str, dict]], dict]:  # fmt: skip
    """Every filter of the scenario that declares a fit on its "own" innovations (`ekf-ml`)
    fitted on each run's (`inputs`, in run order; `labels` name them: drive ids or segment
    numbers) through `fitting.fit.fit_specs`: the fits spread over `jobs` threads, each cached
    in `cache_dir` by its fingerprint (a resumed batch does not refit). Returns, per run index,
    the noise of each such instance (instance name -> the sigma keys of `noise_sigmas`), and the
    manifest's account of every fit and its cost."""
    specs = [spec for spec in scenario.filters if "own" in spec.fit_sources]
    if not specs:
        return {}, {}
    started = time.perf_counter()
    owns = [own_innovations(scenario, inp) for inp in inputs]
    requests = [(spec, own) for spec in specs for own in owns]
    found = iter(fit_specs(requests, cache_dir, jobs))
    noise: dict[int, dict[str, dict]] = {}
    record = {}
    for spec in specs:
        runs = []
        for inp, label in zip(inputs, labels, strict=True):
            fit = next(found)
            noise.setdefault(inp.segment.index, {})[spec.name] = fit.fitted
            runs.append({"run": inp.segment.index, "label": label, "fingerprint": fit.fingerprint,
                         "cached": fit.cached, **fit.fitted})  # fmt: skip
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
    fitted_now = sum(not r["cached"] for f in record.values() for r in f["runs"])
    return noise, {"filters": record, "seconds": seconds, "fitted_now": fitted_now}
