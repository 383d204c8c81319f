"""Monte Carlo batches: worker calls of a few runs each, fanned out with joblib (benchopt style).

`dispatch_runs` is the one way runs are dispatched, for every source: a batch is a list of
picklable calls, one run each (a simulated run: `simulated_run`; a recorded segment or drive:
real_experiment's `recorded_run`; both end in the one per-run function, `run_one`), grouped
into worker tasks (`run_chunk`) on local threads (a batch wholly on the compiled fast engine),
local processes or a Dask cluster. The calls are top-level functions taking plain data and
returning plain data; they mutate nothing shared. The truth path and the scans' landmark
geometry are computed once per batch and shipped with the tasks.
Run i draws from `SeedSequence(seed).spawn(runs)[i]` only (SPEC 6), so results do not depend on
the number of workers or on the order in which runs finish. The same holds on a Dask
cluster (`backend="dask"`): the same calls are submitted to the cluster's workers, one Dask task
each, and a batch whose workers are all gone (or whose scheduler is) ends in one line.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import copy
import logging
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from functools import partial
from typing import Literal

import numpy as np
from joblib import Parallel, delayed

from .analysis.metrics import add_trace_metrics, recorded_steps
from .config import Engine, SimulatedScenario, World
from .engines.filterpy_engine import run_filter
from .filters import FilterContext, FilterSpec
from .filters.context import filter_context
from .filters.custom import CustomSpec, contained
from .sources.simulator import RunData, WorldPath, simulate_run, world_path
from .timeline import Timeline, from_run
from .workers import local_workers


def simulate(
    scenario: SimulatedScenario,
    world: World,
    seed: np.random.SeedSequence,
    path: WorldPath | None = None,
) -> RunData:
    """One run's data, every draw from its own seed (SPEC 6); `path` (the truth and the scans'
    geometry, the same in every run) may be passed in so that it is computed once per world."""
    path = world_path(world) if path is None else path
    sigmas, rng = scenario.true_noise.radians(), np.random.default_rng(seed)
    return simulate_run(
        world, path.truth, sigmas, rng, path.geometry, scenario.noise_schedule,
        getattr(scenario, "error_sources", None),
    )  # fmt: skip


def run_filter_on(
    engine: Engine, spec: FilterSpec, scenario, world: World, data: RunData,
    start: float | None = None, name: str | None = None,
) -> dict:  # fmt: skip
    """One filter (the instance `name` from naive start `start`, when given) over one simulated
    run's data on `engine` (`run_spec` on the run's timeline)."""
    tl = from_run(data, world, scenario.record_every)
    return run_spec(engine, spec, filter_context(spec, scenario, world, start), tl, name=name)


def run_spec(
    engine: Engine, spec: FilterSpec, ctx: FilterContext, tl: Timeline, *, name: str | None = None
) -> dict:
    """One filter over one timeline (a simulated run or a recorded span) on `engine`: the fast
    engine runs the filters and motion models it implements, every other filter (a user's own,
    a zoo baseline) runs on filterpy (`engine_of` says which), and so does a context that
    carries the true noise of every step (the oracle under a noise schedule, SPEC 14: the
    kernels take constant noise). `name`: the instance name a custom filter's errors are
    reported under."""
    if runs_fast(engine, spec, ctx):
        from .engines import fast

        return fast.run_filter_fast(spec, ctx, tl)
    if isinstance(spec, CustomSpec):
        # A user's filter gets its own copy of the run's arrays (it could write into the scans
        # every other filter reads), and anything it raises is one line naming it.
        flt, mine = spec.build(ctx), copy.deepcopy(tl)
        hook = "predict/update"
        return contained(name or spec.name, spec.class_path, hook, run_filter, flt, mine)
    return run_filter(spec.build(ctx), tl)


def runs_fast(engine: Engine, spec: FilterSpec, ctx: FilterContext) -> bool:
    """Whether `run_spec` runs `spec` in `ctx` on the fast engine's kernels (see there)."""
    if engine != "fast" or ctx.true_noise is not None:
        return False
    from .engines import fast  # numba (when installed) is imported only for this engine

    return fast.supports(spec, ctx.model)


