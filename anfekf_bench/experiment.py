"""One scenario end to end, whatever its source: resolve, prepare, run the batch, save every
finished run, write the results.

A `Plan` is a scenario with the command line's overrides applied and its source: a
`SimulatedSource` (runs simulated from the scenario's world, one per seed) or a
`real_experiment.RecordedSource` (a recorded log's held-out segments or drives). What really
differs sits behind the source: how many runs there are, what is checked before any work, what
the resume fingerprint covers, the preparation (fits, tuning, training) and the runs it hands
out as picklable calls, the default comparison pairs and the summary's extra columns. The rest
is one pipeline (`execute`): the same folder rules, run store, dispatch (`runner.dispatch_runs`:
local processes or Dask), tables (`result_tables`) and manifest (`write_result`).

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
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import pandas as pd
from pydantic import ValidationError

from .analysis.comparisons import (
    comparison_pairs,
    comparisons_frame,
    evaluate_claims,
    filters_arrays,
)
from .analysis.phases import phases_frame, summary_tracking
from .analysis.tables import (
    runs_frame,
    steps_frame,
    summary_records,
    update_statistics,
)
from .config import BackendConfig, Engine, Scenario, SimulatedScenario, World
from .filters.context import build_filter
from .filters.custom import CustomFilterFailed, CustomSpec
from .fitting.simulated import TrainingSet, fit_filters, fitted_filters
from .outputs import (
    STORE_AFTER_S,
    OutputExists,
    PlanError,
    ResultTables,
    RunStore,
    code_version,
    finish_result,
    machine_info,
    package_versions,
    prepare_output,
    result_staging,
    scenario_folder,
    survey_output,
    write_result_table,
    write_result_tables,
)
from .runner import (
    Prepared,
    connect_dask,
    dispatch_runs,
    engine_of,
    fast_compiled,
    runs_in_threads,
    simulated_items,
)
from .signals import deferred
from .sources.simulator import RouteNotCompleted, simulate_truth, world_path
from .storage import (
    MANIFEST_FILE,
    RESULT_FORMAT,
    RUNS_DIR,
    STEPS_FILE,
    FolderBusy,
    folder_lock,
    scenario_name_problem,
    write_json,
)

__all__ = ["FolderBusy", "OutputExists", "PlanError", "RUNS_DIR", "execute", "make_plan"]


class Source(Protocol):
    """What differs between the sources of a plan's runs (`SimulatedSource`,
    `real_experiment.RecordedSource`); `plan` is the `Plan` the source belongs to."""

    world: object  # World, Recording or DriveSet: has landmarks and waypoints

    @property
    def runs(self) -> int:
        """How many runs the batch has (run indices 0 .. runs - 1)."""

    def filter_names(self, scenario) -> list[str]:
        """The names every run's filters are recorded under, in order."""

    def fingerprint_doc(self, plan: Plan) -> dict:
        """What determines a run's bytes (the plan adds the code version and hashes it)."""

    def check(self, plan: Plan) -> int:
        """PlanError (one line) for what would fail, before any work; the evaluation steps."""

    def engines(self, plan: Plan) -> dict[str, str]:
        """For the manifest: the engine each filter (instance) runs on."""

    def comparison_pairs(self, scenario) -> list[tuple[str, str]]:
        """The (filter, vs) pairs of comparisons.parquet."""

    def summary(self, plan: Plan, records: list[dict], steps, ordered: list[dict]):
        """(summary records with the source's own columns, the phases table or None)."""

    def prepare(self, plan: Plan, store: Path, progress=None) -> Prepared:
        """Fits, tuning, training (cached in the run store `store`), then the runs as calls."""


@dataclass(frozen=True)
class Plan:
    """A scenario with the command line's overrides applied, and where its runs come from."""

    scenario: Scenario
    source: Source
    seed: int
    jobs: int
    backend: BackendConfig = BackendConfig()
    engine: Engine = "filterpy"

    @property
    def name(self) -> str:
        return self.scenario.name

    @property
    def runs(self) -> int:
        return self.source.runs

    @property
    def world(self):
        """The simulated world, or the recorded log (a `Recording` or `DriveSet`)."""
        return self.source.world

    def filter_names(self) -> list[str]:
        """The filters of every run (a recorded plan has one per filter and naive start)."""
        return self.source.filter_names(self.scenario)

    def fingerprint(self) -> str:
        """Hash of everything that determines a run's bytes (not jobs or backend: they change
        nothing, so a batch started locally may be resumed on a Dask cluster and back)."""
        doc = {**self.source.fingerprint_doc(self), "code": code_version()}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def make_plan(
    scenario: Scenario,
    world,
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
        source=plan_source(scenario, world, runs),
        seed=scenario.seed if seed is None else seed,
        jobs=scenario.jobs if jobs is None else jobs,
        backend=resolve_backend(scenario.backend, backend, scheduler),
        engine=scenario.engine if engine is None else engine,
    )


