"""The worst case over a suite of scenarios (SPEC 19): one row per filter, ranked by its WORST
position-RMSE ratio to the oracle over every scenario, not by wins or by a median.

Per scenario s the ratio r_s = RMSE(filter) / RMSE(oracle) is the paired statistic of the
scenario tables (`statistics.rmse_statistic` on the runs where neither diverged). Over the suite:

    worst = max_s r_s,      geometric mean = exp(mean_s log r_s)

with 95 % percentile intervals from one bootstrap: in each resample every scenario's runs are
drawn with replacement (independently across scenarios: their runs are independent; the filter
and the oracle with the same indices: paired), r_s recomputed, and the max and the geometric
mean taken over the resampled ratios. A percentile interval of a max is biased low where two
scenarios are close to the max (the resampled max is at least each scenario's resampled ratio);
it says how much the worst case could move with other runs, not more.

Beside them: the lowest share of steps with NEES in the 95 % bounds over the constant-noise
scenarios (and over all), the runs that lost lock (diverged, or a largest position error above
`LOST_LOCK_M` and `LOST_LOCK_FACTOR` times the oracle's on the same run) and the inconsistent runs
(`metrics.inconsistent_runs`: time-mean NEES above NEES_EXPLODED), summed over the suite.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from . import statistics as st
from .metrics import inconsistent_runs

LOST_LOCK_M = 1.0  # as report.real.LOST_LOCK_M for recorded drives
LOST_LOCK_FACTOR = 3.0  # ... and this many times the oracle's largest error on the same run
RESAMPLES = 1000

SUITE_COLUMNS = [
    "rank", "filter", "kind", "scenarios", "worst", "worst_lo", "worst_hi", "worst_scenario",
    "geomean", "geomean_lo", "geomean_hi", "nees_in_bounds_min_constant", "nees_in_bounds_min",
    "lost_lock", "inconsistent", "diverged", "runs", "drives_vs_tuned",
]  # fmt: skip


@dataclass(frozen=True)
class FilterRuns:
    """One filter's (runs, steps) position error and NEES and its (runs,) divergence flags."""

    pos_err: np.ndarray
    nees: np.ndarray
    diverged: np.ndarray


@dataclass(frozen=True)
class SuiteScenario:
    """One scenario of the suite: its filters' runs, which one is the oracle, whether its true
    noise changes (a schedule) and each filter's kind."""

    name: str
    oracle: str
    changing: bool
    filters: dict[str, FilterRuns]
    kinds: dict[str, str] = field(default_factory=dict)


def _lost_lock(f: FilterRuns, oracle: FilterRuns) -> int:
    """Runs that diverged, or whose largest position error exceeds both LOST_LOCK_M and
    LOST_LOCK_FACTOR times the oracle's largest on the same run (where the oracle drifts too, a
    blackout, so does the bar)."""
    with np.errstate(invalid="ignore"):
        worst = np.nanmax(np.where(np.isfinite(f.pos_err), f.pos_err, np.inf), axis=1)
        bar = np.maximum(LOST_LOCK_M, LOST_LOCK_FACTOR * np.nanmax(oracle.pos_err, axis=1))
        big = worst > bar
    lost = np.asarray(f.diverged, bool) | (big & ~np.asarray(oracle.diverged, bool))
    return int(lost.sum())


def _ratio_draws(
    f: FilterRuns, oracle: FilterRuns, rng: np.random.Generator, resamples: int
) -> tuple[float, np.ndarray]:
    """The scenario's ratio and `resamples` paired bootstrap draws of it (NaN: no common run)."""
    ok = st.common_runs(f.diverged, oracle.diverged)
    a, b = f.pos_err[ok], oracle.pos_err[ok]
    n = a.shape[0]
    if n == 0:
        return math.nan, np.full(resamples, np.nan)
    with np.errstate(all="ignore"):
        estimate = float(st.rmse_statistic(a) / st.rmse_statistic(b))
        idx = rng.integers(0, n, size=(resamples, n))
        draws = st.resampled_statistic(st.rmse_statistic, a, idx) / st.resampled_statistic(
            st.rmse_statistic, b, idx
        )
    return estimate, np.asarray(draws, dtype=float)


