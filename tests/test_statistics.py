"""Paired bootstrap intervals, the paired test and claim verdicts (SPEC section 8)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from anfekf_bench.analysis import run_means, statistics
from anfekf_bench.analysis.metrics import summarize_filter
from anfekf_bench.analysis.statistics import (
    METRICS,
    Interval,
    bootstrap_one,
    common_runs,
    in_bounds_statistic,
    interval_too_wide,
    mean_statistic,
    paired_bootstrap,
    paired_test,
    per_run_mean,
    per_run_rmse,
    rmse_statistic,
    too_few_runs,
    verdict,
)


def _arrays(runs: int = 20, steps: int = 30, seed: int = 3) -> dict[str, np.ndarray]:
    """(runs, steps) arrays shaped like a filter's trace: pos_err, heading_err, nees, diverged."""
    rng = np.random.default_rng(seed)
    return {
        "pos_err": np.hypot(*rng.normal(0.0, 0.5, size=(2, runs, steps))),
        "heading_err": np.abs(rng.normal(0.0, 0.05, size=(runs, steps))),
        "nees": rng.chisquare(3, size=(runs, steps)) * rng.uniform(0.8, 1.2, size=steps),
        "diverged": rng.random(runs) < 0.15,
    }


@pytest.fixture(autouse=True)
def _no_warnings():
    """Every call in this file must be quiet: no RuntimeWarning, no scipy DegenerateDataWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


# --- statistics match the scenario metrics -------------------------------------------------------


def test_statistics_equal_summarize_filter():
    a = _arrays()
    assert a["diverged"].any()
    record = summarize_filter(a["pos_err"], a["heading_err"], a["nees"], a["diverged"])
    ok = ~a["diverged"]
    for name, spec in METRICS.items():
        assert spec.statistic(a[spec.column][ok]) == record[name], name
    assert set(METRICS) == {"rmse_pos", "rmse_heading", "anees", "nees_in_bounds"}
    assert 0.0 < record["nees_in_bounds"] < 1.0  # the share is not trivially 0 or 1 here


@pytest.mark.parametrize("statistic", [rmse_statistic, mean_statistic, in_bounds_statistic])
def test_statistics_on_a_batch_equal_one_at_a_time(statistic):
    x = _arrays()["nees"]
    idx = np.random.default_rng(0).integers(0, x.shape[0], size=(7, x.shape[0]))
    batch = statistic(x[idx])
    assert batch.shape == (7,)
    np.testing.assert_allclose(batch, [statistic(x[i]) for i in idx], rtol=1e-13)


def test_per_run_values_by_hand():
    err = np.array([[3.0, 4.0], [1.0, 1.0]])
    np.testing.assert_allclose(per_run_rmse(err), [math.sqrt(12.5), 1.0])
    np.testing.assert_allclose(per_run_mean(err), [3.5, 1.0])


def test_common_runs_keeps_a_run_for_both_filters_or_neither():
    mask = common_runs(np.array([0, 1, 0, 0]), np.array([0, 0, 1, 0]))
    np.testing.assert_array_equal(mask, [True, False, False, True])


# --- paired bootstrap: exact edge cases ---------------------------------------------------------


@pytest.mark.parametrize("statistic", [rmse_statistic, mean_statistic])
def test_identical_filters_give_exactly_one_and_zero_width(statistic):
    b = _arrays()["pos_err"]
    ratio = paired_bootstrap(b, b.copy(), statistic)
    assert (ratio.estimate, ratio.lo, ratio.hi) == (1.0, 1.0, 1.0)
    diff = paired_bootstrap(b, b.copy(), statistic, kind="difference")
    assert (diff.estimate, diff.lo, diff.hi) == (0.0, 0.0, 0.0)
    assert ratio.method == diff.method == "degenerate"


@pytest.mark.parametrize("statistic", [rmse_statistic, mean_statistic])
def test_constant_per_run_ratio_gives_that_ratio(statistic):
    b = _arrays()["pos_err"]
    iv = paired_bootstrap(0.37 * b, b, statistic)
    assert iv.estimate == pytest.approx(0.37, abs=1e-12)
    assert iv.lo == iv.hi == iv.estimate


def test_nonfinite_statistic_gives_nan_bounds():
    a = _arrays()["pos_err"]
    iv = paired_bootstrap(a, np.zeros_like(a), rmse_statistic)  # statistic(b) == 0
    assert math.isinf(iv.estimate) and math.isnan(iv.lo) and math.isnan(iv.hi)
    inf_run = a.copy()
    inf_run[4, 2] = np.inf  # e.g. a diverged run left in (NaN marks an unscored step instead)
    for iv in (
        paired_bootstrap(inf_run, a, rmse_statistic),
        bootstrap_one(inf_run, mean_statistic),
    ):
        assert math.isnan(iv.lo) and math.isnan(iv.hi) and iv.method == "undefined"


def test_the_run_weight_path_equals_indexing_the_runs():
    """The BLAS path (run means through resample weights) gives the interval of the plain one."""
    a, b = _arrays()["pos_err"], _arrays(seed=5)["pos_err"]
    fast = paired_bootstrap(a, b, rmse_statistic, resamples=300)
    plain = paired_bootstrap(a, b, lambda x: rmse_statistic(x), resamples=300)  # no run-mean form
    assert fast.method == plain.method == "BCa"
    for key in ("estimate", "lo", "hi"):
        assert getattr(fast, key) == pytest.approx(getattr(plain, key), rel=1e-12)


@pytest.mark.parametrize("statistic", [rmse_statistic, mean_statistic], ids=["rmse", "mean"])
def test_the_run_weight_path_equals_indexing_the_runs_with_unscored_steps(statistic):
    """Recorded logs: NaN where a step has no score (Vicon gaps, padding after a short drive;
    here one step no run scores). The weighted path leaves each run out of the steps it does not
    score, as np.nanmean over the resampled runs does, and gives the plain path's interval."""
    rng = np.random.default_rng(11)
    a, b = (np.abs(rng.normal(1.0, 0.5, (11, 40))) for _ in range(2))
    for x in (a, b):
        x[rng.random(x.shape) < 0.2] = np.nan
        x[3, 25:] = np.nan  # a short drive
        x[:, 7] = np.nan  # a step no run scores
    idx = rng.integers(0, 11, (50, 11))
    weighted = statistics._resampled(statistic, a)
    assert weighted is not None
    direct = np.array([statistic(a[i]) for i in idx])
    np.testing.assert_allclose(weighted(idx), direct, rtol=1e-12)
    fast = paired_bootstrap(a, b, statistic, resamples=300)
    plain = paired_bootstrap(a, b, lambda x: statistic(x), resamples=300)  # no run-mean form
    assert math.isfinite(fast.lo) and fast.method == plain.method
    for key in ("estimate", "lo", "hi"):
        assert getattr(fast, key) == pytest.approx(getattr(plain, key), rel=1e-12)