def plan_source(scenario: Scenario, world, runs: int | None) -> Source:
    """The source of a scenario's runs, by the member of the source union it is
    (`Scenario.source`): the one place past `scenarios.load_scenario` that tells them apart."""
    if scenario.source == "simulated":
        return SimulatedSource(world, scenario.runs if runs is None else runs)
    if runs is not None:
        raise PlanError(
            f"--runs {runs}: a real-data scenario's runs are its held-out segments (set"
            " segment_s in the scenario file)"
        )
    # imported here: a simulated plan never pays for the recorded logs' readers, fits and audit
    from .real_experiment import RecordedSource

    return RecordedSource(world)


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
    filters = len(plan.filter_names())
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


# A fitted filter's training set, per training run and control step [bytes]: the simulated run
# (truth, odometry, scans) and the tuning kernel's copy of it (measured: 62 and 115 bytes on the
# builtin map); a parallel fit's threads share them
TRAINING_RUN_BYTES_PER_STEP = 64
TRAINING_PROBLEM_BYTES_PER_STEP = 128


def training_memory_estimate(plan: Plan, control_steps: int) -> int:
    """Bytes the fitted filters' training needs at its peak (0 without fitted filters): the
    `training.runs` simulated runs held in this process, the tuning kernel's copy of them, and a
    process's base."""
    if not fitted_filters(plan.scenario):
        return 0
    per_run = control_steps * (TRAINING_RUN_BYTES_PER_STEP + TRAINING_PROBLEM_BYTES_PER_STEP)
    return WORKER_BASE_BYTES + plan.scenario.training.runs * per_run


# What a batch costs, for the line `anfekf run` prints before a long one [CPU seconds]: per
# control step of a simulated run, of a filter on each engine (filterpy: the EKF 9.5 us, the
# ANFEKF 14-22 us, results/bench.json), of one objective evaluation of a noise fit per training
# run, and of one KalmanNet epoch per training run (README: 50 runs x 30 epochs in ~55 s)
SIMULATE_STEP_S = 1.5e-6
FILTER_STEP_S = {"filterpy": 20e-6, "fast": 0.2e-6}
FIT_EVALUATION_STEP_S = 0.1e-6
KALMANNET_EPOCH_STEP_S = 5e-6
LONG_PLAN_S = 600.0  # plans estimated longer than this get a line with the estimate first


def seconds_estimate(plan: Plan, control_steps: int) -> tuple[float, float]:
    """(training, batch) wall seconds a simulated plan is estimated to take: CPU costs above
    spread over the workers. Rough (a factor of 2 either way): for a warning, not a limit."""
    scenario = plan.scenario
    engines = plan.source.engines(plan)
    per_run = control_steps * (
        SIMULATE_STEP_S + sum(FILTER_STEP_S.get(e, FILTER_STEP_S["filterpy"])
                              for e in engines.values())
    )  # fmt: skip
    batch = plan.runs * per_run / max(1, min(plan.jobs, plan.runs))
    fitted = fitted_filters(scenario)
    if not fitted:
        return 0.0, batch
    steps = scenario.training.runs * control_steps
    training = steps * SIMULATE_STEP_S
    for spec in fitted:
        request = spec.noise_fit_request()
        if request is not None:
            _, starts, evaluations = request
            parallel = max(1, min(plan.jobs, len(starts)))
            training += steps * FIT_EVALUATION_STEP_S * evaluations * len(starts) / parallel
        else:  # a trained network: its epochs over the training runs
            training += steps * KALMANNET_EPOCH_STEP_S * getattr(spec, "epochs", 1)
    return training, batch


def _duration(seconds: float) -> str:
    if seconds < 3600:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


