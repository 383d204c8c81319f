"""Paired statistics over Monte Carlo runs (SPEC section 8): intervals, tests and claim verdicts.

Every filter of a scenario sees the same random numbers in run i, so a comparison of two filters
is paired over runs. The scenario metrics (`metrics.summarize_filter`) are not per-run averages:
rmse_pos is the time mean of the RMSE-over-runs curve, nees_in_bounds a share of steps whose
run-averaged NEES is inside bounds that depend on the number of runs. A bootstrap therefore
resamples run indices (once per resample for both filters) and recomputes the scenario statistic
on the resampled (runs, steps) arrays.

Statistics take arrays of shape (..., runs, steps) and reduce the last two axes, so a whole batch
of resamples is computed in one call; on a (runs, steps) array they return a float equal to the
value `summarize_filter` reports for the same (non-diverged) runs.
"""

from __future__ import annotations

import hashlib
import inspect
import math
import threading
import warnings
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, NamedTuple

import numpy as np
from scipy import stats
from threadpoolctl import ThreadpoolController

from .metrics import (
    nan_aware_mean,
    nees_bounds,
    rmse_curve,
    runs_counted,
    share_inside,
    share_inside_bounds,
)
from .run_means import COMPILED, time_means

Statistic = Callable[[np.ndarray], "float | np.ndarray"]
Kind = Literal["ratio", "difference"]
Verdict = Literal["holds", "fails", "inconclusive"]

# Bootstrap distributions whose spread is below this share of their size are treated as constant:
# identical filters, or a constant per-run ratio with a homogeneous statistic, differ by rounding.
DEGENERATE_RTOL = 1e-12
# Upper bound on the array cells of one batch of resamples (`_cells_per_resample`).
_BATCH_CELLS = 1 << 22
# scipy >= 1.15 names the generator `rng`; older releases call it `random_state`.
_RNG_KEYWORD = "rng" if "rng" in inspect.signature(stats.bootstrap).parameters else "random_state"
_WILCOXON = "Wilcoxon signed-rank"


@dataclass(frozen=True)
class Interval:
    """A point estimate with a two-sided bootstrap confidence interval.

    estimate: the statistic on the full sample. lo, hi: the interval bounds (NaN when undefined).
    confidence: the nominal coverage, e.g. 0.95. resamples: the bootstrap resamples drawn.
    method: "BCa"; "percentile" when BCa is undefined for the bootstrap distribution (e.g. every
    resample on one side of the estimate); "degenerate" when the distribution is constant, giving
    lo == hi == estimate; "undefined" when the statistic is not finite or there are fewer than two
    runs, and "biased" when the interval does not contain its own estimate (the bootstrap
    distribution sits beside it, e.g. for nees_in_bounds): both give NaN bounds.
    """

    estimate: float
    lo: float
    hi: float
    confidence: float
    resamples: int
    method: str


@dataclass(frozen=True)
class TestResult:
    """A paired test over runs: the test statistic, its two-sided p-value and the test's name."""

    __test__ = False  # not a pytest test class

    statistic: float
    p_value: float
    name: str


class MetricSpec(NamedTuple):
    """A scenario metric: its per-step column, its statistic, and whether it may be bootstrapped.

    bootstrap is False when a bootstrap over runs gives no usable interval for the metric (see
    `in_bounds_statistic`).
    """

    column: str
    statistic: Statistic
    bootstrap: bool = True


def _float_or_array(x: np.ndarray) -> float | np.ndarray:
    """A float for a 0-d result (one (runs, steps) array), the array for a batch."""
    return float(x) if np.ndim(x) == 0 else x


def rmse_statistic(err: np.ndarray) -> float | np.ndarray:
    """Time mean of the RMSE-over-runs curve, for err (..., runs, steps): rmse_pos, rmse_heading."""
    err = np.asarray(err, dtype=float)
    curve = rmse_curve(np.moveaxis(err, -2, 0))
    if np.isnan(curve).any():  # steps without a score (recorded logs): metrics.nan_aware_mean
        return _float_or_array(nan_aware_mean(curve, axis=-1))
    return _float_or_array(curve.mean(axis=-1))