@pytest.mark.parametrize("cells", [1, 5_000], ids=["one-per-batch", "some"])
def test_the_batch_size_does_not_change_the_interval(monkeypatch, cells):
    """Batches bound memory only: the resamples drawn are the same, so is the interval (to the
    rounding of a matrix product, whose BLAS kernel depends on its shape)."""
    from anfekf_bench.analysis import statistics

    a, b = _arrays()["pos_err"], _arrays(seed=5)["pos_err"]
    ratio = paired_bootstrap(a, b, rmse_statistic, resamples=300, seed=4)
    one = bootstrap_one(a, mean_statistic, resamples=300, seed=4)
    monkeypatch.setattr(statistics, "_BATCH_CELLS", cells)
    for batched, reference in (
        (paired_bootstrap(a, b, rmse_statistic, resamples=300, seed=4), ratio),
        (bootstrap_one(a, mean_statistic, resamples=300, seed=4), one),
    ):
        assert batched.method == reference.method == "BCa"
        for key in ("estimate", "lo", "hi"):
            assert getattr(batched, key) == pytest.approx(getattr(reference, key), rel=1e-12)


def test_zero_in_some_resamples_gives_nan_bounds():
    b = np.zeros((20, 3))
    b[0] = 1.0  # statistic(b) > 0 on the full sample, 0 in resamples without run 0
    iv = paired_bootstrap(np.ones((20, 3)), b, rmse_statistic)
    assert math.isfinite(iv.estimate) and math.isnan(iv.lo) and math.isnan(iv.hi)


