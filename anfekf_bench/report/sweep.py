"""The report of a sweep, drawn from its sweep.parquet and manifest only (SPEC 10).

One axis: each metric and each ratio to the oracle against the swept value, one line per filter,
with the 95 % paired interval as a band (log axes for factor axes). Two axes: one heatmap per
filter and metric, every cell annotated. A third axis, if any, gives one set per value.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from ..storage import (
    MANIFEST_FILE,
    SWEEP_FILE,
    ResultsError,
    read_json,
    read_parquet,
)
from .document import Block, Cell, Heading, Paragraph, TableBlock
from .plots import (
    FigureSaver,
    filter_style,
    legend_entries,
    ratio_cmap,
    ratio_colourbar,
    ratio_image,
    ratio_norm,
)
from .render import general_number

# (column, its interval's columns or None, title, log scale, the value marking "as good as" the
# reference, or None)
PANELS = (
    ("rmse_pos_vs_oracle", ("rmse_pos_vs_oracle_lo", "rmse_pos_vs_oracle_hi"),
     "position RMSE / oracle (95 % paired interval)", True, 1.0),
    ("rmse_pos", None, "position RMSE [m] (time mean of the RMSE over runs)", True, None),
    ("anees_vs_oracle", ("anees_vs_oracle_lo", "anees_vs_oracle_hi"),
     "ANEES / oracle (95 % paired interval)", True, 1.0),
    ("nees_in_bounds", None, "share of steps with NEES in the 95 % bounds", False, None),
)  # fmt: skip


@dataclass(frozen=True)
class SweepData:
    """A sweep folder's table and manifest."""

    folder: Path
    name: str
    axes: list[str]
    factor_axes: set[str]
    table: pd.DataFrame
    runs: int


def read_sweep(folder: Path) -> SweepData:
    folder = Path(folder)
    doc = read_json(folder / MANIFEST_FILE)
    table = read_parquet(folder / SWEEP_FILE)
    try:
        # an axis's label: its field, or "<scale>_factor" for a `scale:` axis (no field)
        labels = [a["field"] if a.get("field") else f"{a['scale']}_factor" for a in doc["axes"]]
        axes = [str(label) for label in labels]
        # factor axes (log scale): every `scale:` axis, and any axis given as `factors:`
        factor_axes = {
            label
            for a, label in zip(doc["axes"], axes, strict=True)
            if a.get("scale") or a.get("factors")
        }
        name, runs = str(doc["name"]), int(doc["runs"])
    except (KeyError, TypeError, ValueError):
        raise ResultsError(f"{folder / MANIFEST_FILE}: not a sweep manifest") from None
    # The table's axis columns have plain names (dots as underscores); older tables, dotted.
    axes = [a if a in table.columns else a.replace(".", "_") for a in axes]
    factor_axes = {a if a in table.columns else a.replace(".", "_") for a in factor_axes}
    if "filter" in table.columns and not isinstance(table["filter"].dtype, pd.CategoricalDtype):
        table["filter"] = pd.Categorical(
            table["filter"], categories=list(dict.fromkeys(table["filter"]))
        )
    missing = [a for a in axes if a not in table.columns]
    if missing:
        raise ResultsError(f"{folder / SWEEP_FILE}: missing the axis columns {', '.join(missing)}")
    return SweepData(folder, name, axes, factor_axes, table, runs)


def _log_axis(axis) -> None:
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(general_number))
    axis.set_minor_formatter(NullFormatter())


