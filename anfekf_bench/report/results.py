"""One loader for every result folder (issue 33): what it is, which of its tables it holds, its
manifest and its filters with their roles, whatever wrote it.

`load_result` reads any folder `anfekf run` writes: a simulated scenario, a recorded log
(protocol segments or drives), a sweep or a problem beyond the robot (SPEC 17), into one
`LoadedResult`; `find_results` finds every one under the folders given. The report
(`write_report`), the Python API (`api.open_result`, `api.Result`) and `anfekf compare` read
results through it. A folder that lacks a table its kind needs is refused in one line naming
the file. The readers of each kind (`report.load_scenarios`, `real.load_real`,
`sweep.read_sweep`, the problems' reader) then build what their sections draw from it.

Light on purpose: no matplotlib, so the command line and the sweeps' writer may import it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from ..filters.registry import role_of
from ..storage import (
    AUDIT_FILES,
    CLAIMS_FILE,
    COMPARISONS_FILE,
    MANIFEST_FILE,
    PHASES_FILE,
    PROBLEM_FORMAT,
    PROBLEM_TABLES,
    RUNS_FILE,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    SWEEP_FILE,
    SWEEP_KIND,
    ResultsError,
    check_one_batch,
    read_json,
    read_manifest,
    read_parquet,
    scenario_dirs,
    sweep_folders,
)

SIMULATED, RECORDED, SWEEP, PROBLEM = "simulated", "recorded", "sweep", "problem"
KINDS = (SIMULATED, RECORDED, SWEEP, PROBLEM)

# Every table a result folder may hold, in the order `LoadedResult.tables` lists them.
TABLE_FILES = (
    STEPS_FILE, RUNS_FILE, SUMMARY_PARQUET, SUMMARY_JSON, COMPARISONS_FILE, CLAIMS_FILE,
    PHASES_FILE, *AUDIT_FILES.values(), SWEEP_FILE, *PROBLEM_TABLES.values(),
)  # fmt: skip

# The tables without which a result of each kind cannot be reported. A simulated scenario with
# `steps_table: false` has summary.parquet in place of steps.parquet (`required_tables`).
REQUIRED = {
    SIMULATED: (STEPS_FILE,),
    RECORDED: (STEPS_FILE, SUMMARY_JSON, COMPARISONS_FILE),
    SWEEP: (SWEEP_FILE,),
    PROBLEM: tuple(PROBLEM_TABLES.values()),
}


@dataclass(frozen=True)
class ResultFilter:
    """One filter of a result: its name in the tables, its kind and the role the registry gives
    it (reference, oracle, fitted, trained, adaptive; None for a kind this version does not
    know), and for a recorded result's instance the filter it was made from and its naive start
    (a multiple of the naive noise; None: tuned or trained)."""

    name: str
    kind: str
    role: str | None
    base: str
    start: float | None = None


@dataclass(frozen=True)
class LoadedResult:
    """A result folder as every reader of results sees it."""

    folder: Path
    kind: str  # one of KINDS
    manifest: dict
    tables: tuple[str, ...]  # the files of TABLE_FILES the folder holds
    filters: tuple[ResultFilter, ...]

    @property
    def name(self) -> str:
        scenario = self.manifest.get("scenario")
        name = scenario.get("name") if isinstance(scenario, dict) else self.manifest.get("name")
        return str(name) if name is not None else self.folder.name

    @property
    def protocol(self) -> str | None:
        """A recorded result's protocol ('segments', 'drives'); None for the other kinds."""
        if self.kind != RECORDED:
            return None
        return str(self.manifest.get("protocol") or "segments")

    def has(self, table: str) -> bool:
        return table in self.tables

    def path(self, table: str) -> Path:
        """The path of one of the folder's tables; ResultsError naming it when it is absent."""
        if not self.has(table):
            raise ResultsError(f"{self.folder / table}: missing (this {self.kind} result has"
                               f" {', '.join(self.tables) or 'no tables'})")  # fmt: skip
        return self.folder / table

    def read(self, table: str) -> pd.DataFrame | dict | list:
        """One of the folder's tables (a DataFrame, or the JSON document of a .json table),
        checked to belong to the manifest's batch."""
        path = self.path(table)
        if table.endswith(".json"):
            return read_json(path)
        check_one_batch(self.folder, self.manifest)
        return read_parquet(path)

    def roles(self) -> dict[str, str | None]:
        """Filter name -> its role."""
        return {f.name: f.role for f in self.filters}


def result_kind(manifest: dict) -> str:
    """Which of KINDS a manifest describes."""
    if manifest.get("format") == PROBLEM_FORMAT:
        return PROBLEM
    if manifest.get("kind") == SWEEP_KIND:
        return SWEEP
    if manifest.get("kind") == RECORDED:
        return RECORDED
    return SIMULATED