def long_plan_line(plan: Plan, control_steps: int) -> str | None:
    """The line `anfekf run` prints before a plan estimated to take over LONG_PLAN_S (its
    estimate, what it is made of), or None: a simulated plan under it, or a recorded one."""
    if not isinstance(plan.source, SimulatedSource):
        return None
    training, batch = seconds_estimate(plan, control_steps)
    if training + batch <= LONG_PLAN_S:
        return None
    parts = [f"{plan.runs} runs x {control_steps} control steps x"
             f" {len(plan.filter_names())} filters on {min(plan.jobs, plan.runs)} workers"
             f" ~{_duration(batch)}"]  # fmt: skip
    if training:
        parts.append(
            f"training of {', '.join(f.name for f in fitted_filters(plan.scenario))} on"
            f" {plan.scenario.training.runs} training runs ~{_duration(training)}"
        )
    return (
        f"{plan.name}: estimated to take about {_duration(training + batch)} ({'; '.join(parts)});"
        " Ctrl-C stops it, finished runs are saved and the same command resumes them"
    )


def check_plan(plan: Plan) -> int:
    """Everything about a plan that can fail before its batch, checked without touching disk
    (the source's checks: a simulated route, completed and long enough to record, and the
    memory the batch needs; a recorded log's segments). Returns the evaluation steps the source
    counts (a route's control steps; a log's held-out evaluation times); PlanError (a one-line
    message naming the field) otherwise."""
    problem = scenario_name_problem(plan.name)
    if problem:
        raise PlanError(f"name: {problem}")
    return plan.source.check(plan)


@dataclass(frozen=True)
class SimulatedSource:
    """Runs simulated from the scenario's world: run i from the i-th child of the plan's seed
    (SPEC 6); fitted filters are fitted on training runs of a disjoint seed branch
    (fitting.simulated)."""

    world: World
    runs: int

    def filter_names(self, scenario: SimulatedScenario) -> list[str]:
        return scenario.instance_names()

    def fingerprint_doc(self, plan: Plan) -> dict:
        return {
            "scenario": plan.scenario.model_dump(mode="json", exclude={"jobs", "runs", "backend"}),
            "seed": plan.seed,
            "engine": plan.engine,
            "landmarks": self.world.landmarks.tolist(),
            "waypoints": self.world.waypoints.tolist(),
        }

    def training_fingerprint(self, plan: Plan, spec) -> str:
        """The cache key of a fitted filter's fit on the plan's training runs
        (`fitting.simulated.TrainingSet.fingerprint`)."""
        return TrainingSet(scenario=plan.scenario, world=self.world, seed=plan.seed).fingerprint(
            spec
        )

    def check(self, plan: Plan) -> int:
        """The fitted filters' training, the route (completed, long enough to record), a
        user's filter's __init__, and the memory; returns the route's control steps."""
        for f in plan.scenario.filters:  # a fitted filter that the training runs cannot train
            message = f.fitted_on_training and f.training_problem(plan.scenario.training.runs)
            if message:
                raise PlanError(f"filters.{f.name}.{message}")
        try:
            control_steps = len(simulate_truth(self.world).u)
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
                f"record_every: {every} is longer than the route ({control_steps} control"
                f" steps); use at most {control_steps}"
            )
        for i, spec in enumerate(plan.scenario.filters):
            if isinstance(spec, CustomSpec):  # a user's __init__ that fails does so before work
                try:
                    build_filter(spec, plan.scenario, self.world)
                except CustomFilterFailed as exc:
                    raise PlanError(f"filters.{i}: {exc}") from None
        need, have = memory_estimate(plan, control_steps), machine_memory()
        if have is not None and need > MEMORY_SHARE * have:
            recorded = control_steps // every
            raise PlanError(
                f"runs: {plan.runs} runs of {recorded} recorded steps x"
                f" {len(plan.filter_names())} filters (jobs {plan.jobs}) need about"
                f" {_bytes(need)} of memory, more than {MEMORY_SHARE:.0%} of this machine's"
                f" {_bytes(have)}; use fewer runs, a larger record_every, fewer jobs or a smaller"
                " map"
            )
        need = training_memory_estimate(plan, control_steps)
        if have is not None and need > MEMORY_SHARE * have:
            raise PlanError(
                f"training.runs: {plan.scenario.training.runs} training runs of {control_steps}"
                f" control steps (fitted filters) need about"
                f" {_bytes(need)} of memory, more than {MEMORY_SHARE:.0%} of this machine's"
                f" {_bytes(have)}; use fewer training runs or a shorter route"
            )
        return control_steps

    def engines(self, plan: Plan) -> dict[str, str]:
        return {
            name: engine_of(plan.engine, spec, plan.scenario)
            for name, spec, _ in plan.scenario.instances()
        }

    def comparison_pairs(self, scenario: SimulatedScenario) -> list[tuple[str, str]]:
        """Every instance against each reference kind's first instance, the one from the
        assumed noise itself (start 1 or none) when there is one."""
        found = [(name, spec.role, m in (None, 1.0)) for name, spec, m in scenario.instances()]
        return comparison_pairs(
            [(name, role) for name, role, _ in found],
            scenario.compare,
            prefer={name for name, _, at_one in found if at_one},
        )

    def summary(self, plan: Plan, records: list[dict], steps, ordered: list[dict]):
        """With a noise schedule (SPEC 14): per-phase metrics, recovery and tracking errors."""
        schedule, phases = plan.scenario.noise_schedule, None
        if schedule is not None:
            sigmas = plan.scenario.true_noise.radians()
            oracles = [f.name for f in plan.scenario.filters if f.role == "oracle"]
            oracle = oracles[0] if oracles else None
            phases = phases_frame(steps, schedule, sigmas, oracle, seed=plan.seed)
            tracking = summary_tracking(steps, schedule, sigmas)
            for record in records:
                record.update(tracking[record["filter"]])
        return records, phases

    def prepare(self, plan: Plan, store: Path, progress=None) -> Prepared:
        """Filters fitted on training runs: fitted (or read from the run store's cache) here,
        once; the workers get the fitted values in their copy of the scenario."""
        fits = fit_filters(plan, store, progress)
        action = ""
        if fits.records:
            action = "; " + ", ".join(
                f"{name} {'read from the cache' if r['cached'] else 'fitted'}"
                f" ({r['training_runs']} training runs)"
                for name, r in fits.records.items()
            )
        path = world_path(self.world)
        items = simulated_items(fits.scenario, self.world, plan.runs, plan.seed, plan.engine, path)
        return Prepared(items, action, {"training": fits.records}, len(path.truth.u))


