"""Metrics of a scenario whose true noise changes (SPEC 14): per phase, recovery, noise tracking.

Phases: the intervals between consecutive change points of the schedule (`NoiseSchedule.
change_points`: every start and end of a change, an outlier window or a blackout), from t = 0 to
the last recorded step. A recorded step at t belongs to the phase [start, end) holding t (the
last phase holds the last step), the convention of the schedule itself (a step change is in
force from its start_s on).

Recovery time after a change at c (the start of every phase but the first): with rmse_f(t) and
rmse_o(t) the RMSE-over-runs position curves of the filter and of the oracle (over the runs
that neither diverged in), the first recorded time t >= c from which rmse_f <= 1.2 rmse_o holds
at every recorded step of [t, t + RECOVERY_HOLD_S] (or up to the phase's end, when that comes
first), minus c. The hold makes the time robust to a lucky crossing of a noisy curve, without
letting one late excursion of a long phase (a curve averaged over few runs) undo a recovery
that held for many seconds. When no such t exists the filter did not recover within the
phase: the time is censored at the phase's length (`recovery_censored` true). Without an
oracle in the scenario there is no recovery time.

Noise-tracking error of every filter, channel by channel (R_rr, R_bb, Q_vv, Q_gg): the mean over
kept runs and recorded steps of |ln(the filter's variance / the true variance)|, the true one
being `NoiseSchedule.true_variances` (outliers moment matched). A fixed-noise EKF has one too:
that of its constant assumption, the baseline an adaptive filter should beat.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from ..schedule import NoiseSchedule
from .comparisons import compare
from .metrics import rmse_curve, summarize_filter
from .tables import filter_arrays, filter_names

RECOVERY_TOLERANCE = 1.2  # recovered: RMSE within this factor of the oracle's
RECOVERY_HOLD_S = 10.0  # ... and staying within for this long [s] (or to the phase's end)
TRACKED = (("R_rr", 2), ("R_bb", 3), ("Q_vv", 0), ("Q_gg", 1))  # column, true_variances index
TRACK_COLUMNS = [f"track_{c}" for c, _ in TRACKED]

PHASE_COLUMNS = [
    "scenario", "filter", "phase", "t_start", "t_end", "runs", "diverged", "runs_used",
    "rmse_pos", "rmse_heading", "anees", "nees_lo", "nees_hi", "nees_in_bounds",
    "rmse_vs_oracle", "rmse_vs_oracle_lo", "rmse_vs_oracle_hi",
    "recovery_s", "recovery_censored", *TRACK_COLUMNS,
]  # fmt: skip


def phase_bounds(schedule: NoiseSchedule, t_end: float) -> list[tuple[float, float]]:
    """(start, end) of every phase from 0 to t_end [s]."""
    points = [0.0, *schedule.change_points(t_end), float(t_end)]
    return list(zip(points[:-1], points[1:], strict=True))


def phase_masks(t: np.ndarray, bounds: list[tuple[float, float]]) -> list[np.ndarray]:
    """Which recorded steps (times t) lie in each phase; the last phase holds t_end itself."""
    masks = []
    for i, (a, b) in enumerate(bounds):
        last = i == len(bounds) - 1
        masks.append((t >= a) & ((t <= b) if last else (t < b)))
    return masks


def recovery_time(
    t: np.ndarray, rmse_filter: np.ndarray, rmse_oracle: np.ndarray, change: float, end: float
) -> tuple[float, bool]:
    """(seconds after `change` until the filter is back within RECOVERY_TOLERANCE of the oracle
    for good, censored) over one phase's recorded steps t (see the module docstring)."""
    if len(t) == 0:
        return float("nan"), False
    within = rmse_filter <= RECOVERY_TOLERANCE * rmse_oracle
    # next_out[i]: the first step j >= i outside the band (len(t): none)
    n = len(t)
    next_out = np.full(n + 1, n)
    for i in range(n - 1, -1, -1):
        next_out[i] = next_out[i + 1] if within[i] else i
    for i in np.flatnonzero(within):
        j = next_out[i]
        if j == n or t[j] > t[i] + RECOVERY_HOLD_S:
            return float(t[i] - change), False
    return float(end - change), True