def follows_schedule(spec: FilterSpec, scenario) -> bool:
    """Whether `spec` is told the true noise of every step (the oracle of a scenario with a
    noise schedule, SPEC 14): the fast engine's kernel takes constant noise, so it runs on
    filterpy (the manifest's `engines` says so)."""
    return spec.uses_true_noise and getattr(scenario, "noise_schedule", None) is not None


def engine_of(engine: Engine, spec: FilterSpec, scenario=None, model=None) -> Engine:
    """The engine that actually runs `spec` (on `model`, when given) when `engine` is asked for
    (for the manifest)."""
    if engine == "fast":
        from .engines import fast

        runs_fast = fast.supports(spec, model) and not follows_schedule(spec, scenario)
        return "fast" if runs_fast else "filterpy"
    return "filterpy"


def runs_in_threads(engine: Engine, engines: dict[str, str]) -> bool:
    """Whether a batch's local runs go on threads: every instance runs on the fast engine
    (`engines`: instance -> the engine that runs it) and its kernels are compiled. Those
    release the GIL (threads took 1.8-2x the runs of one thread on two cores, recorded drives
    and simulated batches alike); filterpy's Python holds it, so its runs go to processes."""
    return engine == "fast" and set(engines.values()) <= {"fast"} and bool(fast_compiled(engine))


def fast_compiled(engine: Engine) -> bool | None:
    """For the manifest: whether the fast engine's kernels are numba-compiled (False: plain
    Python, much slower: numba is missing); None when the fast engine is not asked for."""
    if engine != "fast":
        return None
    from .engines import fast

    return bool(fast.JIT)


@dataclass(frozen=True, eq=False)
class RunInputs:
    """One run as every filter of it sees it and as it is scored, whatever the source (SPEC 12):
    the timeline the filters step, the evaluation steps and times (a recorded span shorter than
    the longest is padded: NaN times), the truth there (NaN where it is not scored) and the
    run's length (a simulated run's control steps; a recorded span's evaluation times)."""

    run: int
    timeline: Timeline
    step: np.ndarray
    t: np.ndarray
    x_true: np.ndarray
    control_steps: int


# A filter's per-step arrays, padded with NaN to the run's evaluation steps.
TRACE_ARRAYS = ("x", "P", "R_diag", "Q_diag", "P_infl")


def pad_to(a: np.ndarray, n: int) -> np.ndarray:
    """`a` with NaN rows appended up to `n` rows (itself when it has them)."""
    if len(a) == n:
        return a
    out = np.full((n, *a.shape[1:]), np.nan, dtype=float)
    out[: len(a)] = a
    return out


def run_one(
    inputs: RunInputs,
    instances: Iterable[tuple[str, FilterSpec, FilterContext]],
    engine: Engine = "filterpy",
) -> dict:
    """One Monte Carlo run, whatever its source: every filter instance (name, spec, starting
    context: `filters.context`) over the same timeline (common random numbers) on `engine`
    (`run_spec`), its trace padded to the run's evaluation steps and scored against the truth.
    The sources' calls build the inputs: `simulated_run`, real_experiment's `recorded_run`."""
    n = len(inputs.step)
    filters = {}
    for name, spec, ctx in instances:
        trace = run_spec(engine, spec, ctx, inputs.timeline, name=name)
        for key in TRACE_ARRAYS:
            trace[key] = pad_to(trace[key], n)
        # scored as the engine that ran it scores: a filter on filterpy keeps numpy's bits
        filters[name] = add_trace_metrics(
            trace, inputs.x_true, compiled=runs_fast(engine, spec, ctx)
        )
    return {
        "run": inputs.run,
        "control_steps": inputs.control_steps,
        "step": inputs.step,
        "t": inputs.t,
        "x_true": inputs.x_true,
        "filters": filters,
    }