# --------------------------------------------------------------------------------------------
# The one pipeline: validate, survey, connect, lock, prepare, run, tables, manifest


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
    prepared = plan.source.prepare(plan, target / RUNS_DIR, progress)
    if on_start is not None:
        on_start(action + prepared.action, len(done), plan.runs)
    run_started = time.perf_counter()
    store = RunStore(target, plan.fingerprint(), STORE_AFTER_S if plan.engine == "fast" else 0.0)

    def keep(result: dict) -> None:
        store.keep(result)
        if on_result is not None:
            on_result(result)

    results = dict(done)
    placement: dict = {}
    try:
        batch = dispatch_runs(
            [call for run, call in sorted(prepared.items.items()) if run not in done],
            jobs=plan.jobs,
            on_result=keep,
            backend=plan.backend.kind,
            scheduler=plan.backend.scheduler,
            connect_timeout_s=plan.backend.connect_timeout_s,
            engine=plan.engine,
            client=client,
            placement=placement,
            in_threads=runs_in_threads(plan.engine, plan.source.engines(plan)),
        )
        for result in batch:
            results[result["run"]] = result
        run_seconds = time.perf_counter() - run_started
        ordered = [results[i] for i in range(plan.runs)]
        tables, steps_written = tables_writing_steps(plan, ordered, result_staging(target))
        write_result(
            plan, target, tables, prepared, sorted(done), started, run_seconds, placement,
            steps_written=steps_written, store=store,
        )  # fmt: skip
    except BaseException:  # interrupted or failed before the result was in place (finish_result
        # empties the store then): the runs it holds are saved for a resume, whole (a second
        # Ctrl-C or SIGTERM meanwhile is held, then dropped: the first is the one to report)
        with contextlib.suppress(Exception, KeyboardInterrupt), deferred():
            store.flush()
        raise
    return tables.summary, target


