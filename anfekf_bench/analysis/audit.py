"""The drive audit's numerics (SPEC 18): how a real robot's errors differ from white noise.

Plain functions on arrays (no log, no filter), so each is tested on synthetic data where the
answer is known (tests/test_audit.py); `drive_audit` applies them to the MRCLAM drives.

- Odometry against Vicon: the commanded v and turn rate and the Vicon-derived ones averaged over
  the same short windows (`held_means`, `truth_velocities`), and a regression true = scale x
  commanded + bias (`fit_scale_bias`) with its OLS standard errors and a moving-block bootstrap
  interval (the residuals are autocorrelated: a turn lasts several windows).
- Range and bearing residuals against the truth: bias (mean and median) and spread (std and the
  robust 1.4826 x MAD), per landmark, per range bin and overall (`residual_stats`), and the
  range's error as a linear function of the true range (`range_dependence`: a scale error).
- Innovation whiteness: the sample autocorrelation at lags 1-10 of a normalised innovation
  sequence, its 95 % band +-1.96 / sqrt(n) for white noise and the Ljung-Box test
  (`autocorrelation`, `ljung_box`).
- Time without any landmark (`landmark_gaps`).
- Lost-lock episodes (`episodes`: the error above a threshold; `lead_window`: what came before
  one) and the label of what caused one from the measured facts (`episode_cause`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import chi2

MAD_TO_STD = 1.4826  # robust std = 1.4826 x median absolute deviation (normal data)
RANGE_BINS_M = (0.0, 1.5, 3.0, 5.0, math.inf)


def robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation from the median (NaN for no data)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if not len(x):
        return math.nan
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x))))


# --------------------------------------------------------------------------------------------
# Odometry against the truth


def held_means(t_held: np.ndarray, values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Time means over [edges[i], edges[i + 1]] of a zero-order-held signal (value[k] from
    t_held[k] until the next sample; 0 before the first), exactly, from its running integral."""
    t_held = np.asarray(t_held, dtype=float)
    values = np.asarray(values, dtype=float)
    edges = np.asarray(edges, dtype=float)
    if not len(t_held):
        return np.zeros(max(len(edges) - 1, 0))
    cum = np.r_[0.0, np.cumsum(values[:-1] * np.diff(t_held))]

    def integral(t: np.ndarray) -> np.ndarray:
        k = np.searchsorted(t_held, t, side="right") - 1
        kk = np.maximum(k, 0)
        return np.where(k >= 0, cum[kk] + values[kk] * (t - t_held[kk]), 0.0)

    F = integral(edges)
    return np.diff(F) / np.diff(edges)


