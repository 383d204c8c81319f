"""The per-drive audit against Vicon (SPEC 18, issue 35): what a recorded drive's errors are,
and what makes the tuned EKF lose lock on it.

For each drive of a `protocol: drives` scenario (`audit_tables`, run by real_experiment while it
prepares the drives; the tables go into the result folder as audit_*.parquet,
storage.AUDIT_FILES):

- **odometry**: the commanded v and turn rate against the Vicon-derived ones, both averaged over
  `WINDOW_S` windows, the truth's delayed by the drive's response lag (`response_lag`; only
  windows whose ground truth is scorable throughout), fitted as
  true = scale x commanded + bias with OLS standard errors and a 95 % moving-block bootstrap
  interval (blocks of 30 s; seeded by the scenario's seed);
- **measurements**: range and bearing residuals (measured minus the value from the Vicon pose
  and the map, at scorable times): bias and spread overall, per landmark and per true-range
  bin, and the range error's slope in the true range (fitted without the outliers: beyond 5
  robust stds);
- **whiteness**: the ekf-tuned EKF (the drive's cross-dataset tuning) run over the drive on the
  compiled innovation kernel (`engines.innovations`); the autocorrelation at lags 1-10 of each
  normalised innovation component (nu_i / sqrt(S_ii), every associated landmark, in order), its
  white-noise band and the Ljung-Box p;
- **gaps**: the stretches without any landmark measurement;
- **episodes**: each stretch where that run's position error exceeds `LOST_LOCK_M` at a scored
  time, what its lead-up held (the longest landmark gap, the share of time turning, the outlier
  measurements and how many the filter accepted, the heading and distance the odometry's error
  accumulated), and three counterfactual re-runs of the whole drive with one error source
  removed: the odometry corrected by the drive's own fitted scale and bias, the odometry replaced
  by the Vicon-derived velocities (at scorable times), the outlier measurements dropped. An
  episode a re-run does not repeat (its error stays under the threshold over the lead-up and the
  episode) is caused by that source (`analysis.audit.episode_cause`).

The audit reads the truth throughout: it is a diagnosis of the data, never an input of a filter.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pandas as pd

from .analysis import audit
from .engines.innovations import InnovationTrace, run_innovations
from .filters.ekf import gate_threshold
from .models import wrap_angle
from .sources import mrclam
from .storage import AUDIT_FILES

WINDOW_S = 0.5  # odometry is compared with the truth over windows of this length
LAGS_S = np.arange(0.0, 0.41, 0.05)  # the response lags tried (`response_lag`)
BLOCK_S = 30.0  # the bootstrap's blocks (a turn lasts 1-3 s; the errors of a manoeuvre persist)
RESAMPLES = 1000
LOST_LOCK_M = 1.0  # as analysis.suite.LOST_LOCK_M
LAGS = 10
GAP_S = 2.0  # landmark gaps counted in the drive table are longer than this


# --------------------------------------------------------------------------------------------
# Odometry


def odometry_windows(
    log: mrclam.RobotLog, ex: mrclam.Exclusions, t0: float, t1: float, lag_s: float = 0.0
) -> dict:
    """Commanded and true (v, w) over consecutive WINDOW_S windows of [t0, t1] inside the
    odometry span whose ground truth is scorable throughout; the truth's windows `lag_s` later
    (the robot follows its commands late)."""
    a = max(t0, float(log.odo_t[0])) if len(log.odo_t) else t0
    b = min(t1, float(log.odo_t[-1])) if len(log.odo_t) else t0
    edges = np.arange(a, b, WINDOW_S) if b > a else np.zeros(0)
    if len(edges) < 2:
        empty = np.zeros(0)
        return {"t0": empty, "t1": empty, "v_cmd": empty, "w_cmd": empty, "v": empty, "w": empty}
    v_cmd = audit.held_means(log.odo_t, log.odo_v, edges)
    w_cmd = audit.held_means(log.odo_t, log.odo_w, edges)
    v, w = audit.truth_velocities(
        log.truth_t, log.truth_x, log.truth_y, log.truth_phi_unwrapped, edges + lag_s
    )
    ok = _clear(ex, edges[:-1] + lag_s, edges[1:] + lag_s)
    return {
        "t0": edges[:-1][ok], "t1": edges[1:][ok], "v_cmd": v_cmd[ok], "w_cmd": w_cmd[ok],
        "v": v[ok], "w": w[ok],
    }  # fmt: skip


def _clear(ex: mrclam.Exclusions, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Windows [a, b] inside the ground-truth span that no gap or mis-fit touches."""
    ok = (a >= ex.t_start) & (b <= ex.t_end)
    for iv in (ex.gaps, ex.misfits):
        if len(iv):  # sorted, disjoint: an interval (s, e) touches [a, b] when s < b and e > a
            ok &= np.searchsorted(iv[:, 0], b, "left") <= np.searchsorted(iv[:, 1], a, "right")
    return ok


