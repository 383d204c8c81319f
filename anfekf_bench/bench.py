"""`anfekf bench`: what the harness costs over filterpy, what the ANFIS costs, what workers buy.

Figures, all taken in one process unless said otherwise. Timings are medians of repeats; the
sides of a ratio are timed back to back in every repeat and the ratio is the median of the
per-repeat ratios (`paired_ratio`), so load from elsewhere on the machine hits both sides alike:

- per-step cost of a bare filterpy EKF loop against the same EKF inside the harness
  (`runner.run_filter` plus the metrics `runner.run_one` computes); simulation excluded from both
  (the run is simulated once and its `RunData` reused): `overhead_ratio`;
- ANFEKF (adapt R) against EKF per-step cost, both through the harness on the same data;
- one Monte Carlo batch with 1 and with 2 joblib workers: `speedup_2_workers`;
- every scenario file of the configs folder (the paper's four, 50 runs each) run end to end by
  `experiment.execute` in a subprocess of its own: wall time, peak memory (see `scenario_probe`)
  and the size of its steps.parquet.

The fast engine against the filterpy engine (SPEC 11, issue 14), on the same data in one process:

- per-control-step cost of each filter kind (EKF, ANFEKF adapting R, Q and RQ) on both engines
  (`filterpy_engine.run_filter` and `fast.run_filter_fast`, engine calls only: filters and
  contexts are built outside the timed call, no metrics) and their paired ratio fast / filterpy;
  flattening the run's scans into arrays (once per run, shared by its filters) is timed apart;
- compile time apart: numba compiling every kernel from scratch, and loading them from its
  on-disk cache, each in a fresh interpreter (full sizes only);
- end to end with the fast engine (kernels warmed in this process and in the workers first, so
  compile is excluded): the step scenario's runs through `experiment.execute` on 2 workers, its
  summaries compared with those of the filterpy run of the same file; and a sweep-sized batch,
  10 cells x 30 runs x 5 filters = 1500 filter-runs, summaries only (no steps.parquet);
- the whole command `anfekf run <step scenario> --engine fast --jobs 2` from a fresh interpreter
  (imports and the workers' start included, the kernels in numba's cache): `fast_e2e_cli_s`.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import datetime, timezone
from functools import partial
from pathlib import Path

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from rich.table import Table

from .analysis.metrics import add_trace_metrics, recorded_steps
from .bench_figures import DEFINITIONS, TARGETS
from .breakdown import (
    breakdown_rows,
    compiled_signatures,
    first_run_compiles,
    make_zoo_wall,
    paper_breakdown,
)
from .config import Scenario, World, parse_scenario, scenario_files
from .engines.filterpy_engine import run_filter
from .experiment import execute, machine_info, make_plan, package_versions
from .filters import ANFEKFSpec, EKFSpec, FilterContext, FilterSpec, RobotEKF, build_filter
from .filters.context import filter_context
from .models import H_jacobian, f, h, jacobians, residual_z
from .runner import run_batch, simulate
from .scenarios import load_scenario
from .sources.simulator import RunData
from .storage import STEPS_FILE, output_path_problem, write_json
from .workers import local_workers

# Per-step figures use the correct-noise scenario: there the gate accepts (nearly) every
# measurement for both filters, so the bare loop (no gate) and the harness do the same updates.
STEP_SCENARIO = "correct.yaml"
BATCH_SCENARIO = "wrong_r.yaml"
# The fast engine end to end: the step scenario (four filters) as a whole, and the base of the
# sweep-sized batch (its filter_noise.sigma_range scaled per cell, like a one-axis sweep).
E2E_SCENARIO = STEP_SCENARIO
SWEEP_BASE = BATCH_SCENARIO
MIB = 2**20

# The filter kinds timed on both engines: every built-in kind the fast engine runs, read from
# the registry (each `adapt` mode of a family that has one), with defaults; the banks with a 3 x 3
# grid (their cost grows with the grid; on filterpy the default 125 members take seconds a run).
# Kinds fitted on training runs are the plain EKF with other noise (timed as `ekf`), but for
# `kalmannet`: a network of the default size with seeded random weights (no training, no torch:
# its cost does not depend on the weights' values).
SMALL_BANK = {"qu_factors": [0.1, 1.0, 10.0], "range_factors": [0.1, 1.0, 10.0],
              "bearing_factors": [1.0]}  # fmt: skip


def engine_kinds() -> dict[str, FilterSpec]:
    """label -> spec of every built-in kind (and mode) the fast engine implements."""
    from .engines import fast
    from .filters.registry import SPEC_BY_KIND

    out: dict[str, FilterSpec] = {}
    for kind, cls in SPEC_BY_KIND.items():
        if cls.role == "trained":  # seeded random weights: the per-step cost is the same
            spec = bench_kalmannet()
            if fast.supports(spec):
                out[kind] = spec
            continue
        if cls.fitted_on_training or cls.user_defined or cls.role == "oracle":
            continue
        adapt = cls.model_fields.get("adapt")
        modes = list(adapt.annotation.__args__) if adapt is not None else [None]
        for mode in modes:
            params = {"name": kind, "kind": kind}
            if mode is not None:
                params["adapt"] = mode
            if "qu_factors" in cls.model_fields and not cls.default_filter:  # a bank: the small one
                params.update(SMALL_BANK)
            spec = cls.model_validate(params)
            if fast.supports(spec):
                out[kind if mode is None else f"{kind}_{mode}"] = spec
    return out


def default_step_cost(engine_us: dict[str, dict[str, float]]) -> float | None:
    """The default filter's per-step time over the EKF's on the fast engine (None: no such
    kind timed)."""
    from .filters.registry import SPEC_BY_KIND, kinds_with_role

    kinds = [k for k, cls in SPEC_BY_KIND.items() if cls.default_filter and k in engine_us]
    (ekf,) = kinds_with_role("reference")
    if not kinds or ekf not in engine_us:
        return None
    return max(engine_us[k]["fast"] for k in kinds) / engine_us[ekf]["fast"]


def bench_kalmannet(seed: int = 0) -> FilterSpec:
    """`kalmannet` with the default hidden size and seeded random weights (KalmanNetWeights.random),
    built without PyTorch (model_construct skips the check that it is installed)."""
    from .filters.kalmannet import KalmanNetSpec, KalmanNetWeights

    hidden = KalmanNetSpec.model_fields["hidden_size"].default
    spec = KalmanNetSpec.model_construct(name="kalmannet", kind="kalmannet", hidden_size=hidden)
    return spec.with_weights(KalmanNetWeights.random(hidden_size=hidden, seed=seed))


ENGINE_KINDS: dict[str, FilterSpec] = engine_kinds()
# The sweep-sized batch's five filters (all run by the fast engine).
SWEEP_FILTERS = [
    {"name": "ekf", "kind": "ekf"},
    {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
    {"name": "anfekf-q", "kind": "anfekf", "adapt": "Q"},
    {"name": "anfekf-rq", "kind": "anfekf", "adapt": "RQ"},
    {"name": "ekf-oracle", "kind": "ekf-oracle"},
]


class BenchError(Exception):
    """The bench cannot run with what it was given; `str()` is the one-line message for the user."""


@dataclasses.dataclass(frozen=True)
class BenchSizes:
    """How much to measure. FULL is the real measurement; QUICK only exercises the machinery."""

    repeats: int = 25  # per-step timing repeats (each times bare EKF, EKF, ANFEKF once)
    batch_runs: int = 20  # runs in the 1-worker / 2-worker batch
    batch_repeats: int = 3
    scenario_runs: int | None = None  # None: each scenario file's own runs (50)
    waypoints: int | None = None  # None: the full route; n: only its first n waypoints
    fast_inner: int = 10  # fast-engine passes per timed call (one pass takes about a millisecond)
    compile_probe: bool = True  # time numba's compile and cache load in fresh interpreters
    e2e_jobs: int = 2  # workers of the fast end-to-end figures
    sweep_cells: int = 10  # the sweep-sized batch: cells x runs x 5 filters
    sweep_runs: int = 30
    cli_repeats: int = 3  # `anfekf run --engine fast` of the step scenario from a fresh process
    zoo: bool = True  # `make zoo`'s two commands timed (the configs folder's zoo/, when it has one)


FULL = BenchSizes()
QUICK = BenchSizes(
    repeats=2, batch_runs=2, batch_repeats=1, scenario_runs=2, waypoints=3, fast_inner=2,
    compile_probe=False, e2e_jobs=1, sweep_cells=2, sweep_runs=2, cli_repeats=0, zoo=False,
)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# The bare filterpy loop and the harness pass


class BareEKF(ExtendedKalmanFilter):
    """filterpy's EKF with only the motion model plugged in (filterpy's documented way:
    override `predict_x`); no gate, no health check, no symmetrisation, nothing recorded."""

    def __init__(self, x0: np.ndarray, P0: np.ndarray, R: np.ndarray, T: float, B: float):
        super().__init__(dim_x=3, dim_z=2)
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        self.R = np.array(R, dtype=float)
        self.T = T
        self.B = B

    def predict_x(self, u=0):
        self.x = f(self.x, u, self.T, self.B)


def bare_ekf_loop(flt: BareEKF, data: RunData, world: World, Qu: np.ndarray) -> None:
    """Predict at every control step and update per landmark seen: the same F, G, Q = G Qu G^T,
    h, H and residual as RobotEKF, called the plain filterpy way."""
    T, B = world.T, world.B
    landmarks = world.landmarks
    every = world.sensor_every
    scans = data.scans
    for k, u in enumerate(data.u_odo, start=1):
        flt.F, G = jacobians(flt.x, u, T, B)
        flt.Q = G @ Qu @ G.T
        flt.predict(u)
        if k % every == 0:
            scan = scans[k // every - 1]
            for lid, z in zip(scan.ids, scan.z, strict=True):
                lm = landmarks[lid]
                flt.update(z, H_jacobian, h, args=(lm,), hx_args=(lm,), residual=residual_z)


def harness_pass(
    flt: RobotEKF, data: RunData, world: World, record_every: int, x_true: np.ndarray
) -> dict:
    """One filter as `runner.run_one` runs it: `run_filter`, then the per-run metrics."""
    return add_trace_metrics(run_filter(flt, data, world, record_every), x_true)


@dataclasses.dataclass(frozen=True)
class StepSetup:
    """One simulated run (run 0 of the scenario's seed) and what the three filters need."""

    scenario: Scenario
    world: World
    data: RunData
    x_true: np.ndarray  # truth at the recorded steps

    @property
    def control_steps(self) -> int:
        return len(self.data.u_odo)

    def ekf(self) -> RobotEKF:
        return self._build(EKFSpec(name="ekf"))

    def anfekf(self) -> RobotEKF:
        return self._build(ANFEKFSpec(name="anfekf", kind="anfekf", adapt="R"))

    def bare(self) -> BareEKF:
        ref = self.ekf()  # same x0, P0, R and Qu as the harness's EKF
        return BareEKF(ref.x, ref.P, ref.R, self.world.T, self.world.B)

    def bare_Qu(self) -> np.ndarray:
        return self.ekf().Qu

    def _build(self, spec) -> RobotEKF:
        return build_filter(spec, self.scenario, self.world)

    def context(self, spec: FilterSpec) -> FilterContext:
        """What the fast engine starts from: the context `build_filter` builds this spec from
        (not read back from a built filter: a bank's R and Qu are its mixture's, not its start)."""
        return filter_context(spec, self.scenario, self.world)


def step_setup(scenario: Scenario, world: World) -> StepSetup:
    """Simulate once; every timed filter pass reuses these data (simulation is not timed)."""
    data = simulate(scenario, world, np.random.SeedSequence(scenario.seed).spawn(1)[0])
    steps = recorded_steps(len(data.u_odo), scenario.record_every)
    return StepSetup(scenario=scenario, world=world, data=data, x_true=data.truth.x[steps])


def _timed(fn: Callable[[], object]) -> float:
    """Seconds one call takes, with the garbage collector off as timeit does."""
    gc_was_on = gc.isenabled()
    gc.disable()
    try:
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0
    finally:
        if gc_was_on:
            gc.enable()


def time_step_costs(setup: StepSetup, repeats: int) -> dict[str, list[float]]:
    """Seconds per pass of the bare EKF, the harness EKF and the harness ANFEKF, `repeats` each.

    The three are interleaved within each repeat; filters are built outside the timed call.
    """
    world, every = setup.world, setup.scenario.record_every
    times: dict[str, list[float]] = {"bare": [], "ekf": [], "anfekf": []}
    Qu = setup.bare_Qu()
    for _ in range(repeats):
        passes = {
            "bare": partial(bare_ekf_loop, setup.bare(), setup.data, world, Qu),
            "ekf": partial(harness_pass, setup.ekf(), setup.data, world, every, setup.x_true),
            "anfekf": partial(harness_pass, setup.anfekf(), setup.data, world, every, setup.x_true),
        }
        for name, one_pass in passes.items():
            times[name].append(_timed(one_pass))
    return times


def paired_ratio(a: list[float], b: list[float]) -> float:
    """Median over repeats of a_i / b_i: each pair was timed back to back, so a load spike from
    elsewhere on the machine mostly hits both sides of one pair (more robust than a ratio of
    medians when the machine is shared)."""
    return statistics.median(x / y for x, y in zip(a, b, strict=True))


def update_counts(setup: StepSetup) -> dict[str, dict[str, int]]:
    """Measurements each harness filter fused and rejected on the timed run (the work done)."""
    out = {}
    for name, flt in (("ekf", setup.ekf()), ("anfekf", setup.anfekf())):
        harness_pass(flt, setup.data, setup.world, setup.scenario.record_every, setup.x_true)
        out[name] = {"fused": flt.n_updates, "rejected": flt.n_rejected}
    return out


# ---------------------------------------------------------------------------------------------
# The fast engine against the filterpy engine, per step


def _fast_passes(spec: FilterSpec, ctx: FilterContext, setup: StepSetup, n: int) -> None:
    """`n` fast-engine passes over the run, its timeline already made (a run's filters share
    it; `time_scan_flattening` times it)."""
    # Imported here: the scenario probes import this module, and numba would weigh on their
    # peak memory.
    from .engines import fast

    every = setup.scenario.record_every
    for _ in range(n):
        fast.run_filter_fast(spec, ctx, setup.data, setup.world, every)


def time_engine_costs(
    setup: StepSetup, repeats: int, inner: int, kinds: dict[str, FilterSpec] | None = None
) -> dict[str, dict[str, list]]:
    """Seconds per pass of each filter kind (`kinds`, by default ENGINE_KINDS) on the filterpy
    and on the fast engine.

    Within each repeat every kind is timed on filterpy and then on the fast engine, back to back
    (the fast side as the mean of `inner` passes); filters, contexts and the flattened scans are
    made outside.
    """
    from .engines import fast

    every = setup.scenario.record_every
    kinds = ENGINE_KINDS if kinds is None else kinds
    times = {kind: {"filterpy": [], "fast": []} for kind in kinds}
    for _ in range(repeats):
        for kind, spec in kinds.items():
            flt = setup._build(spec)
            times[kind]["filterpy"].append(
                _timed(partial(run_filter, flt, setup.data, setup.world, every))
            )
            ctx = setup.context(spec)
            fast.from_run(setup.data, setup.world, every)  # kept for the passes (once per run)
            times[kind]["fast"].append(
                _timed(partial(_fast_passes, spec, ctx, setup, inner)) / inner
            )
    return times


def time_scan_flattening(setup: StepSetup, repeats: int) -> list[float]:
    """Seconds spent turning the run into its timeline (`timeline.from_run`, what both engines
    read; made once per run), `repeats` times."""
    from .engines import fast

    def flatten() -> None:
        fast.clear_cache()
        fast.from_run(setup.data, setup.world, setup.scenario.record_every)

    out = [_timed(flatten) for _ in range(repeats)]
    fast.clear_cache()
    return out


def engine_agreement(
    setup: StepSetup, kinds: dict[str, FilterSpec] | None = None
) -> tuple[dict[str, dict], float]:
    """Each kind (`kinds`, by default ENGINE_KINDS) once on both engines: their counts (which
    must be equal) and the largest |fast - filterpy| of x, P, R_diag and Q_diag."""
    from .engines import fast

    every = setup.scenario.record_every
    counts, worst = {}, 0.0
    for kind, spec in (ENGINE_KINDS if kinds is None else kinds).items():
        ref = run_filter(setup._build(spec), setup.data, setup.world, every)
        out = fast.run_filter_fast(spec, setup.context(spec), setup.data, setup.world, every)
        keys = ("n_updates", "n_rejected", "diverged")
        if any(ref[k] != out[k] for k in keys):
            raise BenchError(
                f"{kind}: the fast engine's counts differ from filterpy's:"
                f" {[ref[k] for k in keys]} vs {[out[k] for k in keys]}"
            )
        counts[kind] = {"fused": out["n_updates"], "rejected": out["n_rejected"]}
        for key in ("x", "P", "R_diag", "Q_diag"):
            d = np.abs(ref[key] - out[key])
            if np.isfinite(d).any():
                worst = max(worst, float(np.nanmax(d)))
    return counts, worst


def engine_figures(
    times: dict[str, dict[str, list]], prep: list[float], K: int
) -> dict[str, dict[str, float]]:
    """Per kind: median us per step on each engine, the paired ratio fast / filterpy, and that
    ratio with the run's whole scan flattening charged to this one filter."""
    prep_s = statistics.median(prep)
    out = {}
    for kind, t in times.items():
        fp, fa = statistics.median(t["filterpy"]), statistics.median(t["fast"])
        out[kind] = {
            "filterpy": fp / K * 1e6,
            "fast": fa / K * 1e6,
            "ratio": paired_ratio(t["fast"], t["filterpy"]),
            "ratio_with_prep": (fa + prep_s) / fp,
        }
    return out


_COMPILE_CODE = (
    "import json, time\n"
    "from anfekf_bench.engines import fast\n"
    "print(json.dumps({'jit': fast.JIT, 'warm_up_s': fast.warm_up()}))\n"
)


def compile_probe(cache_dir: Path) -> dict:
    """numba compiling every kernel into an empty on-disk cache, then a second fresh interpreter
    loading them from it: {"compile_s", "cache_load_s", "signatures"} (None without numba;
    signatures: `breakdown.compiled_signatures` of the compile)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    out = []
    for _ in range(2):
        proc = subprocess.run(
            [sys.executable, "-c", _COMPILE_CODE], capture_output=True, text=True, env=env,
            check=False,
        )  # fmt: skip
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            raise BenchError(f"fast-engine compile probe failed: {tail}")
        out.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    if not out[0]["jit"]:
        return {"compile_s": None, "cache_load_s": None, "signatures": None}
    return {
        "compile_s": out[0]["warm_up_s"], "cache_load_s": out[1]["warm_up_s"],
        "signatures": compiled_signatures(cache_dir),
    }  # fmt: skip


# ---------------------------------------------------------------------------------------------
# The fast engine end to end


def _warm_worker() -> int:
    """In a worker: load (or compile) the fast engine's kernels; its process id."""
    from .engines import fast

    fast.warm_up()
    return os.getpid()


def warm_workers(jobs: int) -> set[int]:
    """Start the pool of `jobs` workers that batches use (`runner.local_workers`: joblib keeps
    one reusable pool per configuration, so warming any other would start a second one) and
    load the fast engine in each, so that the timed batches exclude compile and cache loading.
    Returns the workers' process ids."""
    seen: set[int] = set()
    if jobs <= 1:
        return seen
    from joblib import Parallel, delayed

    with local_workers():
        for _ in range(10):
            seen |= set(Parallel(n_jobs=jobs)(delayed(_warm_worker)() for _ in range(2 * jobs)))
            if len(seen) >= jobs:
                break
    return seen


def sweep_cells(base: Scenario, cells: int, runs: int) -> list[Scenario]:
    """A one-axis sweep's cells: the base scenario with five filters, summaries only, the fast
    engine, and its assumed range noise scaled by factors from 0.25 to 4 (one per cell)."""
    doc = base.model_dump(mode="json")
    doc.update(runs=runs, steps_table=False, engine="fast", filters=SWEEP_FILTERS)
    for key in ("claims", "compare"):  # they name the base's filters
        if key in doc:
            doc[key] = []
    out = []
    for i, factor in enumerate(np.geomspace(0.25, 4.0, cells)):
        cell = json.loads(json.dumps(doc))
        cell["name"] = f"{base.name}-cell{i}"
        cell["filter_noise"]["sigma_range"] = base.filter_noise.sigma_range * float(factor)
        out.append(parse_scenario(cell, f"<{base.name} cell {i}>"))
    return out


def _timed_execute(scenario: Scenario, world: World, out_dir: Path, runs: int | None, jobs: int):
    """(wall seconds, summary records) of one `experiment.execute` on the fast engine."""
    plan = make_plan(scenario, world, runs, None, jobs, engine="fast")
    t0 = time.perf_counter()
    records, _ = execute(plan, out_dir, force=True)
    return time.perf_counter() - t0, records


def summary_max_rel_diff(a: list[dict], b: list[dict]) -> float:
    """Largest relative difference of a numeric summary figure between two engines' summaries
    of the same runs (inf when a filter, a figure or a NaN is in one only)."""
    by_name = {r["filter"]: r for r in b}
    if set(by_name) != {r["filter"] for r in a}:
        return float("inf")
    worst = 0.0
    for ra in a:
        rb = by_name[ra["filter"]]
        for key, va in ra.items():
            vb = rb.get(key)
            if isinstance(va, bool) or not isinstance(va, (int, float)):
                continue
            if not isinstance(vb, (int, float)):
                return float("inf")
            if np.isnan(va) or np.isnan(vb):
                if not (np.isnan(va) and np.isnan(vb)):
                    return float("inf")
                continue
            scale = max(abs(va), abs(vb))
            worst = max(worst, abs(va - vb) / scale if scale > 0 else 0.0)
    return worst


def fast_end_to_end(configs: Path, sizes: BenchSizes, tmp: Path, say) -> dict:
    """The step scenario on the fast engine and the sweep-sized batch, workers warmed first."""
    from .engines import fast

    scenario, world = load_scenario(configs / E2E_SCENARIO)
    world = trimmed(world, sizes.waypoints)
    base, base_world = load_scenario(configs / SWEEP_BASE)
    base_world = trimmed(base_world, sizes.waypoints)
    cells = sweep_cells(base, sizes.sweep_cells, sizes.sweep_runs)
    fast.warm_up()
    warm_workers(sizes.e2e_jobs)
    runs = scenario.runs if sizes.scenario_runs is None else sizes.scenario_runs
    say(f"fast engine end to end: {scenario.name}, {runs} runs on {sizes.e2e_jobs} workers")
    wall, records = _timed_execute(
        scenario, world, tmp / "e2e", sizes.scenario_runs, sizes.e2e_jobs
    )
    n = sizes.sweep_cells * sizes.sweep_runs * len(SWEEP_FILTERS)
    say(f"fast engine sweep-sized batch: {sizes.sweep_cells} cells x {sizes.sweep_runs} runs x"
        f" {len(SWEEP_FILTERS)} filters = {n} filter-runs, summaries only")  # fmt: skip
    cell_walls = [
        _timed_execute(cell, base_world, tmp / "sweep", None, sizes.e2e_jobs)[0] for cell in cells
    ]
    _shutdown_workers()
    cli_walls = []
    if sizes.cli_repeats:
        say(f"anfekf run {E2E_SCENARIO} --engine fast from a fresh process, {sizes.cli_repeats}x")
        cli_walls = time_cli_runs(configs / E2E_SCENARIO, tmp / "cli", sizes.cli_repeats)
    return {
        "scenario": scenario.name,
        "cli_wall_s": cli_walls,
        "runs": runs,
        "jobs": sizes.e2e_jobs,
        "wall_s": wall,
        "summary": records,
        "sweep": {
            "base": base.name,
            "cells": sizes.sweep_cells,
            "runs": sizes.sweep_runs,
            "filters": len(SWEEP_FILTERS),
            "filter_runs": n,
            "cell_wall_s": cell_walls,
            "wall_s": sum(cell_walls),
        },
    }


CLI_TIMEOUT_S = 600.0  # a 50-run fast-engine command takes seconds; this only stops a hang
_CLI_CODE = "import sys\nfrom anfekf_bench.cli import main\nsys.argv[0] = 'anfekf'\nmain()\n"


def time_cli_runs(path: Path, out_dir: Path, repeats: int) -> list[float]:
    """Wall seconds of `anfekf run path --engine fast --jobs 2`, each in a fresh interpreter (the
    kernels are in numba's on-disk cache by now: this process loaded or compiled them)."""
    args = ["run", str(path), "--engine", "fast", "--jobs", "2", "--out", str(out_dir), "--force"]
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(
                [sys.executable, "-c", _CLI_CODE, *args],
                capture_output=True, text=True, check=False, timeout=CLI_TIMEOUT_S,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            raise BenchError(
                f"{path}: anfekf run took more than {CLI_TIMEOUT_S:g} s in the bench subprocess"
            ) from None
        walls.append(time.perf_counter() - t0)
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            raise BenchError(f"{path}: anfekf run failed in the bench subprocess: {tail}")
    return walls


# ---------------------------------------------------------------------------------------------
# Workers


def time_batch(scenario: Scenario, world: World, runs: int, jobs: int) -> float:
    """Wall seconds of one `run_batch` of `runs` runs on `jobs` joblib workers."""
    t0 = time.perf_counter()
    n = sum(1 for _ in run_batch(scenario, world, runs=runs, seed=scenario.seed, jobs=jobs))
    elapsed = time.perf_counter() - t0
    if n != runs:
        raise RuntimeError(f"run_batch returned {n} of {runs} runs")
    return elapsed


def time_batches(scenario: Scenario, world: World, runs: int, repeats: int) -> dict[str, list]:
    """1-worker and 2-worker batches on the same tasks, interleaved, after warming the pool.

    joblib's loky executor is reused between calls; a 2-run batch first starts both workers and
    imports the package in them, so the timed 2-worker batches do not pay start-up.
    """
    time_batch(scenario, world, 2, 2)
    out: dict[str, list] = {"jobs_1": [], "jobs_2": []}
    for _ in range(repeats):
        out["jobs_1"].append(time_batch(scenario, world, runs, 1))
        out["jobs_2"].append(time_batch(scenario, world, runs, 2))
    return out


def _shutdown_workers() -> None:
    """Stop joblib's reusable loky workers (idle workers would otherwise linger for minutes)."""
    from joblib.externals.loky import get_reusable_executor

    get_reusable_executor().shutdown(wait=True)


# ---------------------------------------------------------------------------------------------
# Scenarios end to end, each in a subprocess


def trimmed(world: World, waypoints: int | None) -> World:
    """The world with only its first `waypoints` waypoints (quick mode), or unchanged."""
    if waypoints is None:
        return world
    return dataclasses.replace(world, waypoints=world.waypoints[:waypoints])


def _peak_rss_mb(pid: int | str = "self") -> float:
    """VmHWM of a live process: its own peak resident set since its last exec, in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024  # kB
    raise OSError(f"/proc/{pid}/status: no VmHWM line")


def _child_pids() -> list[int]:
    """PIDs of this process's live children (loky's workers and its resource tracker)."""
    me, pids = os.getpid(), []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:  # gone meanwhile
            continue
        # the command name in parentheses may hold spaces: fields after the last ')'
        if int(stat.rsplit(")", 1)[1].split()[1]) == me:
            pids.append(int(entry.name))
    return pids


def scenario_probe(path: str, out_dir: str, runs: int | None, waypoints: int | None) -> dict:
    """Run one scenario file with `experiment.execute` (its own jobs); meant for a fresh process.

    Peak memory is read from /proc (Linux) while joblib's loky workers are still alive: VmHWM of
    this process (it gathers the runs and builds the tables) and of each child. ru_maxrss of
    RUSAGE_CHILDREN would not do: Linux carries a forked child's pre-exec high-water mark (the
    parent's size at fork) through exec. `peak_rss_mb` is the sum of the peaks: an upper bound on
    what the processes held at one time (shared library pages are counted once per process).
    """
    scenario, world = load_scenario(path)
    plan = make_plan(scenario, trimmed(world, waypoints), runs, None, None)
    t0 = time.perf_counter()
    records, target = execute(plan, Path(out_dir), force=True)
    wall = time.perf_counter() - t0
    children = {}
    for pid in _child_pids():
        try:
            children[pid] = _peak_rss_mb(pid)
        except OSError:
            continue
    main_mb = _peak_rss_mb()
    _shutdown_workers()
    return {
        "name": plan.name,
        "runs": plan.runs,
        "jobs": plan.jobs,
        "wall_time_s": wall,
        "peak_rss_main_mb": main_mb,
        "peak_rss_children_mb": sorted(children.values(), reverse=True),
        "peak_rss_mb": main_mb + sum(children.values()),
        "steps_parquet_mb": (target / STEPS_FILE).stat().st_size / MIB,
        "engine": plan.engine,
        "summary": records,  # compared with the fast engine's (run_bench drops it from the JSON)
    }


_PROBE_CODE = (
    "import json, sys\n"
    "from anfekf_bench.bench import scenario_probe\n"
    "print(json.dumps(scenario_probe(*json.loads(sys.argv[1]))))\n"
)


def probe_in_subprocess(path: Path, out_dir: Path, runs: int | None, waypoints: int | None) -> dict:
    """`scenario_probe` in a fresh interpreter, so its peak memory is this scenario's alone."""
    args = json.dumps([str(path), str(out_dir), runs, waypoints])
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE_CODE, args], capture_output=True, text=True, check=False
    )
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise BenchError(f"{path}: scenario run failed in the bench subprocess: {tail}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------------
# The report


def targets_met(report: dict) -> dict[str, dict]:
    """Each target: its text, the measured value and whether it is met."""
    out = {}
    for key, (op, limit, unit) in TARGETS.items():
        value = report[key]
        if value is None:
            met = False
        else:
            met = value <= limit if op == "<=" else value >= limit
        out[key] = {"target": f"{op} {limit:g} {unit}".strip(), "value": value, "met": bool(met)}
    return out


def check_inputs(configs: Path, out: Path) -> list[Path]:
    """Fail fast, before minutes of measuring: the scenario files and a writable output file."""
    if not configs.is_dir():
        raise BenchError(f"{configs}: --configs must be a folder of scenario YAML files")
    for name in (STEP_SCENARIO, BATCH_SCENARIO):
        if not (configs / name).is_file():
            raise BenchError(f"{configs}: holds no {name}; the bench needs the paper's scenarios")
    problem = output_path_problem(out, folder=False)
    if problem:
        raise BenchError(f"{out}: {problem}")
    files = scenario_files(configs)
    for path in files:  # a bad file fails now (ScenarioError), not after minutes of timing
        load_scenario(path)
    return files


def run_bench(
    configs: Path,
    out: Path,
    sizes: BenchSizes = FULL,
    say: Callable[[str], None] = lambda _: None,
) -> dict:
    """Measure everything, write `out` (JSON, atomically) and return the report."""
    from .engines import fast

    configs, out = Path(configs), Path(out)
    files = check_inputs(configs, out)
    started = time.time()
    load_before = os.getloadavg()
    scenario, world = load_scenario(configs / STEP_SCENARIO)
    setup = step_setup(scenario, trimmed(world, sizes.waypoints))
    K = setup.control_steps
    say(f"per-step cost: bare EKF, EKF, ANFEKF over {K} control steps, {sizes.repeats} repeats")
    step_s = time_step_costs(setup, sizes.repeats)
    bare_us, ekf_us, anf_us = (
        statistics.median(step_s[k]) / K * 1e6 for k in ("bare", "ekf", "anfekf")
    )

    say("fast engine: kernels compiled or loaded from numba's cache")
    fast_warm_up_s = fast.warm_up()
    counts, fast_diff = engine_agreement(setup)
    kinds = ", ".join(ENGINE_KINDS)
    say(f"per-step cost on filterpy and fast engines: {kinds}; {sizes.repeats} repeats")
    engine_s = time_engine_costs(setup, sizes.repeats, sizes.fast_inner)
    prep_s = time_scan_flattening(setup, max(sizes.repeats, 5))
    engine_us = engine_figures(engine_s, prep_s, K)
    compiled = {"compile_s": None, "cache_load_s": None, "signatures": None}
    first_run = None
    zoo = configs / "zoo"
    if sizes.compile_probe and fast.JIT:
        say("fast engine: numba compile and cache load, each in a fresh interpreter")
        with tempfile.TemporaryDirectory(prefix="anfekf-numba-") as cache_dir:
            compiled = compile_probe(Path(cache_dir))
            say("first runs after the warm-up: what numba still compiles")
            folders = [configs, *([zoo] if zoo.is_dir() else [])]
            first_run = first_run_compiles(Path(cache_dir), folders, Path(cache_dir) / "out")

    say(f"batch of {sizes.batch_runs} runs on 1 and on 2 workers, {sizes.batch_repeats} repeats")
    batch_scenario, batch_world = load_scenario(configs / BATCH_SCENARIO)
    batch_world = trimmed(batch_world, sizes.waypoints)
    batch_s = time_batches(batch_scenario, batch_world, sizes.batch_runs, sizes.batch_repeats)
    _shutdown_workers()
    t1, t2 = statistics.median(batch_s["jobs_1"]), statistics.median(batch_s["jobs_2"])

    scenarios = {}
    with tempfile.TemporaryDirectory(prefix="anfekf-bench-") as tmp:
        for path in files:
            say(f"scenario {path.name} end to end in a subprocess")
            res = probe_in_subprocess(path, Path(tmp), sizes.scenario_runs, sizes.waypoints)
            scenarios[res.pop("name")] = res
        e2e = fast_end_to_end(configs, sizes, Path(tmp), say)
        trim = partial(trimmed, waypoints=sizes.waypoints)
        breakdown = paper_breakdown(files, Path(tmp), sizes.scenario_runs, say, trim)
        make_zoo = None
        if sizes.zoo and zoo.is_dir():
            say(f"make zoo: anfekf run {zoo} and anfekf report, each in a fresh process")
            make_zoo = make_zoo_wall(zoo, Path(tmp))
    reference = scenarios[e2e["scenario"]]
    summary_diff = None  # no filterpy reference when the file itself asks for the fast engine
    if reference["engine"] == "filterpy":
        summary_diff = summary_max_rel_diff(reference["summary"], e2e.pop("summary"))
    e2e.pop("summary", None)
    for res in scenarios.values():
        res.pop("summary", None)
    walls = {name: r["wall_time_s"] for name, r in scenarios.items()}
    walls["total"] = sum(walls.values())

    report = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "quick": sizes != FULL,
        "sizes": dataclasses.asdict(sizes),
        "step_scenario": scenario.name,
        "control_steps": K,
        "measurements": int(sum(len(s.ids) for s in setup.data.scans)),
        "updates": update_counts(setup),
        "ekf_bare_step_us": bare_us,
        "ekf_harness_step_us": ekf_us,
        "overhead_ratio": paired_ratio(step_s["ekf"], step_s["bare"]),
        "anfekf_step_us": anf_us,
        "anfekf_over_ekf_step_cost": paired_ratio(step_s["anfekf"], step_s["ekf"]),
        "batch_scenario": batch_scenario.name,
        "batch_runs": sizes.batch_runs,
        "batch_1_worker_s": t1,
        "batch_2_workers_s": t2,
        "speedup_2_workers": paired_ratio(batch_s["jobs_1"], batch_s["jobs_2"]),
        "fast_jit": fast.JIT,
        "engine_step_us": engine_us,
        "engine_updates": counts,
        "fast_step_ratio_ekf": engine_us["ekf"]["ratio"],
        "fast_step_ratio_anfekf": max(
            v["ratio"] for k, v in engine_us.items() if k.startswith("anfekf")
        ),
        "fast_step_ratio_max": max(v["ratio"] for v in engine_us.values()),
        "default_over_ekf_fast_step_cost": default_step_cost(engine_us),
        "fast_prep_step_us": statistics.median(prep_s) / K * 1e6,
        "fast_engine_max_abs_diff": fast_diff,
        "fast_warm_up_s": fast_warm_up_s,
        "fast_compile_s": compiled["compile_s"],
        "fast_cache_load_s": compiled["cache_load_s"],
        "fast_compiled_signatures": (compiled["signatures"] or {}).get("signatures"),
        "fast_compiled_twice": (compiled["signatures"] or {}).get("compiled_twice"),
        "fast_e2e_scenario_s": e2e["wall_s"],
        "fast_e2e": e2e,
        "fast_e2e_cli_s": statistics.median(e2e["cli_wall_s"]) if e2e["cli_wall_s"] else None,
        "fast_summary_max_rel_diff": summary_diff,
        "fast_sweep_batch_s": e2e["sweep"]["wall_s"],
        "fast_e2e_paper_total_s": breakdown["e2e_total_s"],
        "fast_e2e_over_filter": max(
            (b["e2e_over_filter"] or math.inf for b in breakdown["scenarios"].values()),
            default=None,
        ),
        "fast_e2e_breakdown": breakdown,
        "report_paper_total_s": breakdown["report_total_s"],
        "make_zoo_s": None if make_zoo is None else make_zoo["total_s"],
        "make_zoo": make_zoo,
        "first_run_compiled": None if first_run is None else first_run["count"],
        "first_run": first_run,
        "peak_rss_mb": max(r["peak_rss_mb"] for r in scenarios.values()),
        "steps_parquet_mb": max(r["steps_parquet_mb"] for r in scenarios.values()),
        "wall_time_paper_scenarios_s": walls,
        "scenarios": scenarios,
        "raw_seconds": {"step_pass": step_s, "batch": batch_s, "engine_pass": engine_s},
        "bench_wall_time_s": time.time() - started,
        "machine": machine_info(),
        "load_average_1min": {"start": load_before[0], "end": os.getloadavg()[0]},
        "versions": package_versions(),
        "definitions": DEFINITIONS,
    }
    report["targets"] = targets_met(report)
    write_json(out, report)
    return report


