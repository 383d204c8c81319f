"""Sweeps (SPEC 10): how much mismatch does each filter survive?

A scenario with a `sweep:` block is a grid of cells; each cell is the scenario with the axes'
values set, validated like any scenario before anything runs, and run as an ordinary scenario
(same seed in every cell, so cells are paired too; resumable per run, and a complete cell is
reused on a rerun). The sweep folder holds

    <out>/<name>/cells/cell-000/ ...   one ordinary result folder per cell
    <out>/<name>/sweep.parquet         one row per (cell, filter): the swept values, the summary
                                       metrics and the paired ratios to the references with their
                                       95 % intervals
    <out>/<name>/manifest.json         the axes, the cells and their values; written last
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from .config import (
    ScenarioError,
    SimulatedScenario,
    SweepAxis,
    World,
    parse_scenario,
    resolve_world,
)
from .experiment import (
    OutputExists,
    Plan,
    PlanError,
    check_plan,
    execute,
    make_plan,
    package_versions,
    survey_output,
)
from .outputs import check_not_nested
from .report.results import load_result
from .storage import (
    COMPARISONS_FILE,
    LOCK_FILE,
    MANIFEST_FILE,
    SUMMARY_PARQUET,
    SWEEP_CELLS_DIR,
    SWEEP_FILE,
    SWEEP_KIND,
    ResultsError,
    folder_lock,
    is_result_manifest,
    parquet_provenance,
    read_json,
    scenario_name_problem,
    write_json,
    write_parquet,
)

CELLS_DIR = SWEEP_CELLS_DIR
# The per-cell summary metrics kept in the sweep table.
SUMMARY_METRICS = ("runs", "runs_used", "diverged", "rmse_pos", "rmse_heading", "anees",
                   "nees_in_bounds", "anis", "gate_rejected")  # fmt: skip
RATIO_METRICS = ("rmse_pos", "anees")


def column_of(label: str) -> str:
    """An axis's column in sweep.parquet: its label with plain characters only (a field path's
    dots become underscores: filter_noise.sigma_range -> filter_noise_sigma_range), so SQL and
    pandas need no quoting."""
    return label.replace(".", "_")


def sweep_fingerprint(plans: list[Plan]) -> str:
    """One fingerprint for the whole grid: the cells' own, in order."""
    digest = hashlib.sha256("\n".join(p.fingerprint() for p in plans).encode())
    return digest.hexdigest()[:16]


class SweepError(Exception):
    """A sweep cannot be run as written; `str()` is the one-line message for the user."""


@dataclass(frozen=True)
class Cell:
    """One grid point: its folder name, the swept values (axis label -> value), the scenario."""

    index: int
    name: str
    coords: dict[str, float]
    scenario: SimulatedScenario
    world: World


def _set_path(doc: dict, path: str, value: float, *, source: Path, where: str) -> None:
    """doc[path] = value for a dotted path of existing keys / list indices, else ScenarioError."""
    parts = path.split(".")
    node = doc
    for depth, part in enumerate(parts):
        shown = ".".join(parts[: depth + 1])
        last = depth == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ScenarioError(
                    source, where, f"{path}: {shown} is not an index of a list of {len(node)}"
                )
            key = int(part)
        elif isinstance(node, dict):
            if part not in node:
                known = ", ".join(sorted(map(str, node)))
                raise ScenarioError(source, where, f"{path}: no field {shown} (there: {known})")
            key = part
        else:
            raise ScenarioError(source, where, f"{path}: {'.'.join(parts[:depth])} is a value")
        if last:
            if isinstance(node[key], (dict, list)):
                raise ScenarioError(source, where, f"{path}: is a block, not a value")
            node[key] = value
        else:
            node = node[key]


def _scale(doc: dict, axis: SweepAxis, factor: float) -> None:
    """A variance factor on the assumed R or Qu: both standard deviations times sqrt(factor)."""
    keys = (
        ("sigma_range", "sigma_bearing_deg")
        if axis.scale == "R"
        else ("sigma_v", "sigma_gamma_deg")
    )
    for key in keys:
        doc["filter_noise"][key] = doc["filter_noise"][key] * math.sqrt(factor)


def expand(scenario: SimulatedScenario, source: Path) -> list[Cell]:
    """Every cell of the scenario's sweep, each validated as a scenario (ScenarioError names the
    axis or the cell and the field)."""
    sweep = scenario.sweep
    base = scenario.model_dump(mode="json", by_alias=True, exclude={"sweep"})
    grid = itertools.product(*(axis.points() for axis in sweep.axes))
    cells = []
    for index, values in enumerate(grid):
        doc = copy.deepcopy(base)
        doc["name"] = f"cell-{index:03d}"
        doc["steps_table"] = sweep.cell_steps
        coords = {}
        for i, (axis, value) in enumerate(zip(sweep.axes, values, strict=True)):
            if axis.field is not None:
                _set_path(doc, axis.field, value, source=source, where=f"sweep.axes.{i}.field")
            else:
                _scale(doc, axis, value)
            coords[axis.label] = float(value)
        try:
            cell = parse_scenario(doc, source)
        except ScenarioError as exc:
            shown = ", ".join(f"{k} = {v:g}" for k, v in coords.items())
            raise ScenarioError(source, f"sweep cell {index} ({shown})", str(exc.message)) from None
        cells.append(Cell(index, doc["name"], coords, cell, resolve_world(cell.world, source)))
    return cells