def response_lag(log: mrclam.RobotLog, ex: mrclam.Exclusions, t0: float, t1: float) -> float:
    """The delay [s] of the robot's response to its commands: the lag of LAGS_S whose windows
    leave the smallest residual std of the turn rate's fit (Datasets 6 and 7: about 0.2 s,
    which a fit at lag 0 reads as a smaller scale)."""
    best, best_std = 0.0, math.inf
    for lag in LAGS_S:
        win = odometry_windows(log, ex, t0, t1, float(lag))
        std = audit.fit_scale_bias(win["w_cmd"], win["w"], resamples=0)["resid_std"]
        if std < best_std:
            best, best_std = float(lag), std
    return best


def odometry_rows(drive: str, win: dict, seed: int) -> list[dict]:
    block = max(1, round(BLOCK_S / WINDOW_S))
    rows = []
    for q, unit in (("v", "m/s"), ("w", "rad/s")):
        fit = audit.fit_scale_bias(win[f"{q}_cmd"], win[q], block=block, resamples=RESAMPLES,
                                   seed=seed)  # fmt: skip
        rows.append({"drive": drive, "quantity": q, "unit": unit,
                     "seconds": float(len(win["t0"]) * WINDOW_S), **fit})  # fmt: skip
    return rows


# --------------------------------------------------------------------------------------------
# Measurements


def measurement_residuals(log: mrclam.RobotLog, ex: mrclam.Exclusions) -> dict:
    """Every landmark measurement's true range and range / bearing residual (NaN where the
    ground truth is not scorable), in log order (the timeline's z rows, in its span)."""
    x, y, phi = mrclam.interpolate_truth(log, log.meas_t)
    dx, dy = log.meas_xy[:, 0] - x, log.meas_xy[:, 1] - y
    true_range = np.hypot(dx, dy)
    d_range = log.meas_range - true_range
    d_bearing = wrap_angle(log.meas_bearing - wrap_angle(np.arctan2(dy, dx) - phi))
    ok = ex.scorable(log.meas_t) & np.isfinite(true_range)
    d_range, d_bearing = np.where(ok, d_range, np.nan), np.where(ok, d_bearing, np.nan)
    far = np.zeros(len(ok), bool)
    far[ok] = audit.outliers(d_range[ok], d_bearing[ok])
    return {"t": log.meas_t, "landmark": log.meas_landmark, "true_range": true_range,
            "d_range": d_range, "d_bearing": d_bearing, "scored": ok, "outlier": far}  # fmt: skip


def measurement_rows(drive: str, res: dict) -> list[dict]:
    ok = res["scored"]
    lm, r, dr, db = (res[k][ok] for k in ("landmark", "true_range", "d_range", "d_bearing"))
    rows = [{"drive": drive, "landmark": -1, "range_bin": "all", **audit.residual_stats(dr, db)}]
    for i in np.unique(lm):
        at = lm == i
        rows.append({"drive": drive, "landmark": int(i), "range_bin": "all",
                     **audit.residual_stats(dr[at], db[at])})  # fmt: skip
    bins = audit.range_bin(r)
    for b, label in enumerate(audit.range_bin_labels()):
        at = bins == b
        rows.append({"drive": drive, "landmark": -1, "range_bin": label,
                     **audit.residual_stats(dr[at], db[at])})  # fmt: skip
    return rows


# --------------------------------------------------------------------------------------------
# Counterfactual inputs


def _calibrated(tl, fits: dict) -> object:
    s = np.array([fits["v"]["scale"], fits["w"]["scale"]])
    b = np.array([fits["v"]["bias"], fits["w"]["bias"]])
    if not (np.isfinite(s).all() and np.isfinite(b).all()):
        return None
    return replace(tl, u=np.ascontiguousarray(tl.u * s + b))


def _true_odometry(tl, log: mrclam.RobotLog, ex: mrclam.Exclusions, calibrated) -> object:
    """Each stamp's command replaced by the Vicon-derived (v, w) over its interval (t[k-1],
    t[k]]; where that interval's truth is not scorable, the calibrated command (or the
    commanded one)."""
    edges = np.r_[tl.t_start, tl.t]
    v, w = audit.truth_velocities(
        log.truth_t, log.truth_x, log.truth_y, log.truth_phi_unwrapped, edges
    )
    ok = ex.scorable(edges[:-1]) & ex.scorable(edges[1:])
    base = (calibrated if calibrated is not None else tl).u
    u = np.where(ok[:, None], np.column_stack([v, w]), base)
    return replace(tl, u=np.ascontiguousarray(u))