def simulated_run(
    scenario: SimulatedScenario,
    world: World,
    run: int,
    seed: np.random.SeedSequence,
    path: WorldPath | None = None,
    engine: Engine = "filterpy",
) -> dict:
    """One simulated run: simulate once from its own seed, then `run_one` with every instance
    from the context `filter_context` gives it."""
    data = simulate(scenario, world, seed, path)
    steps = recorded_steps(len(data.u_odo), scenario.record_every)
    tl = from_run(data, world, scenario.record_every)
    inputs = RunInputs(run, tl, steps, steps * world.T, data.truth.x[steps], len(data.u_odo))
    instances = (
        (name, spec, filter_context(spec, scenario, world, start))
        for name, spec, start in scenario.instances()
    )
    return run_one(inputs, instances, engine)


@dataclass(frozen=True)
class Prepared:
    """What a plan's source hands experiment's one pipeline once its preparation (fits, tuning,
    training) is done: one picklable call per run (run index -> call, for `dispatch_runs`), the
    start line's account of the preparation ("; ekf-ml fitted ...", appended to the action),
    the manifest keys only this source writes, and the manifest's world.control_steps."""

    items: dict[int, Callable[[], dict]]
    action: str
    manifest: dict
    control_steps: int
    tables: dict = field(default_factory=dict)  # file name -> DataFrame (the drive audit)


def run_chunk(items: list[Callable[[], dict]]) -> list[dict]:
    """Several runs in one worker task (a fast engine's run takes milliseconds: one task per run
    would cost more in dispatch than in filtering). `items`: picklable calls, one run each."""
    return [item() for item in items]


def run_tasks(scenario: SimulatedScenario, world: World, runs: int, seed: int) -> Iterator[dict]:
    """Plain keyword dicts, one per run: run i gets the i-th child of the root seed (SPEC 6)."""
    for i, child in enumerate(np.random.SeedSequence(seed).spawn(runs)):
        yield {"scenario": scenario, "world": world, "run": i, "seed": child}


def simulated_items(
    scenario: SimulatedScenario, world: World, runs: int, seed: int, engine: Engine = "filterpy",
    path: WorldPath | None = None,
) -> dict[int, Callable[[], dict]]:  # fmt: skip
    """The work of a simulated batch: run index -> its call (`simulated_run` with its own seed;
    the truth path and the scans' geometry, the same in every run, computed once and shipped)."""
    path = world_path(world) if path is None else path
    return {
        t["run"]: partial(simulated_run, scenario, world, t["run"], t["seed"], path, engine)
        for t in run_tasks(scenario, world, runs, seed)
    }


def runs_per_task(n_runs: int, workers: int) -> int:
    """About four tasks per worker, so that the load balances and progress moves."""
    return max(1, math.ceil(n_runs / (4 * max(workers, 1))))


# What starting local workers costs before their first run: process start, importing the
# package and loading the fast engine's compiled kernels from numba's cache: about 2 s, paid in
# parallel (an estimate from the bench's fresh-process figures: `fast_e2e_cli_s` 3.9 s against
# `fast_e2e_scenario_s` 0.85 s on warm workers; the bench does not measure it alone yet). The
# environment variable ANFEKF_WORKER_START_S replaces it (0: workers whenever jobs > 1).
WORKER_START_S = 2.0
WORKERS_PAY = 0.8  # workers are used when they are estimated to take at most this share


def worker_start_s() -> float:
    """WORKER_START_S, or the environment's ANFEKF_WORKER_START_S when it is a number >= 0."""
    try:
        value = float(os.environ.get("ANFEKF_WORKER_START_S", WORKER_START_S))
    except ValueError:
        return WORKER_START_S
    return value if math.isfinite(value) and value >= 0 else WORKER_START_S


def place_runs(n_runs: int, jobs: int, run_s: float, start_s: float | None = None) -> dict:
    """Where a local batch's remaining `n_runs` runs go, from the measured cost of one run
    (`run_s`, the probe run done in-process): in this process, or on `jobs` workers, whichever
    is estimated to finish first (workers only when they save a fifth: the estimate is rough).
    The record goes into the manifest (`placement`)."""
    start_s = worker_start_s() if start_s is None else start_s
    workers = max(1, min(jobs, n_runs))
    in_process_s = n_runs * run_s
    workers_s = start_s + in_process_s / workers
    use = workers > 1 and workers_s <= WORKERS_PAY * in_process_s
    return {
        "where": "workers" if use else "in-process",
        "workers": workers if use else 0,
        "probe_run_s": round(run_s, 4),
        "estimate_in_process_s": round(in_process_s, 3),
        "estimate_workers_s": round(workers_s, 3),
        "worker_start_s": start_s,
    }


