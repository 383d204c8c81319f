"""The report's figures over all scenarios: the overview (ratios to the oracle, NEES in bounds)
and the leaderboard (filters x scenarios on the one ratio colour scale). They draw filters in the
report's one style map (`plots.filter_style`)."""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.legend_handler import HandlerTuple
from matplotlib.patches import Rectangle

from ..analysis.metrics import format_sig
from ..filters.registry import comparison_rank, role_of
from .data import FEW_RUNS, Ratio, SummaryRow
from .plots import (
    MAX_LABELLED_GROUP,
    ORACLE_COLOUR,
    RC,
    filter_colour,
    filter_marker,
    filter_style,
    legend_entries,
    plain_log_axis,
    ratio_colour,
    ratio_colourbar,
    ratio_image,
)
from .ranking import CONSISTENCY_NOTE, GREY_NOTE, consistent, rank, ranking_note, rmse_ratio


def _ratio_points(ax: Axes, groups: dict, width: float, key: str, get, labelled: set[str]) -> None:
    """One point per filter and scenario at its ratio, with its 95 % interval as error bar."""
    for j, (scen, group) in enumerate(groups.items()):
        for i, row in enumerate(group):
            ratio: Ratio | None = get(row)
            if ratio is None or not math.isfinite(ratio.estimate) or ratio.estimate <= 0:
                continue
            x = j + (i - (len(group) - 1) / 2) * width
            colour = filter_colour(row.filter)
            if ratio.has_interval:
                err = [[max(ratio.estimate - ratio.lo, 0.0)], [max(ratio.hi - ratio.estimate, 0.0)]]
            else:
                err = None
            bars = ax.errorbar(
                [x], [ratio.estimate], yerr=err, fmt=filter_marker(row.filter), ms=5,
                color=colour, ecolor=colour,
                elinewidth=1.4, capsize=3,
                label=None if row.filter in labelled else row.filter,
            )  # fmt: skip
            bars.lines[0].set_gid(f"overview_{key}/{scen}/{row.filter}")
            if err is not None:
                bars.lines[2][0].set_gid(f"overview_{key}_ci/{scen}/{row.filter}")
            labelled.add(row.filter)
            if len(group) > MAX_LABELLED_GROUP:
                continue
            ax.annotate(format_sig(ratio.estimate), (x, ratio.hi if ratio.has_interval else
                        ratio.estimate), xytext=(0, 3), textcoords="offset points",
                        ha="center", va="bottom", fontsize=6.5)  # fmt: skip


@matplotlib.rc_context(RC)
def overview_figure(rows: Sequence[SummaryRow]) -> Figure:
    """Per scenario and filter: position RMSE and ANEES divided by the oracle EKF's (log scale,
    95 % paired bootstrap intervals as error bars), and the share of steps with NEES in bounds.

    Ratios to the reference on a log axis: a filter 1 % worse than the oracle shows as 1.01, and
    one diverging filter (RMSE 20 x) cannot flatten the others into the floor."""
    scenarios = list(dict.fromkeys(r.scenario for r in rows))
    # In every group: the plain EKF first, then the adaptive filters, the oracle last
    ordered = sorted(rows, key=lambda r: comparison_rank(r.kind))
    groups = {s: [r for r in ordered if r.scenario == s] for s in scenarios}
    width = 0.8 / max(len(g) for g in groups.values())
    fig = Figure(figsize=(max(11.0, 3.4 * len(scenarios) + 1.5), 5.0), layout="constrained")
    ax_rmse, ax_anees, ax_cons = fig.subplots(1, 3, width_ratios=[1.2, 1.2, 1])
    labelled: set[str] = set()
    _ratio_points(ax_rmse, groups, width, "rmse_ratio", lambda r: r.rmse_vs_oracle, labelled)
    _ratio_points(ax_anees, groups, width, "anees_ratio", lambda r: r.anees_vs_oracle, labelled)
    for j, (scen, group) in enumerate(groups.items()):
        for i, row in enumerate(group):
            centre = j + (i - (len(group) - 1) / 2) * width
            value = 100 * row.nees_in_bounds
            bars = ax_cons.bar(
                centre,
                value if math.isfinite(value) else 0.0,  # all runs diverged: an empty slot
                width,
                color=filter_colour(row.filter),
                hatch=filter_style(row.filter).hatch,
                edgecolor="white",
                linewidth=0,
                label=None if row.filter in labelled else row.filter,
                gid=f"overview_nees_in_bounds/{scen}/{row.filter}",
            )
            labelled.add(row.filter)
            if len(group) <= MAX_LABELLED_GROUP:
                ax_cons.bar_label(bars, labels=[format_sig(value)], fontsize=6, padding=2,
                                  rotation=90)  # fmt: skip
    ticks = [_tick(s, groups[s]) for s in scenarios]
    for ax in (ax_rmse, ax_anees, ax_cons):
        ax.set_xticks(np.arange(len(scenarios)), ticks)
        ax.set_xlim(-0.6, len(scenarios) - 0.4)
        ax.grid(axis="x", visible=False)
    oracle = next((r.oracle_name for r in rows if role_of(r.kind) == "oracle"), "ekf-oracle")
    for ax, what in ((ax_rmse, "position RMSE"), (ax_anees, "ANEES")):
        ax.axhline(1.0, color=ORACLE_COLOUR, lw=1.0, ls="--",
                   label=f"{oracle} (= 1)" if oracle not in labelled else None)  # fmt: skip
        labelled.add(oracle)
        plain_log_axis(ax)
        ax.set_ylabel(f"{what} / {oracle}'s (log)")
        ax.margins(y=0.12)
    ax_rmse.set_title("accuracy: position RMSE / oracle's\n(lower is better)", fontsize=9)
    ax_anees.set_title("ANEES / oracle's\n(oracle's ANEES is about 3)", fontsize=9)
    ax_cons.set_ylabel("steps with run-averaged NEES in bounds [%]")
    ax_cons.set_ylim(0, 108)
    ax_cons.set_title("steps with NEES in 95 % bounds\n(higher is better)", fontsize=9)
    handles, labels = legend_entries((ax_rmse, ax_anees, ax_cons))
    # each filter's marker and its bar (colour and hatch) side by side: the bars' key too
    swatches = {name: Rectangle((0, 0), 1, 1, facecolor=filter_colour(name), edgecolor="white",
                                hatch=filter_style(name).hatch, linewidth=0)
                for name in dict.fromkeys(r.filter for r in rows)}  # fmt: skip
    pairs = zip(handles, labels, strict=True)
    handles = [(h, swatches[lab]) if lab in swatches else h for h, lab in pairs]
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 6),
               handler_map={tuple: HandlerTuple(ndivide=None, pad=0.3)},
               title="error bars: 95 % paired bootstrap interval over runs")  # fmt: skip
    runs = "/".join(str(n) for n in sorted({r.runs for r in rows}))
    fig.suptitle(f"Overview: {len(scenarios)} scenarios, {runs} runs each")
    return fig