def required_tables(kind: str, manifest: dict) -> tuple[str, ...]:
    """REQUIRED[kind]; for a scenario with `steps_table: false`, without steps.parquet (a
    simulated one then needs summary.parquet)."""
    scenario = manifest.get("scenario")
    if isinstance(scenario, dict) and scenario.get("steps_table") is False:
        rest = tuple(t for t in REQUIRED[kind] if t != STEPS_FILE)
        return (SUMMARY_PARQUET,) if kind == SIMULATED else rest
    return REQUIRED[kind]


def _start(value) -> float | None:
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    return float(value) if is_number and math.isfinite(value) else None


def _filters(manifest: dict) -> tuple[ResultFilter, ...]:
    """The filters as the tables name them: a recorded result's (or a simulated one's with naive
    starts) instances, else the scenario's filters. Entries that are not plain records are left
    to the kind's reader, which refuses them with its own message."""
    scenario = manifest.get("scenario")
    specs = scenario.get("filters") if isinstance(scenario, dict) else None
    specs = [s for s in specs if isinstance(s, dict)] if isinstance(specs, list) else []
    instances = manifest.get("filters")
    entries = instances if isinstance(instances, list) and instances else specs
    out = []
    for entry in entries:
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            continue
        kind = entry.get("kind")
        kind = str(kind) if isinstance(kind, str) else "?"
        base = entry.get("base")
        out.append(ResultFilter(entry["name"], kind, role_of(kind),
                                base if isinstance(base, str) else entry["name"],
                                _start(entry.get("start"))))  # fmt: skip
    return tuple(out)


def load_result(folder: Path) -> LoadedResult:
    """Any result folder as a `LoadedResult`; ResultsError in one line when it holds no
    manifest, or lacks a table its kind needs (naming the file)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    kind = result_kind(manifest)
    tables = tuple(name for name in TABLE_FILES if os.path.lexists(folder / name))
    for name in required_tables(kind, manifest):
        if name not in tables:
            if kind == SIMULATED and name == STEPS_FILE and SUMMARY_PARQUET in tables:
                # The scenario writes steps.parquet: its absence is damage, not a summary-only
                # result.
                raise ResultsError(
                    f"{folder / STEPS_FILE}: missing, though {folder / MANIFEST_FILE} says the"
                    " scenario writes it (steps_table: true); the result is damaged: run it"
                    " again with --force"
                )
            raise ResultsError(f"{folder / name}: missing; a {kind} result needs"
                               f" {', '.join(required_tables(kind, manifest))}")  # fmt: skip
    return LoadedResult(folder, kind, manifest, tables, _filters(manifest))


def find_scenarios(results_dirs: Sequence[Path], out_dir: Path | None = None) -> list[Path]:
    """The scenario folders (simulated or recorded) under the given folders, minus the report
    folder, each once."""
    found: dict[Path, Path] = {}
    skip = Path(out_dir).resolve() if out_dir is not None else None
    for results_dir in results_dirs:
        for folder in scenario_dirs(Path(results_dir)):
            resolved = folder.resolve()
            if skip is not None and (resolved == skip or skip in resolved.parents):
                continue
            found.setdefault(resolved, folder)
    if not found:
        shown = ", ".join(str(d) for d in results_dirs)
        raise ResultsError(f"{shown}: no results found outside the report folder {out_dir}")
    return list(found.values())


def find_sweeps(folders: Sequence[Path]) -> list[Path]:
    """The sweep folders among `folders` and their children."""
    return [sweep for folder in folders for sweep in sweep_folders(Path(folder))]


def has_scenario_results(folders: Sequence[Path]) -> bool:
    """Whether any folder holds (or is) an ordinary scenario result, besides the sweeps."""

    def is_result(p: Path) -> bool:
        return (p / MANIFEST_FILE).is_file() and (p / SUMMARY_PARQUET).is_file()

    for folder in map(Path, folders):
        if is_result(folder) or (
            folder.is_dir() and any(is_result(p) for p in folder.iterdir() if p.is_dir())
        ):
            return True
    return False


def find_results(
    results_dirs: Sequence[Path], out_dir: Path | None = None, sweeps: Sequence[Path] | None = None
) -> list[LoadedResult]:
    """Every result under `results_dirs` (the folders themselves or their children), loaded:
    the scenarios (simulated and recorded, minus the report folder `out_dir`), then the sweeps
    (`sweeps`, else those found there), then the problem results. ResultsError when there is
    none; folders of sweeps or of problem results alone are results too."""
    results_dirs = [Path(d) for d in results_dirs]
    sweeps = find_sweeps(results_dirs) if sweeps is None else [Path(s) for s in sweeps]
    # imported here: loading a robot's result (`anfekf run` prints its comparisons through this
    # module) never pays for the problems' pipeline and schema
    from ..problems.experiment import problem_result_folders

    problems = problem_result_folders(results_dirs)
    try:
        found = (
            find_scenarios(results_dirs, out_dir)
            if not sweeps or has_scenario_results(results_dirs)
            else []
        )
    except ResultsError:
        if not problems:
            raise
        found = []
    return [load_result(f) for f in (*found, *sweeps, *problems)]