def mean_statistic(nees: np.ndarray) -> float | np.ndarray:
    """Time mean of the run-averaged values, for nees (..., runs, steps): anees."""
    nees = np.asarray(nees, dtype=float)
    if np.isnan(nees).any():  # steps without a score (recorded logs): metrics.nan_aware_mean
        return _float_or_array(nan_aware_mean(nan_aware_mean(nees, axis=-2), axis=-1))
    return _float_or_array(nees.mean(axis=-2).mean(axis=-1))


def in_bounds_statistic(nees: np.ndarray) -> float | np.ndarray:
    """Share of steps whose run-averaged NEES lies strictly inside the 95 % chi-square bounds.

    nees is (..., runs, steps); the bounds are `metrics.nees_bounds` for that number of runs.
    Not for a bootstrap over runs: drawing runs with replacement repeats runs, which widens the
    spread of each run-average, so resampled shares sit systematically below the estimate (for a
    consistent filter, 95 % intervals covered the true 95 % share in 5-12 % of trials).
    """
    nees = np.asarray(nees, dtype=float)
    if np.isnan(nees).any():  # steps without a score: bounds for the runs each step has
        avg, counts = nan_aware_mean(nees, axis=-2), runs_counted(nees)
        if avg.ndim == 1:
            return share_inside_bounds(avg, counts)
        rows = zip(avg.reshape(-1, avg.shape[-1]), counts.reshape(-1, avg.shape[-1]), strict=True)
        flat = [share_inside_bounds(a, c) for a, c in rows]
        return np.array(flat).reshape(avg.shape[:-1])
    lo, hi = nees_bounds(nees.shape[-2])
    avg = nees.mean(axis=-2)
    if avg.ndim == 1:
        return share_inside(avg, lo, hi)
    return np.apply_along_axis(share_inside, -1, avg, lo, hi)


# The statistics above take a mean over runs first: statistic(x) = g(mean over runs of h(x)). A
# resample of run indices is then a weight per run, and the run means of every resample at once
# are one matrix product (`_resampled`): no (resamples, runs, steps) copy of the data. Steps
# without a score (NaN: recorded logs) leave a run out of that step's mean: the weighted sum over
# the runs that have a value, over their summed weight (np.nanmean over the resampled runs); g's
# time mean then leaves out the steps no resampled run scores (`nan_aware_mean`).
def _time_mean_of(m: np.ndarray) -> np.ndarray:
    """nan_aware_mean(m, axis=-1), bit for bit (the same sums: np.nanmean is the sum of the
    values with NaN set to 0 over the count of the others), for a temporary `m` it overwrites:
    one NaN mask and no copy, where np.nanmean makes a copy and a second mask. The bootstrap's
    (resamples, steps) run means are the largest arrays a table builds."""
    nan = np.isnan(m)
    if not nan.any():
        return np.mean(m, axis=-1)
    np.copyto(m, 0.0, where=nan)
    count = np.sum(~nan, axis=-1, dtype=np.intp)
    with np.errstate(invalid="ignore", divide="ignore"):  # a resample that scores no step: NaN
        return np.divide(np.sum(m, axis=-1), count)


# (h, root): g is the time mean of the run means (`_time_mean_of`), of their square root where root
rmse_statistic.run_mean_form = (np.square, True)
mean_statistic.run_mean_form = (lambda x: x, False)


# A comparison table bootstraps every filter against each of its references with one seed, so
# the same resamples of run indices reach the same filter's data again and again (a reference in
# each of its rows, a filter once per reference). Their statistics are kept, keyed by digests of
# the data and the indices: the same product on the same arrays, so the same bits, computed once.
_RESAMPLED_MEMO: OrderedDict[bytes, np.ndarray] = OrderedDict()
_MEMO_ENTRIES = 1024
# One lock for both memos: a comparison table's chunks run on threads (comparisons_frame), and
# an entry read by one may be evicted by another. What is computed is not locked: two threads
# that compute the same entry compute the same bits.
_MEMO_LOCK = threading.Lock()