def dispatch_runs(
    items: list[Callable[[], dict]],
    *,
    jobs: int,
    on_result: Callable[[dict], None] | None = None,
    backend: Literal["local", "dask"] = "local",
    scheduler: str | None = None,
    connect_timeout_s: float = 10.0,
    engine: Engine = "filterpy",
    client=None,
    placement: dict | None = None,
    in_threads: bool = False,
) -> Iterator[dict]:
    """Run results as they finish (any order), whatever the source: `items` are picklable
    calls, one run each (simulated: `simulated_items`; recorded: real_experiment's segments or
    drives); `on_result` sees each result as it arrives (execute keeps it there for a resume).

    backend "local" runs the first two runs in this process, timing the second, then the rest
    here or on up to `jobs` local processes, whichever `place_runs` estimates to be faster (a
    fast-engine batch of a few seconds does not pay for starting workers); `placement`, when
    given, is filled with that decision. `in_threads` (`runs_in_threads`: every instance on
    the compiled fast engine): the local runs on `jobs` threads of this process instead.
    "dask" runs on the existing Dask cluster whose
    scheduler listens at `scheduler` (all its worker threads; `jobs` is not used there). The
    cluster is reached here (unless `client`, from `connect_dask`, is given: the caller reached
    it before touching its output), before the first result is asked for, so a scheduler that
    cannot be reached raises BackendUnavailable at once. Local workers end when this process
    dies.
    """
    if not items:
        return iter(())
    if backend == "dask":
        calls = (delayed(run_chunk)([item]) for item in items)
        if client is None:
            client = connect_dask(scheduler, connect_timeout_s)
        if placement is not None:
            placement.update(where="dask", workers=None)
        return _announce(_run_on_dask(client, calls, scheduler, connect_timeout_s), on_result)
    return _announce(_run_local(items, jobs, engine, placement, in_threads), on_result)


def _run_local(
    items: list[Callable[[], dict]],
    jobs: int,
    engine: Engine,
    placement: dict | None,
    in_threads: bool = False,
) -> Iterator[list[dict]]:
    """`dispatch_runs`'s local batches. `in_threads`: every run on `jobs` threads of this
    process (the compiled kernels release the GIL, so threads share the cores without starting
    processes, importing in them or shipping data to them). Otherwise two runs here, the
    second timed (the first pays this process's one-time costs: loading the compiled kernels,
    first calls), then the rest where `place_runs` says it pays."""
    threads = min(jobs, len(items))
    if in_threads and threads > 1:
        if placement is not None:
            placement.update(where="threads", workers=threads)
        yield from Parallel(n_jobs=threads, backend="threading", return_as="generator_unordered")(
            delayed(run_chunk)([item]) for item in items
        )
        return
    yield run_chunk(items[:1])
    t0 = time.perf_counter()
    yield run_chunk(items[1:2])
    probe_s = time.perf_counter() - t0
    rest = items[2:]
    decision = place_runs(len(rest), jobs, probe_s)
    if placement is not None:
        placement.update(decision)
    if not rest:
        return
    if decision["where"] == "in-process":
        for item in rest:  # one at a time: progress (and the run store) move with every run
            yield run_chunk([item])
        return
    # A filterpy run takes a good part of a second: one task per run (progress and resume move
    # with every run); a fast-engine run takes milliseconds, so its tasks hold several runs.
    workers = decision["workers"]
    size = runs_per_task(len(rest), workers) if engine == "fast" else 1
    calls = (delayed(run_chunk)(rest[i : i + size]) for i in range(0, len(rest), size))
    with local_workers():
        yield from Parallel(n_jobs=workers, return_as="generator_unordered")(calls)


