"""One scenario end to end: resolve, run the batch, save every finished run, write the results.

Each finished run is saved at once under <out>/<name>/.runs/ (atomically), so an interrupted batch
loses at most the runs in flight; the next `anfekf run` into the same folder resumes from them when
the scenario is unchanged. The result files are written last, manifest.json after everything else.

Validate everything first, then touch disk: `check_plan` (values, route, memory) and
`survey_output` (what <out>/<name> holds, read only) run, and a Dask cluster is reached with its
workers, before anything is created or removed; the folder is then locked (storage.folder_lock)
for the whole batch, so two commands cannot mix their runs in it. `--force` removes only this
tool's files from a folder of anfekf results (never a foreign folder, never through a symlink),
and only once the batch can start.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pydantic import ValidationError

from .analysis.comparisons import comparison_pairs, comparisons_frame, evaluate_claims
from .analysis.phases import phases_frame, summary_tracking
from .analysis.tables import (
    runs_frame,
    steps_frame,
    summary_records,
    update_statistics,
)
from .config import BackendConfig, Engine, Scenario, World
from .filters.custom import CustomFilterFailed, CustomSpec
from .filters.registry import build_filter
from .outputs import (
    OutputExists,
    PlanError,
    ResultTables,
    code_version,
    finish_result,
    machine_info,
    package_versions,
    prepare_output,
    result_staging,
    save_run,
    scenario_folder,
    survey_output,
    write_result_tables,
)
from .runner import connect_dask, engine_of, fast_compiled, run_batch
from .sources.simulator import RouteNotCompleted, simulate_truth
from .storage import (
    MANIFEST_FILE,
    RESULT_FORMAT,
    RUNS_DIR,
    FolderBusy,
    folder_lock,
    scenario_name_problem,
    write_json,
)
from .training import fit_filters

__all__ = ["FolderBusy", "OutputExists", "PlanError", "RUNS_DIR", "execute", "make_plan"]


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

    def filter_names(self) -> list[str]:
        """The filters of every run (a real-data plan has one per filter and naive start)."""
        return [f.name for f in self.scenario.filters]

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

    def training_fingerprint(self, spec) -> str:
        """Hash of everything a fitted filter's fit depends on (anfekf_bench.training): its own
        parameters, the scenario's world, noise, start, gate, recording and training settings,
        the seed and the code; not the evaluation runs, the other filters or the engine."""
        fields = {"world", "true_noise", "filter_noise", "p0", "gate_probability", "training",
                  "record_every"}  # fmt: skip
        doc = {
            "filter": spec.model_dump(mode="json", exclude={"name"}),
            "scenario": self.scenario.model_dump(mode="json", include=fields),
            "seed": self.seed,
            "landmarks": self.world.landmarks.tolist(),
            "waypoints": self.world.waypoints.tolist(),
            "code": code_version(),
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


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
    if not isinstance(scenario, Scenario):  # a recorded log (SPEC 9): real_experiment
        from .real_experiment import make_real_plan

        return make_real_plan(
            scenario, world, runs, seed, jobs, backend=backend, scheduler=scheduler, engine=engine
        )
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


FLOATS_PER_TRACE_STEP = 24
STEPS_TABLE_BYTES_PER_ROW = 2 * 8 * 28
WORKER_BASE_BYTES = 250 * 2**20
MEMORY_SHARE = 0.8  # refuse a batch estimated to need more of the machine's memory than this


def machine_memory() -> int | None:
    """Bytes of memory this process may use: physical memory, or a cgroup limit if lower."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None
    for limit_file in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(limit_file).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


def _bytes(n: float) -> str:
    for unit in ("bytes", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.0f} bytes"  # pragma: no cover


