"""Monte Carlo batches: one worker call per run, fanned out with joblib (benchopt style).

`run_one` is a top-level function taking plain keyword data and returning plain data; it mutates
nothing shared. Run i draws from `SeedSequence(seed).spawn(runs)[i]` only (SPEC 6), so results do
not depend on the number of workers or on the order in which runs finish. The same holds on a Dask
cluster (`backend="dask"`): joblib's dask backend ships the same calls to the cluster's workers.
"""

from __future__ import annotations

import concurrent.futures
import math
from collections.abc import Callable, Iterable, Iterator
from typing import Literal

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

from .config import Scenario, World
from .filters import FilterDiverged, RobotEKF, build_filter
from .metrics import nees, pose_errors, summarize_filter
from .simulation import RunData, simulate_run, simulate_truth

STEP_COLUMNS = [
    "scenario", "filter", "run", "step", "t",
    "x_true", "y_true", "phi_true", "x_est", "y_est", "phi_est",
    "P_xx", "P_xy", "P_xphi", "P_yy", "P_yphi", "P_phiphi",
    "pos_err", "heading_err", "nees",
    "R_rr", "R_bb", "Q_vv", "Q_gg", "diverged",
]  # fmt: skip
_P_INDEX = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def _healthy(flt: RobotEKF) -> bool:
    """x and P finite, P positive definite, the diagonals of R and Qu positive.

    Called after every scan that saw a landmark; on the 3 + 9 + 4 numbers it checks, plain
    floats cost a fraction of numpy's reductions (the same answer: math.isfinite and > 0 treat
    NaN as np.isfinite does).
    """
    if not all(map(math.isfinite, flt.x.ravel().tolist() + flt.P.ravel().tolist())):
        return False
    try:
        np.linalg.cholesky(flt.P)
    except np.linalg.LinAlgError:
        return False
    return all(v > 0 for v in flt.R.diagonal().tolist() + flt.Qu.diagonal().tolist())


