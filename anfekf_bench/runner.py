"""Monte Carlo batches: worker calls of a few runs each, fanned out with joblib (benchopt style).

`run_chunk` / `run_one` are top-level functions taking plain data and returning plain data; they
mutate nothing shared. The truth path is computed once per batch and shipped with the tasks.
Run i draws from `SeedSequence(seed).spawn(runs)[i]` only (SPEC 6), so results do not depend on
the number of workers or on the order in which runs finish. The same holds on a Dask
cluster (`backend="dask"`): joblib's dask backend ships the same calls to the cluster's workers.
"""

from __future__ import annotations

import concurrent.futures
import math
from collections.abc import Callable, Iterable, Iterator
from typing import Literal

import numpy as np
from joblib import Parallel, delayed

from .analysis.tables import add_trace_metrics, recorded_steps
from .config import Engine, Scenario, World
from .engines.filterpy_engine import run_filter
from .filters import FilterSpec
from .filters.registry import build_filter, filter_context
from .sources.simulator import RunData, Truth, simulate_run, simulate_truth


def simulate(
    scenario: Scenario, world: World, seed: np.random.SeedSequence, truth: Truth | None = None
) -> RunData:
    """One run's data, every draw from its own seed (SPEC 6); `truth`, the same in every run,
    may be passed in so that it is computed once per world, not once per run."""
    truth = simulate_truth(world) if truth is None else truth
    return simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(seed))


def run_filter_on(engine: Engine, spec: FilterSpec, scenario, world: World, data: RunData) -> dict:
    """One filter over one run's data on `engine`; the fast engine runs the filters it
    implements, every other filter (a user's own, a zoo baseline) runs on filterpy."""
    if engine == "fast":
        from .engines import fast  # numba (when installed) is imported only for this engine

        if fast.supports(spec):
            ctx = filter_context(spec, scenario, world)
            return fast.run_filter_fast(spec, ctx, data, world, scenario.record_every)
    return run_filter(build_filter(spec, scenario, world), data, world, scenario.record_every)


def engine_of(engine: Engine, spec: FilterSpec) -> Engine:
    """The engine that actually runs `spec` when `engine` is asked for (for the manifest)."""
    if engine == "fast":
        from .engines import fast

        return "fast" if fast.supports(spec) else "filterpy"
    return "filterpy"


def run_one(
    scenario: Scenario,
    world: World,
    run: int,
    seed: np.random.SeedSequence,
    truth: Truth | None = None,
    engine: Engine = "filterpy",
) -> dict:
    """One Monte Carlo run: simulate once, feed the same data to every filter (CRN)."""
    data = simulate(scenario, world, seed, truth)
    steps = recorded_steps(len(data.u_odo), scenario.record_every)
    x_true = data.truth.x[steps]
    filters = {
        spec.name: add_trace_metrics(run_filter_on(engine, spec, scenario, world, data), x_true)
        for spec in scenario.filters
    }
    return {
        "run": run,
        "control_steps": len(data.u_odo),
        "step": steps,
        "t": steps * world.T,
        "x_true": x_true,
        "filters": filters,
    }


def run_chunk(
    scenario: Scenario,
    world: World,
    runs: list[tuple[int, np.random.SeedSequence]],
    truth: Truth,
    engine: Engine,
) -> list[dict]:
    """Several runs in one worker task (a fast engine's run takes milliseconds: one task per run
    would cost more in dispatch than in filtering)."""
    return [run_one(scenario, world, run, seed, truth, engine) for run, seed in runs]


def run_tasks(scenario: Scenario, world: World, runs: int, seed: int) -> Iterator[dict]:
    """Plain keyword dicts, one per run: run i gets the i-th child of the root seed (SPEC 6)."""
    for i, child in enumerate(np.random.SeedSequence(seed).spawn(runs)):
        yield {"scenario": scenario, "world": world, "run": i, "seed": child}


def runs_per_task(n_runs: int, workers: int) -> int:
    """About four tasks per worker, so that the load balances and progress moves."""
    return max(1, math.ceil(n_runs / (4 * max(workers, 1))))


