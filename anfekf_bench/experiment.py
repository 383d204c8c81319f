"""One scenario end to end: resolve, run the batch, save every finished run, write the results.

Each finished run is saved at once under <out>/<name>/.runs/ (atomically), so an interrupted batch
loses at most the runs in flight; the next `anfekf run` into the same folder resumes from them when
the scenario is unchanged. The result files are written last, manifest.json after everything else.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import joblib
import pandas as pd
from pydantic import ValidationError

from .analysis.comparisons import comparison_pairs, comparisons_frame, evaluate_claims
from .analysis.tables import runs_frame, steps_frame, summary_records, update_statistics
from .config import BackendConfig, Engine, Scenario, World
from .runner import engine_of, run_batch
from .sources.simulator import simulate_truth
from .storage import (
    CLAIMS_FILE,
    COMPARISONS_FILE,
    MANIFEST_FILE,
    RUNS_DIR,
    RUNS_FILE,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    write_atomic,
    write_json,
    write_parquet,
)

_PACKAGES = (
    "anfekf-bench",
    "numpy",
    "scipy",
    "filterpy",
    "pandas",
    "pyarrow",
    "joblib",
    "pydantic",
)


class OutputExists(Exception):
    """The output folder holds results we must not overwrite silently."""


class PlanError(ValueError):
    """Command-line overrides that do not fit together; `str()` is the one-line message."""


@dataclass(frozen=True)
class Plan:
    """A scenario with the command line's overrides applied."""

    scenario: Scenario
    world: World
    runs: int
    seed: int
    jobs: int
    backend: BackendConfig = BackendConfig()
    engine: Engine = "filterpy"

    @property
    def name(self) -> str:
        return self.scenario.name

    def fingerprint(self) -> str:
        """Hash of everything that determines a run's bytes (not jobs or backend: they change
        nothing, so a batch started locally may be resumed on a Dask cluster and back)."""
        doc = {
            "scenario": self.scenario.model_dump(mode="json", exclude={"jobs", "runs", "backend"}),
            "seed": self.seed,
            "engine": self.engine,
            "landmarks": self.world.landmarks.tolist(),
            "waypoints": self.world.waypoints.tolist(),
            "code": code_version(),
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def code_version() -> str:
    """Hash of this package's source: runs saved by other code must not be resumed into a batch."""
    digest = hashlib.sha256()
    package = Path(__file__).parent
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def machine_info() -> dict:
    """Cores this process may use, the CPU model (from /proc/cpuinfo) and the platform."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        model = platform.processor() or "unknown"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cores": cores, "cpu_model": model, "platform": platform.platform()}


def make_plan(
    scenario: Scenario,
    world: World,
    runs: int | None,
    seed: int | None,
    jobs: int | None,
    *,
    backend: str | None = None,
    scheduler: str | None = None,
    engine: str | None = None,
) -> Plan:
    """Apply the command line's overrides (None: keep the scenario file's value)."""
    return Plan(
        scenario=scenario,
        world=world,
        runs=scenario.runs if runs is None else runs,
        seed=scenario.seed if seed is None else seed,
        jobs=scenario.jobs if jobs is None else jobs,
        backend=resolve_backend(scenario.backend, backend, scheduler),
        engine=scenario.engine if engine is None else engine,
    )


def resolve_backend(base: BackendConfig, kind: str | None, scheduler: str | None) -> BackendConfig:
    """The scenario file's backend with `--backend` / `--scheduler` applied; PlanError if unfit."""
    kind = base.kind if kind is None else kind
    if kind == "local":
        if scheduler is not None:
            raise PlanError(f"--scheduler {scheduler}: only used with --backend dask")
        return BackendConfig(kind="local", connect_timeout_s=base.connect_timeout_s)
    address = base.scheduler if scheduler is None else scheduler
    if address is None:
        raise PlanError(
            "--backend dask needs --scheduler tcp://HOST:PORT"
            " (or backend.scheduler in the scenario file)"
        )
    try:
        return BackendConfig(
            kind="dask", scheduler=address, connect_timeout_s=base.connect_timeout_s
        )
    except ValidationError:
        raise PlanError(
            f"--scheduler {address}: expected a Dask scheduler address like tcp://HOST:PORT"
        ) from None


