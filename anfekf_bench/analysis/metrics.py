"""Error metrics (SPEC section 5), computed in bulk from arrays, never inside the filter loop."""

from __future__ import annotations

import functools
import math
import warnings

import numpy as np
from scipy.stats import chi2

from ..compiled import is_compiled, maybe_njit
from ..models import wrap_angle, wrap_scalar

# A run that did not diverge is counted `inconsistent` when the time mean of its NEES exceeds
# this: its errors average sqrt(1e4 / 3) ~ 58 of its own standard deviations, where a consistent
# filter's NEES averages 3 (the worst paper scenario's EKF averages ~120). Such runs stay finite,
# so they are not diverged and stay in every mean; the count makes them visible.
NEES_EXPLODED = 1e4


def pose_errors(x_true: np.ndarray, x_est: np.ndarray) -> np.ndarray:
    """e = X_true - X_est, (..., 3), heading wrapped to (-pi, pi]."""
    e = np.asarray(x_true, dtype=float) - np.asarray(x_est, dtype=float)
    e[..., 2] = wrap_angle(e[..., 2])
    return e


def nees(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """eps_k = e^T P^-1 e (eq. 45) by a solve, for stacks e (n, 3), P (n, 3, 3)."""
    try:
        sol = np.linalg.solve(P, e[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a singular P (p0 = 0 before the first updates): row by row
        return _nees_rows(np.asarray(e, dtype=float), np.asarray(P, dtype=float))
    return np.einsum("...i,...i->...", e, sol)


def _nees_rows(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """eps_k one row at a time; where P_k is singular, e^T P^+ e with the pseudo-inverse (the
    NEES over the directions P_k claims any uncertainty in)."""
    flat_e, flat_P = e.reshape(-1, e.shape[-1]), P.reshape(-1, *P.shape[-2:])
    out = np.empty(len(flat_e))
    for i, (ei, Pi) in enumerate(zip(flat_e, flat_P, strict=True)):
        try:
            out[i] = ei @ np.linalg.solve(Pi, ei)
        except np.linalg.LinAlgError:
            out[i] = ei @ np.linalg.pinv(Pi) @ ei
    return out.reshape(e.shape[:-1])


# Cached: scipy's chi2.ppf costs ~0.3 ms a call, and the tables ask for the same bounds once per
# run and filter (half the per-run table's time on a 50-run scenario).
@functools.lru_cache(maxsize=256)
def nees_bounds(runs: int, dim: int = 3, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds on the N-run average NEES: chi2(N dim) quantiles / N (paper Sec. 6)."""
    alpha = 1.0 - confidence
    dof = runs * dim
    return float(chi2.ppf(alpha / 2, dof) / runs), float(chi2.ppf(1 - alpha / 2, dof) / runs)


@functools.lru_cache(maxsize=64)
def single_run_bounds(dim: int = 3, confidence: float = 0.95) -> tuple[float, float]:
    """The two-sided bounds of ONE run's NEES: chi-square(dim) quantiles."""
    a = (1 - confidence) / 2
    return float(chi2.ppf(a, dim)), float(chi2.ppf(1 - a, dim))


def nees_single_run(nees: np.ndarray, dim: int = 3, confidence: float = 0.95) -> dict:
    """Each run's own NEES against the single-run chi-square(dim) bounds, for (runs, steps)
    NEES with NaN where a step has no score: the share strictly inside, per run and pooled
    over every scored step of every run (each step counts once, so a longer run weighs more)."""
    nees = np.atleast_2d(np.asarray(nees, dtype=float))
    lo, hi = single_run_bounds(dim, confidence)
    scored = np.isfinite(nees) | np.isposinf(nees)
    inside = (nees > lo) & (nees < hi)
    counts = scored.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_run = np.where(counts > 0, inside.sum(axis=1) / counts, np.nan)
    total = int(counts.sum())
    return {
        "lo": lo,
        "hi": hi,
        "per_run": per_run,
        "scored": counts,
        "pooled": float(inside.sum() / total) if total else math.nan,
    }


def add_trace_metrics(trace: dict, x_true: np.ndarray, *, compiled: bool = False) -> dict:
    """Per-step pos_err, heading_err and NEES of a filter's trace, in bulk from its arrays.
    `compiled` (the fast engine's runs): in one compiled pass (`trace_metrics`) where numba is
    in use; numpy's otherwise (the filterpy engine's tables keep numpy's bits)."""
    if compiled and TRACE_METRICS_COMPILED:
        return _add_compiled_trace_metrics(trace, x_true)
    e = pose_errors(x_true, trace["x"])
    trace["pos_err"] = np.hypot(e[:, 0], e[:, 1])
    trace["heading_err"] = np.abs(e[:, 2])
    trace["nees"] = _nees_where_finite(e, trace["P"])
    return trace


def _add_compiled_trace_metrics(trace: dict, x_true: np.ndarray) -> dict:
    x_true = np.ascontiguousarray(x_true, dtype=float)
    x = np.ascontiguousarray(trace["x"], dtype=float)
    P = np.ascontiguousarray(trace["P"], dtype=float)
    n = len(x)
    if x.shape != (n, 3) or x_true.shape != (n, 3) or P.shape != (n, 3, 3):  # compiled: unchecked
        raise ValueError(f"trace metrics: x {x.shape}, x_true {x_true.shape}, P {P.shape}")
    pos_err, heading_err, eps = np.empty(n), np.empty(n), np.empty(n)
    by_numpy = trace_metrics(x_true, x, P, pos_err, heading_err, eps)
    if by_numpy.any():  # a (nearly) singular P, p0 = 0 before the first updates: numpy's path
        e = pose_errors(x_true[by_numpy], x[by_numpy])
        eps[by_numpy] = nees(e, P[by_numpy])
    trace["pos_err"], trace["heading_err"], trace["nees"] = pos_err, heading_err, eps
    return trace


# A run's metrics on the fast engine: on numpy they are a dozen passes over its steps and a
# LAPACK solve per step, about 0.5 ms a trace, which on threads held the GIL that the compiled
# filters of the other runs wait for (a tenth of a paper scenario's end-to-end time). One pass,
# without the GIL; the NEES by the same LU with partial pivoting as LAPACK's dgesv, whose sums may
# round differently: tests/test_metrics.py holds it to numpy's path within 1e-12 (relative). A P
# singular in exact arithmetic (p0 = 0, then G Qu G^T of rank 2) may get an exactly zero pivot on
# one path and a rounding error on the other, so a pivot below NEAR_SINGULAR of P's largest entry
# leaves the step to numpy's path (its solve, or its pseudo-inverse where LAPACK finds a zero).
NEAR_SINGULAR = 1e-9
_wrap = maybe_njit(wrap_scalar)


@maybe_njit
def trace_metrics(x_true, x, P, pos_err, heading_err, nees_out):
    """pos_err, heading_err and nees (`add_trace_metrics`) of each step, written to the outputs;
    returns the steps whose P is (nearly) singular: their nees is left to the caller."""
    n = x.shape[0]
    singular = np.zeros(n, dtype=np.bool_)
    A = np.empty((3, 3))
    b = np.empty(3)
    for k in range(n):
        e0 = x_true[k, 0] - x[k, 0]
        e1 = x_true[k, 1] - x[k, 1]
        e2 = _wrap(x_true[k, 2] - x[k, 2])
        pos_err[k] = np.hypot(e0, e1)
        heading_err[k] = abs(e2)
        finite = math.isfinite(e0) and math.isfinite(e1) and math.isfinite(e2)
        for i in range(3):
            for j in range(3):
                A[i, j] = P[k, i, j]
                finite = finite and math.isfinite(A[i, j])
        if not finite:
            nees_out[k] = math.nan
            continue
        b[0], b[1], b[2] = e0, e1, e2
        nees_out[k] = _lu_quadratic_form(A, b, singular, k)
    return singular


@maybe_njit
def _lu_quadratic_form(A, b, singular, k):
    """b^T A^-1 b for 3x3 A (overwritten) by LU with partial pivoting; NaN and singular[k]
    set when a pivot is at most NEAR_SINGULAR of A's largest entry."""
    e0, e1, e2 = b[0], b[1], b[2]
    scale = 0.0
    for i in range(3):
        for j in range(3):
            scale = max(scale, abs(A[i, j]))
    for c in range(3):
        p = c
        for r in range(c + 1, 3):
            if abs(A[r, c]) > abs(A[p, c]):
                p = r
        if abs(A[p, c]) <= NEAR_SINGULAR * scale:
            singular[k] = True
            return math.nan
        if p != c:
            for j in range(3):
                A[c, j], A[p, j] = A[p, j], A[c, j]
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, 3):
            f = A[r, c] / A[c, c]
            for j in range(c + 1, 3):
                A[r, j] -= f * A[c, j]
            b[r] -= f * b[c]
    s2 = b[2] / A[2, 2]
    s1 = (b[1] - A[1, 2] * s2) / A[1, 1]
    s0 = (b[0] - A[0, 1] * s1 - A[0, 2] * s2) / A[0, 0]
    return e0 * s0 + e1 * s1 + e2 * s2


TRACE_METRICS_COMPILED: bool = is_compiled(trace_metrics)


def _nees_where_finite(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    out = np.full(len(e), np.nan)
    ok = np.all(np.isfinite(P), axis=(1, 2)) & np.all(np.isfinite(e), axis=1)
    if ok.any():
        out[ok] = nees(e[ok], P[ok])
    return out


def recorded_steps(n_controls: int, record_every: int) -> np.ndarray:
    """The control steps a run records: every `record_every`-th, from the first such step."""
    return np.arange(record_every, n_controls + 1, record_every)


def nan_aware_mean(x: np.ndarray, axis=None):
    """np.mean, or, when `x` holds NaN, np.nanmean (NaN where a slice has no value).

    NaN marks a step without a score: on a recorded log, a time whose ground truth must not be
    used (a Vicon gap or mis-fit) or the padding after a segment's end (real_experiment). A
    simulated run has none (a diverged run is left out before any mean), so its metrics are
    computed exactly as by np.mean.
    """
    x = np.asarray(x, dtype=float)
    if not np.isnan(x).any():
        return np.mean(x, axis=axis)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a slice with no value at all: NaN
        return np.nanmean(x, axis=axis)


def rmse_curve(err: np.ndarray) -> np.ndarray:
    """RMSE over runs at each step: sqrt(mean_runs err^2) for err (runs, steps); NaN entries
    (steps without a score) are left out of the mean (`nan_aware_mean`)."""
    return np.sqrt(nan_aware_mean(np.square(err), axis=0))


def runs_counted(values: np.ndarray) -> np.ndarray:
    """How many runs have a value at each step, for (runs, steps) values."""
    return np.sum(~np.isnan(np.asarray(values, dtype=float)), axis=-2)


def share_inside_bounds(avg: np.ndarray, counts: np.ndarray, confidence: float = 0.95) -> float:
    """Share of the steps with at least one run whose run-averaged NEES `avg` lies strictly
    inside the bounds for the `counts` runs averaged there (steps without a score differ in
    their run counts: recorded logs)."""
    avg, counts = np.asarray(avg, dtype=float), np.asarray(counts)
    has = counts > 0
    if not has.any():
        return float("nan")
    inside = np.zeros(len(avg), dtype=bool)
    for n in np.unique(counts[has]):
        lo, hi = nees_bounds(int(n), confidence=confidence)
        at = counts == n
        inside[at] = (avg[at] > lo) & (avg[at] < hi)
    return float(np.mean(inside[has]))


def share_inside(values: np.ndarray, lo: float, hi: float) -> float:
    """Share of entries strictly inside (lo, hi)."""
    values = np.asarray(values)
    return float(np.mean((values > lo) & (values < hi))) if values.size else float("nan")


def format_number(x: float | None, digits: int) -> str:
    """A metric for tables and legends: '-' when undefined (every run diverged)."""
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def format_sig(x: float | None, digits: int = 3) -> str:
    """`x` to `digits` significant digits in plain notation (0.0574, 1.05, 18.9, 122; never
    1.05e+00), so that a 1 % difference shows; '-' when undefined."""
    if x is None or not math.isfinite(x):
        return "-"
    if x == 0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(x))))
    text = f"{x:.{decimals}f}"
    # Rounding may carry into a new digit (9.996 -> 10.00): drop the extra decimal.
    if decimals and len(text.lstrip("-").replace(".", "").lstrip("0")) > digits:
        text = f"{x:.{decimals - 1}f}"
    return text


def format_share(x: float | None) -> str:
    """A share (0..1) as a percentage; '-' when undefined."""
    return "-" if x is None or not math.isfinite(x) else f"{100 * x:.1f} %"


def summarize_filter(
    pos_err: np.ndarray, heading_err: np.ndarray, nees_: np.ndarray, diverged: np.ndarray
) -> dict:
    """One summary record from (runs, steps) arrays of a filter.

    Diverged runs are counted and left out of every mean, so they cannot poison it.
    inconsistent: the runs kept whose time-mean NEES exceeds NEES_EXPLODED (still in the means).
    rmse_pos / rmse_heading: the time mean of the RMSE-over-runs curve [m] / [rad].
    anees: the time mean of the run-averaged NEES; nees_in_bounds: the share of steps whose
    run-averaged NEES lies strictly inside the 95 % chi-square bounds for the runs kept.
    NaN entries of kept runs are steps without a score (recorded logs): every mean leaves them
    out, and a step's NEES bounds are those for the runs that have it (nees_lo / nees_hi: for
    all runs kept).
    """
    ok = ~np.asarray(diverged, dtype=bool)
    n = int(ok.sum())
    record = {
        "runs": int(len(ok)),
        "diverged": int((~ok).sum()),
        "inconsistent": inconsistent_runs(nees_, ok),
        "runs_used": n,
    }
    if n == 0:
        nan = float("nan")
        record.update(
            rmse_pos=nan,
            rmse_heading=nan,
            anees=nan,
            nees_lo=nan,
            nees_hi=nan,
            nees_in_bounds=nan,
        )
        return record
    lo, hi = nees_bounds(n)
    if np.isnan(nees_[ok]).any():  # steps without a score (recorded logs): see nan_aware_mean
        avg_nees = nan_aware_mean(nees_[ok], axis=0)
        record.update(
            rmse_pos=float(nan_aware_mean(rmse_curve(pos_err[ok]))),
            rmse_heading=float(nan_aware_mean(rmse_curve(heading_err[ok]))),
            anees=float(nan_aware_mean(avg_nees)),
            nees_lo=lo,
            nees_hi=hi,
            nees_in_bounds=share_inside_bounds(avg_nees, runs_counted(nees_[ok])),
        )
        return record
    avg_nees = nees_[ok].mean(axis=0)
    record.update(
        rmse_pos=float(rmse_curve(pos_err[ok]).mean()),
        rmse_heading=float(rmse_curve(heading_err[ok]).mean()),
        anees=float(avg_nees.mean()),
        nees_lo=lo,
        nees_hi=hi,
        nees_in_bounds=share_inside(avg_nees, lo, hi),
    )
    return record


def inconsistent_runs(nees_: np.ndarray, kept: np.ndarray) -> int:
    """Runs among `kept` whose time-mean NEES exceeds NEES_EXPLODED (an infinite NEES counts)."""
    values = np.asarray(nees_, dtype=float)[np.asarray(kept, dtype=bool)]
    if values.size == 0 or values.shape[-1] == 0:
        return 0
    with warnings.catch_warnings():  # a row of NaN only (no estimate) is simply not counted
        warnings.simplefilter("ignore", RuntimeWarning)
        per_run = np.nanmean(values, axis=-1)
    return int(np.sum(per_run > NEES_EXPLODED))
