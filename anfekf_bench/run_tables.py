"""The tables `anfekf run` prints at the end of a scenario or a sweep (rich): the summary, the
paired ratios with their intervals, the claims' verdicts, a sweep's ratios to the oracle."""

from __future__ import annotations

import math
from pathlib import Path

from rich.console import Console
from rich.table import Table
from rich.text import Text

from .text import one_line, plural


def summary_table(title: str, records: list[dict]) -> Table:
    from .analysis.metrics import format_number, format_share

    table = Table(title=title, title_justify="left")
    for col in (
        "filter",
        "runs",
        "diverged",
        "inconsistent",
        "RMSE pos (m)",
        "RMSE head (deg)",
        "ANEES",
        "in bounds",
    ):
        table.add_column(col, justify="left" if col == "filter" else "right")
    for r in records:
        table.add_row(
            Text(one_line(str(r["filter"]))),  # plain text: no markup, no control characters
            str(r["runs"]),
            str(r["diverged"]),
            str(r.get("inconsistent", "-")),
            format_number(r["rmse_pos"], 3),
            format_number(math.degrees(r["rmse_heading"]), 3),
            format_number(r["anees"], 2),
            format_share(r["nees_in_bounds"]),
        )
    return table


def sweep_summary_table(name: str, table, runs: int) -> Table:
    """The end of a sweep: per filter, its position RMSE over the oracle's across the cells
    (best, median, worst cell) and the cells within 1.5 x, with divergences."""
    from .analysis.metrics import format_number

    out = Table(title=f"sweep {name}: {plural(table['cell'].nunique(), 'cell')} x {runs} runs",
                title_justify="left")  # fmt: skip
    for col in ("filter", "RMSE / oracle best", "median", "worst", "cells <= 1.5x", "diverged"):
        out.add_column(col, justify="left" if col == "filter" else "right")
    for name_, rows in table.groupby("filter", observed=True, sort=False):
        ratio = rows["rmse_pos_vs_oracle"].astype(float)
        ok = int((ratio <= 1.5).sum())
        out.add_row(
            Text(one_line(str(name_))),
            format_number(ratio.min(), 3),
            format_number(ratio.median(), 3),
            format_number(ratio.max(), 3),
            f"{ok}/{len(rows)}",
            str(int(rows["diverged"].fillna(0).sum())),
        )
    return out


def format_interval(estimate: float, lo: float, hi: float, digits: int = 3) -> str:
    """'0.496 [0.452, 0.543]', '0.0536 [0.0395, 0.0670]' (significant digits, as in the report),
    or the estimate alone when it has no interval."""
    from .analysis.metrics import format_sig

    text = format_sig(estimate, digits)
    if math.isfinite(lo) and math.isfinite(hi):
        text += f" [{format_sig(lo, digits)}, {format_sig(hi, digits)}]"
    return text


def print_comparisons(out: Console, target: Path) -> None:
    """The paired ratios (95 % bootstrap intervals) and the claims' verdicts of a result."""
    from .analysis.metrics import format_number
    from .report.results import load_result
    from .storage import CLAIMS_FILE, COMPARISONS_FILE

    result = load_result(target)  # the report's one loader of results
    comparisons = result.read(COMPARISONS_FILE)
    if len(comparisons):
        table = Table(
            title="paired ratios over runs, 95 % bootstrap interval (p: Wilcoxon signed-rank)",
            title_justify="left",
        )
        for col in ("filter", "vs", "RMSE pos ratio", "p", "ANEES ratio", "runs"):
            table.add_column(col, justify="left" if col in ("filter", "vs") else "right")
        for (name, ref), rows in comparisons.groupby(["filter", "vs"], sort=False):
            by = rows.set_index("metric")
            rmse, anees = by.loc["rmse_pos"], by.loc["anees"]
            table.add_row(
                name, ref, format_interval(rmse.estimate, rmse.lo, rmse.hi),
                format_number(rmse.p_value, 4), format_interval(anees.estimate, anees.lo, anees.hi),
                str(int(rmse.runs_used)),
            )  # fmt: skip
        out.print(table)
        if int(comparisons["runs_used"].min()) < 10:
            out.print(
                "warning: fewer than 10 runs: intervals are wide and the NEES bounds hardly"
                " discriminate",
                highlight=False,
            )
    claims = result.read(CLAIMS_FILE)
    if claims:
        table = Table(title="claims (decided on the interval)", title_justify="left")
        for col in ("claim", "estimate [95 % interval]", "verdict", "note"):
            table.add_column(col)
        for c in claims:
            # summary JSON writes NaN as null
            est, lo, hi = (math.nan if c[k] is None else c[k] for k in ("estimate", "lo", "hi"))
            table.add_row(c["claim"], format_interval(est, lo, hi), c["verdict"], c["warning"])
        out.print(table)
