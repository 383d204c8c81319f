"""The report's section of the problems beyond the robot (SPEC 17): per result, the filters'
state figures and noise-estimate errors, and every entry of the estimated Q and R."""

from __future__ import annotations

from collections.abc import Sequence

from ..problems.report import SUMMARY_HEADER, noise_table, summary_rows
from .document import Block, Heading, Paragraph, TableBlock


def problem_blocks(results: Sequence[dict]) -> list[Block]:
    """A heading and two tables per problem result (nothing without results)."""
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
        blocks.append(Paragraph(text))
        blocks.append(TableBlock(SUMMARY_HEADER, summary_rows(result),
                                 numeric=[False, False, False] + [True] * 6))  # fmt: skip
        header, rows = noise_table(result)
        caption = "Q and R at the last step: mean ± sd over runs"
        numeric = [False] + [True] * (len(header) - 1)
        blocks.append(TableBlock(header, rows, numeric=numeric, caption=caption))
    return blocks