def memory_estimate(plan: Plan, control_steps: int) -> int:
    """Bytes a batch needs at its peak: every run's traces and the steps table in this process,
    plus each local worker's simulation of one run (its noise for every landmark at every scan)."""
    recorded = control_steps // plan.scenario.record_every
    filters = len(plan.scenario.filters)
    per_run = recorded * (filters * FLOATS_PER_TRACE_STEP + 5) * 8
    parent = plan.runs * (per_run + recorded * filters * STEPS_TABLE_BYTES_PER_ROW)
    scans = control_steps // plan.world.sensor_every
    per_worker = (
        WORKER_BASE_BYTES
        + 3 * scans * len(plan.world.landmarks) * 2 * 8
        + 10 * control_steps * 8
        + per_run
    )
    workers = min(plan.jobs, plan.runs) if plan.backend.kind == "local" else 0
    return parent + workers * per_worker


def check_plan(plan: Plan) -> int:
    """Everything about a plan that can fail before its batch, checked without touching disk:
    the route (completed, long enough to record) and the memory the batch needs. Returns the
    route's control steps; PlanError (a one-line message naming the field) otherwise."""
    if not isinstance(plan, Plan):  # a recorded log (SPEC 9)
        from .real_experiment import check_real_plan

        return check_real_plan(plan)
    problem = scenario_name_problem(plan.name)
    if problem:
        raise PlanError(f"name: {problem}")
    for f in plan.scenario.filters:  # a fitted filter that the training runs cannot train
        message = f.fitted_on_training and f.training_problem(plan.scenario.training.runs)
        if message:
            raise PlanError(f"filters.{f.name}.{message}")
    try:
        control_steps = len(simulate_truth(plan.world).u)
    except RouteNotCompleted as exc:
        raise PlanError(f"world.max_steps: {exc}") from None
    except (OverflowError, ValueError, FloatingPointError, MemoryError) as exc:
        raise PlanError(f"world: the route cannot be driven ({type(exc).__name__})") from None
    if control_steps == 0:
        raise PlanError(
            "world.waypoints: the route has no control steps (the start is already within"
            " waypoint_tolerance of every waypoint)"
        )
    every = plan.scenario.record_every
    if every > control_steps:
        raise PlanError(
            f"record_every: {every} is longer than the route ({control_steps} control steps);"
            f" use at most {control_steps}"
        )
    for i, spec in enumerate(plan.scenario.filters):
        if isinstance(spec, CustomSpec):  # a user's __init__ that fails does so before any work
            try:
                build_filter(spec, plan.scenario, plan.world)
            except CustomFilterFailed as exc:
                raise PlanError(f"filters.{i}: {exc}") from None
    need, have = memory_estimate(plan, control_steps), machine_memory()
    if have is not None and need > MEMORY_SHARE * have:
        recorded = control_steps // every
        raise PlanError(
            f"runs: {plan.runs} runs of {recorded} recorded steps x"
            f" {len(plan.scenario.filters)} filters (jobs {plan.jobs}) need about {_bytes(need)}"
            f" of memory, more than {MEMORY_SHARE:.0%} of this machine's {_bytes(have)}; use"
            " fewer runs, a larger record_every, fewer jobs or a smaller map"
        )
    return control_steps


# --------------------------------------------------------------------------------------------
# The scenario folder: confined, surveyed read-only, then (locked) prepared