def line_figure(data: SweepData, axis: str, rows: pd.DataFrame, title: str) -> Figure:
    """Every panel against one swept axis, a line per filter, interval bands."""
    fig = Figure(figsize=(10, 7), layout="constrained")
    grid = fig.subplots(2, 2)
    for ax, (column, interval, label, log, reference) in zip(grid.ravel(), PANELS, strict=True):
        if not np.isfinite(rows[column].to_numpy(float)).any():
            # e.g. a ratio to the oracle in a sweep without ekf-oracle: nothing to draw (and a
            # log axis over no data cannot be scaled)
            ax.text(0.5, 0.5, "no values (no reference filter in this sweep)", ha="center",
                    va="center", transform=ax.transAxes)  # fmt: skip
            ax.set_title(label)
            ax.set_axis_off()
            continue
        for name, sub in rows.groupby("filter", observed=True, sort=False):
            sub = sub.sort_values(axis)
            x, y = sub[axis].to_numpy(float), sub[column].to_numpy(float)
            kind = str(sub["kind"].iloc[0]) if "kind" in sub else None
            style = filter_style(str(name), kind)
            colour = style.colour
            ax.plot(x, y, marker=style.marker, label=str(name), gid=f"{column}/{name}", ms=3,
                    **style.line())  # fmt: skip
            if interval is not None:
                lo, hi = sub[interval[0]].to_numpy(float), sub[interval[1]].to_numpy(float)
                ax.fill_between(x, lo, hi, color=colour, alpha=0.15, linewidth=0)
        if reference is not None:
            ax.axhline(reference, color="k", lw=0.8, ls=":")
        values = sorted(rows[axis].unique())
        if axis in data.factor_axes:
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(values, [f"{v:.3g}" for v in values])
        shown = rows[column].to_numpy(float)
        shown = shown[np.isfinite(shown)]
        # A log axis only when the values span a decade: below that it shows one tick label.
        if log and shown.size and shown.min() > 0 and shown.max() / shown.min() >= 10:
            ax.set_yscale("log")
            _log_axis(ax.yaxis)
        ax.set_xlabel(axis)
        ax.set_title(label)
    handles, labels = legend_entries(grid.ravel())
    if handles:  # beside the panels, never over the data
        fig.legend(handles, labels, loc="outside right upper", fontsize=8)
    fig.suptitle(title)
    return fig


def heatmap_figure(
    data: SweepData, x_axis: str, y_axis: str, rows: pd.DataFrame, column: str, label: str
) -> Figure:
    """One heatmap per filter of `column` over two axes, every cell annotated. Ratios to the
    oracle use the report's one ratio scale (log, white at 1, ticks 1, 1.5, 2, 3, 5, 10, 30), and
    the oracle's own panel (1 everywhere) is left out; the cells show point estimates (the
    intervals are in sweep.parquet)."""
    ratio = column.endswith("_vs_oracle")
    names = [str(n) for n in rows["filter"].cat.categories if (rows["filter"] == n).any()]
    if ratio:  # the reference against itself: a constant panel of 1.00 says nothing
        names = [n for n in names if not np.allclose(rows.loc[rows["filter"] == n, column], 1.0)]
    cols = max(1, min(3, len(names)))
    nrows = max(1, math.ceil(len(names) / cols))
    fig = Figure(figsize=(4.2 * cols + 0.8, 3.6 * nrows + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, cols)).ravel()
    xs = sorted(rows[x_axis].unique())
    ys = sorted(rows[y_axis].unique())
    values = rows[column].to_numpy(float)
    finite = values[np.isfinite(values) & (values > 0)]
    if ratio:
        norm, cmap = ratio_norm(), ratio_cmap()
    elif column.startswith("rmse") and finite.size:
        norm, cmap = LogNorm(vmin=float(finite.min()), vmax=float(finite.max())), "RdYlGn_r"
    else:
        norm, cmap = None, "RdYlGn"
    image = None
    for ax, name in zip(axes, names, strict=False):
        sub = rows[rows["filter"] == name].pivot_table(index=y_axis, columns=x_axis, values=column)
        grid = sub.reindex(index=ys, columns=xs).to_numpy(float)
        if ratio:  # coloured by log10 of the ratio, clipped to the scale's ends
            image = ratio_image(ax, grid, origin="lower", interpolation=None,
                                gid=f"{column}/{name}")  # fmt: skip
        else:
            image = ax.imshow(grid, origin="lower", cmap=cmap, norm=norm, aspect="auto",
                              gid=f"{column}/{name}")  # fmt: skip
        for (i, j), v in np.ndenumerate(grid):
            share = column == "nees_in_bounds"
            text = "-" if not math.isfinite(v) else (f"{v:.0%}" if share else f"{v:#.3g}")
            ax.text(j, i, text, ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(xs)), [f"{v:.3g}" for v in xs], rotation=45)
        ax.set_yticks(range(len(ys)), [f"{v:.3g}" for v in ys])
        ax.set_xlabel(x_axis)
        ax.set_ylabel(y_axis)
        ax.set_title(name)
    for ax in axes[len(names) :]:
        ax.set_visible(False)
    if image is not None and ratio:
        ratio_colourbar(fig, image, axes[: len(names)].tolist(), "ratio (log)")
    elif image is not None:
        fig.colorbar(image, ax=axes[: len(names)].tolist(), shrink=0.8)
    # the heatmaps show point estimates: no promise of intervals in their title
    fig.suptitle(f"{data.name}: {label.replace(' (95 % paired interval)', '')}")
    return fig