def _tick(scenario: str, group: list) -> str:
    """The scenario's x label, with a warning when its runs are too few."""

    used = min(r.runs_used for r in group)
    return f"{scenario}\n(only {used} runs)" if used < FEW_RUNS else scenario


def _text_colour(rgba) -> str:
    r, g, b = rgba[:3]
    return "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "white"


@matplotlib.rc_context(RC)
def leaderboard_figure(rows: Sequence[SummaryRow]) -> Figure:
    """Filters x scenarios: each cell the filter's position RMSE over the oracle's in that
    scenario (colour on the fixed ratio scale, the value written in), with a frame where the 95 %
    interval of the ratio includes 1 and a dot where the filter is consistent
    (`ranking.consistent`). Filters are ranked by their median ratio over the scenarios every
    ranked filter ran (`ranking.rank`); those that ran in fewer are listed below a line,
    unranked. Grey cells (no value) say why: '-' not run, 'n/a' every run diverged."""
    ranking = rank(rows)
    scenarios = ranking.all_scenarios
    cells: dict[tuple[str, str], SummaryRow] = {(r.filter, r.scenario): r for r in rows}
    oracle = next((r.oracle_name for r in rows if role_of(r.kind) == "oracle"), "ekf-oracle")
    names = ranking.ranked + ranking.unranked
    values = np.array([[rmse_ratio(cells.get((n, s))) for s in scenarios] for n in names])
    n, m = len(names), len(scenarios)
    fig = Figure(figsize=(max(6.5, 3.6 + 1.15 * m), max(5.6, 3.4 + 0.3 * n)), layout="constrained")
    ax = fig.subplots()
    image = ratio_image(ax, values, gid="leaderboard")
    for i, name in enumerate(names):
        for j, scen in enumerate(scenarios):
            row = cells.get((name, scen))
            value = values[i, j]
            colour = ratio_colour(value)
            if row is None or not math.isfinite(value):
                ax.text(j, i, "-" if row is None else "n/a", ha="center", va="center",
                        fontsize=7, gid=f"leaderboard_none/{scen}/{name}")  # fmt: skip
                continue
            text = ("ref." if name == row.oracle_name else format_sig(value)) + (
                " •" if consistent(row) else ""
            )
            ax.text(j, i, text, ha="center", va="center", fontsize=7,
                    color=_text_colour(colour), gid=f"leaderboard_value/{scen}/{name}")  # fmt: skip
            ratio = row.rmse_vs_oracle
            if ratio is not None and ratio.has_interval and ratio.lo <= 1.0 <= ratio.hi:
                frame = Rectangle((j - 0.46, i - 0.44), 0.92, 0.88, fill=False, lw=1.2,
                                  edgecolor="black")  # fmt: skip
                frame.set_gid(f"leaderboard_ci1/{scen}/{name}")
                ax.add_patch(frame)
    if ranking.unranked:  # a line between the ranked filters and those listed apart
        ax.axhline(len(ranking.ranked) - 0.5, color="black", lw=2.0, gid="leaderboard_unranked")
    ax.set_xticks(np.arange(m), scenarios, rotation=30, ha="left", fontsize=8)
    ax.xaxis.tick_top()
    labels = ranking.ranked + [f"{u} (unranked: {ranking.ran_in[u]}/{m})" for u in ranking.unranked]
    ax.set_yticks(np.arange(n), labels, fontsize=8)
    for label, name in zip(ax.get_yticklabels(), names, strict=True):
        grey = name == oracle or name in ranking.unranked
        label.set_color(ORACLE_COLOUR if grey else "black")
    ax.grid(False)
    ax.set_xlim(-0.5, m - 0.5)
    ax.set_ylim(n - 0.5, -0.5)
    ratio_colourbar(fig, image, ax, f"position RMSE / {oracle}'s (log)")
    fig.suptitle(f"Leaderboard: position RMSE over {oracle}'s\n{n} filters x {m} scenarios")
    notes = [ranking_note(ranking), "frame: the 95 % paired interval includes 1",
             CONSISTENCY_NOTE, GREY_NOTE]  # fmt: skip
    ax.set_xlabel("\n".join(textwrap.fill(t, 95) for t in notes), fontsize=7)
    return fig
