"""Checks that a saved result is one batch's, before `anfekf report` draws anything from it.

A result folder can be edited by hand or assembled from copies: a steps table copied from another
scenario, rows duplicated, runs missing. The metric code would then average whatever it is given
and the report would look fine. These checks refuse such a folder in one line instead
(`ResultsError`), naming the file and what is wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..analysis.tables import in_key_order
from ..config import FILTER_NAME_PATTERN
from ..storage import MANIFEST_FILE, STEPS_FILE, ResultsError, scenario_name_problem


def _distinct(column: pd.Series) -> tuple[np.ndarray, list[str]]:
    """A column's values as text, in order of first appearance, and each row's position in that
    list (a categorical column is read from its codes, not turned into 1.5 million strings)."""
    if not isinstance(column.dtype, pd.CategoricalDtype):
        column = column.astype(str).astype("category")
    codes = column.cat.codes.to_numpy()
    present = pd.unique(codes)  # the codes in order of first appearance
    position = np.full(len(column.cat.categories) + 1, -1, dtype=np.int64)
    position[present] = np.arange(len(present))
    names = [str(column.cat.categories[c]) if c >= 0 else "nan" for c in present]
    return position[codes], names


def _manifest_runs(manifest: dict, where: Path) -> int:
    runs = manifest.get("runs")
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise ResultsError(f"{where}: runs: expected an integer >= 1, found {runs!r:.40}")
    return runs


# Columns of steps.parquet that hold numbers; the first ones must also be finite (the truth and
# the clock: an estimate may be NaN, in a diverged run).
NUMBER_COLUMNS = (
    "run", "step", "t", "x_true", "y_true", "phi_true", "x_est", "y_est", "phi_est",
    "P_xx", "P_xy", "P_xphi", "P_yy", "P_yphi", "P_phiphi", "pos_err", "heading_err", "nees",
    "R_rr", "R_bb", "Q_vv", "Q_gg", "diverged",
)  # fmt: skip
FINITE_COLUMNS = ("run", "step", "t", "x_true", "y_true", "phi_true")


def check_saved_result(folder: Path, steps: pd.DataFrame, manifest: dict) -> None:
    """ResultsError unless `steps` (steps.parquet) is the table of the batch `manifest` describes:
    its scenario, every filter and run once, the same steps for every (filter, run), plain names.
    """
    folder = Path(folder)
    steps_path, manifest_path = folder / STEPS_FILE, folder / MANIFEST_FILE
    scenario = manifest.get("scenario")
    name = scenario.get("name") if isinstance(scenario, dict) else None
    if not isinstance(name, str) or scenario_name_problem(name):
        raise ResultsError(f"{manifest_path}: scenario.name: not a valid scenario name")
    for column in NUMBER_COLUMNS:
        if column in steps.columns and steps[column].dtype.kind not in "biuf":
            raise ResultsError(f"{steps_path}: column {column}: expected numbers")
    for column in FINITE_COLUMNS:
        if column in steps.columns and not np.isfinite(steps[column].to_numpy(float)).all():
            raise ResultsError(f"{steps_path}: column {column}: expected finite numbers")
    found = sorted(_distinct(steps["scenario"])[1])
    if found != [name]:
        shown = ", ".join(repr(s[:40]) for s in found[:3])
        raise ResultsError(
            f"{steps_path}: holds scenario {shown}, but {manifest_path} is scenario {name!r};"
            " the two files come from different results"
        )
    codes, filters = _distinct(steps["filter"])
    for filt in filters:
        if not FILTER_NAME_PATTERN.fullmatch(filt):
            raise ResultsError(f"{steps_path}: filter name {filt[:40]!r} is not plain text")
    # The filter instances the batch ran (a scenario with naive starts runs '<filter> x<m>');
    # a result written before the manifest listed them: the scenario's filters.
    specs = manifest.get("filters")
    specs = specs if isinstance(specs, list) else scenario.get("filters")
    declared = (
        [s.get("name") for s in specs if isinstance(s, dict)] if isinstance(specs, list) else []
    )
    absent = [d for d in declared if d not in filters]
    if absent:
        raise ResultsError(
            f"{steps_path}: filter {str(absent[0])[:40]!r} of {manifest_path} has no rows"
        )
    # the filter as its position in `filters`: the checks below compare integers, not names
    run, step = steps["run"].to_numpy(), steps["step"].to_numpy()
    key = pd.DataFrame({"filter": codes, "run": run, "step": step})
    # as a batch writes its table, strictly in (filter, run, step) order: no row repeats, and
    # the keys need no hashing
    strictly = in_key_order(codes, run, step, strict=True)
    in_order = strictly or in_key_order(codes, run, step)
    if not strictly and key.duplicated().any():
        dup = key[key.duplicated()].iloc[0]
        raise ResultsError(
            f"{steps_path}: duplicated rows (filter {filters[dup['filter']][:40]!r}, run"
            f" {dup['run']}, step {dup['step']} appears more than once)"
        )
    runs = _manifest_runs(manifest, manifest_path)
    expected = np.arange(runs)
    for filt, rows in key.groupby("filter", sort=False):
        have = np.unique(rows["run"].to_numpy())
        if not np.array_equal(have, expected):
            missing = np.setdiff1d(expected, have)
            extra = np.setdiff1d(have, expected)
            what = (
                f"runs {', '.join(map(str, missing[:5]))} missing"
                if missing.size
                else f"runs {', '.join(map(str, extra[:5]))} not in the batch"
            )
            raise ResultsError(
                f"{steps_path}: filter {filters[filt][:40]!r}: {what} ({manifest_path} says"
                f" {runs} runs)"
            )
    counts = key.groupby(["filter", "run"], sort=False).size()
    if counts.nunique() != 1:
        raise ResultsError(f"{steps_path}: filters or runs have different numbers of steps")
    ordered = step if in_order else step[np.lexsort((step, run, codes))]  # no sort in order
    grid = ordered.reshape(len(counts), int(counts.iloc[0]))
    if not (grid == grid[0]).all():
        raise ResultsError(f"{steps_path}: filters or runs were recorded at different steps")
