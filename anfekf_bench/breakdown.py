"""`anfekf bench`'s end-to-end breakdown (SPEC 20): where a scenario's time goes on the fast engine.

Per scenario file, in this process with warm caches: the whole `experiment.execute` (the run as
`anfekf run` does it, process start excluded, work placed by `runner.place_runs`), E2E_REPEATS
times, its median wall the figure (the first execute of a file in a process pays its first calls,
and the machine's noise moved a single wall by a third: 0.47-0.78 s on one file), then the same
runs once more phase by phase, each timed on its own: simulate (the truth path and every run's
odometry and scans), filter (every filter instance on every run, its timeline included),
metrics (per-step errors and NEES), store (each run kept for a resume as `execute` keeps it:
`outputs.RunStore`, which saves none of a batch's first ten seconds of runs unless it is
interrupted), tables (every table computed and written), and report (the report of the
result `execute` wrote, figures included, drawn in worker processes as `anfekf report` draws
them). `e2e_over_filter` is the end-to-end wall over the
filters' own time: issue 37 asks for at most 3x on a 50-run paper scenario.

Beside it, from fresh processes (process start included): `make_zoo` (`anfekf run configs/zoo`
then `anfekf report` on it, as `make zoo` runs them; issue 37: at most 40 s) and `first_run`
(the first `anfekf run` of the paper's scenarios and the zoo after numba's cache holds only what
`make setup`'s warm-up compiled: which functions numba still compiled; issue 37: none).
"""

from __future__ import annotations

import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .analysis.metrics import add_trace_metrics, recorded_steps
from .config import World
from .experiment import execute, make_plan, result_tables
from .outputs import STORE_AFTER_S, RunStore, write_result_tables
from .report import write_report
from .runner import run_filter_on, simulate
from .scenarios import load_scenario
from .sources.simulator import world_path
from .storage import MANIFEST_FILE, read_json, sync_files

PHASES = ("simulate", "filter", "metrics", "store", "tables", "report")
E2E_REPEATS = 3
REPORT_JOBS = 2  # as `anfekf report` draws its figures by default
E2E_OVER_FILTER_TARGET = 3.0  # issue 37


def scenario_breakdown(
    path: Path,
    tmp: Path,
    runs: int | None = None,
    *,
    trim: Callable[[World], World] | None = None,
    report: bool = True,
    repeats: int = E2E_REPEATS,
) -> dict:
    """The breakdown of one scenario file on the fast engine (see the module's docstring);
    `trim` shortens the world's route (the bench's quick sizes); `repeats` end-to-end walls,
    the median reported."""
    scenario, world = load_scenario(path)
    world = world if trim is None else trim(world)
    plan = make_plan(scenario, world, runs, None, None, engine="fast")
    walls = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        _, target = execute(plan, tmp / "e2e", force=True)
        walls.append(time.perf_counter() - t0)
    e2e_s = statistics.median(walls)
    seconds = dict.fromkeys(PHASES, 0.0)
    clock = [time.perf_counter()]

    def lap(phase: str) -> None:  # the time since the last lap goes to `phase`
        now = time.perf_counter()
        seconds[phase] += now - clock[0]
        clock[0] = now

    sc, world_ = plan.scenario, plan.world
    wp = world_path(world_)
    lap("simulate")
    ordered = []
    fingerprint = plan.fingerprint()
    store = RunStore(tmp / "store", fingerprint, STORE_AFTER_S)  # as execute's on the fast engine
    for run, seed in enumerate(np.random.SeedSequence(plan.seed).spawn(plan.runs)):
        data = simulate(sc, world_, seed, wp)
        steps = recorded_steps(len(data.u_odo), sc.record_every)
        x_true = data.truth.x[steps]
        lap("simulate")
        filters = {}
        for name, spec, start in sc.instances():
            trace = run_filter_on("fast", spec, sc, world_, data, start, name)
            lap("filter")
            filters[name] = add_trace_metrics(trace, x_true, compiled=True)
            lap("metrics")
        ordered.append({
            "run": run, "control_steps": len(data.u_odo), "step": steps,
            "t": steps * world_.T, "x_true": x_true, "filters": filters,
        })  # fmt: skip
        store.keep(ordered[-1])  # one file a run, as execute's run store holds them
        lap("store")
    tables = result_tables(plan, ordered)
    with tempfile.TemporaryDirectory(dir=tmp) as staging:  # as execute stages and flushes them
        write_result_tables(Path(staging), tables, steps_table=True, durable=False)
        sync_files(sorted(Path(staging).iterdir()))
    lap("tables")
    if report:
        write_report([target], tmp / "report", html=True, jobs=REPORT_JOBS)
        lap("report")
    placement = read_json(target / MANIFEST_FILE).get("placement", {})
    filter_s = seconds["filter"]
    return {
        "runs": plan.runs,
        "filters": len(plan.filter_names()),
        "e2e_s": e2e_s,
        "e2e_walls_s": walls,
        "placement": placement.get("where"),
        "phases_s": seconds,
        "harness_s": sum(seconds.values()) - filter_s,
        "e2e_over_filter": e2e_s / filter_s if filter_s > 0 else None,
    }


