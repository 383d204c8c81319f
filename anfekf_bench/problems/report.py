"""A problem result's tables as text (SPEC 17), for `anfekf run`'s console and `anfekf report`:
per filter the state's figures and the noise estimate's relative error, then every entry of the
estimated Q and R at the last step (mean and standard deviation over runs) beside the true one.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from .experiment import read_problem_result

SUMMARY_HEADER = ("filter", "kind", "estimates", "RMSE / oracle [95 %]", "ANEES",
                  "NEES in bounds", "Q rel. err", "R rel. err", "s / run")  # fmt: skip


def _g(value: float, digits: int = 3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def _mean_sd(mean: float, sd: float) -> str:
    if math.isfinite(sd) and sd <= 1e-12 * abs(mean):  # a constant's rounding (a fitted filter)
        sd = 0.0
    return f"{_g(mean)} ± {_g(sd, 2)}"


def summary_rows(result: dict) -> list[list[str]]:
    summary, timing = result["summary"], result["timing"]
    seconds = timing.groupby("filter", sort=False)["seconds"].mean()
    rows = []
    for r in summary.itertuples(index=False):
        ratio = _g(r.rmse_ratio, 4)
        if math.isfinite(r.rmse_ratio_lo) and math.isfinite(r.rmse_ratio_hi):
            ratio += f" [{_g(r.rmse_ratio_lo, 4)}, {_g(r.rmse_ratio_hi, 4)}]"
        q_err = _mean_sd(r.q_rel_err, r.q_rel_err_sd) if "Q" in r.estimates else "(assumed)"
        r_err = _mean_sd(r.r_rel_err, r.r_rel_err_sd) if "R" in r.estimates else "(assumed)"
        rows.append([r.filter, r.kind, r.estimates or "-", ratio, _g(r.anees),
                     f"{r.nees_in_bounds:.0%}", q_err, r_err,
                     _g(float(seconds.get(r.filter, math.nan)), 2)])  # fmt: skip
        if "gated" in summary:
            rows[-1].insert(-1, _g(r.gated, 3))
    return rows


def summary_header(result: dict) -> tuple[str, ...]:
    """SUMMARY_HEADER, with the gated measurements per run where the problem gates."""
    if "gated" not in result["summary"]:
        return SUMMARY_HEADER
    return (*SUMMARY_HEADER[:-1], "gated / run", SUMMARY_HEADER[-1])


def noise_table(result: dict) -> tuple[list[str], list[list[str]]]:
    """Header and rows: one row per filter that estimates noise, one column per entry of Q and
    R (upper triangle: they are symmetric), 'mean ± sd' over runs; first row the truth."""
    noise: pd.DataFrame = result["noise"]
    entries = noise[noise["i"] <= noise["j"]][["matrix", "i", "j", "true"]].drop_duplicates(
        subset=["matrix", "i", "j"]
    )
    keys = list(zip(entries["matrix"], entries["i"], entries["j"], strict=True))
    header = ["filter"] + [f"{m}{i + 1}{j + 1}" for m, i, j in keys]
    rows = [["true"] + [_g(v) for v in entries["true"]]]
    for name, rows_f in noise.groupby("filter", sort=False):
        if not rows_f["estimated"].any():
            continue
        by = rows_f.set_index(["matrix", "i", "j"])
        cells = []
        for m, i, j in keys:
            row = by.loc[(m, i, j)]
            cells.append(_mean_sd(row["mean"], row["sd"]) if row["estimated"] else "(assumed)")
        rows.append([name, *cells])
    return header, rows


def problem_console_table(folder: Path):
    """A rich table group of a problem result (the summary, then the noise entries)."""
    from rich.console import Group
    from rich.table import Table

    result = read_problem_result(folder)
    m = result["manifest"]
    tables = []
    title = (f"{m['scenario']['name']}: problem {m['problem']}, {m['runs']} runs, seed"
             f" {m['seed']}")  # fmt: skip
    t = Table(title=title, title_justify="left")
    for col in summary_header(result):
        t.add_column(col, justify="left" if col in ("filter", "kind") else "right")
    for row in summary_rows(result):
        t.add_row(*row)
    tables.append(t)
    header, rows = noise_table(result)
    t = Table(title="Q and R at the last step: mean ± sd over runs", title_justify="left")
    for col in header:
        t.add_column(col, justify="left" if col == "filter" else "right")
    for row in rows:
        t.add_row(*row)
    tables.append(t)
    return Group(*tables)