def cell_plans(cells: list[Cell], **overrides) -> list[Plan]:
    """A plan per cell with the command line's overrides (runs, seed, jobs, backend, engine)."""
    runs, seed, jobs = overrides.pop("runs"), overrides.pop("seed"), overrides.pop("jobs")
    return [make_plan(c.scenario, c.world, runs, seed, jobs, **overrides) for c in cells]


def cell_complete(folder: Path, plan: Plan) -> bool:
    """A cell folder with a complete result of this very plan (same fingerprint)."""
    manifest = folder / MANIFEST_FILE
    if not manifest.is_file():
        return False
    try:
        found = read_json(manifest)
    except ResultsError as exc:
        raise SweepError(str(exc)) from None
    if not isinstance(found, dict) or found.get("fingerprint") != plan.fingerprint():
        raise SweepError(
            f"{folder}: holds a result of another version of this cell; use --force to redo it"
        )
    return True


def is_sweep_manifest(doc: object) -> bool:
    """A manifest this tool wrote for a sweep (its kind and this package's version)."""
    if not isinstance(doc, dict) or doc.get("kind") != SWEEP_KIND:
        return False
    versions = doc.get("versions")
    return isinstance(versions, dict) and isinstance(versions.get("anfekf-bench"), str)


def survey_sweep(name: str, out_dir: Path) -> None:
    """SweepError unless <out>/<name> is absent or a sweep folder of this tool: never a symlink
    (nor its cells/), no manifest.json of anything but a sweep of ours (an ordinary result of
    the same name is refused, --force or not), no entries of other kinds. Reads only."""
    problem = scenario_name_problem(name)
    if problem:
        raise SweepError(f"name: {problem}")
    target = Path(out_dir) / name
    if target.is_symlink():
        raise SweepError(f"{target}: is a symbolic link; results are never written through one")
    if not target.exists():
        return
    if not target.is_dir():
        raise SweepError(f"{target}: exists and is not a folder")
    cells = target / CELLS_DIR
    if cells.is_symlink() or (cells.exists() and not cells.is_dir()):
        raise SweepError(f"{cells}: is not a folder (a symbolic link or a file); refusing it")
    manifest = target / MANIFEST_FILE
    if manifest.is_symlink() or (manifest.exists() and not manifest.is_file()):
        raise SweepError(f"{manifest}: not a regular file; refusing to overwrite it")
    if manifest.exists():
        try:
            doc = read_json(manifest)
        except ResultsError:
            doc = None
        if is_result_manifest(doc):
            raise SweepError(
                f"{target}: holds an ordinary result of this name, not a sweep; move it away or"
                " use another --out"
            )
        if not is_sweep_manifest(doc):
            raise SweepError(
                f"{manifest}: not a sweep manifest of this tool; nothing is overwritten: move it"
                " away or use another --out"
            )
    sweep_file = target / SWEEP_FILE
    if sweep_file.is_symlink() or (sweep_file.exists() and not sweep_file.is_file()):
        raise SweepError(f"{sweep_file}: not a regular file; refusing to overwrite it")
    if sweep_file.exists() and not manifest.exists():
        try:
            ours = "version" in parquet_provenance(sweep_file)
        except ResultsError:
            ours = False
        if not ours:
            raise SweepError(f"{sweep_file}: not written by this tool; nothing is overwritten")
    allowed = {CELLS_DIR, SWEEP_FILE, MANIFEST_FILE, LOCK_FILE}
    foreign = sorted(
        e.name
        for e in target.iterdir()
        if e.name not in allowed and not (e.name.startswith(".") and e.name.endswith(".tmp"))
    )
    if foreign:
        raise SweepError(
            f"{target}: holds entries this tool did not write ({', '.join(foreign[:3])}); move"
            " them away or use another --out"
        )


def validate_sweep(
    name: str, cells: list[Cell], plans: list[Plan], out_dir: Path, *, force: bool
) -> None:
    """Everything that can refuse a sweep, for every cell, before any cell runs: the sweep
    folder, each cell's route and memory (check_plan) and each cell folder (survey_output).
    SweepError, PlanError or OutputExists; reads only."""
    survey_sweep(name, out_dir)
    try:
        check_not_nested(Path(out_dir) / name)
    except OutputExists as exc:
        raise SweepError(str(exc)) from None
    cells_dir = Path(out_dir) / name / CELLS_DIR
    for cell, plan in zip(cells, plans, strict=True):
        try:
            check_plan(plan)
        except PlanError as exc:
            shown = ", ".join(f"{k} = {v:g}" for k, v in cell.coords.items())
            raise PlanError(f"sweep cell {cell.index} ({shown}): {exc}") from None
        folder = cells_dir / cell.name
        if force or not cell_complete(folder, plan):
            try:
                survey_output(plan, folder, force)
            except OutputExists as exc:
                raise SweepError(str(exc)) from None