def package_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for pkg in _PACKAGES:
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def prepare_output(plan: Plan, out_dir: Path, force: bool) -> tuple[Path, dict[int, dict], str]:
    """Create <out>/<name>; return it, the saved runs to resume and a sentence saying what we do."""
    target = Path(out_dir) / plan.name
    if target.exists() and not target.is_dir():
        raise OutputExists(f"{target}: exists and is not a folder")
    runs_dir = target / RUNS_DIR
    if force and target.exists():
        shutil.rmtree(target)
        action = "overwriting the previous results (--force)"
    elif (target / MANIFEST_FILE).exists():
        raise OutputExists(
            f"{target}: holds a complete result already; use --force to overwrite it"
            " or --out to write elsewhere"
        )
    else:
        action = "new results"
    done: dict[int, dict] = {}
    stamp = runs_dir / "fingerprint"
    if runs_dir.is_dir() and stamp.is_file():
        if stamp.read_text().strip() != plan.fingerprint():
            raise OutputExists(
                f"{target}: holds runs of a different scenario or seed; use --force to discard them"
            )
        for path in sorted(runs_dir.glob("run-*.joblib")):
            try:
                result = joblib.load(path)
            except Exception:  # a torn file from a crash: redo that run
                path.unlink(missing_ok=True)
                continue
            if result["run"] < plan.runs:
                done[result["run"]] = result
        action = f"resuming: {len(done)} of {plan.runs} runs already done in {runs_dir}"
    runs_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(stamp, lambda tmp: tmp.write_text(plan.fingerprint() + "\n"))
    for stale in (
        STEPS_FILE,
        RUNS_FILE,
        SUMMARY_PARQUET,
        SUMMARY_JSON,
        COMPARISONS_FILE,
        CLAIMS_FILE,
    ):
        (target / stale).unlink(missing_ok=True)
    # Temporary files of writes a kill cut short (storage.write_atomic names them .<name>.*.tmp).
    for torn in [*target.glob(".*.tmp"), *runs_dir.glob(".*.tmp")]:
        torn.unlink(missing_ok=True)
    return target, done, action


def save_run(target: Path, result: dict) -> None:
    path = target / RUNS_DIR / f"run-{result['run']:06d}.joblib"
    write_atomic(path, lambda tmp: joblib.dump(result, tmp))


def execute(
    plan: Plan,
    out_dir: Path,
    *,
    force: bool = False,
    on_start: Callable[[str, int, int], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
) -> tuple[list[dict], Path]:
    """Run the plan and write its results; returns (summary records, scenario folder)."""
    started = time.time()
    # A route the controller cannot finish fails here, before --force deletes anything.
    simulate_truth(plan.world)
    target, done, action = prepare_output(plan, out_dir, force)

    def keep(result: dict) -> None:
        save_run(target, result)
        if on_result is not None:
            on_result(result)

    results = dict(done)
    # Reaches a Dask cluster now, so an unreachable one fails before any progress is shown.
    batch = run_batch(
        plan.scenario,
        plan.world,
        runs=plan.runs,
        seed=plan.seed,
        jobs=plan.jobs,
        on_result=keep,
        skip=set(done),
        backend=plan.backend.kind,
        scheduler=plan.backend.scheduler,
        connect_timeout_s=plan.backend.connect_timeout_s,
        engine=plan.engine,
    )
    if on_start is not None:
        on_start(action, len(done), plan.runs)
    for result in batch:
        results[result["run"]] = result
    ordered = [results[i] for i in range(plan.runs)]
    tables = result_tables(plan, ordered)
    records = tables.summary
    write_result_tables(target, tables, steps_table=plan.scenario.steps_table)
    manifest = {
        "scenario": plan.scenario.model_dump(mode="json"),
        "runs": plan.runs,
        "seed": plan.seed,
        "jobs": plan.jobs,
        "backend": plan.backend.model_dump(mode="json"),
        "engine": plan.engine,
        "engines": {f.name: engine_of(plan.engine, f) for f in plan.scenario.filters},
        "fingerprint": plan.fingerprint(),
        "world": {
            "landmarks": plan.world.landmarks.tolist(),
            "waypoints": plan.world.waypoints.tolist(),
            "control_steps": ordered[0]["control_steps"],
        },
        "resumed_runs": sorted(done),
        "versions": package_versions(),
        "machine": machine_info(),
        "wall_time_s": round(time.time() - started, 3),
    }
    write_json(target / MANIFEST_FILE, manifest)
    shutil.rmtree(target / RUNS_DIR, ignore_errors=True)
    return records, target


@dataclass(frozen=True)
class ResultTables:
    """What a finished batch writes (besides the manifest), all computed from its runs."""

    steps: pd.DataFrame
    runs: pd.DataFrame
    summary: list[dict]
    comparisons: pd.DataFrame
    claims: list[dict]


def result_tables(plan: Plan, ordered: list[dict]) -> ResultTables:
    """The steps, per-run, summary, comparison and claim tables of a batch (runs in order).

    Bootstrap intervals draw from the scenario's root seed, so they are as reproducible as the
    runs themselves.
    """
    names = [f.name for f in plan.scenario.filters]
    steps = steps_frame(plan.name, names, ordered)
    pairs = comparison_pairs(
        ((f.name, f.kind) for f in plan.scenario.filters), plan.scenario.compare
    )
    return ResultTables(
        steps=steps,
        runs=runs_frame(plan.name, names, ordered),
        summary=summary_records(steps, update_statistics(ordered, names)),
        comparisons=comparisons_frame(steps, pairs, seed=plan.seed),
        claims=evaluate_claims(steps, plan.scenario.claims, seed=plan.seed),
    )


def write_result_tables(target: Path, tables: ResultTables, *, steps_table: bool) -> None:
    """Write every table atomically; steps.parquet only when the scenario asks for it."""
    if steps_table:
        write_parquet(target / STEPS_FILE, tables.steps)
    write_parquet(target / RUNS_FILE, tables.runs)
    write_parquet(target / SUMMARY_PARQUET, pd.DataFrame(tables.summary))
    write_json(target / SUMMARY_JSON, tables.summary)
    write_parquet(target / COMPARISONS_FILE, tables.comparisons)
    write_json(target / CLAIMS_FILE, tables.claims)
