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

import numpy as np
from joblib import Parallel, delayed

from ..engines.tuning import TimelineLikelihood, fit_noise
from ..filters.context import recorded_p0
from ..filters.ekf import gate_threshold
from ..filters.fitted import EKFMLSpec, sigmas_problem
from ..outputs import FIT_FILE, code_version, read_cached_fit, write_fit
from ..sources.recorded import RecordedScenario
from ..workers import local_workers

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


def own_innovations(scenario: RecordedScenario, inputs) -> OwnInnovations:
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
    scenario: RecordedScenario, inputs: list, labels: list[str],
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