def _memo_get(memo: OrderedDict, key: bytes) -> np.ndarray | None:
    with _MEMO_LOCK:
        found = memo.get(key)
        if found is not None:
            memo.move_to_end(key)
        return found


def _memo_put(memo: OrderedDict, key: bytes, value: np.ndarray, entries: int) -> np.ndarray:
    with _MEMO_LOCK:
        memo[key] = value
        if len(memo) > entries:
            memo.popitem(last=False)
    return value


def _digest(*parts: np.ndarray | str) -> bytes:
    # SHA-256 rather than BLAKE2: OpenSSL's runs on the CPU's SHA instructions, 2.3x the speed
    # here (the memo's keys hash each filter's (runs, steps) data once per comparison)
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, str):
            h.update(part.encode())
            continue
        a = np.ascontiguousarray(part)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.data)
    return h.digest()


def _resampled(statistic: Statistic, x: np.ndarray) -> Callable[[np.ndarray], np.ndarray] | None:
    """statistic(x[idx]) for stacks of run indices idx (..., k), through the weights of each
    resample's runs (memoised: `_RESAMPLED_MEMO`); None when the statistic has no run-mean
    form."""
    form = getattr(statistic, "run_mean_form", None)
    if form is None:
        return None
    compute = _resampled_by_weights(form, x)
    of_x = _digest(f"{statistic.__module__}.{statistic.__qualname__}", x)

    def of(idx: np.ndarray) -> np.ndarray:
        key = of_x + _digest(idx)
        found = _memo_get(_RESAMPLED_MEMO, key)
        if found is None:
            found = _memo_put(_RESAMPLED_MEMO, key, compute(idx), _MEMO_ENTRIES)
        return found.copy()

    return of


