"""A problem scenario end to end (SPEC 17): training fits, the runs, the tables, the manifest.

Seeds: evaluation run i draws from SeedSequence(seed, spawn_key=(0, i)), training run i of the
fitted filters from SeedSequence(seed, spawn_key=(1, i)): the two never share a stream, and run
i's numbers do not depend on the number of runs or of workers. Every filter of a run sees the
same truth and measurements (paired comparisons).

The result folder OUT/<name>/ holds problem_summary.parquet, problem_runs.parquet,
problem_noise.parquet (the noise estimate per entry), problem_timing.parquet (seconds per
filter and run: the only table that changes between identical runs) and manifest.json, written
last, under the folder's lock. A folder holding anything but this tool's files is refused, and
a complete result is only replaced with `force`.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ..provenance import git_commit, package_version
from ..storage import (
    MANIFEST_FILE,
    PROBLEM_FORMAT,
    PROBLEM_TABLES,
    ResultsError,
    folder_lock,
    foreign_entries,
    read_json,
    read_parquet,
    scenario_name_problem,
    write_json,
    write_parquet,
)
from .base import NotCompilable
from .module import ModuleProblemError, file_digest
from .schema import ProblemScenario
from .scoring import score

TABLES = PROBLEM_TABLES  # the result's file names (storage: the loader reads them too)


class ProblemRunError(Exception):
    """A problem batch cannot run or write; `str()` is the one-line message."""


def run_rng(seed: int, i: int, *, training: bool = False) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(int(training), i)))


def fit_training(scenario: ProblemScenario, seed: int) -> tuple[dict, dict]:
    """{name: (Q, R)} of the filters fitted on training runs, and their manifest records."""
    fitted, records = {}, {}
    specs = [s for s in scenario.filters if s.fits_on_training()]
    if not specs:
        return fitted, records
    problem = scenario.build_problem()
    runs = [problem.simulate(run_rng(seed, i, training=True))
            for i in range(scenario.training.runs)]  # fmt: skip
    Q0, R0 = scenario.assumed_noise()
    for spec in specs:
        Q, R, record = spec.fit_training(problem, runs, Q0, R0)
        fitted[spec.name] = (Q, R)
        records[spec.name] = record
    return fitted, records


def run_one(scenario: ProblemScenario, seed: int, i: int, fitted: dict) -> tuple[np.ndarray, dict]:
    """(truth x, {filter name: Trace}) of evaluation run i. On the fast engine every filter
    runs its family's compiled loop (`problems.fast`); the truth and measurements are the same
    on both engines (the problem's simulator)."""
    problem = scenario.build_problem()
    model = problem.compiled_model() if scenario.engine == "fast" else None
    trajectory = problem.simulate(run_rng(seed, i))
    Q_a, R_a = scenario.assumed_noise()
    traces = {}
    for spec in scenario.filters:
        Q, R = (problem.Q, problem.R) if spec.uses_true_noise else (Q_a, R_a)
        Q, R = fitted.get(spec.name, (Q, R))
        flt = spec.build(problem, Q, R)
        flt.model = model
        traces[spec.name] = flt.run(trajectory.z)
    return trajectory.x, traces


def prepare_engine(scenario: ProblemScenario) -> dict:
    """The fast engine's loops and the problem's functions compiled (or loaded from numba's
    cache) once, before the runs, and what that cost: {} on filterpy; ProblemRunError when the
    problem's functions do not compile."""
    if scenario.engine != "fast":
        return {}
    started = time.perf_counter()
    try:
        model = scenario.build_problem().compiled_model()
    except (NotCompilable, ImportError) as exc:  # ImportError: numba missing (fast.py says so)
        raise ProblemRunError(f"engine fast: {exc}") from None
    return {"prepare_seconds": round(time.perf_counter() - started, 3),
            "model_compile_seconds": round(model.compile_seconds, 3)}  # fmt: skip


def run_batch(scenario: ProblemScenario, runs: int, seed: int, jobs: int, fitted: dict):
    """Every run, in order (joblib's processes when jobs > 1: the same numbers)."""
    if jobs > 1 and runs > 1:
        from joblib import Parallel, delayed

        from ..workers import local_workers

        with local_workers():
            return Parallel(n_jobs=min(jobs, runs))(
                delayed(run_one)(scenario, seed, i, fitted) for i in range(runs)
            )
    return [run_one(scenario, seed, i, fitted) for i in range(runs)]


def module_digest(scenario: ProblemScenario) -> str | None:
    """The sha256 of a module problem's file (its results depend on its code), else None."""
    return None if scenario.module is None else file_digest(scenario.build_problem().path)


def fingerprint(scenario: ProblemScenario, runs: int, seed: int) -> str:
    """A hash of what the result depends on. The keys a linear scenario on filterpy leaves at
    their defaults (engine, module) are left out: its fingerprint is the one before they were."""
    dump = scenario.model_dump(mode="json", exclude={"jobs", "runs", "engine", "module"})
    doc = {"scenario": dump, "runs": runs, "seed": seed, "version": package_version()}
    if scenario.engine != "filterpy":
        doc["engine"] = scenario.engine
    if scenario.module is not None:  # a module's results depend on its code
        doc["module"] = {**scenario.module.model_dump(mode="json"),
                         "sha256": module_digest(scenario)}  # fmt: skip
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def is_problem_result(folder: Path) -> bool:
    try:
        doc = read_json(Path(folder) / MANIFEST_FILE)
    except (ResultsError, OSError):
        return False
    return isinstance(doc, dict) and doc.get("format") == PROBLEM_FORMAT


def check_target(out: Path, name: str, force: bool) -> Path:
    """OUT/<name>, or ProblemRunError: a bad name, a symlink, a foreign folder, a result that
    `force` does not allow replacing."""
    problem = scenario_name_problem(name)
    if problem:
        raise ProblemRunError(f"name {name!r}: {problem}")
    target = Path(out) / name
    if target.is_symlink() or (os.path.lexists(target) and not target.is_dir()):
        raise ProblemRunError(f"{target}: exists and is not a folder")
    if target.is_dir():
        foreign = foreign_entries(target)
        if foreign:
            raise ProblemRunError(
                f"{target}: holds files this tool did not write ({', '.join(foreign[:3])});"
                " use another --out"
            )
        if (target / MANIFEST_FILE).exists():
            if not is_problem_result(target):
                raise ProblemRunError(f"{target}: holds another kind of result; use another --out")
            if not force:
                raise ProblemRunError(
                    f"{target}: holds a complete result already; use --force to overwrite it"
                )
    return target


def execute_problem(scenario: ProblemScenario, out: Path, *, runs: int | None = None,
                    seed: int | None = None, jobs: int | None = None, force: bool = False,
                    engine: str | None = None) -> tuple[pd.DataFrame, Path]:  # fmt: skip
    """Run a problem scenario and write its result; (summary, folder). `engine` overrides the
    scenario's (filterpy or fast)."""
    started = time.time()
    if engine is not None:
        scenario = scenario.model_copy(update={"engine": engine})
    runs = scenario.runs if runs is None else runs
    seed = scenario.seed if seed is None else seed
    jobs = scenario.jobs if jobs is None else jobs
    target = check_target(out, scenario.name, force)
    with folder_lock(target):
        check_target(out, scenario.name, force)
        engine_record = prepare_engine(scenario)
        try:
            fitted, fit_records = fit_training(scenario, seed)
            run_started = time.perf_counter()
            results = run_batch(scenario, runs, seed, jobs, fitted)
            run_seconds = time.perf_counter() - run_started
        except ModuleProblemError as exc:  # the user's module failed during a run
            raise ProblemRunError(f"module {scenario.module.file}: {exc}") from None
        truth = np.stack([x for x, _ in results])
        names = [s.name for s in scenario.filters]
        traces = {name: [tr[name] for _, tr in results] for name in names}
        specs = {s.name: s for s in scenario.filters}
        oracles = [s.name for s in scenario.filters if s.role == "oracle"]
        problem = scenario.build_problem()
        tables = score(problem, truth, traces, specs, oracles[0] if oracles else None, seed)
        fp = fingerprint(scenario, runs, seed)
        if (target / MANIFEST_FILE).exists():
            (target / MANIFEST_FILE).unlink()  # the old result is incomplete from here on
        meta = {"scenario": scenario.name, "seed": str(seed), "fingerprint": fp}
        for key, file in TABLES.items():
            write_parquet(target / file, tables[key], metadata=meta)
        write_json(target / MANIFEST_FILE, {
            "format": PROBLEM_FORMAT,
            "scenario": scenario.model_dump(mode="json"),
            "problem": scenario.problem, "state_dimension": problem.n,
            "position_unit": problem.position_unit,
            "engine": scenario.engine, "engine_setup": engine_record,
            "module_sha256": module_digest(scenario),
            "runs": runs, "seed": seed, "jobs": jobs, "fingerprint": fp,
            "reference": oracles[0] if oracles else None,
            "training": fit_records,
            "version": package_version(), "git_commit": git_commit() or "unknown",
            "run_seconds": round(run_seconds, 3),
            "wall_time_s": round(time.time() - started, 3),
        })  # fmt: skip
    return tables["summary"], target


def read_problem_result(folder: Path) -> dict:
    """{'manifest': dict, 'summary': DataFrame, ...} of a complete problem result."""
    folder = Path(folder)
    manifest = read_json(folder / MANIFEST_FILE)
    if not isinstance(manifest, dict) or manifest.get("format") != PROBLEM_FORMAT:
        raise ResultsError(f"{folder}: not a problem result")
    out = {"manifest": manifest}
    for key, file in TABLES.items():
        out[key] = read_parquet(folder / file)
    return out


def problem_result_folders(folders: list[Path]) -> list[Path]:
    """The complete problem results among `folders` and their children."""
    found = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            continue
        candidates = [folder] + sorted(p for p in folder.iterdir() if p.is_dir())
        found += [p for p in candidates if is_problem_result(p)]
    return found
