"""The report's worst case over its scenarios (SPEC 19; analysis/suite.py): the table in the
report and as worst_case.parquet / worst_case.csv in the report folder.

A report over several simulated scenarios with an oracle (`anfekf report results/zoo
results/changing`, or a parent folder of both) gets it; recorded drives among its results add a
column: each filter's geometric mean over drives of its RMSE over ekf-tuned's (the worst of its
naive starts).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from ..analysis.suite import LOST_LOCK_FACTOR, LOST_LOCK_M, FilterRuns, SuiteScenario, suite_table
from ..analysis.tables import filter_arrays, filter_names
from ..filters.registry import role_of
from ..storage import read_steps, write_atomic
from . import real
from .data import ScenarioData
from .document import Block, Cell, Heading, Paragraph, TableBlock

TABLE_FILE = "worst_case"  # .parquet and .csv in the report folder
_COLUMNS = ["filter", "run", "step", "t", "pos_err", "nees", "diverged"]


def _oracle(sc: ScenarioData) -> str | None:
    return next((f.name for f in sc.filters if role_of(f.kind) == "oracle"), None)


def suite_input(sc: ScenarioData) -> SuiteScenario | None:
    """One scenario's runs as the suite table reads them (steps.parquet); None without an oracle
    or without steps."""
    oracle = _oracle(sc)
    path = sc.folder / "steps.parquet"
    if oracle is None or not path.exists():
        return None
    steps = read_steps(sc.folder, columns=_COLUMNS)
    filters = {}
    for name in filter_names(steps):
        runs = filter_arrays(steps, name, series=("pos_err", "nees"))
        filters[name] = FilterRuns(runs["pos_err"], runs["nees"], runs["diverged"])
    changing = sc.schedule is not None
    kinds = {f.name: f.kind for f in sc.filters}
    order = [f.name for f in sc.filters if f.name in filters]
    return SuiteScenario(sc.name, oracle, changing, {n: filters[n] for n in order}, kinds)


def drive_ratios(recorded: Sequence[real.RealData]) -> dict[str, float]:
    """Per filter (its instances' base name): the geometric mean over drives of its RMSE over
    ekf-tuned's, the worst over its starts and over the drive results given."""
    out: dict[str, float] = {}
    for rd in recorded:
        if not real.is_drives_result(rd) or rd.reference is None:
            continue
        rmse = real.drive_rmse(rd)
        ref = rmse.loc[rd.reference]
        for inst in rd.instances():
            if inst["name"] == rd.reference:
                continue
            with np.errstate(all="ignore"):
                ratio = (rmse.loc[inst["name"]] / ref).to_numpy(float)
                value = float(np.exp(np.mean(np.log(ratio)))) if ratio.size else math.nan
            base = str(inst.get("base", inst["name"]))
            if not math.isfinite(value):
                value = math.inf
            out[base] = max(out.get(base, -math.inf), value)
    return out


def worst_case(
    scenarios: Sequence[ScenarioData], recorded: Sequence[real.RealData] = ()
) -> pd.DataFrame | None:
    """The suite table over the report's simulated scenarios (at least two with an oracle)."""
    inputs = [s for s in (suite_input(sc) for sc in scenarios) if s is not None]
    if len(inputs) < 2:
        return None
    drives = drive_ratios(recorded)
    return suite_table(inputs, drives=drives or None)


def write_tables(df: pd.DataFrame, out_dir: Path) -> list[Path]:
    """worst_case.parquet and worst_case.csv in the report folder (atomically)."""
    paths = [out_dir / f"{TABLE_FILE}.parquet", out_dir / f"{TABLE_FILE}.csv"]
    write_atomic(paths[0], lambda tmp: df.to_parquet(tmp, index=False))
    write_atomic(paths[1], lambda tmp: df.to_csv(tmp, index=False, float_format="%.6g"))
    return paths


def _ratio(v: float, lo: float, hi: float) -> Cell:
    if not math.isfinite(v):
        return Cell("n/a", math.inf)
    text = f"{v:.3g}x"
    if math.isfinite(lo) and math.isfinite(hi):
        text += f" [{lo:.3g}, {hi:.3g}]"
    return Cell(text, v)


def _share(v: float) -> Cell:
    return Cell("n/a" if not math.isfinite(v) else f"{100 * v:.0f} %", v)


def blocks(df: pd.DataFrame, total: int) -> list[Block]:
    """The report's section: a heading, what the columns mean, the table (sortable)."""
    drives = bool(np.isfinite(df["drives_vs_tuned"].to_numpy(float)).any())
    header = [
        "#", "filter", "worst / oracle [95 %]", "where", "geo-mean / oracle [95 %]",
        "NEES in bounds, min (constant)", "min (all)", "lost lock", "inconsistent",
    ]  # fmt: skip
    if drives:
        header.append("drives / ekf-tuned")
    body = []
    for r in df.itertuples(index=False):
        name = r.filter if r.scenarios == total else f"{r.filter} ({r.scenarios}/{total})"
        line = [
            Cell(str(r.rank), r.rank), Cell(name), _ratio(r.worst, r.worst_lo, r.worst_hi),
            Cell(r.worst_scenario), _ratio(r.geomean, r.geomean_lo, r.geomean_hi),
            _share(r.nees_in_bounds_min_constant), _share(r.nees_in_bounds_min),
            Cell(f"{r.lost_lock}/{r.runs}", r.lost_lock),
            Cell(f"{r.inconsistent}/{r.runs}", r.inconsistent),
        ]  # fmt: skip
        if drives:
            line.append(_ratio(r.drives_vs_tuned, math.nan, math.nan))
        body.append(line)
    caption = (
        f"Worst case over {total} scenarios: each filter's position RMSE over the oracle's, its"
        " worst and its geometric mean over the scenarios it ran, with 95 % percentile intervals"
        " (runs resampled in every scenario at once, paired with the oracle); sorted by the worst"
        " case, filters run in fewer scenarios after (n/m). NEES in bounds: the lowest share of"
        " steps in the 95 % bounds over the constant-noise scenarios and over all. Lost lock:"
        f" runs that diverged or whose largest position error exceeds {LOST_LOCK_M:g} m and"
        f" {LOST_LOCK_FACTOR:g}x the oracle's on the same run; inconsistent: runs whose"
        " time-mean NEES exceeds 1e4 (summed over"
        f" the scenarios). Also in {TABLE_FILE}.parquet and {TABLE_FILE}.csv."
    )
    numeric = [True, False, True, False, True, True, True, True, True] + ([True] if drives else [])
    text = (
        "Which filter to use when you do not know what is wrong: ranked by the worst ratio to the"
        " oracle over every scenario of this report, not by wins (SPEC 19)."
    )
    return [
        Heading("Worst case across scenarios", level=3, anchor="worst-case"),
        Paragraph(text),
        TableBlock(header, body, numeric, caption=caption),
    ]