def _interval(draws: np.ndarray, confidence: float) -> tuple[float, float]:
    if draws.size == 0 or not np.all(np.isfinite(draws)):
        return math.nan, math.nan
    tail = 50.0 * (1.0 - confidence)
    lo, hi = np.percentile(draws, [tail, 100.0 - tail])
    return float(lo), float(hi)


def suite_table(
    scenarios: Sequence[SuiteScenario],
    *,
    drives: dict[str, float] | None = None,
    resamples: int = RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> pd.DataFrame:
    """The leaderboard (module doc), one row per filter other than the oracles, sorted by the
    worst ratio (NaN, a scenario with no common run, counts as worst); filters absent from some
    scenario come after those in every one (`scenarios` says in how many each ran). `drives`:
    per filter name, its ratio to ekf-tuned on recorded drives (a column of its own)."""
    total = len(scenarios)
    names: dict[str, str] = {}
    for sc in scenarios:
        for name in sc.filters:
            if name != sc.oracle and name not in names:
                names[name] = sc.kinds.get(name, "")
    rows = []
    for name, kind in names.items():
        ratios, draws, in_bounds, in_bounds_const, where = [], [], [], [], []
        lost = incons = diverged = runs = 0
        for s, sc in enumerate(scenarios):
            f = sc.filters.get(name)
            if f is None:
                continue
            oracle = sc.filters[sc.oracle]
            # One stream per (scenario, filter): a filter's interval does not depend on which
            # other filters the suite holds.
            rng = np.random.default_rng([seed, s, *name.encode()])
            r, d = _ratio_draws(f, oracle, rng, resamples)
            ratios.append(r)
            draws.append(d)
            where.append(sc.name)
            ok = ~np.asarray(f.diverged, bool)
            share = float(st.in_bounds_statistic(f.nees[ok])) if ok.any() else math.nan
            in_bounds.append(share)
            if not sc.changing:
                in_bounds_const.append(share)
            lost += _lost_lock(f, oracle)
            incons += inconsistent_runs(f.nees, ok)
            diverged += int((~ok).sum())
            runs += len(ok)
        r = np.where(np.isfinite(ratios), ratios, np.inf)
        D = np.where(np.isfinite(np.array(draws)), np.array(draws), np.inf)
        worst_i = int(np.argmax(r))
        with np.errstate(all="ignore"):
            geo = float(np.exp(np.mean(np.log(r))))
            geo_draws = np.exp(np.mean(np.log(D), axis=0))
        worst_lo, worst_hi = _interval(D.max(axis=0), confidence)
        geo_lo, geo_hi = _interval(geo_draws, confidence)
        rows.append({
            "filter": name, "kind": kind, "scenarios": len(ratios),
            "worst": float(r[worst_i]), "worst_lo": worst_lo, "worst_hi": worst_hi,
            "worst_scenario": where[worst_i], "geomean": geo,
            "geomean_lo": geo_lo, "geomean_hi": geo_hi,
            "nees_in_bounds_min_constant": min(in_bounds_const, default=math.nan),
            "nees_in_bounds_min": min(in_bounds, default=math.nan),
            "lost_lock": lost, "inconsistent": incons, "diverged": diverged, "runs": runs,
            "drives_vs_tuned": (drives or {}).get(name, math.nan),
        })  # fmt: skip
    df = pd.DataFrame(rows, columns=[c for c in SUITE_COLUMNS if c != "rank"])
    df["_all"] = df["scenarios"] < total
    df = df.sort_values(["_all", "worst", "geomean"], kind="stable").drop(columns="_all")
    df.insert(0, "rank", np.arange(1, len(df) + 1))
    return df.reset_index(drop=True)
