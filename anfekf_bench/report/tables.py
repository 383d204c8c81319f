"""The report's tables: the summary (report.md, report.html and the terminal) and the
leaderboard, built from the summary rows of every scenario."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from rich import box
from rich.console import Console, ConsoleOptions, RenderResult
from rich.measure import Measurement
from rich.table import Table
from rich.text import Text

from ..analysis.metrics import format_share, format_sig
from .data import FilterSeries, Ratio, ScenarioData, SummaryRow, first_with_role
from .document import Cell, Document, TableBlock, to_markdown
from .ranking import CONSISTENCY_NOTE, consistent, rank, ranking_note, rmse_ratio


def _ratio(value: float, reference: FilterSeries | None) -> float:
    if reference is None:
        return math.nan
    ref = reference.summary["rmse_pos"]
    return value / ref if ref and math.isfinite(ref) else math.nan


def summary_rows(scenarios: Sequence[ScenarioData]) -> list[SummaryRow]:
    """One row per filter and scenario, with the RMSE ratios against the EKF and the oracle."""
    rows = []
    for sc in scenarios:
        ekf, oracle = first_with_role(sc, "reference"), first_with_role(sc, "oracle")
        for f in sc.filters:
            s = f.summary
            rows.append(
                SummaryRow(
                    scenario=sc.name,
                    filter=f.name,
                    kind=f.kind,
                    runs=s["runs"],
                    runs_used=s["runs_used"],
                    rmse_pos=s["rmse_pos"],
                    rmse_heading_deg=math.degrees(s["rmse_heading"]),
                    anees=s["anees"],
                    nees_in_bounds=s["nees_in_bounds"],
                    nees_lo=s["nees_lo"],
                    nees_hi=s["nees_hi"],
                    vs_ekf=_ratio(s["rmse_pos"], ekf),
                    vs_oracle=_ratio(s["rmse_pos"], oracle),
                    rmse_vs_ekf=sc.ratio(f.name, ekf),
                    rmse_vs_oracle=sc.ratio(f.name, oracle),
                    anees_vs_oracle=sc.ratio(f.name, oracle, "anees"),
                    outliers=f.outliers,
                    ekf_name=ekf.name if ekf else "ekf",
                    oracle_name=oracle.name if oracle else "ekf-oracle",
                )
            )
    return rows


def format_ratio(r: Ratio | None, *, reference: bool = False, sep: str = " ") -> str:
    """'1.05 [1.03, 1.08]' (3 significant digits); 'ref.' for the reference itself."""
    if r is None:
        return "ref." if reference else "-"
    text = format_sig(r.estimate)
    if r.has_interval:
        text += f"{sep}[{format_sig(r.lo)}, {format_sig(r.hi)}]"
    return text


def _ratio_cell(r: Ratio | None, row: SummaryRow, ref_name: str, sep: str = " ") -> Cell:
    is_ref = row.filter == ref_name
    return Cell(format_ratio(r, reference=is_ref, sep=sep), r.estimate if r else None)


TABLE_HEADER = (
    "scenario", "filter", "runs used", "diverged", "RMSE pos [m]", "RMSE heading [deg]", "ANEES",
    "NEES in 95 % bounds", "RMSE / ekf [95 % CI]", "RMSE / oracle [95 % CI]",
    "ANEES / oracle [95 % CI]", "outlier runs",
)  # fmt: skip
_NUMERIC = (False, False) + (True,) * (len(TABLE_HEADER) - 2)


def table_row(row: SummaryRow, sep: str = " ") -> list[Cell]:
    """The cells of one summary row, shared by report.md, report.html and the terminal."""
    return [
        Cell(row.scenario),
        Cell(row.filter),
        Cell(f"{row.runs_used}/{row.runs}", row.runs_used),
        Cell(str(row.runs - row.runs_used), row.runs - row.runs_used),
        Cell(format_sig(row.rmse_pos), row.rmse_pos),
        Cell(format_sig(row.rmse_heading_deg), row.rmse_heading_deg),
        Cell(format_sig(row.anees), row.anees),
        Cell(format_share(row.nees_in_bounds), row.nees_in_bounds),
        _ratio_cell(row.rmse_vs_ekf, row, row.ekf_name, sep),
        _ratio_cell(row.rmse_vs_oracle, row, row.oracle_name, sep),
        _ratio_cell(row.anees_vs_oracle, row, row.oracle_name, sep),
        Cell(str(len(row.outliers)), len(row.outliers)),
    ]


def table_cells(row: SummaryRow) -> list[str]:
    """The formatted cells of one summary row (text only)."""
    return [c.text for c in table_row(row)]


# The terminal table: the same cells under two-line headers, intervals on a second line.
TERMINAL_HEADER = (
    "scenario", "filter", "runs\nused", "RMSE\npos [m]", "RMSE\nhead [deg]", "ANEES",
    "NEES in\nbounds", "RMSE\n/ ekf", "RMSE\n/ oracle", "ANEES\n/ oracle", "out-\nliers",
)  # fmt: skip
_TERMINAL_SKIP = (3,)  # "diverged": the terminal shows it in "runs used" (48/50) only


def _full_table(rows: Sequence[SummaryRow]) -> Table:
    """Every column of the summary, one table (a terminal wide enough for it)."""
    table = Table(
        title="Summary across scenarios (RMSE: time mean of the RMSE-over-runs curve;"
        " ratios: paired, 95 % bootstrap interval below)",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
        collapse_padding=True,
    )
    for i, col in enumerate(TERMINAL_HEADER):
        # Text, not str: "[m]" would be read as rich markup and vanish. An interval stays on one
        # line (its own, below the ratio).
        ratio = "/" in col
        table.add_column(Text(col), justify="left" if i < 2 else "right", no_wrap=i < 2 or ratio,
                         min_width=14 if ratio else None)  # fmt: skip
    previous = None
    for row in rows:
        if previous is not None and row.scenario != previous:
            table.add_section()
        cells = [c for i, c in enumerate(table_row(row, sep="\n")) if i not in _TERMINAL_SKIP]
        table.add_row(*(Text(c.text) for c in cells))
        previous = row.scenario
    return table


# A narrow terminal (80 columns) gets the columns that decide a comparison, one table per
# scenario (its name as the title instead of a column): squeezed into 80 columns, the full
# table cut every number to "0.1…".
COMPACT_HEADER = ("filter", "runs\nused", "RMSE\npos [m]", "ANEES", "NEES in\nbounds",
                  "RMSE / oracle\n[95 % CI]")  # fmt: skip
_COMPACT_CELLS = (1, 2, 4, 6, 7, 9)  # their places in table_row


def _compact_tables(rows: Sequence[SummaryRow]) -> list:
    out: list = [
        Text(
            "Summary (narrow terminal: RMSE heading, the ratios to the EKF, ANEES / oracle and"
            " outlier runs are in report.md; a wider terminal shows them here)"
        )
    ]
    for scenario in dict.fromkeys(r.scenario for r in rows):
        table = Table(title=Text(scenario), title_justify="left", box=box.SIMPLE_HEAD,
                      pad_edge=False, collapse_padding=True)  # fmt: skip
        for i, col in enumerate(COMPACT_HEADER):
            table.add_column(Text(col), justify="left" if i == 0 else "right", no_wrap=True)
        for row in rows:
            if row.scenario == scenario:
                cells = table_row(row, sep=" ")
                table.add_row(*(Text(cells[i].text) for i in _COMPACT_CELLS))
        out.append(table)
    return out


@dataclass(frozen=True)
class SummaryTable:
    """The terminal's summary table: every column where the terminal fits it whole, else the
    compact tables (decided when printed, from the console's width)."""

    rows: Sequence[SummaryRow]

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        full = _full_table(self.rows)
        # the full table where it fits unsqueezed (its widest cells whole), else the compact one
        if Measurement.get(console, options.update(width=10**4), full).maximum <= options.max_width:
            yield full
        else:
            yield from _compact_tables(self.rows)


def rich_table(rows: Sequence[SummaryRow]) -> SummaryTable:
    """The summary table for the terminal (readable at 80 columns: `SummaryTable`)."""
    return SummaryTable(list(rows))


def markdown_table(rows: Sequence[SummaryRow]) -> str:
    """The summary table as GitHub markdown."""
    return to_markdown(Document("", [summary_table(rows)])).split("\n", 2)[2].strip()


def summary_table(rows: Sequence[SummaryRow]) -> TableBlock:
    # A filter without a covariance (KalmanNet) has runs but no NEES: the caption says so.
    no_nees = sorted({r.filter for r in rows if r.runs_used and math.isnan(r.anees)})
    caption = (
        f"NEES not available (-) for {', '.join(no_nees)}: no covariance (a learned gain)"
        if no_nees
        else ""
    )
    return TableBlock(TABLE_HEADER, [table_row(r) for r in rows], _NUMERIC, caption)


def leaderboard_table(rows: Sequence[SummaryRow]) -> TableBlock:
    """Filters x scenarios: position RMSE over the oracle's with its interval (sortable in the
    HTML by any scenario or by the median), a dot where the filter is consistent
    (`ranking.consistent`). Ranked as the figure is (`ranking.rank`): the median is over the
    scenarios every ranked filter ran; filters that ran in fewer follow, unranked."""
    ranking = rank(rows)
    scenarios = ranking.all_scenarios
    cells = {(r.filter, r.scenario): r for r in rows}
    body = []
    for name in ranking.ranked + ranking.unranked:
        line: list[Cell] = [Cell(name)]
        for scen in scenarios:
            r = cells.get((name, scen))
            if r is None:
                line.append(Cell("-"))
                continue
            reference = r.filter == r.oracle_name
            value = rmse_ratio(r)
            mark = " •" if consistent(r) else ""
            text = format_ratio(r.rmse_vs_oracle, reference=reference)
            line.append(Cell(text + mark, value))
        if name in ranking.median:
            median = ranking.median[name]
            line.append(Cell(format_sig(median) if math.isfinite(median) else "n/a", median))
        else:
            m = len(scenarios)
            line.append(Cell(f"unranked ({ranking.ran_in[name]}/{m} scenarios)", math.inf))
        body.append(line)
    header = ("filter", *scenarios, "median")
    caption = (
        f"Position RMSE / oracle's [95 % interval]; {ranking_note(ranking)}; {CONSISTENCY_NOTE};"
        " '-': not run in that scenario; click a header to sort"
    )
    return TableBlock(header, body, (False, *[True] * (len(scenarios) + 1)), caption=caption)


LEADERBOARD_CAPTION = (
    "Leaderboard: each filter's position RMSE over the oracle EKF's in each scenario, on one"
    " log colour scale centred on 1 (white); frame: the 95 % paired interval includes 1;"
    " dot: consistent (ANEES within the 95 % chi-square band of the run-averaged NEES, and NEES"
    " in that band on at least 85 % of steps); grey: no value ('-': the filter was not run in"
    " that scenario; 'n/a': every run diverged); filters ranked best first by the median over"
    " the scenarios every ranked filter ran, those that ran in fewer listed below, unranked"
)