def write_result(
    plan: Plan,
    target: Path,
    tables: ResultTables,
    prepared: Prepared,
    resumed: list[int],
    started: float,
    run_seconds: float,
    placement: dict | None = None,
    steps_written: bool = False,
    store: RunStore | None = None,
) -> None:
    """The batch's tables and manifest, staged and then swapped in whole (finish_result).
    `placement`: where the runs ran and why (`runner.place_runs`; empty when none was run).
    `steps_written`: steps.parquet is staged already. `store`: the batch's run store."""
    fingerprint = plan.fingerprint()
    staging = result_staging(target)
    write_result_tables(
        staging,
        tables,
        steps_table=plan.scenario.steps_table,
        metadata=result_metadata(plan),
        extra=prepared.tables,
        durable=False,  # finish_result flushes the staged files together before installing
        steps_written=steps_written,
    )
    manifest = {
        "scenario": plan.scenario.model_dump(mode="json"),
        "runs": plan.runs,
        "seed": plan.seed,
        "jobs": plan.jobs,
        "backend": plan.backend.model_dump(mode="json"),
        "engine": plan.engine,
        "engines": plan.source.engines(plan),
        "filters": [
            {"name": name, "base": spec.name, "kind": spec.kind, "start": m}
            for name, spec, m in plan.scenario.instances()
        ],
        "fast_compiled": fast_compiled(plan.engine),  # false: numba missing, plain Python
        "format": RESULT_FORMAT,
        "fingerprint": fingerprint,
        "world": {
            "landmarks": plan.world.landmarks.tolist(),
            "waypoints": plan.world.waypoints.tolist(),
            "control_steps": prepared.control_steps,
        },
        **prepared.manifest,  # the source's own keys (training, data, tuning, ...)
        "resumed_runs": resumed,
        "versions": package_versions(),
        "machine": machine_info(),
        "placement": placement or {"where": "none"},
        "run_seconds": round(run_seconds, 3),
        "wall_time_s": round(time.time() - started, 3),
    }
    write_json(staging / MANIFEST_FILE, manifest, durable=False)
    finish_result(target, staging, store)


def tables_writing_steps(
    plan: Plan, ordered: list[dict], staging: Path
) -> tuple[ResultTables, bool]:
    """`result_tables`, with steps.parquet (the largest file: 355 MB on the drives) written to
    `staging` and flushed on a thread while the other tables are computed (pyarrow releases the
    GIL as it encodes). Returns the tables and whether steps.parquet was written."""
    with ThreadPoolExecutor(max_workers=1) as writer:
        written: list[Future] = []

        def write_steps(steps: pd.DataFrame) -> None:
            if plan.scenario.steps_table:
                path, meta = staging / STEPS_FILE, result_metadata(plan)
                written.append(writer.submit(write_result_table, path, steps, meta))

        tables = result_tables(plan, ordered, on_steps=write_steps)
        for future in written:
            future.result()  # the writer's error, if any, is raised here
    return tables, bool(written)


def result_metadata(plan: Plan) -> dict[str, str]:
    """What every result table of `plan` says of where it came from (write_result_tables)."""
    return {"scenario": plan.name, "seed": str(plan.seed), "fingerprint": plan.fingerprint()}


def result_tables(
    plan: Plan, ordered: list[dict], on_steps: Callable[[pd.DataFrame], None] | None = None
) -> ResultTables:
    """The steps, per-run, summary, comparison and claim tables of a batch (runs in order).
    `on_steps` gets the steps table as soon as it is built (the others take longer).

    Bootstrap intervals draw from the scenario's root seed, so they are as reproducible as the
    runs themselves.
    """
    names = plan.filter_names()
    local_jobs = plan.jobs if plan.backend.kind == "local" else 1  # the batch's own workers
    steps = steps_frame(plan.name, names, ordered, jobs=local_jobs)
    if on_steps is not None:
        on_steps(steps)
    pairs = plan.source.comparison_pairs(plan.scenario)
    arrays = filters_arrays(steps, names)  # read by the summary and the comparisons
    records = summary_records(steps, update_statistics(ordered, names), arrays)
    summary, phases = plan.source.summary(plan, records, steps, ordered)
    return ResultTables(
        steps=steps,
        runs=runs_frame(plan.name, names, ordered),
        summary=summary,
        comparisons=comparisons_frame(steps, pairs, seed=plan.seed, jobs=local_jobs, arrays=arrays),
        claims=evaluate_claims(steps, plan.scenario.claims, seed=plan.seed, arrays=arrays),
        phases=phases,
    )
