"""The report's section of the problems beyond the robot (SPEC 17): per result, the filters'
state figures and noise-estimate errors, and every entry of the estimated Q and R."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from ..problems.report import noise_table, summary_header, summary_rows
from .document import Block, Heading, Paragraph, TableBlock
from .plots import FigureSaver


def estimates_figure(result: dict) -> Figure | None:
    """One panel per entry of Q and R (upper triangle): each estimating filter's per-run
    estimates at the last step as a box, the true value dashed; None when no filter estimates."""
    runs, noise = result["runs"], result["noise"]
    estimating = [name for name, rows in noise.groupby("filter", sort=False)
                  if rows["estimated"].any()]  # fmt: skip
    if not estimating:
        return None
    entries = noise[(noise["i"] <= noise["j"])].drop_duplicates(subset=["matrix", "i", "j"])
    cols = min(3, len(entries))
    rows_n = -(-len(entries) // cols)
    fig = Figure(figsize=(3.6 * cols, 2.6 * rows_n + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows_n, cols, squeeze=False)).ravel()
    for ax, entry in zip(axes, entries.itertuples(index=False), strict=False):
        column = f"{entry.matrix.lower()}_{entry.i}_{entry.j}"
        shown = [name for name in estimating
                 if bool(noise[(noise["filter"] == name) & (noise["matrix"] == entry.matrix)]
                         ["estimated"].any())]  # fmt: skip
        data = [runs.loc[runs["filter"] == name, column].to_numpy() for name in shown]
        ax.boxplot(data, showfliers=False)
        ax.set_xticks(range(1, len(shown) + 1), shown, rotation=45, ha="right", fontsize=7)
        ax.axhline(entry.true, color="k", linestyle="--", linewidth=1)
        ax.set_title(f"{entry.matrix}{entry.i + 1}{entry.j + 1} (true {entry.true:g})", fontsize=9)
    for ax in axes[len(entries) :]:
        ax.set_visible(False)
    return fig


def problem_blocks(results: Sequence[dict], save: FigureSaver, fmt: str) -> list[Block]:
    """A heading, two tables and the estimates' figure per problem result (nothing without
    results)."""
    if not results:
        return []
    blocks: list[Block] = [Heading("Problems beyond the robot", anchor="problems")]
    for result in results:
        m = result["manifest"]
        name = m["scenario"]["name"]
        blocks.append(Heading(name, level=3, anchor=f"problem-{name}"))
        text = (f"Problem `{m['problem']}`, {m['runs']} runs, seed {m['seed']}. RMSE over the"
                f" oracle's ({m.get('reference') or 'no oracle'}) with its paired 95 % bootstrap"
                " interval; NEES of the whole state against the chi-square bounds of its"
                " dimension; relative Frobenius error of Q and R at the last step (mean ± sd"
                " over runs); seconds per run.")  # fmt: skip
        if m["scenario"].get("description"):
            text = m["scenario"]["description"] + " " + text
        if "gated" in result["summary"]:
            text += (" Gated / run: the measurements the filter's gate dropped, mean per run (it"
                     " neither updates nor adapts on them).")  # fmt: skip
        blocks.append(Paragraph(text))
        header = summary_header(result)
        numeric = [False, False, False] + [True] * (len(header) - 3)
        blocks.append(TableBlock(header, summary_rows(result), numeric=numeric))
        header, rows = noise_table(result)
        caption = "Q and R at the last step: mean ± sd over runs"
        numeric = [False] + [True] * (len(header) - 1)
        blocks.append(TableBlock(header, rows, numeric=numeric, caption=caption))
        fig = estimates_figure(result)
        if fig is not None:
            blocks.append(save(fig, f"{name}_estimates.{fmt}", f"{name}: the estimates of every"
                               " entry of Q and R at the last step over runs (boxes: quartiles,"
                               " whiskers 1.5 IQR), the true value dashed"))  # fmt: skip
    return blocks