def _value(x: float | None) -> str:
    if x is None:
        return "-"
    return f"{x:.3g}" if abs(x) < 100 else f"{x:.0f}"


def bench_table(report: dict) -> Table:
    """figure | value | target | met, for the terminal."""
    title = f"anfekf bench, {report['date']}, {report['machine']['cores']} cores"
    if report["quick"]:
        title += " (QUICK sizes: figures not comparable to the targets)"
    table = Table(title=title, title_justify="left")
    for col in ("figure", "value", "target", "met"):
        table.add_column(col, justify="left" if col == "figure" else "right")
    rows = [
        ("ekf_bare_step_us", "us"),
        ("ekf_harness_step_us", "us"),
        ("overhead_ratio", "x"),
        ("anfekf_step_us", "us"),
        ("anfekf_over_ekf_step_cost", "x"),
        ("batch_1_worker_s", "s"),
        ("batch_2_workers_s", "s"),
        ("speedup_2_workers", "x"),
        ("peak_rss_mb", "MiB"),
        ("steps_parquet_mb", "MiB"),
    ]

    def row(key: str, value: float | None, unit: str) -> None:
        t = report["targets"].get(key)
        met = "-" if t is None else ("yes" if t["met"] else "NO")
        shown = f"{_value(value)} {unit}".strip() if value is not None else "-"
        table.add_row(key, shown, "-" if t is None else t["target"], met)

    for key, unit in rows:
        row(key, report[key], unit)
    for name, wall in report["wall_time_paper_scenarios_s"].items():
        table.add_row(f"wall_time_s ({name})", f"{_value(wall)} s", "-", "-")
    engine = "numba" if report["fast_jit"] else "plain Python, numba not installed"
    table.add_section()
    for kind, figures in report["engine_step_us"].items():
        table.add_row(f"step_us {kind}: filterpy", f"{_value(figures['filterpy'])} us", "-", "-")
        table.add_row(f"step_us {kind}: fast ({engine})", f"{figures['fast']:.3g} us", "-", "-")
        ratio = f"{figures['ratio']:.3g} ({figures['ratio_with_prep']:.3g} with scan prep)"
        table.add_row(f"ratio {kind}: fast / filterpy", ratio, "-", "-")
    for key, unit in (
        ("fast_step_ratio_ekf", "x"),
        ("fast_step_ratio_anfekf", "x"),
        ("fast_step_ratio_max", "x"),
        ("fast_prep_step_us", "us"),
        ("fast_engine_max_abs_diff", ""),
        ("fast_warm_up_s", "s"),
        ("fast_compile_s", "s"),
        ("fast_cache_load_s", "s"),
        ("fast_compiled_signatures", ""),
        ("fast_e2e_scenario_s", "s"),
        ("fast_e2e_cli_s", "s"),
        ("fast_summary_max_rel_diff", ""),
        ("fast_sweep_batch_s", "s"),
        ("fast_e2e_paper_total_s", "s"),
        ("fast_e2e_over_filter", "x"),
        ("report_paper_total_s", "s"),
        ("make_zoo_s", "s"),
        ("first_run_compiled", ""),
        ("default_over_ekf_fast_step_cost", "x"),
    ):
        row(key, report.get(key), unit)
    twice = report.get("fast_compiled_twice")
    if twice is not None:  # functions the compile probe compiled for two signatures or more
        table.add_row("fast_compiled_twice", ", ".join(twice) or "none", "-", "-")
    table.add_section()
    for figure, value in breakdown_rows(report.get("fast_e2e_breakdown", {"scenarios": {}})):
        table.add_row(figure, value, "-", "-")
    return table