def test_fewer_than_two_runs_give_nan_bounds():
    iv = paired_bootstrap(np.ones((1, 5)), 2 * np.ones((1, 5)), rmse_statistic)
    assert iv.estimate == 0.5 and math.isnan(iv.lo) and math.isnan(iv.hi)


def test_bad_arguments_raise():
    a = np.ones((5, 3))
    with pytest.raises(ValueError, match="shape"):
        paired_bootstrap(a, np.ones((4, 3)), rmse_statistic)
    with pytest.raises(ValueError, match="kind"):
        paired_bootstrap(a, a, rmse_statistic, kind="quotient")
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_one(a, rmse_statistic, confidence=95)
    with pytest.raises(ValueError, match="runs, steps"):
        bootstrap_one(np.ones(5), rmse_statistic)


# --- paired bootstrap: behaviour ----------------------------------------------------------------


def test_same_seed_same_bytes_other_seed_other_interval():
    x = _arrays()
    a, b = x["pos_err"], 1.3 * x["pos_err"] + 0.2 * x["heading_err"]
    first = paired_bootstrap(a, b, rmse_statistic, resamples=500, seed=11)
    again = paired_bootstrap(a, b, rmse_statistic, resamples=500, seed=11)
    other = paired_bootstrap(a, b, rmse_statistic, resamples=500, seed=12)

    def as_bytes(iv: Interval) -> bytes:
        return np.array([iv.estimate, iv.lo, iv.hi]).tobytes()

    assert first.method == "BCa"
    assert as_bytes(first) == as_bytes(again) and first == again
    assert other.estimate == first.estimate
    assert (other.lo, other.hi) != (first.lo, first.hi)
    assert first.lo < first.estimate < first.hi
    assert (first.confidence, first.resamples) == (0.95, 500)


def test_pairing_narrows_the_interval():
    # Strongly correlated filters: resampling runs jointly cancels the shared run-to-run spread.
    rng = np.random.default_rng(8)
    scale = rng.uniform(0.2, 3.0, size=(30, 1))  # some runs are hard for both filters
    b = scale * np.abs(rng.normal(size=(30, 6)))
    a = 0.8 * b * rng.uniform(0.95, 1.05, size=b.shape)
    paired = paired_bootstrap(a, b, rmse_statistic, resamples=500)
    unpaired = paired_bootstrap(a, b[rng.permutation(30)], rmse_statistic, resamples=500)
    assert paired.hi - paired.lo < 0.25 * (unpaired.hi - unpaired.lo)
    assert paired.lo < 0.8 < paired.hi


def test_bootstrap_one_of_a_mean():
    x = np.random.default_rng(2).chisquare(3, size=(40, 10))
    iv = bootstrap_one(x, mean_statistic, resamples=500)
    assert iv.estimate == pytest.approx(x.mean(), rel=1e-12)
    assert iv.lo < iv.estimate < iv.hi and iv.method == "BCa"


def test_in_bounds_share_is_flagged_for_the_run_bootstrap():
    # A consistent filter: resampled runs repeat, the run-average spreads more and the resampled
    # in-bounds shares sit below the estimate, so the interval misses its own estimate.
    nees = np.random.default_rng(5).chisquare(3, size=(20, 100))
    iv = bootstrap_one(nees, in_bounds_statistic, resamples=500)
    assert iv.estimate == in_bounds_statistic(nees)
    assert iv.method == "biased" and math.isnan(iv.lo) and math.isnan(iv.hi)
    assert METRICS["nees_in_bounds"].bootstrap is False
    assert all(METRICS[m].bootstrap for m in ("rmse_pos", "rmse_heading", "anees"))