def paper_breakdown(
    files: list[Path],
    tmp: Path,
    runs: int | None,
    say: Callable[[str], None],
    trim: Callable[[World], World] | None = None,
) -> dict:
    """`scenario_breakdown` of every paper scenario file: name -> breakdown, plus the total
    end-to-end wall of all of them (issue 37: at most 5 s on the fast engine)."""
    out = {}
    for path in files:
        say(f"end-to-end breakdown of {path.name} on the fast engine")
        name = load_scenario(path)[0].name
        out[name] = scenario_breakdown(path, tmp / "breakdown" / name, runs, trim=trim)
    return {
        "scenarios": out,
        "e2e_total_s": sum(b["e2e_s"] for b in out.values()),
        "report_total_s": sum(b["phases_s"]["report"] for b in out.values()),
    }


def _cli(args: list[str], env: dict | None = None) -> tuple[float, str]:
    """`anfekf ARGS` in a fresh interpreter: its wall time and its output (stdout + stderr)."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "anfekf_bench.entry", *args], capture_output=True, text=True,
        env=env, check=False,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"anfekf {' '.join(args)} failed ({proc.returncode}): {tail}")
    return wall, proc.stdout + proc.stderr


def make_zoo_wall(zoo: Path, tmp: Path) -> dict:
    """`make zoo` as it runs: `anfekf run ZOO` then `anfekf report` on it, each in a fresh
    process (numba's cache warm): their wall times and the sum (issue 37: at most 40 s)."""
    out = tmp / "zoo"
    run_s, _ = _cli(["run", str(zoo), "--out", str(out), "--force"])
    report_s, _ = _cli(["report", str(out), "--out", str(out / "report")])
    return {"run_s": run_s, "report_s": report_s, "total_s": run_s + report_s}


_SAVED = re.compile(r"\[cache\] data saved to '?([^'\n]+)")


def first_run_compiles(cache_dir: Path, folders: list[Path], tmp: Path, runs: int = 2) -> dict:
    """The first `anfekf run FOLDER --engine fast --runs RUNS` of each folder with numba's cache
    at `cache_dir` (holding what the warm-up compiled): the functions numba compiled and saved
    there on the way (its cache log; issue 37 asks for none) and the runs' wall time."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), NUMBA_DEBUG_CACHE="1")
    compiled: list[str] = []
    wall = 0.0
    for i, folder in enumerate(folders):
        args = ["run", str(folder), "--engine", "fast", "--runs", str(runs)]
        seconds, text = _cli([*args, "--out", str(tmp / f"first-run-{i}"), "--force"], env)
        wall += seconds
        compiled += [Path(m).name for m in _SAVED.findall(text) if m.endswith(".nbc")]
    return {"compiled": sorted(set(compiled)), "count": len(set(compiled)), "wall_s": wall}


# A compiled function's file in numba's disk cache: NAME-LINE.pyXY[flags].N.nbc, N its Nth
# signature
_CACHED_SIGNATURE = re.compile(r"(?P<name>.+-\d+)\.py\d+\w*\.\d+\.nbc")


def compiled_signatures(cache_dir: Path) -> dict:
    """What numba compiled into the cache `cache_dir` (empty before): how many signatures, and
    the functions it compiled for more than one (a constant argument typed as a literal of its
    own compiles the callee again: docs/DESIGN.md, "Engines"), as FOLDER/NAME-LINE of their
    cache files."""
    per_function: dict[str, int] = {}
    for path in Path(cache_dir).rglob("*.nbc"):
        match = _CACHED_SIGNATURE.fullmatch(path.name)
        if match:  # one function: its folder (a hash of its source's), name and line
            name = f"{path.parent.name}/{match['name']}"
            per_function[name] = per_function.get(name, 0) + 1
    twice = sorted(name for name, count in per_function.items() if count > 1)
    return {"signatures": sum(per_function.values()), "compiled_twice": twice}


def breakdown_rows(breakdown: dict) -> list[tuple[str, str]]:
    """(figure, value) rows for the bench's terminal table."""
    rows = []
    for name, b in breakdown["scenarios"].items():
        phases = ", ".join(f"{p} {s:.2f}" for p, s in b["phases_s"].items())
        rows.append((f"e2e {name} ({b['runs']} runs, {b['placement']})", f"{b['e2e_s']:.2f} s"))
        rows.append((f"  phases {name} [s]", phases))
        ratio = b["e2e_over_filter"]
        rows.append((f"  e2e / filter {name}", "-" if ratio is None else f"{ratio:.2f} x"))
    rows.append(("e2e paper scenarios, fast engine", f"{breakdown['e2e_total_s']:.2f} s"))
    if "report_total_s" in breakdown:
        rows.append(("report of the paper scenarios", f"{breakdown['report_total_s']:.2f} s"))
    return rows