def run_sweep(
    name: str,
    axes: list[SweepAxis],
    cells: list[Cell],
    plans: list[Plan],
    out_dir: Path,
    *,
    force: bool = False,
    on_cell: Callable[[Cell, str], None] | None = None,
    on_start: Callable[[str, int, int], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
) -> tuple[pd.DataFrame, Path]:
    """Run (or reuse) every cell, then write the sweep table and manifest."""
    started = time.time()
    validate_sweep(name, cells, plans, out_dir, force=force)
    target = Path(out_dir) / name
    cells_dir = target / CELLS_DIR
    reused = []
    # The sweep's own lock serialises every writer of its cells, so a finished cell's lock file
    # can go (no other command can be waiting on it): no .lock is left in a finished cell.
    with folder_lock(target):
        for cell, plan in zip(cells, plans, strict=True):
            folder = cells_dir / cell.name
            if not force and cell_complete(folder, plan):
                reused.append(cell.name)
                (folder / LOCK_FILE).unlink(missing_ok=True)  # left by an earlier version
                if on_cell is not None:
                    on_cell(cell, "complete already: reused")
                continue
            if on_cell is not None:
                on_cell(cell, "running")
            execute(plan, cells_dir, force=force, on_start=on_start, on_result=on_result)
            (folder / LOCK_FILE).unlink(missing_ok=True)
    table = sweep_table(axes, cells, cells_dir)
    write_sweep_table(target / SWEEP_FILE, name, table, plans)
    write_json(
        target / MANIFEST_FILE,
        {
            "kind": SWEEP_KIND,
            "name": name,
            "axes": [a.model_dump(mode="json") for a in axes],
            "cells": [{"name": c.name, **c.coords} for c in cells],
            "runs": plans[0].runs,
            "seed": plans[0].seed,
            "engine": plans[0].engine,
            "reused_cells": reused,
            "versions": package_versions(),
            "wall_time_s": round(time.time() - started, 3),
        },
    )
    return table, target


def write_sweep_table(path: Path, name: str, table: pd.DataFrame, plans: list[Plan]) -> None:
    """sweep.parquet as every result file is written: a scenario column (the sweep's name),
    filter and scenario as plain strings, and the key-value metadata (scenario, seed,
    fingerprint, units, the package version and git commit)."""
    from .analysis.tables import column_units, parquet_frame

    df = parquet_frame(table.assign(scenario=name)[["scenario", *table.columns]])
    metadata = {
        "scenario": name,
        "seed": str(plans[0].seed),
        "fingerprint": sweep_fingerprint(plans),
        "units": column_units(df),
    }
    write_parquet(path, df, metadata)


def sweep_table(axes: list[SweepAxis], cells: list[Cell], cells_dir: Path) -> pd.DataFrame:
    """One row per (cell, filter): swept values, summary metrics, ratios to the references."""
    rows = []
    for cell in cells:
        result = load_result(cells_dir / cell.name)  # the report's one loader of results
        summary = result.read(SUMMARY_PARQUET)
        comparisons = result.read(COMPARISONS_FILE)
        kinds = {f.name: f.kind for f in cell.scenario.filters}
        roles = {f.name: f.role for f in cell.scenario.filters}  # the registry's, on the spec
        refs = {
            "ekf": next((n for n, r in roles.items() if r == "reference"), None),
            "oracle": next((n for n, r in roles.items() if r == "oracle"), None),
        }
        for rec in summary.to_dict("records"):
            coords = {column_of(k): v for k, v in cell.coords.items()}
            row = {"cell": cell.name, **coords, "filter": rec["filter"],
                   "kind": kinds.get(rec["filter"], "")}  # fmt: skip
            row.update({m: rec.get(m, math.nan) for m in SUMMARY_METRICS})
            for ref_label, ref in refs.items():
                for metric in RATIO_METRICS:
                    hit = comparisons[
                        (comparisons["filter"] == rec["filter"])
                        & (comparisons["vs"] == ref)
                        & (comparisons["metric"] == metric)
                    ]
                    found = hit.iloc[0] if len(hit) else None
                    for part in ("estimate", "lo", "hi"):
                        key = f"{metric}_vs_{ref_label}" + (
                            "" if part == "estimate" else f"_{part}"
                        )
                        if ref == rec["filter"]:
                            value = 1.0  # a reference against itself
                        else:
                            value = math.nan if found is None else float(found[part])
                        row[key] = value
            rows.append(row)
    table = pd.DataFrame(rows)
    table["filter"] = pd.Categorical(
        table["filter"], categories=list(dict.fromkeys(table["filter"]))
    )
    return table.sort_values(
        [column_of(a.label) for a in axes] + ["filter"], kind="stable"
    ).reset_index(drop=True)