def _without(tl, drop: np.ndarray) -> object:
    """The timeline with the landmark rows `drop` (bool, (m,)) removed."""
    keep = ~drop
    kept_before = np.r_[0, np.cumsum(keep)]
    return replace(
        tl, z=np.ascontiguousarray(tl.z[keep]), xy=np.ascontiguousarray(tl.xy[keep]),
        lm=kept_before[tl.lm].astype(tl.lm.dtype),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# One drive


def _pos_err(trace: InnovationTrace, truth: np.ndarray) -> np.ndarray:
    return np.hypot(truth[:, 0] - trace.x[:, 0], truth[:, 1] - trace.x[:, 1])


def _longest_gap(gaps: np.ndarray, a: float, b: float) -> float:
    if not len(gaps):
        return 0.0
    lo, hi = np.maximum(gaps[:, 0], a), np.minimum(gaps[:, 1], b)
    return float(max(0.0, np.max(hi - lo)))


def audit_drive(drive, inputs, sigmas, scenario, seed: int = 0) -> dict[str, list[dict]]:
    """The audit's rows for one drive (`recorded.Drive`, its `SegmentInputs`, ekf-tuned's
    sigmas (s_v, s_w, s_range, s_bearing) or None: no whiteness and no episodes)."""
    log, ex, seg = drive.log, drive.exclusions, drive.segment
    lag = response_lag(log, ex, seg.t0, seg.end)
    win = odometry_windows(log, ex, seg.t0, seg.end, lag)
    odo = [{**r, "lag_s": lag} for r in odometry_rows(drive.id, win, seed)]
    fits = {r["quantity"]: r for r in odo}
    res = measurement_residuals(log, ex)
    meas = measurement_rows(drive.id, res)
    ok = res["scored"] & ~res["outlier"]
    dep = audit.range_dependence(res["true_range"][ok], res["d_range"][ok])
    gaps = audit.landmark_gaps(log.meas_t, seg.t0, seg.end)
    long_gaps = gaps[(gaps[:, 1] - gaps[:, 0]) > GAP_S]
    overall = meas[0]
    row = {
        "drive": drive.id, "dataset": drive.dataset, "seconds": float(seg.end - seg.t0),
        "scored_seconds": float(ex.scorable_seconds(seg.t0, seg.end)), "lag_s": lag,
        **{f"{q}_{k}": fits[q][k] for q in ("v", "w")
           for k in ("scale", "scale_lo", "scale_hi", "bias", "bias_lo", "bias_hi")},
        "range_bias": overall["range_median"], "range_robust_std": overall["range_robust_std"],
        "bearing_bias": overall["bearing_median"],
        "bearing_robust_std": overall["bearing_robust_std"],
        "outlier_share": overall["outlier_share"], **dep,
        "longest_gap_s": float(np.max(gaps[:, 1] - gaps[:, 0])) if len(gaps) else 0.0,
        "gaps_over_2s": int(len(long_gaps)),
        "gap_seconds_over_2s": float((long_gaps[:, 1] - long_gaps[:, 0]).sum()),
    }  # fmt: skip
    out = {"drives": [row], "odometry": odo, "measurements": meas, "whiteness": [],
           "episodes": []}  # fmt: skip
    if sigmas is None:
        return out
    tl = inputs.timeline
    P0 = np.diag([scenario.p0_std_xy**2, scenario.p0_std_xy**2, scenario.p0_std_phi_rad**2])
    gate = gate_threshold(scenario.gate_probability)
    T0 = scenario.odometry_period_s

    def run(timeline) -> InnovationTrace:
        return run_innovations(timeline, seg.pose, P0, sigmas, gate, T0)

    base = run(tl)
    # whiteness: every associated landmark's normalised innovation, in order
    norm = base.normalised()
    n = int(np.isfinite(norm[:, 0]).sum())
    band = audit.white_band(n)
    for c, comp in enumerate(("range", "bearing")):
        r = audit.autocorrelation(norm[:, c], LAGS)
        q, p = audit.ljung_box(norm[:, c], LAGS)
        row[f"acf1_{comp}"] = float(r[0])
        row[f"max_acf_{comp}"] = float(np.nanmax(np.abs(r)))
        row[f"ljung_box_p_{comp}"] = p
        for k in range(LAGS):
            out["whiteness"].append({"drive": drive.id, "component": comp, "lag": k + 1,
                                     "acf": float(r[k]), "band": band, "n": n,
                                     "ljung_box_q": q, "ljung_box_p": p})  # fmt: skip
    row["white_band"] = band
    nis = np.einsum("ij,ij->i", base.nu, _solve2(base.S, base.nu))
    row["mean_nis"] = float(np.nanmean(nis))
    row["gate_rejected"] = float(1 - base.accepted.sum() / max(len(base.accepted), 1))

    # lost-lock episodes of this run and their counterfactual re-runs
    t, truth = inputs.t, inputs.truth
    err = _pos_err(base, truth)
    row["max_pos_err"] = float(np.nanmax(err)) if np.isfinite(err).any() else math.nan
    eps = audit.episodes(t, err, LOST_LOCK_M)
    row["lost_lock_episodes"] = int(len(eps))
    causes = []
    if len(eps):
        in_span = (log.meas_t > tl.t_start) & (log.meas_t <= tl.t[-1])
        outlier_rows = res["outlier"][in_span]
        calibrated = _calibrated(tl, fits)
        variants = {
            "fixed_by_calibration": calibrated,
            "fixed_by_true_odometry": _true_odometry(tl, log, ex, calibrated),
            "fixed_by_outlier_removal": _without(tl, outlier_rows),
        }
        errs = {k: None if v is None else _pos_err(run(v), truth) for k, v in variants.items()}
        accepted_outliers = base.accepted & outlier_rows
        z_t = log.meas_t[in_span]
        for e, (i0, i1) in enumerate(eps):
            lead0, onset = audit.lead_window(t, err, int(i0), LOST_LOCK_M)
            end = float(t[i1])
            span = (t >= lead0) & (t <= end)
            lead = (win["t0"] >= lead0) & (win["t1"] <= onset)
            dur = WINDOW_S * lead.sum()
            in_lead = (z_t >= lead0) & (z_t <= onset)
            facts = {
                "drive": drive.id, "episode": e, "t_onset": onset - seg.t0,
                "t_end": end - seg.t0, "lead_s": onset - lead0,
                "peak_err": float(np.nanmax(err[i0 : i1 + 1])),
                "longest_gap_s": _longest_gap(gaps, lead0, onset),
                "turning_share": float(np.mean(np.abs(win["w"][lead]) > audit.TURN_RATE))
                if lead.any() else 0.0,
                "heading_drift_rad": float(np.sum(win["w_cmd"][lead] - win["w"][lead]) * WINDOW_S),
                "distance_drift_m": float(np.sum(win["v_cmd"][lead] - win["v"][lead]) * WINDOW_S),
                "lead_truth_s": float(dur),
                "outliers": int(outlier_rows[in_lead].sum()),
                "outliers_accepted": int(accepted_outliers[in_lead].sum()),
            }  # fmt: skip
            for k, ev in errs.items():
                facts[k] = bool(ev is not None and np.nanmax(ev[span]) < LOST_LOCK_M)
                facts[k.replace("fixed_by", "max_err")] = (
                    float(np.nanmax(ev[span])) if ev is not None else math.nan
                )
            facts["cause"] = audit.episode_cause(facts)
            causes.append(facts["cause"])
            out["episodes"].append(facts)
    row["causes"] = "; ".join(dict.fromkeys(causes))
    return out


def _solve2(S: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """S^-1 nu for stacks of 2 x 2 symmetric S given as (S00, S01, S11)."""
    det = S[:, 0] * S[:, 2] - S[:, 1] ** 2
    return np.column_stack(
        [(S[:, 2] * nu[:, 0] - S[:, 1] * nu[:, 1]) / det,
         (S[:, 0] * nu[:, 1] - S[:, 1] * nu[:, 0]) / det]
    )  # fmt: skip


def audit_tables(scenario, drives, inputs: dict, tuned_for: dict, seed: int = 0) -> dict:
    """The audit's tables (file name -> DataFrame, storage.AUDIT_FILES) over `drives`
    (recorded.Drive, in run order), their `SegmentInputs` by drive id and ekf-tuned's noise by
    drive id."""
    rows: dict[str, list[dict]] = {k: [] for k in AUDIT_FILES}
    for d in drives:
        tuned = tuned_for.get(d.id)
        sig = None if tuned is None else [
            tuned[k] for k in ("sigma_v", "sigma_w_rad", "sigma_range", "sigma_bearing_rad")
        ]  # fmt: skip
        for k, v in audit_drive(d, inputs[d.id], sig, scenario, seed).items():
            rows[k].extend(v)
    return {AUDIT_FILES[k]: pd.DataFrame(v) for k, v in rows.items()}