def tracking_errors(a: dict, true_var: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Mean |ln(variance / true variance)| per channel over the kept runs and (masked) steps."""
    ok = ~np.asarray(a["diverged"], dtype=bool)
    mask = np.ones(len(a["t"]), dtype=bool) if mask is None else mask
    out = {}
    for (col, i), name in zip(TRACKED, TRACK_COLUMNS, strict=True):
        values = a[col][ok][:, mask]
        if values.size == 0:
            out[name] = float("nan")
            continue
        with np.errstate(all="ignore"):
            out[name] = float(np.mean(np.abs(np.log(values / true_var[mask, i][None, :]))))
    return out


def true_variance_curve(schedule: NoiseSchedule, true_sigmas, t: np.ndarray) -> np.ndarray:
    """(len(t), 4) true variances (speed, steering, range, bearing) at the recorded times."""
    return schedule.true_variances(true_sigmas, t)


def phases_frame(
    steps: pd.DataFrame,
    schedule: NoiseSchedule,
    true_sigmas,
    oracle: str | None,
    *,
    resamples: int = 2000,
    seed: int = 0,
) -> pd.DataFrame:
    """The phases table (phases.parquet): one row per (filter, phase), see the module docstring.

    `true_sigmas`: the scenario's nominal true sigmas (radians); `oracle`: the name of the filter
    recovery is measured against (None: no recovery times). rmse_vs_oracle: the phase's position
    RMSE over the oracle's, paired over the runs neither diverged in, with its 95 % paired
    bootstrap interval (comparisons.compare on the phase's steps; `resamples`, `seed`).
    """
    scenario = str(steps["scenario"].iloc[0])
    names = filter_names(steps)
    arrays = {name: filter_arrays(steps, name) for name in names}
    t = arrays[names[0]]["t"]
    bounds = phase_bounds(schedule, float(t[-1]))
    masks = phase_masks(t, bounds)
    true_var = true_variance_curve(schedule, true_sigmas, t)
    rows = []
    for name in names:
        a = arrays[name]
        both = ~a["diverged"]
        if oracle is not None:
            both = both & ~arrays[oracle]["diverged"]
        for p, ((start, end), m) in enumerate(zip(bounds, masks, strict=True)):
            row = {"scenario": scenario, "filter": name, "phase": p, "t_start": start, "t_end": end}
            if not m.any():  # changes closer than the recording interval: nothing recorded
                row.update(dict.fromkeys(PHASE_COLUMNS[5:], float("nan")), recovery_censored=False)
                rows.append(row)
                continue
            row.update(summarize_filter(a["pos_err"][:, m], a["heading_err"][:, m],
                                        a["nees"][:, m], a["diverged"]))  # fmt: skip
            recovery, censored = float("nan"), False
            if oracle is not None and p > 0 and both.any():
                recovery, censored = recovery_time(
                    t[m], rmse_curve(a["pos_err"][both][:, m]),
                    rmse_curve(arrays[oracle]["pos_err"][both][:, m]), start, end,
                )  # fmt: skip
            row.update(recovery_s=recovery, recovery_censored=censored)
            row.update(rmse_vs_oracle=math.nan, rmse_vs_oracle_lo=math.nan,
                       rmse_vs_oracle_hi=math.nan)  # fmt: skip
            if oracle is not None and name != oracle and both.any():
                ratio = compare(_phase(a, m), _phase(arrays[oracle], m), "rmse_pos",
                                resamples=resamples, seed=seed)  # fmt: skip
                row.update(rmse_vs_oracle=ratio["estimate"], rmse_vs_oracle_lo=ratio["lo"],
                           rmse_vs_oracle_hi=ratio["hi"])  # fmt: skip
            row.update(tracking_errors(a, true_var, m))
            rows.append(row)
    df = pd.DataFrame(rows, columns=PHASE_COLUMNS)
    df["phase"] = df["phase"].astype(np.int32)
    return df


def _phase(a: dict, mask: np.ndarray) -> dict:
    """A filter's arrays restricted to a phase's steps (per-run entries kept)."""
    return {k: (v[:, mask] if np.ndim(v) == 2 else v) for k, v in a.items()}


def summary_tracking(steps: pd.DataFrame, schedule: NoiseSchedule, true_sigmas) -> dict:
    """Each filter's tracking errors over the whole run ({filter: {track_R_rr: ...}})."""
    out = {}
    for name in filter_names(steps):
        a = filter_arrays(steps, name)
        out[name] = tracking_errors(a, true_variance_curve(schedule, true_sigmas, a["t"]))
    return out