@pytest.mark.parametrize("kind", ["ratio", "difference"])
def test_coverage_with_a_known_truth(kind):
    """Empirical coverage of the 95 % paired interval over 300 simulated scenarios of 50 runs.

    Errors are N(0, s_k^2) per step, correlated between the filters (common random numbers).
    ratio: of scenario RMSEs, which tend to mean(s_k), so the truth is mean(s_a) / mean(s_b).
    difference: of the time-mean of run-averaged squared errors (an ANEES-like mean of skewed
    values), whose truth is mean(s_a^2) - mean(s_b^2). 50 runs is the paper's count; over 1000
    replications coverage was 0.949 (ratio) and 0.932 (difference), and ~0.92 at 20 runs.
    """
    runs, steps, replications, rho = 50, 4, 300, 0.7
    rng = np.random.default_rng(12345)
    s_b = np.linspace(1.0, 2.0, steps)
    s_a = 0.6 * s_b * np.linspace(0.8, 1.2, steps)
    if kind == "ratio":
        statistic, truth = rmse_statistic, s_a.mean() / s_b.mean()
    else:
        statistic, truth = mean_statistic, np.mean(s_a**2) - np.mean(s_b**2)
    hits = 0
    for i in range(replications):
        z, w = rng.normal(size=(2, runs, steps))
        b = s_b * z
        a = s_a * (rho * z + math.sqrt(1 - rho**2) * w)
        if kind == "difference":
            a, b = a**2, b**2
        iv = paired_bootstrap(a, b, statistic, kind=kind, resamples=999, seed=i)
        hits += iv.lo <= truth <= iv.hi
    assert 0.88 <= hits / replications <= 0.99


# --- paired test ---------------------------------------------------------------------------------


def test_paired_test_on_a_clear_shift_and_on_identical_inputs():
    rng = np.random.default_rng(4)
    b = rng.uniform(1.0, 2.0, size=30)
    shifted = paired_test(b - 0.3 + rng.normal(0.0, 0.05, size=30), b)
    assert shifted.p_value < 1e-4 and shifted.name == "Wilcoxon signed-rank"
    same = paired_test(b, b.copy())
    assert (same.statistic, same.p_value) == (0.0, 1.0)


def test_paired_test_small_or_nonfinite_inputs():
    assert math.isnan(paired_test([1.0], [2.0]).p_value)
    assert math.isnan(paired_test([1.0, np.nan], [2.0, 1.0]).p_value)  # one usable pair
    a = np.arange(1.0, 11.0)
    with_nan = np.append(a, np.nan)
    left_out = paired_test(with_nan, np.append(a + 1.0, 5.0))
    assert left_out == paired_test(a, a + 1.0)


# --- claims --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "lo, hi, expected",
    [(0.4, 0.55, "holds"), (0.5, 0.6, "holds"), (0.61, 0.7, "fails"), (0.5, 0.7, "inconclusive")],
)
def test_verdict_at_most(lo, hi, expected):
    assert verdict(lo, hi, at_most=0.6) == expected


@pytest.mark.parametrize(
    "lo, hi, expected",
    [(0.6, 0.9, "holds"), (0.65, 0.7, "holds"), (0.3, 0.59, "fails"), (0.5, 0.7, "inconclusive")],
)
def test_verdict_at_least(lo, hi, expected):
    assert verdict(lo, hi, at_least=0.6) == expected


def test_verdict_nan_and_arguments():
    nan = float("nan")
    assert verdict(nan, nan, at_most=0.6) == "inconclusive"
    assert verdict(0.1, nan, at_least=0.0) == "inconclusive"
    with pytest.raises(ValueError):
        verdict(0.1, 0.2)
    with pytest.raises(ValueError):
        verdict(0.1, 0.2, at_most=0.5, at_least=0.0)


def test_few_runs_and_too_wide_intervals():
    assert too_few_runs(4) and not too_few_runs(10) and too_few_runs(40, minimum=50)
    wide = Interval(0.62, 0.52, 0.71, 0.95, 2000, "BCa")
    message = interval_too_wide(wide, 0.6)
    assert message is not None and "[0.52, 0.71]" in message and "95 %" in message
    assert interval_too_wide(wide, 0.75) is None
    undefined = Interval(float("inf"), float("nan"), float("nan"), 0.95, 2000, "undefined")
    assert interval_too_wide(undefined, 0.6) is not None


