"""The leaderboard's ranking and its consistency mark, shared by its figure (plots.py) and its
table (tables.py), so the two can never order or mark filters differently.

A median over only the scenarios each filter ran in compares filters on different scenarios: a
filter run only where every filter does well ranks above one that was tested everywhere. So the
ranking is over the scenarios that every ranked filter ran; filters that ran in fewer are listed
apart, unranked, with the number of scenarios they ran in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .data import SummaryRow

# NEES in the 95 % bounds on at least this share of steps: one half of the consistency mark.
CONSISTENT_SHARE = 0.85


def consistent(row: SummaryRow) -> bool:
    """The leaderboard's consistency mark: the ANEES lies within the 95 % chi-square band of the
    run-averaged NEES (nees_lo..nees_hi for the runs used) AND the run-averaged NEES is in that
    band on at least CONSISTENT_SHARE of the steps. A share of steps alone passes a filter whose
    NEES is in bounds most of the time but averages 100x the pose dimension (a few huge peaks)."""
    values = (row.anees, row.nees_lo, row.nees_hi, row.nees_in_bounds)
    if not all(math.isfinite(v) for v in values):
        return False
    return row.nees_lo <= row.anees <= row.nees_hi and row.nees_in_bounds >= CONSISTENT_SHARE


def rmse_ratio(row: SummaryRow | None) -> float:
    """The cell's value: position RMSE over the oracle's (1 for the oracle; NaN: no value)."""
    if row is None:
        return math.nan
    if row.filter == row.oracle_name:
        return 1.0
    return row.rmse_vs_oracle.estimate if row.rmse_vs_oracle is not None else row.vs_oracle


@dataclass(frozen=True)
class Ranking:
    """The leaderboard's order: `ranked` (best first) by the median ratio over `scenarios`, the
    scenarios every ranked filter ran; `unranked` ran in fewer (`ran_in`: how many each ran in)."""

    ranked: list[str]
    unranked: list[str]
    scenarios: list[str]  # the scenarios the ranking is over (every ranked filter ran them)
    all_scenarios: list[str]
    ran_in: dict[str, int]
    median: dict[str, float]  # ranked filters: the median over `scenarios` (inf: no value)


def rank(rows: Sequence[SummaryRow]) -> Ranking:
    """Rank the filters that ran in the most scenarios, over the scenarios they all ran (for one
    report of one folder of scenarios: every scenario); every other filter is unranked. A cell
    with no value (every run diverged) counts as the worst in the median."""
    scenarios = list(dict.fromkeys(r.scenario for r in rows))
    names = list(dict.fromkeys(r.filter for r in rows))
    ran = {n: {r.scenario for r in rows if r.filter == n} for n in names}
    most = max((len(s) for s in ran.values()), default=0)
    # The filters that ran in the most scenarios; among them, those sharing the first one's set
    # (so the ranked filters have one common set of scenarios, never an empty one).
    widest = [n for n in names if len(ran[n]) == most]
    common = ran[widest[0]] if widest else set()
    ranked_set = [n for n in widest if ran[n] == common]
    over = [s for s in scenarios if s in common]
    cells = {(r.filter, r.scenario): r for r in rows}
    median = {}
    for n in ranked_set:
        values = np.array([rmse_ratio(cells.get((n, s))) for s in over], dtype=float)
        values = np.where(np.isfinite(values), values, np.inf)
        median[n] = float(np.median(values)) if values.size else math.inf
    ranked = sorted(ranked_set, key=lambda n: median[n])  # stable: report order on ties
    unranked = sorted((n for n in names if n not in ranked_set), key=lambda n: -len(ran[n]))
    return Ranking(ranked, unranked, over, scenarios, {n: len(ran[n]) for n in names}, median)


def ranking_note(ranking: Ranking) -> str:
    """The sentence saying what the order is over (the figure's and the table's captions)."""
    k, m = len(ranking.scenarios), len(ranking.all_scenarios)
    over = "all " + str(m) if k == m else f"the {k} of {m}"
    text = (
        f"ranked best first by the median position RMSE / oracle's over {over} scenarios that"
        " every ranked filter ran (a cell with no value counts as worst)"
    )
    if ranking.unranked:
        text += (
            f"; listed apart, unranked: {len(ranking.unranked)} filter(s) that ran in fewer"
            " scenarios (compared on fewer scenarios, a median would mislead)"
        )
    return text


CONSISTENCY_NOTE = (
    "•: consistent: ANEES within the 95 % chi-square band of the run-averaged NEES and NEES in"
    f" that band on >= {CONSISTENT_SHARE * 100:.0f} % of steps"
)
GREY_NOTE = "grey: no value (not run in that scenario, '-', or every run diverged, 'n/a')"
