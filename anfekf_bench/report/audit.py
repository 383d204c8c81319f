"""The drive audit's tables in the report (SPEC 18; written by drive_audit as audit_*.parquet)
and the drives' consistency read run by run (runs.parquet's nees_in_bounds), from saved results
only. A result without the files (an older one) shows neither."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from ..analysis.metrics import format_number, format_share
from ..storage import AUDIT_FILES, RUNS_FILE, read_parquet
from .document import Block, Cell, Paragraph, TableBlock


def _read(folder: Path, key: str) -> pd.DataFrame | None:
    path = Path(folder) / AUDIT_FILES[key]
    return read_parquet(path) if path.is_file() else None


def _num(value, digits: int) -> Cell:
    v = math.nan if value is None else float(value)
    return Cell(format_number(v, digits), v)


def _ci(value, lo, hi, digits: int = 2) -> Cell:
    """'0.60 [0.55, 0.66]'."""
    v = float(value)
    text = format_number(v, digits)
    if math.isfinite(float(lo)) and math.isfinite(float(hi)):
        text += f" [{float(lo):.{digits}f}, {float(hi):.{digits}f}]"
    return Cell(text, v)


AUDIT_TEXT = (
    "The audit against Vicon (SPEC 18, drive_audit). Odometry: true = scale x commanded + "
    "bias, fitted on 0.5 s windows of scorable ground truth, the truth's windows delayed by "
    "the drive's response lag (the lag, 0-0.4 s, that leaves the smallest turn-rate "
    "residual), with a 95 % moving-block bootstrap interval (30 s blocks). Range and bearing "
    "residuals (measured minus the value from the Vicon pose and the map): median (bias) and "
    "robust std (1.4826 MAD); range slope: the range error per metre of true range (outliers,"
    " beyond 5 robust stds, left out). Whiteness: the lag-1 autocorrelation of ekf-tuned's "
    "normalised innovations (every associated landmark, in order; white noise stays within "
    "the band +-1.96/sqrt(n)). Gaps: stretches without any landmark. Lost lock: ekf-tuned's "
    "episodes with a position error above 1 m."
)

EPISODES_TEXT = (
    "What preceded each of ekf-tuned's lost-lock episodes. Lead-up: from the last time its error"
    " was below 0.5 m (5-30 s before the onset). Each episode is re-run three times over the whole"
    " drive with one error source removed; the max error over the lead-up and the episode under"
    " each: odometry corrected by the drive's own scale and bias (calibrated), odometry replaced"
    " by the Vicon-derived velocities (true odometry), the outlier measurements dropped. A source"
    " whose removal keeps the error under 1 m is a cause; a gap of 3 s or more and turning for"
    " 30 % of the lead-up are listed beside."
)


def audit_blocks(folder: Path) -> list[Block]:
    """The per-drive audit table and the lost-lock episodes table (nothing without the files)."""
    drives = _read(folder, "drives")
    episodes = _read(folder, "episodes")
    if drives is None or drives.empty:
        return []
    has_runs = "acf1_range" in drives.columns
    header = [
        "drive", "lag [s]", "v scale [95 %]", "v bias [m/s]", "w scale [95 %]", "w bias [rad/s]",
        "range bias [m]", "range robust std [m]", "range slope", "bearing bias [rad]",
        "bearing robust std [rad]", "outliers", "longest gap [s]", "in gaps > 2 s",
    ]  # fmt: skip
    if has_runs:
        header += ["r1 range", "r1 bearing", "band", "ekf-tuned max err [m]", "lost lock: cause"]
    rows = []
    for _, d in drives.iterrows():
        row = [
            Cell(str(d["drive"])), _num(d.get("lag_s"), 2),
            _ci(d["v_scale"], d["v_scale_lo"], d["v_scale_hi"]),
            _num(d["v_bias"], 3), _ci(d["w_scale"], d["w_scale_lo"], d["w_scale_hi"]),
            _num(d["w_bias"], 3), _num(d["range_bias"], 3), _num(d["range_robust_std"], 3),
            _num(d["range_slope"], 3), _num(d["bearing_bias"], 4),
            _num(d["bearing_robust_std"], 4),
            Cell(format_share(d["outlier_share"]), float(d["outlier_share"])),
            _num(d["longest_gap_s"], 1),
            Cell(format_share(d["gap_seconds_over_2s"] / d["seconds"]),
                 float(d["gap_seconds_over_2s"] / d["seconds"])),
        ]  # fmt: skip
        if has_runs:
            row += [
                _num(d["acf1_range"], 2), _num(d["acf1_bearing"], 2), _num(d["white_band"], 3),
                _num(d["max_pos_err"], 2),
                Cell(d["causes"] if d["lost_lock_episodes"] else "-", int(d["lost_lock_episodes"])),
            ]  # fmt: skip
        rows.append(row)
    out: list[Block] = [
        Paragraph(AUDIT_TEXT),
        TableBlock(header, rows, (False,) + (True,) * (len(header) - 2) + (False,)),
    ]
    out += range_blocks(_read(folder, "measurements"))
    if episodes is not None and not episodes.empty:
        header = ("drive", "onset [s]", "peak [m]", "lead-up [s]", "longest gap [s]", "turning",
                  "heading drift [rad]", "outliers (accepted)", "calibrated [m]",
                  "true odometry [m]", "no outliers [m]", "cause")  # fmt: skip
        rows = [
            [
                Cell(str(e["drive"])), _num(e["t_onset"], 1), _num(e["peak_err"], 2),
                _num(e["lead_s"], 1), _num(e["longest_gap_s"], 1),
                Cell(format_share(e["turning_share"]), float(e["turning_share"])),
                _num(e["heading_drift_rad"], 2),
                Cell(f"{int(e['outliers'])} ({int(e['outliers_accepted'])})", int(e["outliers"])),
                _num(e["max_err_calibration"], 2), _num(e["max_err_true_odometry"], 2),
                _num(e["max_err_outlier_removal"], 2), Cell(str(e["cause"])),
            ]
            for _, e in episodes.iterrows()
        ]  # fmt: skip
        out += [Paragraph(EPISODES_TEXT),
                TableBlock(header, rows, (False,) + (True,) * 10 + (False,))]  # fmt: skip
    return out


def range_blocks(meas: pd.DataFrame | None) -> list[Block]:
    """Per drive and true-range bin: the range and bearing residuals' median and robust std."""
    if meas is None or meas.empty:
        return []
    binned = meas[(meas["landmark"] == -1) & (meas["range_bin"] != "all")]
    bins = list(dict.fromkeys(binned["range_bin"]))
    rows = []
    for drive, sub in binned.groupby("drive", sort=False):
        by = sub.set_index("range_bin")
        row = [Cell(str(drive))]
        for b in bins:
            r = by.loc[b]
            row.append(Cell(f"{format_number(r['range_median'], 3)} / "
                            f"{format_number(r['range_robust_std'], 3)} ({int(r['n'])})",
                            float(r["range_median"])))  # fmt: skip
        for b in bins:
            r = by.loc[b]
            row.append(Cell(f"{format_number(r['bearing_median'], 4)} / "
                            f"{format_number(r['bearing_robust_std'], 4)}",
                            float(r["bearing_median"])))  # fmt: skip
        rows.append(row)
    header = ("drive", *(f"range {b} [m]" for b in bins), *(f"bearing {b} [rad]" for b in bins))
    return [
        TableBlock(
            header,
            rows,
            (False,) + (True,) * (len(header) - 1),
            caption="Residuals by true range: median / robust std (measurements):",
        )
    ]


def nees_per_drive_blocks(folder: Path, names: list[str], drives: list[str]) -> list[Block]:
    """Each instance's share of steps whose own NEES lies inside the single-run chi-square(3)
    bounds, per drive (runs.parquet's nees_in_bounds; nothing for an older result)."""
    path = Path(folder) / RUNS_FILE
    if not path.is_file():
        return []
    runs = read_parquet(path)
    if "nees_in_bounds" not in runs.columns:
        return []
    table = runs.pivot_table(index="filter", columns="run", values="nees_in_bounds",
                             aggfunc="first", dropna=False, observed=False)  # fmt: skip
    table = table.reindex([n for n in names if n in table.index])
    cols = [r for r in table.columns if 0 <= int(r) < len(drives)]
    rows = [
        [Cell(str(name)), *(Cell(format_share(v), float(v)) for v in table.loc[name, cols])]
        for name in table.index
    ]
    return [TableBlock(
        ("filter", *(drives[int(r)] for r in cols)), rows, (False,) + (True,) * len(cols),
        caption="Per drive share of scored steps whose own NEES lies inside the single-run 95 %"
        " chi-square(3) bounds [0.216, 9.35] (NEES in bounds, pooled, above: every scored step of"
        " every drive):",
    )]  # fmt: skip