def run_filter(flt: RobotEKF, data: RunData, world: World, record_every: int) -> dict:
    """Run one filter over one run's data; record every `record_every`-th control step.

    A filter that stops being finite and positive definite is marked diverged; its remaining
    records stay NaN and the caller goes on with the next filter.
    """
    K = len(data.u_odo)
    n = K // record_every
    x = np.full((n, 3), np.nan)
    P = np.full((n, 3, 3), np.nan)
    R = np.full((n, 2), np.nan)
    Qu = np.full((n, 2), np.nan)
    landmarks = world.landmarks
    every = world.sensor_every
    diverged = False
    j = 0
    try:
        for k in range(1, K + 1):
            flt.predict(data.u_odo[k - 1])
            if k % every == 0:
                scan = data.scans[k // every - 1]
                # Only updates (and the supervisor inside them) can break x, P, R or Qu: the
                # predict of a healthy filter stays healthy, so empty scans need no check.
                if len(scan.ids):
                    for lid, z in zip(scan.ids, scan.z, strict=True):
                        flt.update_landmark(z, landmarks[lid])
                    if not _healthy(flt):
                        raise FilterDiverged(f"step {k}")
            if k % record_every == 0:
                x[j] = flt.x
                P[j] = flt.P
                R[j] = flt.R[0, 0], flt.R[1, 1]
                Qu[j] = flt.Qu[0, 0], flt.Qu[1, 1]
                j += 1
        # Health is checked at scans; a blow-up in the predictions after the last one shows here.
        if not (np.isfinite(x).all() and np.isfinite(P).all()):
            raise FilterDiverged("non-finite estimate after the last scan")
    except (FilterDiverged, np.linalg.LinAlgError):
        diverged = True
        x[j:] = P[j:] = R[j:] = Qu[j:] = np.nan
    return {
        "x": x,
        "P": P,
        "R_diag": R,
        "Q_diag": Qu,
        "diverged": diverged,
        "nis_sum": flt.nis_sum,
        "n_updates": flt.n_updates,
        "n_rejected": flt.n_rejected,
    }


def recorded_steps(n_controls: int, record_every: int) -> np.ndarray:
    """The control steps a run records: every `record_every`-th, from the first such step."""
    return np.arange(record_every, n_controls + 1, record_every)


def simulate(scenario: Scenario, world: World, seed: np.random.SeedSequence) -> RunData:
    """One run's data, every draw from its own seed (SPEC 6)."""
    truth = simulate_truth(world)
    return simulate_run(world, truth, scenario.true_noise.radians(), np.random.default_rng(seed))


def add_trace_metrics(trace: dict, x_true: np.ndarray) -> dict:
    """Per-step pos_err, heading_err and NEES of a filter's trace, in bulk from its arrays."""
    e = pose_errors(x_true, trace["x"])
    trace["pos_err"] = np.hypot(e[:, 0], e[:, 1])
    trace["heading_err"] = np.abs(e[:, 2])
    trace["nees"] = _nees_where_finite(e, trace["P"])
    return trace


def run_one(scenario: Scenario, world: World, run: int, seed: np.random.SeedSequence) -> dict:
    """One Monte Carlo run: simulate once, feed the same data to every filter (CRN)."""
    data = simulate(scenario, world, seed)
    steps = recorded_steps(len(data.u_odo), scenario.record_every)
    x_true = data.truth.x[steps]
    filters = {
        spec.name: add_trace_metrics(
            run_filter(build_filter(spec, scenario, world), data, world, scenario.record_every),
            x_true,
        )
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


def _nees_where_finite(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    out = np.full(len(e), np.nan)
    ok = np.all(np.isfinite(P), axis=(1, 2)) & np.all(np.isfinite(e), axis=1)
    if ok.any():
        out[ok] = nees(e[ok], P[ok])
    return out


def run_tasks(scenario: Scenario, world: World, runs: int, seed: int) -> Iterator[dict]:
    """Plain keyword dicts, one per run: run i gets the i-th child of the root seed (SPEC 6)."""
    for i, child in enumerate(np.random.SeedSequence(seed).spawn(runs)):
        yield {"scenario": scenario, "world": world, "run": i, "seed": child}


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
) -> Iterator[dict]:
    """Run results as they finish (any order); `skip` leaves out runs already done.

    backend "local" uses `jobs` local processes; "dask" runs on the existing Dask cluster whose
    scheduler listens at `scheduler` (all its worker threads; `jobs` is not used there). The
    cluster is reached here, before the first result is asked for, so a scheduler that cannot be
    reached raises BackendUnavailable at once.
    """
    tasks = [t for t in run_tasks(scenario, world, runs, seed) if t["run"] not in skip]
    if not tasks:
        return iter(())
    calls = (delayed(run_one)(**task) for task in tasks)
    if backend == "dask":
        results = _run_on_dask(connect_dask(scheduler, connect_timeout_s), calls, scheduler)
    else:
        parallel = Parallel(n_jobs=min(jobs, len(tasks)), return_as="generator_unordered")
        results = parallel(calls)
    return _announce(results, on_result)


def _announce(results: Iterable[dict], on_result: Callable[[dict], None] | None) -> Iterator[dict]:
    for result in results:
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


def steps_frame(scenario_name: str, filter_names: list[str], results: list[dict]) -> pd.DataFrame:
    """The long table of steps.parquet: one row per (filter, run, recorded step)."""
    results = sorted(results, key=lambda r: r["run"])
    blocks = []
    for name in filter_names:
        for res in results:
            tr = res["filters"][name]
            n = len(res["step"])
            cols = {
                "run": np.full(n, res["run"], dtype=np.int32),
                "step": res["step"].astype(np.int32),
                "t": res["t"],
                "x_true": res["x_true"][:, 0],
                "y_true": res["x_true"][:, 1],
                "phi_true": res["x_true"][:, 2],
                "x_est": tr["x"][:, 0],
                "y_est": tr["x"][:, 1],
                "phi_est": tr["x"][:, 2],
            }
            for (i, j), col in zip(_P_INDEX, STEP_COLUMNS[11:17], strict=True):
                cols[col] = tr["P"][:, i, j]
            cols.update(
                pos_err=tr["pos_err"],
                heading_err=tr["heading_err"],
                nees=tr["nees"],
                R_rr=tr["R_diag"][:, 0],
                R_bb=tr["R_diag"][:, 1],
                Q_vv=tr["Q_diag"][:, 0],
                Q_gg=tr["Q_diag"][:, 1],
                diverged=np.full(n, tr["diverged"]),
            )
            block = pd.DataFrame(cols)
            block.insert(0, "filter", name)
            blocks.append(block)
    df = pd.concat(blocks, ignore_index=True)
    df.insert(0, "scenario", scenario_name)
    df["scenario"] = pd.Categorical(df["scenario"])
    df["filter"] = pd.Categorical(df["filter"], categories=filter_names)
    return df[STEP_COLUMNS]


def filter_arrays(steps: pd.DataFrame, name: str) -> dict[str, np.ndarray]:
    """(runs, steps) arrays of one filter's pos_err, heading_err, nees, R/Q and run ids."""
    sub = steps[steps["filter"] == name].sort_values(["run", "step"])
    runs = sub["run"].unique()
    n = len(sub) // max(len(runs), 1)
    out = {"run": runs, "step": sub["step"].to_numpy()[:n], "t": sub["t"].to_numpy()[:n]}
    for col in ("pos_err", "heading_err", "nees", "R_rr", "R_bb", "Q_vv", "Q_gg"):
        out[col] = sub[col].to_numpy().reshape(len(runs), n)
    out["diverged"] = sub["diverged"].to_numpy().reshape(len(runs), n)[:, 0]
    return out


def summary_records(steps: pd.DataFrame, update_stats: dict[str, dict] | None = None) -> list[dict]:
    """One summary record per filter, computed from the steps table alone (plus NIS totals)."""
    scenario = str(steps["scenario"].iloc[0])
    names = [str(n) for n in steps["filter"].cat.categories if (steps["filter"] == n).any()]
    records = []
    for name in names:
        a = filter_arrays(steps, name)
        rec = {"scenario": scenario, "filter": name}
        rec.update(summarize_filter(a["pos_err"], a["heading_err"], a["nees"], a["diverged"]))
        if update_stats and name in update_stats:
            rec.update(update_stats[name])
        records.append(rec)
    return records


def update_statistics(results: list[dict], filter_names: list[str]) -> dict[str, dict]:
    """Average NIS per accepted update and share of measurements the gate rejected."""
    results = sorted(results, key=lambda r: r["run"])  # a float sum depends on its order
    stats = {}
    for name in filter_names:
        traces = [r["filters"][name] for r in results if not r["filters"][name]["diverged"]]
        nis = sum(t["nis_sum"] for t in traces)
        used = sum(t["n_updates"] for t in traces)
        rejected = sum(t["n_rejected"] for t in traces)
        seen = used + rejected
        stats[name] = {
            "anis": nis / used if used else float("nan"),
            "gate_rejected": rejected / seen if seen else float("nan"),
        }
    return stats