def execute(
    plan: Plan,
    out_dir: Path,
    *,
    force: bool = False,
    on_start: Callable[[str, int, int], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
    progress=None,
) -> tuple[list[dict], Path]:
    """Run the plan and write its results; returns (summary records, scenario folder).
    `progress`: the CLI's rich Progress, to which a long fit (kalmannet) adds its bar."""
    if not isinstance(plan, Plan):  # a recorded log (SPEC 9)
        from .real_experiment import execute_real

        return execute_real(
            plan, out_dir, force=force, on_start=on_start, on_result=on_result, progress=progress
        )
    started = time.time()
    # Validate everything first (nothing is touched): values, route, memory, the folder's state,
    # the Dask cluster and its workers. Only then lock the folder and (--force) remove.
    check_plan(plan)
    survey_output(plan, scenario_folder(out_dir, plan.name), force)
    client = None
    if plan.backend.kind == "dask":
        client = connect_dask(plan.backend.scheduler, plan.backend.connect_timeout_s)
    try:
        with folder_lock(Path(out_dir) / plan.name):
            return _execute_locked(
                plan, out_dir, force, client, started, on_start, on_result, progress
            )
    finally:
        if client is not None:
            with contextlib.suppress(Exception):
                client.close()


def _execute_locked(plan, out_dir, force, client, started, on_start, on_result, progress=None):
    target, done, action = prepare_output(plan, out_dir, force)
    fingerprint = plan.fingerprint()

    def keep(result: dict) -> None:
        save_run(target, result, fingerprint)
        if on_result is not None:
            on_result(result)

    # Filters fitted on training runs: fitted (or read from the run store's cache) here, once;
    # the workers get the fitted values in their copy of the scenario.
    fits = fit_filters(plan, target / RUNS_DIR, progress)
    if fits.records:
        action += "; " + ", ".join(
            f"{name} {'read from the cache' if r['cached'] else 'fitted'}"
            f" ({r['training_runs']} training runs)"
            for name, r in fits.records.items()
        )
    results = dict(done)
    batch = run_batch(
        fits.scenario,
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
        client=client,
    )
    if on_start is not None:
        on_start(action, len(done), plan.runs)
    for result in batch:
        results[result["run"]] = result
    ordered = [results[i] for i in range(plan.runs)]
    tables = result_tables(plan, ordered)
    records = tables.summary
    staging = result_staging(target)
    write_result_tables(
        staging,
        tables,
        steps_table=plan.scenario.steps_table,
        metadata={"scenario": plan.name, "seed": str(plan.seed), "fingerprint": fingerprint},
    )
    manifest = {
        "scenario": plan.scenario.model_dump(mode="json"),
        "runs": plan.runs,
        "seed": plan.seed,
        "jobs": plan.jobs,
        "backend": plan.backend.model_dump(mode="json"),
        "engine": plan.engine,
        "engines": {
            f.name: engine_of(plan.engine, f, plan.scenario) for f in plan.scenario.filters
        },
        "fast_compiled": fast_compiled(plan.engine),  # false: numba missing, plain Python
        "format": RESULT_FORMAT,
        "fingerprint": fingerprint,
        "world": {
            "landmarks": plan.world.landmarks.tolist(),
            "waypoints": plan.world.waypoints.tolist(),
            "control_steps": ordered[0]["control_steps"],
        },
        "resumed_runs": sorted(done),
        "training": fits.records,
        "versions": package_versions(),
        "machine": machine_info(),
        "wall_time_s": round(time.time() - started, 3),
    }
    write_json(staging / MANIFEST_FILE, manifest)
    finish_result(target, staging)
    return records, target


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
    summary = summary_records(steps, update_statistics(ordered, names))
    schedule, phases = plan.scenario.noise_schedule, None
    if schedule is not None:  # SPEC 14: per-phase metrics, recovery and tracking errors
        sigmas = plan.scenario.true_noise.radians()
        oracles = [f.name for f in plan.scenario.filters if f.kind == "ekf-oracle"]
        oracle = oracles[0] if oracles else None
        phases = phases_frame(steps, schedule, sigmas, oracle, seed=plan.seed)
        tracking = summary_tracking(steps, schedule, sigmas)
        for record in summary:
            record.update(tracking[record["filter"]])
    return ResultTables(
        steps=steps,
        runs=runs_frame(plan.name, names, ordered),
        summary=summary,
        comparisons=comparisons_frame(steps, pairs, seed=plan.seed),
        claims=evaluate_claims(steps, plan.scenario.claims, seed=plan.seed),
        phases=phases,
    )
