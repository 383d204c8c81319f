"""Tables from run results: per-step traces with their metrics, the steps table, the summaries."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from .metrics import nan_aware_mean, nees_single_run, summarize_filter

STEP_COLUMNS = [
    "scenario", "filter", "run", "step", "t",
    "x_true", "y_true", "phi_true", "x_est", "y_est", "phi_est",
    "P_xx", "P_xy", "P_xphi", "P_yy", "P_yphi", "P_phiphi",
    "pos_err", "heading_err", "nees",
    "R_rr", "R_bb", "Q_vv", "Q_gg", "P_infl", "diverged",
]  # fmt: skip
_P_INDEX = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
_THREADED_CELLS = 10_000_000  # a steps table of fewer cells is built on one thread


def steps_frame(
    scenario_name: str, filter_names: list[str], results: list[dict], jobs: int = 1
) -> pd.DataFrame:
    """The long table of steps.parquet: one row per (filter, run, recorded step), filters in
    `filter_names` order, runs in run order. Built column by column (one array per column), the
    columns on `jobs` threads (numpy copies without the GIL: the drives' 21 columns of 3.7
    million rows took 1.4 s on one)."""
    results = sorted(results, key=lambda r: r["run"])
    lengths = [len(res["step"]) for res in results]

    # Each column is a build, called below on one thread or several: per_run's, one array per
    # run (the same for every filter); per_trace's, one per (filter, run), filters outermost.
    def per_run(get) -> Callable[[], np.ndarray]:
        return lambda: np.tile(np.concatenate([get(res) for res in results]), len(filter_names))

    def per_trace(get) -> Callable[[], np.ndarray]:
        return lambda: np.concatenate(
            [get(res["filters"][name], len(res["step"])) for name in filter_names
             for res in results]
        )  # fmt: skip

    total = len(filter_names) * sum(lengths)
    builds = {
        "scenario": lambda: pd.Categorical.from_codes(
            np.zeros(total, dtype=np.int8), [scenario_name]
        ),
        "filter": lambda: pd.Categorical.from_codes(
            np.repeat(np.arange(len(filter_names), dtype=np.int16), sum(lengths)), filter_names
        ),
        "run": per_run(lambda r: np.full(len(r["step"]), r["run"], dtype=np.int32)),
        "step": per_run(lambda r: r["step"].astype(np.int32)),
        "t": per_run(lambda r: r["t"]),
        "x_true": per_run(lambda r: r["x_true"][:, 0]),
        "y_true": per_run(lambda r: r["x_true"][:, 1]),
        "phi_true": per_run(lambda r: r["x_true"][:, 2]),
        "x_est": per_trace(lambda tr, n: tr["x"][:, 0]),
        "y_est": per_trace(lambda tr, n: tr["x"][:, 1]),
        "phi_est": per_trace(lambda tr, n: tr["x"][:, 2]),
    }
    for (i, j), col in zip(_P_INDEX, STEP_COLUMNS[11:17], strict=True):
        builds[col] = per_trace(lambda tr, n, i=i, j=j: tr["P"][:, i, j])
    builds.update(
        pos_err=per_trace(lambda tr, n: tr["pos_err"]),
        heading_err=per_trace(lambda tr, n: tr["heading_err"]),
        nees=per_trace(lambda tr, n: tr["nees"]),
        R_rr=per_trace(lambda tr, n: tr["R_diag"][:, 0]),
        R_bb=per_trace(lambda tr, n: tr["R_diag"][:, 1]),
        Q_vv=per_trace(lambda tr, n: tr["Q_diag"][:, 0]),
        Q_gg=per_trace(lambda tr, n: tr["Q_diag"][:, 1]),
        P_infl=per_trace(lambda tr, n: tr["P_infl"]),
        diverged=per_trace(lambda tr, n: np.full(n, bool(tr["diverged"]))),
    )
    if jobs > 1 and total * len(builds) >= _THREADED_CELLS:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            cols = dict(zip(builds, pool.map(lambda build: build(), builds.values()), strict=True))
    else:
        cols = {name: build() for name, build in builds.items()}
    # copy=False: one block per column; consolidating them would copy every float column into one
    # 2-D block (240 MB and 0.6 s on a zoo scenario) for nothing that reads the table.
    return pd.DataFrame(cols, columns=STEP_COLUMNS, copy=False)


def in_key_order(*keys: np.ndarray, strict: bool = False) -> bool:
    """Whether rows given by equal-length key columns (most significant first) are sorted by
    them, ties allowed: what np.lexsort of the reversed keys would leave as it is. `strict`:
    and no two rows have the same keys (sorted, a repeated row would sit beside its twin)."""
    last = keys[-1]
    ok = last[1:] > last[:-1] if strict else last[1:] >= last[:-1]
    for key in reversed(keys[:-1]):
        ok = (key[1:] > key[:-1]) | ((key[1:] == key[:-1]) & ok)
    return bool(np.all(ok))


FILTER_SERIES = ("pos_err", "heading_err", "nees", "R_rr", "R_bb", "Q_vv", "Q_gg")


def filter_arrays(
    steps: pd.DataFrame, name: str, series: tuple[str, ...] = FILTER_SERIES
) -> dict[str, np.ndarray]:
    """(runs, steps) arrays of one filter's `series` (pos_err, heading_err, nees, R/Q), its run
    ids, steps, times and divergence flags."""
    # The columns it needs, picked by one mask and one stable (run, step) order: what
    # `steps[mask].sort_values(["run", "step"])` gives, without copying the other columns (the
    # comparisons and the summary call this once per filter). As steps_frame writes the table
    # (a filter's rows in one block, in order), the arrays are read-only views of its columns.
    mask = (steps["filter"] == name).to_numpy(dtype=bool)
    found = np.flatnonzero(mask)
    rows = mask
    if len(found) and found[-1] - found[0] + 1 == len(found):
        rows = slice(int(found[0]), int(found[-1]) + 1)
    run, step = steps["run"].to_numpy()[rows], steps["step"].to_numpy()[rows]
    order = slice(None) if in_key_order(run, step) else np.lexsort((step, run))  # no copy

    def col(c: str) -> np.ndarray:
        view = steps[c].to_numpy()[rows][order]
        view.flags.writeable = False  # a view of the table where nothing was copied
        return view

    run = run[order]
    runs = pd.unique(run)
    n = len(run) // max(len(runs), 1)
    out = {"run": runs, "step": step[order][:n], "t": col("t")[:n]}
    for c in series:
        out[c] = col(c).reshape(len(runs), n)
    out["diverged"] = col("diverged").reshape(len(runs), n)[:, 0]
    return out


def filter_names(steps: pd.DataFrame) -> list[str]:
    """The filters of a steps table in scenario order: the categories' order in memory, the
    order of appearance in a file read back (where `filter` is plain text)."""
    col = steps["filter"]
    if isinstance(col.dtype, pd.CategoricalDtype):
        return [str(n) for n in col.cat.categories if (col == n).any()]
    return [str(n) for n in dict.fromkeys(col)]


def summary_records(
    steps: pd.DataFrame,
    update_stats: dict[str, dict] | None = None,
    arrays: dict[str, dict[str, np.ndarray]] | None = None,
) -> list[dict]:
    """One summary record per filter, computed from the steps table alone (plus NIS totals).
    `arrays`: `filter_arrays` of the filters, when the caller has them (read, never changed)."""
    scenario = str(steps["scenario"].iloc[0])
    names = filter_names(steps)
    records = []
    for name in names:
        a = arrays[name] if arrays and name in arrays else filter_arrays(steps, name)
        rec = {"scenario": scenario, "filter": name}
        rec.update(summarize_filter(a["pos_err"], a["heading_err"], a["nees"], a["diverged"]))
        if update_stats and name in update_stats:
            rec.update(update_stats[name])
        records.append(rec)
    return records


def update_statistics(results: list[dict], filter_names: list[str]) -> dict[str, dict]:
    """Average NIS per accepted update and share of measurements the gate rejected."""
    results = sorted(results, key=lambda r: r["run"])  # a float sum depends on its order
    stats = {}
    for name in filter_names:
        traces = [r["filters"][name] for r in results if not r["filters"][name]["diverged"]]
        nis = sum(t["nis_sum"] for t in traces)
        used = sum(t["n_updates"] for t in traces)
        rejected = sum(t["n_rejected"] for t in traces)
        seen = used + rejected
        stats[name] = {
            "anis": nis / used if used else float("nan"),
            "gate_rejected": rejected / seen if seen else float("nan"),
        }
    return stats


def _peak(peak, values: np.ndarray) -> float:
    """The largest value (NaN for none, or only NaN)."""
    if not len(values) or np.isnan(values).all():
        return float(np.max(values)) if len(values) else float("nan")
    return float(peak(values))


RUN_COLUMNS = [
    "scenario", "filter", "run", "rmse_pos", "rmse_heading", "mean_nees", "max_nees",
    "nees_in_bounds", "diverged", "n_updates", "n_rejected", "anis",
]  # fmt: skip


def runs_frame(scenario_name: str, filter_names: list[str], results: list[dict]) -> pd.DataFrame:
    """The per-run table of runs.parquet (SPEC 8): one row per (filter, run).

    rmse_pos / rmse_heading: the run's own RMSE over its recorded steps [m] / [rad]; mean_nees and
    max_nees over its steps; nees_in_bounds: the share of its scored steps whose own NEES lies
    inside the single-run 95 % chi-square(3) bounds (metrics.nees_single_run; on recorded drives
    the fraction per drive); anis: its mean NIS per accepted update. A diverged run keeps its row
    (NaN metrics), so a comparison can see which runs both filters kept.
    """
    results = sorted(results, key=lambda r: r["run"])
    rows = []
    for name in filter_names:
        for res in results:
            tr = res["filters"][name]
            # A run that did not diverge may hold NaN at steps without a score (recorded logs):
            # they are left out; a diverged run keeps NaN metrics.
            mean = np.mean if tr["diverged"] else nan_aware_mean
            peak = np.max if tr["diverged"] or not np.isnan(tr["nees"]).any() else np.nanmax
            with np.errstate(all="ignore"):
                rows.append({
                    "run": res["run"],
                    "rmse_pos": float(np.sqrt(mean(np.square(tr["pos_err"])))),
                    "rmse_heading": float(np.sqrt(mean(np.square(tr["heading_err"])))),
                    "mean_nees": float(mean(tr["nees"])),
                    "max_nees": _peak(peak, tr["nees"]),
                    "nees_in_bounds": float("nan") if tr["diverged"]
                    else float(nees_single_run(tr["nees"])["per_run"][0]),
                    "diverged": bool(tr["diverged"]),
                    "n_updates": int(tr["n_updates"]),
                    "n_rejected": int(tr["n_rejected"]),
                    "anis": tr["nis_sum"] / tr["n_updates"] if tr["n_updates"] else float("nan"),
                    "filter": name,
                })  # fmt: skip
    df = pd.DataFrame(rows)
    df.insert(0, "scenario", scenario_name)
    df["scenario"] = pd.Categorical(df["scenario"])
    df["filter"] = pd.Categorical(df["filter"], categories=filter_names)
    df["run"] = df["run"].astype(np.int32)
    return df[RUN_COLUMNS]


# The unit of every column the result files hold (written into each Parquet file's metadata as
# `anfekf.units`); columns not listed are counts, flags, names or dimensionless.
COLUMN_UNITS: dict[str, str] = {
    "t": "s",
    **dict.fromkeys(("x_true", "y_true", "x_est", "y_est", "pos_err", "rmse_pos"), "m"),
    **dict.fromkeys(("phi_true", "phi_est", "heading_err", "rmse_heading"), "rad"),
    "P_xx": "m^2", "P_xy": "m^2", "P_yy": "m^2", "P_xphi": "m rad", "P_yphi": "m rad",
    "P_phiphi": "rad^2", "R_rr": "m^2", "R_bb": "rad^2", "Q_vv": "(m/s)^2", "Q_gg": "rad^2",
    **dict.fromkeys(("nees", "mean_nees", "max_nees", "anees", "nees_lo", "nees_hi"), "1"),
    **dict.fromkeys(("anis", "estimate", "lo", "hi", "p_value", "P_infl"), "1"),
    **dict.fromkeys(("nees_in_bounds", "gate_rejected"), "share (0..1)"),
    # phases.parquet (analysis/phases): phase bounds, recovery time, |ln| variance ratios
    **dict.fromkeys(("t_start", "t_end", "recovery_s"), "s"),
    **dict.fromkeys(("track_R_rr", "track_R_bb", "track_Q_vv", "track_Q_gg"), "1 (|ln ratio|)"),
    **dict.fromkeys(("rmse_vs_oracle", "rmse_vs_oracle_lo", "rmse_vs_oracle_hi"), "1"),
}  # fmt: skip
# Columns that name things: plain strings in every result file, so that steps, runs, summary and
# comparisons join on them in any tool (a pandas categorical is written as a dictionary type,
# and polars refuses to join a dictionary column of one file with a string column of another).
KEY_COLUMNS = ("scenario", "filter", "vs")


def parquet_frame(df: pd.DataFrame) -> pd.DataFrame:
    """`df` as a result file stores it: the key columns as plain strings (see KEY_COLUMNS)."""
    df = df.copy(deep=False)
    for col in KEY_COLUMNS:
        if col in df.columns:
            df[col] = _as_str(df[col])
    return df


def _as_str(col: pd.Series) -> pd.Series:
    """col.astype(str); a categorical without missing values by taking from its categories as
    text (the same values and dtype in a tenth of the time on a steps table's 10^5 rows)."""
    if isinstance(col.dtype, pd.CategoricalDtype):
        codes = col.cat.codes.to_numpy()
        if not (codes < 0).any():
            return pd.Series(col.cat.categories.astype(str).take(codes), index=col.index)
    return col.astype(str)


def column_units(df: pd.DataFrame) -> dict[str, str]:
    """The units of `df`'s columns that have one (COLUMN_UNITS)."""
    return {c: COLUMN_UNITS[c] for c in df.columns if c in COLUMN_UNITS}