def breakdown_range(
    table: pd.DataFrame, axis: str, *, within: float = 1.5, metric: str = "rmse_pos_vs_oracle"
) -> dict[str, tuple[float, float]]:
    """Per filter, the range of a factor axis around 1 (no mismatch) over which it stays within
    `within` x the oracle on `metric`: (lowest, highest) factor of that contiguous range; NaN, NaN
    when it is not within even at the factor closest to 1. Rows must vary along `axis` only."""
    out = {}
    for name, rows in table.groupby("filter", observed=True):
        rows = rows.sort_values(axis)
        values = rows[axis].to_numpy(dtype=float)
        ok = (rows[metric] <= within).to_numpy()
        centre = int(np.argmin(np.abs(np.log(values))))
        if not ok[centre]:
            out[str(name)] = (math.nan, math.nan)
            continue
        lo = hi = centre
        while lo > 0 and ok[lo - 1]:
            lo -= 1
        while hi < len(ok) - 1 and ok[hi + 1]:
            hi += 1
        out[str(name)] = (float(values[lo]), float(values[hi]))
    return out


def breakdown_blocks(data: SweepData, within: float) -> list[Block]:
    """Each filter's break-down range on the factor axis of a 1-D sweep: a sentence and a table
    (nothing for other sweeps)."""
    axes = [a for a in data.axes if a in data.factor_axes]
    if len(data.axes) != 1 or not axes:
        return []
    axis = axes[0]
    found = breakdown_range(data.table, axis, within=within)
    rows = [
        [Cell(name), *(Cell("-") if math.isnan(v) else Cell(f"{v:.3g}", v) for v in (lo, hi))]
        for name, (lo, hi) in found.items()
    ]
    return [
        Paragraph(
            f"Break-down: the range of {axis} around 1 over which a filter stays within"
            f" {within:g} x the oracle's position RMSE ('-': not even at 1)."
        ),
        TableBlock(("filter", f"lowest {axis}", f"highest {axis}"), rows, (False, True, True)),
    ]


def anchor(name: str) -> str:
    """The id of a sweep's heading in the report."""
    return "sweep-" + (re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "x")


def section(data: SweepData, save: FigureSaver, within: float = 1.5, level: int = 3) -> list[Block]:
    """A sweep's part of the report: its cells, the break-down ranges (one factor axis) and its
    figures (lines for one axis, a heatmap per metric for two; a set per value of a third),
    saved through `save` (the report's one figure writer)."""
    out: list[Block] = [Heading(f"Sweep {data.name}", level, anchor=anchor(data.name))]
    out.append(Paragraph(
        f"{data.runs} runs per cell, the same seed in every cell (cells are paired); ratios are to"
        " the EKF given the true noise, with 95 % paired bootstrap intervals."
    ))  # fmt: skip
    out += breakdown_blocks(data, within)
    table = data.table
    if len(data.axes) == 1:
        groups = [((), table)]
        plotted = data.axes
    else:
        rest = data.axes[2:]
        groups = list(table.groupby(rest, sort=True)) if rest else [((), table)]
        plotted = data.axes[:2]
    for key, rows in groups:
        values = np.atleast_1d(key)
        suffix = "" if not len(values) else "-" + "-".join(f"{v:g}" for v in values)
        where = "" if not len(values) else " (" + ", ".join(
            f"{a} {v:g}" for a, v in zip(data.axes[2:], values, strict=True)) + ")"  # fmt: skip
        if len(plotted) == 1:
            fig = line_figure(data, plotted[0], rows, data.name)
            out.append(save(fig, f"sweep-{data.name}{suffix}.{save.fmt}", data.name + where))
            continue
        for column, _, label, _, _ in PANELS:
            fig = heatmap_figure(data, plotted[0], plotted[1], rows, column, label)
            name = f"sweep-{data.name}-{column}{suffix}.{save.fmt}"
            out.append(save(fig, name, f"{data.name}: {label}{where}"))
    return out
