"""The Python API, for notebooks and scripts: load a scenario, run it, read its tables, report it.

    from anfekf_bench import api

    experiment = api.load("configs/wrong_r.yaml")            # or api.load({...a dict...})
    result = api.run(experiment, out="results", runs=10, engine="fast")
    result.summary()                                         # pandas DataFrames
    result.comparisons()
    api.report([result], out="results/report")

A problem scenario beyond the robot (SPEC 17, docs/PROBLEMS.md: `problem: linear`, `tracking`,
`module`) loads and runs the same way, through `anfekf run`'s code for it
(`problems.experiment.execute_problem`); its `Result` gives its own tables: `summary()` and
`runs()` are problem_summary.parquet and problem_runs.parquet, `noise()` and `timing()` the
noise estimates and the seconds per run. It runs in local processes only (no `backend`), and a
batch that cannot run (its functions do not compile on the fast engine, a foreign folder) raises
`ProblemRunError` with the command line's line.

It goes through the same plan, execute and report code as `anfekf run` and `anfekf report`, so a
result written here is the same bytes as the command line's for the same scenario, seed and
engine, and the same validation applies (`anfekf_bench.arguments`, shared with the command line):
bad input raises `ScenarioError` (a scenario), `PlanError` (an argument: its type or range, or
an output folder inside another result) or `ResultsError` (a saved result that is missing,
damaged or mixed from two batches), each with the command line's one-line message as its text.
Two states of the output folder are exceptions of their own, also with that line: `OutputExists`
(it holds a complete result and `force` is False) and `FolderBusy` (another process holds it).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from . import arguments
from .config import ScenarioError
from .experiment import FolderBusy, OutputExists, Plan, PlanError, execute, make_plan
from .problems.experiment import TABLES as PROBLEM_TABLES
from .problems.experiment import ProblemRunError, execute_problem, is_problem_result
from .problems.schema import ProblemScenario, is_problem_document, parse_problem_scenario
from .report.results import PROBLEM, LoadedResult, load_result
from .scenarios import load_scenario, read_scenario_document, scenario_from_data
from .storage import (
    CLAIMS_FILE,
    COMPARISONS_FILE,
    RUNS_FILE,
    STEPS_FILE,
    SUMMARY_PARQUET,
    ResultsError,
    read_json,
    read_manifest,
)

__all__ = ["Experiment", "FolderBusy", "OutputExists", "PlanError", "ProblemRunError", "Result",
           "ResultsError", "ScenarioError", "load", "open_result", "report", "run"]  # fmt: skip

# A problem result's tables in place of a robot result's (`Result.summary()`, `.runs()`).
PROBLEM_TABLE_OF = {SUMMARY_PARQUET: PROBLEM_TABLES["summary"], RUNS_FILE: PROBLEM_TABLES["runs"]}


@dataclass(frozen=True)
class Experiment:
    """A validated scenario and what it runs on (its simulated world, or its recorded log; None
    for a problem scenario, whose system is in the scenario)."""

    scenario: object
    world: object
    source: Path  # the file it was read from (relative paths in it are relative to its folder)

    @property
    def name(self) -> str:
        return self.scenario.name


def load(source: str | Path | dict, *, base: str | Path = ".") -> Experiment:
    """A scenario from a YAML file, or from a dict shaped like one (relative paths in a dict are
    taken relative to `base`)."""
    base = arguments.path(base, "base")
    if isinstance(source, dict):
        path = base / "<dict>"
        if is_problem_document(source):
            return Experiment(parse_problem_scenario(source, path), None, source=path)
        return Experiment(*scenario_from_data(source, path), source=path)
    if not isinstance(source, (str, os.PathLike)):
        raise PlanError(f"source: must be a scenario file's path or a dict shaped like one (got"
                        f" {arguments.shown(source)})")  # fmt: skip
    path = arguments.path(source, "source")
    data = read_scenario_document(path)
    if is_problem_document(data):
        return Experiment(parse_problem_scenario(data, path), None, source=path)
    return Experiment(*load_scenario(path), source=path)


@dataclass(frozen=True)
class Result:
    """A finished result folder (`OUT/<name>`) and its tables."""

    folder: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "folder", arguments.path(self.folder, "folder"))

    def manifest(self) -> dict:
        """What ran: the scenario, runs, seed, engines, fingerprint, versions, timings."""
        return read_manifest(self.folder)

    def loaded(self) -> LoadedResult:
        """The result as the report reads it (the report's one loader): its kind (simulated,
        recorded, sweep, problem), the tables it holds, its manifest, its filters and their
        roles."""
        return load_result(self.folder)

    def _table(self, name: str) -> pd.DataFrame:
        """A table of this result; ResultsError when it belongs to another batch than the
        manifest's (the check `anfekf report` and `anfekf check` apply); FileNotFoundError when
        the folder or the table does not exist. A problem result's summary and runs are its own
        tables (`PROBLEM_TABLE_OF`)."""
        if not self.folder.is_dir():
            raise FileNotFoundError(f"{self.folder}: no such result folder")
        loaded = self.loaded()
        if name in PROBLEM_TABLE_OF and loaded.kind == PROBLEM:
            name = PROBLEM_TABLE_OF[name]
        path = self.folder / name
        if not path.exists():
            raise FileNotFoundError(f"{path}: not written for this result")
        return loaded.read(name)

    def summary(self) -> pd.DataFrame:
        """One row per filter: RMSE, ANEES, NEES in bounds, updates, divergence (a problem's:
        RMSE over the oracle's, the noise estimate's errors, gated measurements)."""
        return self._table(SUMMARY_PARQUET)

    def runs(self) -> pd.DataFrame:
        """One row per filter and run (SPEC 8's per-run metrics; a problem's, with the Q and R
        at the last step entry by entry)."""
        return self._table(RUNS_FILE)

    def noise(self) -> pd.DataFrame:
        """A problem result's noise estimate: one row per (filter, matrix, entry), its mean and
        spread over runs beside the true value."""
        return self._table(PROBLEM_TABLES["noise"])

    def timing(self) -> pd.DataFrame:
        """A problem result's seconds per filter and run."""
        return self._table(PROBLEM_TABLES["timing"])

    def steps(self) -> pd.DataFrame:
        """One row per filter, run and recorded step (absent with `steps_table: false`)."""
        return self._table(STEPS_FILE)

    def comparisons(self) -> pd.DataFrame:
        """Paired RMSE and ANEES ratios with their bootstrap intervals."""
        return self._table(COMPARISONS_FILE)

    def claims(self) -> list[dict]:
        """The scenario's declared claims and their verdicts."""
        return read_json(self.folder / CLAIMS_FILE)