def run_batch(
    scenario: Scenario,
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
) -> Iterator[dict]:
    """Run results as they finish (any order); `skip` leaves out runs already done.

    backend "local" uses `jobs` local processes; "dask" runs on the existing Dask cluster whose
    scheduler listens at `scheduler` (all its worker threads; `jobs` is not used there). The
    cluster is reached here, before the first result is asked for, so a scheduler that cannot be
    reached raises BackendUnavailable at once.
    """
    tasks = [(t["run"], t["seed"]) for t in run_tasks(scenario, world, runs, seed)]
    tasks = [task for task in tasks if task[0] not in skip]
    if not tasks:
        return iter(())
    truth = simulate_truth(world)
    # A filterpy run takes a good part of a second: one task per run (progress and resume move
    # with every run); a fast-engine run takes milliseconds, so its tasks hold several runs.
    size = runs_per_task(len(tasks), jobs) if engine == "fast" and backend == "local" else 1
    calls = (
        delayed(run_chunk)(scenario, world, tasks[i : i + size], truth, engine)
        for i in range(0, len(tasks), size)
    )
    if backend == "dask":
        results = _run_on_dask(connect_dask(scheduler, connect_timeout_s), calls, scheduler)
    else:
        n_calls = math.ceil(len(tasks) / size)
        parallel = Parallel(n_jobs=min(jobs, n_calls), return_as="generator_unordered")
        results = parallel(calls)
    return _announce(results, on_result)


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


def _run_on_dask(client, calls: Iterable, scheduler: str | None) -> Iterator[dict]:
    """Run joblib calls on a Dask cluster, one task per run, yielding results as they finish."""
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    try:
        # batch_size=1: one Dask task per run, so the progress bar moves with every run.
        parallel = Parallel(
            backend=_cluster_backend(client), batch_size=1, return_as="generator_unordered"
        )
        yield from parallel(calls)
    except (concurrent.futures.CancelledError, CommClosedError, KilledWorker) as exc:
        # The cluster went away under us (an error inside a run keeps its own type).
        what = "its workers died" if isinstance(exc, KilledWorker) else "connection lost"
        raise BackendUnavailable(
            f"Dask cluster at {scheduler} failed during the batch ({what}); finished runs are"
            " saved: run the same command again to resume"
        ) from exc
    finally:
        client.close()


def _cluster_backend(client):
    """joblib's dask backend on `client`, never falling back to running in this process.

    joblib runs a batch sequentially in the calling process when the backend reports a single
    worker; a cluster of one single-threaded worker would then not be used at all.
    """
    from joblib._dask import DaskDistributedBackend

    class ClusterOnlyBackend(DaskDistributedBackend):
        def effective_n_jobs(self, n_jobs: int) -> int:
            return max(2, super().effective_n_jobs(n_jobs))

    return ClusterOnlyBackend(client=client)


def connect_dask(scheduler: str | None, timeout_s: float):
    """A `distributed.Client` on `scheduler` with at least one worker, or BackendUnavailable."""
    try:
        from distributed import Client
    except ImportError as exc:
        raise BackendUnavailable(
            'the dask backend needs dask[distributed]; install it with: pip install -e ".[dask]"'
        ) from exc
    if not scheduler:
        raise BackendUnavailable("the dask backend needs a scheduler address tcp://HOST:PORT")
    try:
        client = Client(scheduler, timeout=timeout_s, set_as_default=False)
    except Exception as exc:  # refused, timed out, not a Dask scheduler: all mean "not reachable"
        # distributed retries a refused connection until the timeout, then says "Timed out ...".
        reason = "no answer" if str(exc).startswith("Timed out") else _first_line(exc)
        raise BackendUnavailable(
            f"cannot reach Dask scheduler at {scheduler}: {reason} (timeout {timeout_s:g} s)"
        ) from exc
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except Exception as exc:
        client.close()
        raise BackendUnavailable(
            f"Dask scheduler at {scheduler} has no workers after {timeout_s:g} s;"
            f" start some with: dask worker {scheduler}"
        ) from exc
    return client


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
