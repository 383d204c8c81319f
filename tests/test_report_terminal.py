"""The report's terminal table is readable at 80 columns: squeezed into them, the full table cut
every number ("10/…", "0.1…"); a narrow console gets the deciding columns, one table per
scenario, every cell whole, and a wide one every column."""

from __future__ import annotations

import io
import math

from rich.console import Console

from anfekf_bench.report.data import Ratio, SummaryRow
from anfekf_bench.report.tables import rich_table

NAMES = ("ekf", "anfekf", "sage-husa-w10", "akhlaghi-slow", "mmae-wide", "ekf-oracle")


def rows() -> list[SummaryRow]:
    out = []
    for scenario in ("zoo_consistency", "zoo_wrong_r"):
        for i, name in enumerate(NAMES):
            oracle = name == "ekf-oracle"
            r = 0.996 + 0.35 * i
            out.append(SummaryRow(
                scenario=scenario, filter=name, kind="ekf-oracle" if oracle else "anfekf",
                runs=50, runs_used=48, rmse_pos=0.1234 * r, rmse_heading_deg=0.7123,
                anees=1234.5 if i == 2 else 3.21, nees_in_bounds=0.931, nees_lo=2.5, nees_hi=3.5,
                vs_ekf=math.nan, vs_oracle=r,
                rmse_vs_oracle=None if oracle else Ratio(r, 0.993 * r, 1.0123 * r, 50),
                rmse_vs_ekf=None, anees_vs_oracle=None,
            ))  # fmt: skip
    return out


def render(width: int) -> str:
    console = Console(width=width, file=io.StringIO(), record=True, color_system=None)
    console.print(rich_table(rows()))
    return console.export_text()


def test_the_terminal_table_is_whole_at_80_columns():
    text = render(80)
    assert max(len(line) for line in text.splitlines()) <= 80
    assert "…" not in text  # nothing cut
    for name in NAMES:  # every filter's name whole, in each scenario's table
        assert text.count(f" {name} ") == 2, name
    assert "zoo_consistency" in text and "zoo_wrong_r" in text
    assert "48/50" in text and " 1234 " in text and "93.1 %" in text
    # the ratio to the oracle with its whole interval, on one line
    assert "0.996 [0.989, 1.01]" in text


def test_a_wide_terminal_gets_every_column():
    text = render(200)
    assert "…" not in text
    assert "RMSE" in text and "head [deg]" in text and "liers" in text
    assert text.count("zoo_consistency") == len(NAMES)  # the scenario column