def truth_velocities(
    t: np.ndarray, x: np.ndarray, y: np.ndarray, phi_unwrapped: np.ndarray, edges: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Forward speed and turn rate over [edges[i], edges[i + 1]] from the true poses (linearly
    interpolated at the edges): the displacement projected on the mid-window heading, lengthened
    from the chord to the arc of constant curvature (x (h / sin h), h half the heading change),
    and the heading change (unwrapped), each over the window's length."""
    edges = np.asarray(edges, dtype=float)
    xe, ye, pe = (np.interp(edges, t, a) for a in (x, y, phi_unwrapped))
    mid = np.interp(0.5 * (edges[:-1] + edges[1:]), t, phi_unwrapped)
    dt = np.diff(edges)
    half = 0.5 * np.diff(pe)
    arc = np.where(np.abs(half) > 1e-9, half / np.sin(np.where(half == 0, 1.0, half)), 1.0)
    v = (np.diff(xe) * np.cos(mid) + np.diff(ye) * np.sin(mid)) * arc / dt
    return v, 2 * half / dt


def fit_scale_bias(
    commanded: np.ndarray,
    true: np.ndarray,
    block: int = 60,
    resamples: int = 1000,
    seed: int = 0,
    confidence: float = 0.95,
) -> dict:
    """true = scale x commanded + bias by least squares, with OLS standard errors and a
    moving-block bootstrap percentile interval (blocks of `block` consecutive samples, drawn
    with replacement to the sample's length; deterministic for `seed`). NaN pairs are left out;
    scale and bias are NaN when the commands do not vary."""
    c = np.asarray(commanded, dtype=float)
    y = np.asarray(true, dtype=float)
    ok = np.isfinite(c) & np.isfinite(y)
    c, y = c[ok], y[ok]
    n = len(c)
    nan = math.nan
    out = dict.fromkeys(
        ("scale", "bias", "scale_se", "bias_se", "scale_lo", "scale_hi", "bias_lo", "bias_hi",
         "resid_std", "resid_robust_std"), nan,
    )  # fmt: skip
    out["n"] = n
    if n < 3 or not np.ptp(c) > 0:
        return out
    X = np.column_stack([c, np.ones(n)])
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ beta
    s2 = float(resid @ resid) / (n - 2)
    cov = s2 * np.linalg.inv(X.T @ X)
    out.update(
        scale=float(beta[0]), bias=float(beta[1]),
        scale_se=float(math.sqrt(cov[0, 0])), bias_se=float(math.sqrt(cov[1, 1])),
        resid_std=float(np.std(resid, ddof=2)), resid_robust_std=robust_std(resid),
    )  # fmt: skip
    if resamples <= 0:
        return out
    # Moving blocks of `block` samples, floor(n / block) of them per resample: the sums the
    # regression needs are summed per block once (running sums), then per resample.
    block = max(1, min(block, n))
    rng = np.random.default_rng(seed)
    k = max(1, n // block)
    starts = rng.integers(0, n - block + 1, size=(resamples, k))
    sums = []
    for a in (c, y, c * c, c * y):
        cs = np.r_[0.0, np.cumsum(a)]
        sums.append((cs[block:] - cs[:-block])[starts].sum(axis=1))
    sc, sy, scc, scy = sums
    m = k * block
    sxx = scc - sc * sc / m
    sxy = scy - sc * sy / m
    with np.errstate(invalid="ignore", divide="ignore"):
        scale_b = np.where(sxx > 1e-12 * scc, sxy / sxx, np.nan)
    bias_b = (sy - scale_b * sc) / m
    good = np.isfinite(scale_b)
    a = 100 * (1 - confidence) / 2
    if good.sum() >= 10:
        out["scale_lo"], out["scale_hi"] = (
            float(v) for v in np.percentile(scale_b[good], [a, 100 - a])
        )
        out["bias_lo"], out["bias_hi"] = (
            float(v) for v in np.percentile(bias_b[good], [a, 100 - a])
        )
    return out


# --------------------------------------------------------------------------------------------
# Range and bearing residuals


def residual_stats(d_range: np.ndarray, d_bearing: np.ndarray, outlier_mads: float = 5.0) -> dict:
    """Bias and spread of range [m] and bearing [rad] residuals: n, mean, median, std, robust
    std, and the share beyond `outlier_mads` robust stds of the median (either component)."""
    dr = np.asarray(d_range, dtype=float)
    db = np.asarray(d_bearing, dtype=float)
    n = len(dr)
    out: dict = {"n": n}
    for name, d in (("range", dr), ("bearing", db)):
        out[f"{name}_mean"] = float(np.mean(d)) if n else math.nan
        out[f"{name}_median"] = float(np.median(d)) if n else math.nan
        out[f"{name}_std"] = float(np.std(d, ddof=1)) if n > 1 else math.nan
        out[f"{name}_robust_std"] = robust_std(d)
    out["outlier_share"] = float(np.mean(outliers(dr, db, outlier_mads))) if n else math.nan
    return out


def outliers(d_range: np.ndarray, d_bearing: np.ndarray, mads: float = 5.0) -> np.ndarray:
    """Measurements whose range or bearing residual lies beyond `mads` robust stds of the
    median of its sample (an outlier or a misassociation: the truth says it is wrong)."""
    dr = np.asarray(d_range, dtype=float)
    db = np.asarray(d_bearing, dtype=float)
    if not len(dr):
        return np.zeros(0, bool)
    far = np.zeros(len(dr), bool)
    for d in (dr, db):
        s = robust_std(d)
        if s > 0:
            far |= np.abs(d - np.median(d)) > mads * s
    return far


def range_bin_labels(bins=RANGE_BINS_M) -> list[str]:
    """'0-1.5 m', ..., '>= 5 m'."""
    pairs = zip(bins[:-1], bins[1:], strict=True)
    return [f"{a:g}-{b:g} m" if math.isfinite(b) else f">= {a:g} m" for a, b in pairs]


def range_bin(true_range: np.ndarray, bins=RANGE_BINS_M) -> np.ndarray:
    """The index of each true range's bin in `bins` (left-closed)."""
    return np.clip(
        np.searchsorted(np.asarray(bins), true_range, side="right") - 1, 0, len(bins) - 2
    )


def range_dependence(true_range: np.ndarray, d_range: np.ndarray) -> dict:
    """d_range = offset + slope x true range by least squares (slope: a range scale error,
    measured = (1 + slope) x true + offset), with OLS standard errors; robust to nothing (the
    caller leaves outliers out)."""
    fit = fit_scale_bias(true_range, d_range, resamples=0)
    return {
        "range_slope": fit["scale"], "range_slope_se": fit["scale_se"],
        "range_offset": fit["bias"], "range_offset_se": fit["bias_se"],
    }  # fmt: skip


# --------------------------------------------------------------------------------------------
# Innovation whiteness


def autocorrelation(x: np.ndarray, lags: int = 10) -> np.ndarray:
    """The sample autocorrelation r_1..r_lags of a sequence (NaN entries dropped, the mean
    removed; the biased estimator of time-series texts, |r| <= 1)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    n = len(x)
    out = np.full(lags, np.nan)
    if n < 2:
        return out
    d = x - x.mean()
    c0 = float(d @ d)
    if not c0 > 0:
        return out
    for k in range(1, min(lags, n - 1) + 1):
        out[k - 1] = float(d[:-k] @ d[k:]) / c0
    return out


def white_band(n: int, confidence: float = 0.95) -> float:
    """Half-width of the interval holding a white sequence's r_k with `confidence`."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + confidence / 2) / math.sqrt(n)) if n > 0 else math.nan


def ljung_box(x: np.ndarray, lags: int = 10) -> tuple[float, float]:
    """(Q, p): Q = n (n + 2) sum_k r_k^2 / (n - k) over k = 1..lags, chi-square with `lags` dof
    for a white sequence."""
    x = np.asarray(x, dtype=float)
    n = int(np.isfinite(x).sum())
    r = autocorrelation(x, lags)
    if n <= lags + 1 or not np.isfinite(r).all():
        return math.nan, math.nan
    q = float(n * (n + 2) * np.sum(r**2 / (n - np.arange(1, lags + 1))))
    return q, float(chi2.sf(q, lags))


# --------------------------------------------------------------------------------------------
# Gaps and lost-lock episodes


def landmark_gaps(meas_t: np.ndarray, t0: float, t1: float, min_s: float = 0.0) -> np.ndarray:
    """(k, 2) intervals of [t0, t1] without any landmark measurement, longer than `min_s`
    (from t0 to the first measurement, between consecutive ones, from the last to t1)."""
    t = np.asarray(meas_t, dtype=float)
    t = np.unique(t[(t >= t0) & (t <= t1)])
    edges = np.r_[t0, t, t1]
    iv = np.column_stack([edges[:-1], edges[1:]])
    return iv[(iv[:, 1] - iv[:, 0]) > min_s].reshape(-1, 2)


def episodes(
    t: np.ndarray, err: np.ndarray, threshold: float = 1.0, merge_s: float = 5.0
) -> np.ndarray:
    """(k, 2) index ranges [i0, i1] (inclusive) of the times with err > threshold; runs closer
    than `merge_s` seconds (across NaN: unscored times) are one episode."""
    t = np.asarray(t, dtype=float)
    above = np.flatnonzero(np.asarray(err, dtype=float) > threshold)
    if not len(above):
        return np.zeros((0, 2), dtype=int)
    out = [[above[0], above[0]]]
    for i in above[1:]:
        if t[i] - t[out[-1][1]] <= merge_s:
            out[-1][1] = i
        else:
            out.append([i, i])
    return np.array(out, dtype=int)


def lead_window(
    t: np.ndarray,
    err: np.ndarray,
    onset: int,
    threshold: float = 1.0,
    min_s: float = 5.0,
    max_s: float = 30.0,
) -> tuple[float, float]:
    """(start, onset time) of what preceded an episode: from the last time before `onset` whose
    error was below half the threshold (the filter still in lock), at least `min_s` and at most
    `max_s` before the onset."""
    t = np.asarray(t, dtype=float)
    err = np.asarray(err, dtype=float)
    t_on = float(t[onset])
    low = np.flatnonzero(err[:onset] < 0.5 * threshold)
    start = float(t[low[-1]]) if len(low) else float(t[0])
    start = min(max(start, t_on - max_s), t_on - min_s)
    return max(start, float(t[0])), t_on


# What a lost-lock episode's lead-up must show for a fact to count as a cause
GAP_CAUSE_S = 3.0  # a landmark-free stretch at least this long
TURN_RATE = 0.3  # rad/s: the robot is turning
MANOEUVRE_SHARE = 0.3  # ... for at least this share of the lead-up


def episode_cause(facts: dict) -> str:
    """The measured causes of one lost-lock episode, from the counterfactual re-runs (does the
    episode go when the odometry is corrected by the drive's own scale and bias, when it is
    replaced by the Vicon-derived velocities, when the measurements the truth marks as outliers
    are removed?) and the lead-up's facts (its longest landmark-free stretch, its share of
    turning). Causes are listed in that order, joined by ' + '."""
    causes = []
    if facts.get("fixed_by_calibration"):
        causes.append("odometry scale/bias")
    elif facts.get("fixed_by_true_odometry"):
        causes.append("odometry error beyond scale/bias")
    if facts.get("fixed_by_outlier_removal"):
        causes.append("outlier measurements")
    if facts.get("longest_gap_s", 0.0) >= GAP_CAUSE_S:
        causes.append(f"landmark gap ({facts['longest_gap_s']:.1f} s)")
    if facts.get("turning_share", 0.0) >= MANOEUVRE_SHARE:
        causes.append(f"manoeuvre ({100 * facts['turning_share']:.0f} % turning)")
    if not (facts.get("fixed_by_calibration") or facts.get("fixed_by_true_odometry")
            or facts.get("fixed_by_outlier_removal")):  # fmt: skip
        causes.append("not removed by any correction")
    return " + ".join(causes)