def run_batch(
    scenario: SimulatedScenario,
    world: World,
    *,
    runs: int,
    seed: int,
    jobs: int,
    on_result: Callable[[dict], None] | None = None,
    skip: set[int] | frozenset[int] = frozenset(),
    backend: Literal["local", "dask"] = "local",
    scheduler: str | None = None,
    connect_timeout_s: float = 10.0,
    engine: Engine = "filterpy",
    client=None,
) -> Iterator[dict]:
    """A simulated batch's runs (`skip` leaves out runs already done) through `dispatch_runs`:
    for scripts and benchmarks that want the runs without a result folder."""
    items = simulated_items(scenario, world, runs, seed, engine)
    return dispatch_runs(
        [call for run, call in items.items() if run not in skip], jobs=jobs, on_result=on_result,
        backend=backend, scheduler=scheduler, connect_timeout_s=connect_timeout_s,
        engine=engine, client=client,
    )  # fmt: skip


def _announce(
    chunks: Iterable[list[dict]], on_result: Callable[[dict], None] | None
) -> Iterator[dict]:
    for chunk in chunks:
        for result in chunk:
            if on_result is not None:
                on_result(result)
            yield result


class BackendUnavailable(Exception):
    """The chosen backend cannot run the batch; `str()` is the one-line message for the user."""


DASK_POLL_S = 0.5  # how often a waiting batch looks at the cluster's workers


def _run_on_dask(
    client, calls: Iterable, scheduler: str | None, timeout_s: float = 10.0
) -> Iterator[list[dict]]:
    """Run joblib-style calls `(func, args, kwargs)` on a Dask cluster, one Dask task each,
    yielding results as they finish.

    While waiting it looks at the cluster every DASK_POLL_S: when no worker has been there for
    `timeout_s` (every worker died, and nothing restarts them) or the scheduler is gone, the batch
    ends with BackendUnavailable instead of waiting forever.
    """
    from distributed import as_completed
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    futures = []
    try:
        for func, args, kwargs in calls:
            futures.append(client.submit(func, *args, pure=False, **kwargs))
        # with_results: a result is fetched before its future counts as ready, while the loop
        # below watches the workers. Fetching it here after "ready" would wait forever for a
        # result whose worker died in between (the scheduler then recomputes it, on no worker).
        finished = as_completed(futures, loop=client.loop, with_results=True)
        lonely_since: float | None = None
        while not finished.is_empty():
            if _wait_ready(finished, DASK_POLL_S):
                future, result = next(finished)  # a run's own error is raised with its type
                if future.cancelled():  # the cluster went away: `result` is its CancelledError
                    raise concurrent.futures.CancelledError
                yield result
                lonely_since = None
                continue
            if client.status not in ("running", "connecting"):
                raise CommClosedError("client closed")
            workers = _worker_count(client, timeout_s)
            if workers:
                lonely_since = None
            elif lonely_since is None:
                lonely_since = time.monotonic()
            elif time.monotonic() - lonely_since > timeout_s:
                raise BackendUnavailable(
                    f"Dask cluster at {scheduler} has had no workers for {timeout_s:g} s during"
                    " the batch (they died or left); finished runs are saved: run the same"
                    " command again to resume"
                )
    except (
        concurrent.futures.CancelledError,
        CommClosedError,
        KilledWorker,
        OSError,
        TimeoutError,
    ) as exc:
        # The cluster went away under us.
        what = "its workers died" if isinstance(exc, KilledWorker) else "connection lost"
        raise BackendUnavailable(
            f"Dask cluster at {scheduler} failed during the batch ({what}); finished runs are"
            " saved: run the same command again to resume"
        ) from None
    finally:
        with contextlib.suppress(Exception):
            client.cancel([f for f in futures if not f.done()], force=True)
        with contextlib.suppress(Exception):
            client.close(timeout=timeout_s)


def _wait_ready(finished, timeout_s: float) -> bool:
    """Whether a future of `finished` (distributed.as_completed) is done, waiting <= timeout_s."""
    deadline = time.monotonic() + timeout_s
    while not finished.has_ready():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)
    return True