def run(
    experiment: Experiment | str | Path | dict,
    *,
    out: str | Path = "results",
    runs: int | None = None,
    seed: int | None = None,
    jobs: int | None = None,
    engine: str | None = None,
    backend: str | None = None,
    scheduler: str | None = None,
    force: bool = False,
    on_result: Callable[[dict], None] | None = None,
) -> Result:
    """Run every filter of a scenario, simulated or recorded (None: the scenario's own runs,
    seed, jobs, engine, backend) and write its result to `out/<name>` exactly as `anfekf run`
    does (resume, `force`, the lock); `backend="dask"` with `scheduler="tcp://HOST:PORT"` runs
    on a Dask cluster."""
    checked = arguments.run_arguments(
        runs=runs, seed=seed, jobs=jobs, engine=engine, backend=backend, scheduler=scheduler,
        force=force,
    )  # fmt: skip
    folder = arguments.output_folder(out, "out")
    arguments.callback(on_result, "on_result")
    if not isinstance(experiment, (Experiment, dict, str, os.PathLike)):
        raise PlanError(f"experiment: must be an Experiment, a scenario file's path or a dict"
                        f" (got {arguments.shown(experiment)})")  # fmt: skip
    if not isinstance(experiment, Experiment):
        experiment = load(experiment)
    if isinstance(experiment.scenario, ProblemScenario):
        return _run_problem(experiment.scenario, folder, checked, on_result)
    plan: Plan = make_plan(experiment.scenario, experiment.world, **checked.plan_overrides())
    arguments.scenario_target(folder, plan.name, "out")
    _, target = execute(plan, folder, force=checked.force, on_result=on_result)
    return Result(Path(target))


def _run_problem(scenario: ProblemScenario, folder: Path, checked, on_result) -> Result:
    """`run` of a problem scenario: `anfekf run`'s code for it, in local processes."""
    if checked.backend not in (None, "local") or checked.scheduler is not None:
        raise PlanError("backend: a problem scenario runs in local processes only")
    if on_result is not None:
        raise PlanError("on_result: a problem scenario reports no result per run")
    target = arguments.scenario_target(folder, scenario.name, "out")
    if is_problem_result(target) and not checked.force:
        raise OutputExists(f"{target}: holds a complete result already; use force=True to"
                           " overwrite it")  # fmt: skip
    _, target = execute_problem(scenario, folder, runs=checked.runs, seed=checked.seed,
                                jobs=checked.jobs, force=checked.force,
                                engine=checked.engine)  # fmt: skip
    return Result(Path(target))


def open_result(folder: str | Path) -> Result:
    """A result written earlier (by `run` or `anfekf run`)."""
    folder = arguments.path(folder, "folder")
    load_result(folder)  # a folder that holds no result (or lacks a table) fails here, with why
    return Result(folder)


def report(results: Result | str | Path | Iterable[Result | str | Path], out: str | Path) -> Path:
    """Write the report of these results (figures, report.md, report.html) into `out`; returns
    the path of report.md. Results folders or their parents (one, or a list), as `anfekf
    report` takes them, sweeps included."""
    from .report import REPORT_FILE, write_report
    from .report.results import find_sweeps

    folders = arguments.result_paths(results, "results")
    out = arguments.output_folder(out, "out")
    write_report(folders, out, sweeps=find_sweeps(folders))
    return out / REPORT_FILE