def resampled_statistic(statistic: Statistic, x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """statistic(x[idx_b]) for each row idx_b of run indices idx (resamples, k): a bootstrap's
    draws, for a caller that combines several scenarios' draws (analysis.suite)."""
    fast = _resampled(statistic, x)
    if fast is not None:
        return fast(idx)
    return np.array([statistic(x[i]) for i in idx], dtype=float)


# The summed weights of the runs that score each step, per resample (the run means'
# denominators, `_resampled_by_weights`): the same for every filter whose steps without a score
# are the same (a recorded log's, unless a run diverged), so computed once per table and
# resample batch. Each entry is a (resamples, steps) array: few are kept.
_SCORED_MEMO: OrderedDict[bytes, np.ndarray] = OrderedDict()
_SCORED_ENTRIES = 16
_BLOCK_ROWS = 32  # resamples `_resampled_by_weights` takes at once (a block stays in the cache)


def _blocks(rows: int) -> list[tuple[int, int]]:
    """[lo, hi) blocks of `_BLOCK_ROWS` resamples, the last one longer rather than of one row:
    BLAS computes a one-row product as a matrix-vector product, whose sums may round
    differently from the same row's in a matrix product."""
    bounds = list(range(0, rows, _BLOCK_ROWS)) + [rows]
    if len(bounds) > 2 and bounds[-1] - bounds[-2] == 1:
        del bounds[-2]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def _resampled_by_weights(form: tuple, x: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """`_resampled`'s computation: the run means of every resample as one matrix product."""
    h, root = form
    hx = h(x)
    scored = ~np.isnan(hx)
    unscored = not scored.all()
    if unscored:
        hx = np.where(scored, hx, 0.0)
        scored = scored.astype(float)
        of_scored = _digest(scored)
    runs = x.shape[0]

    def of(idx: np.ndarray) -> np.ndarray:
        flat = idx.reshape(-1, idx.shape[-1])
        rows = flat.shape[0]
        cells = (flat + runs * np.arange(rows)[:, None]).ravel()
        weights = np.bincount(cells, minlength=rows * runs).reshape(rows, runs) / flat.shape[-1]
        den = None
        if unscored:
            key = of_scored + _digest(idx)
            den = _memo_get(_SCORED_MEMO, key)
            if den is None:
                den = _memo_put(_SCORED_MEMO, key, weights @ scored, _SCORED_ENTRIES)
        out = np.empty(rows)
        # the run means and g in blocks of resamples that stay in the cache: each step on the
        # whole (resamples, steps) array (33 MB to 130 MB on the drives) went to memory and back
        buffer = np.empty((min(rows, 2 * _BLOCK_ROWS), hx.shape[-1]))
        for lo, hi in _blocks(rows):
            block = np.matmul(weights[lo:hi], hx, out=buffer[: hi - lo])
            if COMPILED:  # g(block / den) in one pass (run_means), the same bits
                time_means(block, block if den is None else den[lo:hi], den is not None, root,
                           out[lo:hi])  # fmt: skip
                continue
            if den is not None:
                with np.errstate(invalid="ignore", divide="ignore"):  # 0 / 0: no run scores it
                    np.divide(block, den[lo:hi], out=block)
            if root:
                np.sqrt(block, out=block)
            out[lo:hi] = _time_mean_of(block)
        return out.reshape(idx.shape[:-1])

    return of


METRICS: Mapping[str, MetricSpec] = MappingProxyType(
    {
        "rmse_pos": MetricSpec("pos_err", rmse_statistic),
        "rmse_heading": MetricSpec("heading_err", rmse_statistic),
        "anees": MetricSpec("nees", mean_statistic),
        "nees_in_bounds": MetricSpec("nees", in_bounds_statistic, bootstrap=False),
    }
)


def common_runs(*diverged: np.ndarray) -> np.ndarray:
    """Boolean mask of the runs that diverged in none of the given filters.

    A paired comparison keeps a run for both filters or for neither.
    """
    masks = [np.asarray(d, dtype=bool) for d in diverged]
    return ~np.logical_or.reduce(masks) if masks else np.ones(0, dtype=bool)


def per_run_rmse(err: np.ndarray) -> np.ndarray:
    """Each run's own RMSE over time, (runs,) from err (runs, steps): sqrt(mean_steps err^2)
    (NaN entries, steps without a score, left out)."""
    return rmse_curve(np.asarray(err, dtype=float).T)


def per_run_mean(x: np.ndarray) -> np.ndarray:
    """Each run's mean over time, (runs,) from x (runs, steps) (NaN entries left out)."""
    return nan_aware_mean(np.asarray(x, dtype=float), axis=1)


def _check_settings(resamples: int, confidence: float) -> None:
    if int(resamples) != resamples or resamples < 1:
        raise ValueError(f"resamples must be a positive integer, got {resamples!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")


def _as_runs_by_steps(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"{name} must be a (runs, steps) array, got shape {x.shape}")
    return x


def _cells_per_resample(a: np.ndarray, weighted: bool) -> int:
    """Array cells one resample of a (runs, steps) array costs: its run weights and run means
    through `_resampled`, else a copy of the resampled runs. Sets the batch size only: the
    resamples drawn are the same whatever the batch (the products' rounding is not: BLAS picks
    its kernel by shape), and the batch depends on the data's shape alone."""
    runs, steps = a.shape
    return runs + steps if weighted else runs * steps


def _bootstrap(
    theta: Callable[[np.ndarray], float | np.ndarray],
    estimate: float,
    runs: int,
    cells: int,
    *,
    resamples: int,
    confidence: float,
    seed: int | np.random.SeedSequence,
) -> Interval:
    """Bootstrap theta(run indices) over runs: BCa, falling back as documented on `Interval`."""

    def interval(lo: float, hi: float, method: str) -> Interval:
        return Interval(estimate, float(lo), float(hi), confidence, int(resamples), method)

    nan = float("nan")
    if runs < 2 or not math.isfinite(estimate):
        return interval(nan, nan, "undefined")

    def statistic(idx: np.ndarray, axis: int = -1) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.asarray(theta(idx), dtype=float)

    data = (np.arange(runs),)
    common = dict(
        statistic=statistic,
        vectorized=True,
        confidence_level=confidence,
        batch=max(1, _BATCH_CELLS // max(cells, 1)),
    )
    rng = np.random.default_rng(seed)
    with one_blas_thread():
        return _bootstrap_interval(data, common, rng, resamples, estimate, interval)


def one_blas_thread():
    """A context with BLAS on one thread. The bootstrap's products are small: BLAS threads cost
    more than they give (40x slower on a busy machine). The limit is the process's: code that
    bootstraps on several threads at once holds it around them all, so that one thread's exit
    does not lift it under another (comparisons_frame)."""
    return _threadpools().limit(limits=1, user_api="blas")


_CONTROLLER: list[ThreadpoolController] = []


def _threadpools() -> ThreadpoolController:
    """The process's thread pools, found once: looking them up reads /proc/self/maps, which
    cost 3 ms a bootstrap (0.3 s of a zoo scenario's 104 comparisons)."""
    if not _CONTROLLER:
        _CONTROLLER.append(ThreadpoolController())
    return _CONTROLLER[0]


def _bootstrap_interval(data, common, rng, resamples, estimate, interval) -> Interval:
    """`_bootstrap`'s work once the statistic is set up: percentile, checks, then BCa."""
    nan = float("nan")
    with np.errstate(all="ignore"):  # inf / NaN resamples are handled below
        res = stats.bootstrap(
            data, n_resamples=int(resamples), method="percentile", **common, **{_RNG_KEYWORD: rng}
        )
    dist = np.asarray(res.bootstrap_distribution, dtype=float)
    if not np.all(np.isfinite(dist)):
        return interval(nan, nan, "undefined")
    if np.ptp(dist) <= DEGENERATE_RTOL * np.max(np.abs(dist)):
        return interval(estimate, estimate, "degenerate")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", stats.DegenerateDataWarning)
        with np.errstate(all="ignore"):
            bca = stats.bootstrap(
                data,
                n_resamples=0,
                bootstrap_result=res,
                method="BCa",
                **common,
                **{_RNG_KEYWORD: rng},
            )
    lo, hi, method = *bca.confidence_interval, "BCa"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi, method = *res.confidence_interval, "percentile"
    slack = DEGENERATE_RTOL * abs(estimate)
    if not lo - slack <= estimate <= hi + slack:
        return interval(nan, nan, "biased")
    return interval(lo, hi, method)


def paired_bootstrap(
    a: np.ndarray,
    b: np.ndarray,
    statistic: Statistic,
    *,
    kind: Kind = "ratio",
    resamples: int = 2000,
    confidence: float = 0.95,
    seed: int | np.random.SeedSequence = 0,
) -> Interval:
    """Paired bootstrap interval for statistic(a) / statistic(b) (or the difference, a - b).

    a, b: (runs, steps) arrays of two filters on the same runs (row i is run i for both). Each
    resample draws one set of run indices and applies it to both filters. The point estimate is
    the statistic on the full sample; the interval is BCa (`Interval.method` says otherwise).
    Identical a and b give exactly 1 (ratio) / 0 (difference) with lo == hi; a non-finite
    statistic (e.g. statistic(b) == 0 for a ratio) gives NaN bounds. Deterministic for a seed.
    """
    a = _as_runs_by_steps(a, "a")
    b = _as_runs_by_steps(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"a and b must have the same (runs, steps) shape: {a.shape} != {b.shape}")
    if kind not in ("ratio", "difference"):
        raise ValueError(f"kind must be 'ratio' or 'difference', got {kind!r}")
    _check_settings(resamples, confidence)

    def combine(sa: float | np.ndarray, sb: float | np.ndarray) -> float | np.ndarray:
        with np.errstate(all="ignore"):
            return np.divide(sa, sb) if kind == "ratio" else np.subtract(sa, sb)

    fast_a, fast_b = _resampled(statistic, a), _resampled(statistic, b)

    def theta(idx: np.ndarray) -> float | np.ndarray:
        if fast_a is not None and fast_b is not None:
            return combine(fast_a(idx), fast_b(idx))
        return combine(statistic(a[idx]), statistic(b[idx]))

    runs = a.shape[0]
    estimate = float(combine(statistic(a), statistic(b))) if runs else float("nan")
    return _bootstrap(
        theta,
        estimate,
        runs,
        2 * _cells_per_resample(a, fast_a is not None and fast_b is not None),
        resamples=resamples,
        confidence=confidence,
        seed=seed,
    )


def bootstrap_one(
    a: np.ndarray,
    statistic: Statistic,
    *,
    resamples: int = 2000,
    confidence: float = 0.95,
    seed: int | np.random.SeedSequence = 0,
) -> Interval:
    """Bootstrap interval for one filter's scenario statistic, a (runs, steps), over runs.

    Same method and edge cases as `paired_bootstrap` (e.g. for a filter's nees_in_bounds share).
    """
    a = _as_runs_by_steps(a, "a")
    _check_settings(resamples, confidence)
    runs = a.shape[0]
    with np.errstate(all="ignore"):
        estimate = float(statistic(a)) if runs else float("nan")
    fast = _resampled(statistic, a)
    return _bootstrap(
        fast if fast is not None else (lambda idx: statistic(a[idx])),
        estimate,
        runs,
        _cells_per_resample(a, fast is not None),
        resamples=resamples,
        confidence=confidence,
        seed=seed,
    )


def paired_test(per_run_a: np.ndarray, per_run_b: np.ndarray) -> TestResult:
    """Two-sided Wilcoxon signed-rank test on paired per-run values (e.g. `per_run_rmse`).

    Pairs with a non-finite value (a diverged run) are left out. All-zero differences give
    p_value 1.0; fewer than two pairs give NaN.
    """
    a = np.asarray(per_run_a, dtype=float)
    b = np.asarray(per_run_b, dtype=float)
    if a.ndim != 1 or a.shape != b.shape:
        raise ValueError(f"per-run values must be two (runs,) arrays: {a.shape}, {b.shape}")
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    if a.size < 2:
        return TestResult(float("nan"), float("nan"), _WILCOXON)
    if np.all(a == b):
        return TestResult(0.0, 1.0, _WILCOXON)
    res = stats.wilcoxon(a, b, alternative="two-sided")
    return TestResult(float(res.statistic), float(res.pvalue), _WILCOXON)


def verdict(
    lo: float, hi: float, *, at_most: float | None = None, at_least: float | None = None
) -> Verdict:
    """Decide a claim on an interval: the whole interval on the right side of the threshold holds.

    at_most t: "holds" if hi <= t, "fails" if lo > t. at_least t: "holds" if lo >= t, "fails" if
    hi < t. Otherwise, or with a NaN bound, "inconclusive". Give exactly one of at_most, at_least.
    """
    if (at_most is None) == (at_least is None):
        raise ValueError("give exactly one of at_most and at_least")
    if math.isnan(lo) or math.isnan(hi):
        return "inconclusive"
    if at_most is not None:
        if hi <= at_most:
            return "holds"
        return "fails" if lo > at_most else "inconclusive"
    if lo >= at_least:
        return "holds"
    return "fails" if hi < at_least else "inconclusive"


def too_few_runs(runs: int, minimum: int = 10) -> bool:
    """True when a scenario has too few runs for its intervals and NEES share to mean much."""
    return runs < minimum


def interval_too_wide(interval: Interval, threshold: float) -> str | None:
    """A warning when the interval cannot support a claim about threshold, else None.

    That is when it straddles the threshold (lo < threshold < hi) or is undefined (NaN bounds).
    """
    level = f"{100 * interval.confidence:g} %"
    if math.isnan(interval.lo) or math.isnan(interval.hi):
        return f"no {level} interval (the statistic is undefined), so it cannot support a claim"
    if interval.lo < threshold < interval.hi:
        return (
            f"the {level} interval [{interval.lo:.3g}, {interval.hi:.3g}] straddles "
            f"{threshold:.3g}: too wide to support the claim"
        )
    return None