def _worker_count(client, timeout_s: float) -> int:
    """Workers the scheduler knows now (an RPC bounded by `timeout_s`; OSError if it is gone)."""
    try:
        info = client.sync(client.scheduler.ncores, callback_timeout=timeout_s)
    except (OSError, TimeoutError):
        raise
    except Exception as exc:  # distributed wraps some comm failures in its own types
        raise OSError(_first_line(exc)) from None
    return len(info)


QUIETED_LOGGERS = ("distributed", "tornado", "asyncio", "bokeh")


def _quiet_dask_logs() -> None:
    """The batch reports a cluster's failure in one line of its own; distributed's loggers would
    add their own lines (with tracebacks) to stderr. Every logger of theirs: distributed's config
    gives some children a level and a handler of their own (distributed.client at WARNING,
    tornado.application at ERROR: its "Exception in callback" traceback after a kill -9 of the
    scheduler), which the parent's level does not cover."""
    names = [*QUIETED_LOGGERS, *logging.root.manager.loggerDict]
    for name in names:
        if name.split(".")[0] in QUIETED_LOGGERS:
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)


async def _handshake(scheduler: str, timeout_s: float) -> None:
    from distributed.comm import connect

    # connect() gives up on a refused or unroutable address after timeout_s by itself; the outer
    # bound (with a margin, so that its own message wins there) ends a handshake that never comes.
    outer = timeout_s + max(1.0, timeout_s / 2)
    comm = await asyncio.wait_for(connect(scheduler, timeout=timeout_s), outer)
    await comm.close()


def _probe_scheduler(scheduler: str, timeout_s: float) -> None:
    """Connect and exchange Dask's handshake, all within `timeout_s`: distributed's own connect
    waits for the handshake without a deadline, so a server that accepts the connection but is not
    a Dask scheduler (an HTTP server, a silent port) would hang it forever."""
    try:
        asyncio.run(_handshake(scheduler, timeout_s))
    except TimeoutError:
        raise BackendUnavailable(
            f"cannot use {scheduler}: it accepted the connection but did not answer as a Dask"
            f" scheduler (timeout {timeout_s:g} s)"
        ) from None
    except OSError as exc:
        # distributed retries a refused connection until the timeout, then says "Timed out ...".
        reason = "no answer" if str(exc).startswith("Timed out") else _first_line(exc)
        raise BackendUnavailable(
            f"cannot reach Dask scheduler at {scheduler}: {reason} (timeout {timeout_s:g} s)"
        ) from None
    except Exception as exc:  # garbage in place of a handshake
        raise BackendUnavailable(
            f"cannot use {scheduler}: it did not answer as a Dask scheduler ({type(exc).__name__})"
        ) from None


def connect_dask(scheduler: str | None, timeout_s: float):
    """A `distributed.Client` on `scheduler` with at least one worker, or BackendUnavailable
    (within about twice `timeout_s`, whatever answers at that address)."""
    try:
        from distributed import Client
    except ImportError as exc:
        raise BackendUnavailable(
            'the dask backend needs dask[distributed]; install it with: pip install -e ".[dask]"'
        ) from exc
    if not scheduler:
        raise BackendUnavailable("the dask backend needs a scheduler address tcp://HOST:PORT")
    _quiet_dask_logs()
    _probe_scheduler(scheduler, timeout_s)
    try:
        client = Client(scheduler, timeout=timeout_s, set_as_default=False)
    except Exception as exc:  # refused, timed out, not a Dask scheduler: all mean "not reachable"
        reason = "no answer" if str(exc).startswith("Timed out") else _first_line(exc)
        raise BackendUnavailable(
            f"cannot reach Dask scheduler at {scheduler}: {reason} (timeout {timeout_s:g} s)"
        ) from None
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except Exception:
        with contextlib.suppress(Exception):
            client.close(timeout=timeout_s)
        raise BackendUnavailable(
            f"Dask scheduler at {scheduler} has no workers after {timeout_s:g} s;"
            f" start some with: dask worker {scheduler}"
        ) from None
    return client


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
