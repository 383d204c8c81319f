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
"""

from __future__ import annotations

import dataclasses
import gc
import json
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

from .analysis.tables import add_trace_metrics, recorded_steps
from .config import Scenario, World, load_scenario, scenario_files
from .engines.filterpy_engine import run_filter
from .experiment import execute, machine_info, make_plan, package_versions
from .filters import ANFEKFSpec, EKFSpec, RobotEKF, build_filter
from .models import F_jacobian, G_jacobian, H_jacobian, f, h, residual_z
from .runner import run_batch, simulate
from .sources.simulator import RunData
from .storage import STEPS_FILE, output_path_problem, write_json

# Per-step figures use the correct-noise scenario: there the gate accepts (nearly) every
# measurement for both filters, so the bare loop (no gate) and the harness do the same updates.
STEP_SCENARIO = "correct.yaml"
BATCH_SCENARIO = "wrong_r.yaml"
MIB = 2**20

# figure: (comparison, limit, unit) on the 2-core machine (issue 6)
TARGETS: dict[str, tuple[str, float, str]] = {
    "overhead_ratio": ("<=", 1.15, "x"),
    "speedup_2_workers": (">=", 1.8, "x"),
    "anfekf_over_ekf_step_cost": ("<=", 1.5, "x"),
    "steps_parquet_mb": ("<=", 50.0, "MiB"),
    "peak_rss_mb": ("<=", 2048.0, "MiB"),
}


# What each figure of the JSON is, written into it so the file explains itself.
DEFINITIONS = {
    "ekf_bare_step_us": "median time per control step of a plain filterpy ExtendedKalmanFilter"
    " loop (predict every step, one update per landmark seen; no gate, checks or recording)",
    "ekf_harness_step_us": "the same EKF (RobotEKF) through runner.run_filter plus the per-run"
    " metrics of runner.run_one (pose errors, NEES); simulation excluded from both",
    "overhead_ratio": "median over repeats of harness / bare time, timed back to back",
    "anfekf_step_us": "ANFEKF (adapt R) through the harness on the same data",
    "anfekf_over_ekf_step_cost": "median over repeats of ANFEKF / EKF harness time",
    "speedup_2_workers": "median over repeats of the 1-worker / 2-worker batch wall time"
    " (joblib loky pool warmed first)",
    "peak_rss_mb": "largest over the scenarios of: peak RSS (VmHWM) of the main process plus"
    " that of each child (workers, resource trackers); an upper bound on memory held at once",
    "steps_parquet_mb": "largest steps.parquet over the scenarios (MiB)",
    "wall_time_paper_scenarios_s": "experiment.execute wall time of each scenario file in a"
    " fresh process (worker start-up included), and their sum",
}


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


FULL = BenchSizes()
QUICK = BenchSizes(repeats=2, batch_runs=2, batch_repeats=1, scenario_runs=2, waypoints=3)


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
        flt.F = F_jacobian(flt.x, u, T, B)
        G = G_jacobian(flt.x, u, T, B)
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
    _, target = execute(plan, Path(out_dir), force=True)
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
        "peak_rss_mb": max(r["peak_rss_mb"] for r in scenarios.values()),
        "steps_parquet_mb": max(r["steps_parquet_mb"] for r in scenarios.values()),
        "wall_time_paper_scenarios_s": walls,
        "scenarios": scenarios,
        "raw_seconds": {"step_pass": step_s, "batch": batch_s},
        "bench_wall_time_s": time.time() - started,
        "machine": machine_info(),
        "load_average_1min": {"start": load_before[0], "end": os.getloadavg()[0]},
        "versions": package_versions(),
        "definitions": DEFINITIONS,
    }
    report["targets"] = targets_met(report)
    write_json(out, report)
    return report


def _value(x: float) -> str:
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
    for key, unit in rows:
        t = report["targets"].get(key)
        met = "-" if t is None else ("yes" if t["met"] else "NO")
        table.add_row(key, f"{_value(report[key])} {unit}", "-" if t is None else t["target"], met)
    for name, wall in report["wall_time_paper_scenarios_s"].items():
        table.add_row(f"wall_time_s ({name})", f"{_value(wall)} s", "-", "-")
    return table