def test_the_memo_of_resampled_statistics_gives_the_same_bits(monkeypatch):
    """A table bootstraps each filter against several references with one seed: the resampled
    statistics are computed once and reused (statistics._RESAMPLED_MEMO), and the intervals
    are the bytes computed without the memo."""
    rng = np.random.default_rng(3)
    a, b, c = (np.abs(rng.normal(size=(20, 40))) * s for s in (1.0, 1.1, 0.9))
    pairs = [(a, b), (c, b), (a, c), (b, c)]

    def intervals():
        return [paired_bootstrap(x, y, rmse_statistic, resamples=300, seed=5) for x, y in pairs]

    monkeypatch.setattr(statistics, "_MEMO_ENTRIES", 0)  # every entry dropped as it is made
    statistics._RESAMPLED_MEMO.clear()
    without = intervals()
    monkeypatch.setattr(statistics, "_MEMO_ENTRIES", 1024)
    statistics._RESAMPLED_MEMO.clear()
    calls = []
    compute = statistics._resampled_by_weights

    def counted(form, x):
        of = compute(form, x)
        return lambda idx: calls.append(1) or of(idx)

    monkeypatch.setattr(statistics, "_resampled_by_weights", counted)
    with_memo = intervals()
    assert with_memo == without  # every field, the same floats
    batches = len(calls)
    assert intervals() == without and len(calls) == batches  # all from the memo
    # the memo keys on the data: another array, another statistic
    other = paired_bootstrap(a * 2.0, b, rmse_statistic, resamples=300, seed=5)
    assert (other.lo, other.hi) == pytest.approx((2.0 * without[0].lo, 2.0 * without[0].hi))


@pytest.mark.parametrize("statistic", [rmse_statistic, mean_statistic])
def test_resampled_statistics_in_cache_sized_blocks_keep_their_bits(statistic, monkeypatch):
    """`_resampled_by_weights` computes the run means and g in blocks of resamples
    (`_BLOCK_ROWS`): the same bits as on the whole (resamples, steps) array at once, blocks
    with and without unscored steps and a last, partial block; and each resample's value is
    the statistic of its runs."""
    rng = np.random.default_rng(12)
    x = np.abs(rng.normal(size=(9, 301)))
    x[2, 40:90] = np.nan  # steps one run does not score
    x[:, 200:203] = np.nan  # steps no run scores
    idx = rng.integers(0, 9, size=(150, 9))
    statistics._RESAMPLED_MEMO.clear()
    monkeypatch.setattr(statistics, "_BLOCK_ROWS", 10_000)
    whole = statistics._resampled_by_weights(statistic.run_mean_form, x)(idx)
    monkeypatch.setattr(statistics, "_BLOCK_ROWS", 64)  # blocks of 64, 64 and 22
    blocks = statistics._resampled_by_weights(statistic.run_mean_form, x)(idx)
    assert blocks.shape == (150,) and blocks.tobytes() == whole.tobytes()
    np.testing.assert_allclose(blocks, [statistic(x[i]) for i in idx], rtol=1e-12)


# Row lengths where numpy's pairwise summation changes shape: below 8, eight running sums up to
# 128, halves at multiples of 8 above (and the drives' 8,245 steps).
_SUM_LENGTHS = [*range(0, 140), 255, 256, 257, 1000, 4097, 8192, 8245, 20_003]


def test_the_compiled_pairwise_sum_is_numpys():
    """run_means.pairwise_sum adds in numpy's order: the same bits as np.sum, from any start."""
    rng = np.random.default_rng(21)
    for n in _SUM_LENGTHS:
        a = rng.random(n + 5) * rng.choice([1e-6, 1.0, 1e6])
        assert run_means.pairwise_sum(a, 3, n) == np.sum(a[3 : 3 + n]), n
        if n < 300:  # the plain-Python function numba compiled
            assert run_means.pairwise_sum.py_func(a, 3, n) == np.sum(a[3 : 3 + n]), n


@pytest.mark.parametrize("divide", [False, True])
@pytest.mark.parametrize("root", [False, True])
def test_the_compiled_time_means_are_the_numpy_paths_bits(divide, root):
    """run_means.time_means (one pass per row) gives the numpy path's bits: divided by the
    summed weights or not, square root or not, rows with a few unscored steps (0 / 0), rows
    with none, a row with no scored step (NaN), every row length numpy sums differently."""
    rng = np.random.default_rng(22)
    for n in _SUM_LENGTHS:
        block = rng.random((5, n)) * rng.choice([1e-3, 1.0, 1e3])
        den = rng.random((5, n)) + 0.5
        if divide and n:
            unscored = rng.random((5, n)) < 0.1
            block[unscored], den[unscored] = 0.0, 0.0
            block[2], den[2] = 0.0, 0.0
            block[3], den[3] = rng.random(n), rng.random(n) + 0.5  # all scored
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            want = block / den if divide else block.copy()
            want = statistics._time_mean_of(np.sqrt(want) if root else want)
        got = run_means.time_means(block, den, divide, root, np.empty(5))
        assert np.array_equal(got, want, equal_nan=True), n
        if n < 40:  # the plain-Python function numba compiled
            with np.errstate(invalid="ignore"):  # numpy scalars' 0 / 0
                py = run_means.time_means.py_func(block, den, divide, root, np.empty(5))
            assert np.array_equal(py, want, equal_nan=True), n


