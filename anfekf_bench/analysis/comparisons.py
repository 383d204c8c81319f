"""Paired comparisons and claims of one scenario (SPEC 8), computed from its steps table.

Every filter of a scenario sees the same random numbers in run i, so two filters are compared on
the runs where neither diverged, with one set of resampled run indices for both (a paired
bootstrap) and a paired test over runs. A claim is decided on its interval: it holds when the
whole interval is on the right side of the threshold, fails when the whole interval is on the
wrong side, and is inconclusive otherwise.

The share of steps with NEES in bounds gets no bootstrap interval: resampling runs with
replacement repeats runs and biases the run-averaged NEES (see `statistics.METRICS`); shares are
compared on their point estimates, and such a verdict says so (`method` "point").
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import pandas as pd

from . import statistics as st
from .tables import filter_arrays

RATIO_METRICS = ("rmse_pos", "rmse_heading", "anees")
SHARE_METRICS = ("nees_in_bounds",)
# The references every filter is compared with, when the scenario has them: the roles
# (filters.spec.ROLES) of the plain EKF and of the oracle, in this order.
REFERENCE_ROLES = ("reference", "oracle")
COMPARISON_COLUMNS = [
    "scenario", "filter", "vs", "metric", "kind", "runs_used", "estimate", "lo", "hi",
    "method", "p_value", "test",
]  # fmt: skip


def comparison_pairs(
    filters: Iterable[tuple[str, str]],
    extra: Iterable[tuple[str, str]] = (),
    prefer: frozenset[str] | set[str] = frozenset(),
) -> list[tuple[str, str]]:
    """(filter, vs) pairs: every filter against each reference present, then the user's pairs.

    `filters` is (name, role) in scenario order (the role its spec declares); the first filter of
    each reference role is that reference, the first of those in `prefer` if any is. A reference
    is not compared with itself.
    """
    filters = list(filters)
    refs = []
    for role in REFERENCE_ROLES:
        of_kind = [n for n, r in filters if r == role]
        name = next((n for n in of_kind if n in prefer), of_kind[0] if of_kind else None)
        if name is not None:
            refs.append(name)
    pairs = [(name, ref) for ref in refs for name, _ in filters if name != ref]
    for pair in extra:
        if tuple(pair) not in pairs:
            pairs.append(tuple(pair))
    return pairs


def filters_arrays(steps: pd.DataFrame, names: Iterable[str]) -> dict[str, dict[str, np.ndarray]]:
    """`tables.filter_arrays` of each filter named (the comparisons only read them)."""
    return {name: filter_arrays(steps, name) for name in dict.fromkeys(names)}


def compare(
    a: dict[str, np.ndarray],
    b: dict[str, np.ndarray],
    metric: str,
    *,
    resamples: int,
    seed: int,
) -> dict:
    """The paired comparison of filter arrays a against b on one metric."""
    ok = st.common_runs(a["diverged"], b["diverged"])
    spec = st.METRICS[metric]
    xa, xb = a[spec.column][ok], b[spec.column][ok]
    record = {"metric": metric, "runs_used": int(ok.sum())}
    if metric in SHARE_METRICS:
        sa = float(spec.statistic(xa)) if ok.any() else math.nan
        sb = float(spec.statistic(xb)) if ok.any() else math.nan
        record.update(
            kind="difference", estimate=sa - sb, lo=math.nan, hi=math.nan, method="point",
            p_value=math.nan, test="",
        )  # fmt: skip
        return record
    interval = st.paired_bootstrap(
        xa, xb, spec.statistic, kind="ratio", resamples=resamples, seed=seed
    )
    per_run = st.per_run_rmse if metric.startswith("rmse") else st.per_run_mean
    test = st.paired_test(per_run(xa), per_run(xb))
    record.update(
        kind="ratio", estimate=interval.estimate, lo=interval.lo, hi=interval.hi,
        method=interval.method, p_value=test.p_value, test=test.name,
    )  # fmt: skip
    return record


# A table of many comparisons is split over `jobs` threads: each comparison draws from `seed`
# alone, so it gives the same row on whichever thread it runs. Below this many (runs x recorded
# steps) cells of ratio comparisons (a tenth of a second or so; a zoo scenario of 50 runs has 6
# million) the table is computed on this thread alone.
PARALLEL_MIN_CELLS = 100_000


def comparisons_frame(
    steps: pd.DataFrame,
    pairs: list[tuple[str, str]],
    *,
    metrics: tuple[str, ...] = ("rmse_pos", "anees"),
    resamples: int = 2000,
    seed: int = 0,
    jobs: int = 1,
    arrays: dict[str, dict[str, np.ndarray]] | None = None,
) -> pd.DataFrame:
    """One row per (filter, vs, metric): ratio with its paired interval, and the paired test.
    `jobs` > 1: a large table's comparisons are shared out over that many threads (the
    same rows, in the same order). `arrays`: `filters_arrays` of the steps, when the caller
    has them."""
    scenario = str(steps["scenario"].iloc[0])
    named = [n for pair in pairs for n in pair]
    if arrays is None or not set(named) <= set(arrays):
        arrays = filters_arrays(steps, named)
    chunks = _chunks(pairs, jobs, sum(m not in SHARE_METRICS for m in metrics), arrays)
    if len(chunks) < 2:
        rows = _rows(scenario, pairs, arrays, metrics, resamples, seed)
    else:
        from joblib import Parallel, delayed

        # threads: the bootstrap's matrix products release the GIL, and nothing is shipped
        with st.one_blas_thread():
            parts = Parallel(n_jobs=len(chunks), backend="threading")(
                delayed(_rows)(scenario, chunk, arrays, metrics, resamples, seed)
                for chunk in chunks
            )
        done: dict[tuple, list] = {pair: [] for pair in pairs}  # the pairs' order
        for row in (row for part in parts for row in part):
            done[(row["filter"], row["vs"])].append(row)
        rows = [row for pair_rows in done.values() for row in pair_rows]
    return pd.DataFrame(rows, columns=COMPARISON_COLUMNS)


def _chunks(pairs: list, jobs: int, ratio_metrics: int, arrays: dict) -> list[list]:
    """`pairs` split into `jobs` chunks when the table is large enough (PARALLEL_MIN_CELLS),
    each filter's pairs in one chunk (its resampled statistics are computed once there), the
    filters dealt out in turn so that the chunks cost about the same; else one chunk."""
    if jobs < 2 or len(set(pairs)) != len(pairs):
        return [pairs]
    cells = sum(arrays[a]["pos_err"].size for a, _ in pairs) * ratio_metrics
    if cells < PARALLEL_MIN_CELLS:
        return [pairs]
    filters = list(dict.fromkeys(a for a, _ in pairs))
    share = {a: i % jobs for i, a in enumerate(filters)}
    chunks = [[pair for pair in pairs if share[pair[0]] == k] for k in range(jobs)]
    return [c for c in chunks if c]


def _rows(scenario: str, pairs, arrays, metrics, resamples: int, seed: int) -> list[dict]:
    rows = []
    for name, ref in pairs:
        for metric in metrics:
            row = {"scenario": scenario, "filter": name, "vs": ref}
            row.update(compare(arrays[name], arrays[ref], metric, resamples=resamples, seed=seed))
            rows.append(row)
    return rows


def claim_text(claim) -> str:
    """'anfekf rmse_pos <= 0.6 x ekf' / 'anfekf nees_in_bounds >= 0.85'."""
    op, threshold = ("<=", claim.at_most) if claim.at_most is not None else (">=", claim.at_least)
    if claim.vs is None:
        return f"{claim.filter} {claim.metric} {op} {threshold:g}"
    if claim.metric in SHARE_METRICS:
        return f"{claim.filter} {claim.metric} - {claim.vs} {op} {threshold:g}"
    return f"{claim.filter} {claim.metric} {op} {threshold:g} x {claim.vs}"


def _point_verdict(value: float, at_most: float | None, at_least: float | None) -> str:
    if not math.isfinite(value):
        return "inconclusive"
    if at_most is not None:
        return "holds" if value <= at_most else "fails"
    return "holds" if value >= at_least else "fails"


def evaluate_claims(
    steps: pd.DataFrame,
    claims,
    *,
    resamples: int = 2000,
    seed: int = 0,
    arrays: dict[str, dict[str, np.ndarray]] | None = None,
) -> list:
    """One verdict record per claim of the scenario (SPEC 8); `arrays` as `comparisons_frame`."""
    names = [c.filter for c in claims] + [c.vs for c in claims if c.vs is not None]
    if arrays is None or not set(names) <= set(arrays):
        arrays = filters_arrays(steps, names)
    out = []
    for claim in claims:
        a = arrays[claim.filter]
        spec = st.METRICS[claim.metric]
        record = {
            "claim": claim_text(claim), "filter": claim.filter, "vs": claim.vs,
            "metric": claim.metric, "at_most": claim.at_most, "at_least": claim.at_least,
            "source": claim.source,
        }  # fmt: skip
        if claim.vs is not None:
            found = compare(a, arrays[claim.vs], claim.metric, resamples=resamples, seed=seed)
        elif claim.metric in SHARE_METRICS:
            ok = ~a["diverged"]
            value = float(spec.statistic(a[spec.column][ok])) if ok.any() else math.nan
            found = {"runs_used": int(ok.sum()), "kind": "value", "estimate": value,
                     "lo": math.nan, "hi": math.nan, "method": "point"}  # fmt: skip
        else:
            ok = ~a["diverged"]
            interval = st.bootstrap_one(
                a[spec.column][ok], spec.statistic, resamples=resamples, seed=seed
            )
            found = {"runs_used": int(ok.sum()), "kind": "value", "estimate": interval.estimate,
                     "lo": interval.lo, "hi": interval.hi, "method": interval.method}  # fmt: skip
        record.update({k: found[k] for k in ("runs_used", "estimate", "lo", "hi", "method")})
        if found["method"] == "point":
            record["verdict"] = _point_verdict(found["estimate"], claim.at_most, claim.at_least)
            record["warning"] = "point estimate: no bootstrap interval for a share"
        else:
            record["verdict"] = st.verdict(
                found["lo"], found["hi"], at_most=claim.at_most, at_least=claim.at_least
            )
            threshold = claim.at_most if claim.at_most is not None else claim.at_least
            interval = st.Interval(found["estimate"], found["lo"], found["hi"], 0.95, resamples,
                                   found["method"])  # fmt: skip
            record["warning"] = st.interval_too_wide(interval, threshold) or ""
        if st.too_few_runs(record["runs_used"]):
            record["warning"] = (record["warning"] + "; " if record["warning"] else "") + (
                f"only {record['runs_used']} runs"
            )
        out.append(record)
    return out