@pytest.mark.parametrize("statistic", [rmse_statistic, mean_statistic])
def test_resampled_statistics_compiled_or_not_keep_their_bits(statistic, monkeypatch):
    """`_resampled_by_weights` with the compiled time means and with numpy's passes (numba
    missing or switched off): the same bits."""
    if not run_means.COMPILED:
        pytest.skip("numba is not in use: only the numpy path runs")
    rng = np.random.default_rng(23)
    x = np.abs(rng.normal(size=(9, 8245)))
    x[2, 40:900] = np.nan
    x[:, 8000:] = np.nan
    idx = rng.integers(0, 9, size=(150, 9))
    compiled = statistics._resampled_by_weights(statistic.run_mean_form, x)(idx)
    monkeypatch.setattr(statistics, "COMPILED", False)
    numpy_path = statistics._resampled_by_weights(statistic.run_mean_form, x)(idx)
    assert compiled.tobytes() == numpy_path.tobytes()


def test_resample_blocks_cover_every_row_and_none_has_one_row_but_a_single_resample():
    """statistics._blocks: consecutive [lo, hi) blocks of at most 2 x _BLOCK_ROWS rows that
    cover every resample, none of a single row (BLAS takes a one-row product as a matrix-vector
    product, which may round otherwise) unless there is one resample in all."""
    size = statistics._BLOCK_ROWS
    for rows in [1, 2, size - 1, size, size + 1, size + 2, 2 * size + 1, 2000, 2001]:
        blocks = statistics._blocks(rows)
        assert blocks[0][0] == 0 and blocks[-1][1] == rows
        assert all(a[1] == b[0] for a, b in zip(blocks[:-1], blocks[1:], strict=True))
        assert all(1 < hi - lo <= 2 * size for lo, hi in blocks) or rows == 1


def test_the_time_mean_of_run_means_is_nanmeans_bits():
    """statistics._time_mean_of (in place, one mask) gives nan_aware_mean's bits: rows with and
    without NaN, a row of NaN only, arrays without NaN, one row."""
    from anfekf_bench.analysis.metrics import nan_aware_mean

    rng = np.random.default_rng(8)
    m = rng.normal(size=(30, 997)) ** 2
    m[rng.random(m.shape) < 0.3] = np.nan
    m[4] = np.nan
    for x in (m, np.abs(rng.normal(size=(7, 513))), m[5], m[4]):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            want = np.asarray(nan_aware_mean(x.copy(), axis=-1))
        got = np.asarray(statistics._time_mean_of(x.copy()))
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got, want, equal_nan=True)


def test_the_memo_of_scored_weights_gives_the_same_bits(monkeypatch):
    """Steps without a score (recorded logs): the resamples' summed weights of the runs scoring
    each step are computed once per batch for every filter with the same unscored steps
    (statistics._SCORED_MEMO); the intervals are the bytes computed without it."""
    rng = np.random.default_rng(4)
    a, b, c = (np.abs(rng.normal(size=(11, 60))) * s for s in (1.0, 1.1, 0.9))
    for x in (a, b, c):
        x[:, 7] = np.nan
        x[3, 40:] = np.nan
    c[0, :5] = np.nan  # another mask: its own entries
    pairs = [(a, b), (c, b), (a, c)]

    def intervals():
        statistics._RESAMPLED_MEMO.clear()
        statistics._SCORED_MEMO.clear()
        return [
            paired_bootstrap(x, y, s, resamples=300, seed=5)
            for x, y in pairs
            for s in (rmse_statistic, mean_statistic)
        ]

    monkeypatch.setattr(statistics, "_SCORED_ENTRIES", 0)  # every entry dropped as it is made
    without = intervals()
    monkeypatch.setattr(statistics, "_SCORED_ENTRIES", 16)
    assert intervals() == without
    assert all(math.isfinite(i.lo) for i in without)
