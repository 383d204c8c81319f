"""The report's part for scenarios whose true noise changes (SPEC 14): figures over time with the
change instants marked, every adapting filter's variances against the true schedule, and the
per-phase table (phases.parquet)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from pydantic import ValidationError

from ..analysis.metrics import format_share, format_sig
from ..analysis.phases import RECOVERY_HOLD_S, RECOVERY_TOLERANCE
from ..filters.registry import role_of
from ..schedule import CHANNELS, NoiseSchedule
from ..storage import PHASES_FILE, ResultsError, read_parquet
from .data import NOISE_COLUMNS, FilterSeries, ScenarioData
from .document import Cell, TableBlock
from .plots import filter_style, legend_entries, plain_log_axis

_CHANNEL_OF = {"R_rr": "range", "R_bb": "bearing", "Q_vv": "speed", "Q_gg": "steering"}


def read_schedule(manifest: dict, path: Path) -> NoiseSchedule | None:
    """The scenario's noise schedule from its manifest (None: constant noise)."""
    raw = (manifest.get("scenario") or {}).get("noise_schedule")
    if raw is None:
        return None
    try:
        return NoiseSchedule.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise ResultsError(f"{path}: scenario.noise_schedule.{where}: {err['msg']}") from None


def read_phases(folder: Path) -> pd.DataFrame | None:
    """phases.parquet of a result folder, when it has one."""
    path = Path(folder) / PHASES_FILE
    return read_parquet(path) if path.is_file() else None


def _mark_changes(ax: Axes, schedule: NoiseSchedule, t_end: float, label: bool) -> None:
    """Change instants as vertical lines, blackouts shaded."""
    for i, c in enumerate(schedule.change_points(t_end)):
        ax.axvline(c, color="black", lw=0.8, ls=":", gid=f"change/{c:g}",
                   label="change" if label and i == 0 else None)  # fmt: skip
    for i, b in enumerate(schedule.blackouts):
        ax.axvspan(b.start_s, min(b.end_s, t_end), color="0.5", alpha=0.15, lw=0,
                   gid=f"blackout/{b.start_s:g}",
                   label="blackout" if label and i == 0 else None)  # fmt: skip


def changes_figure(sc: ScenarioData, schedule: NoiseSchedule) -> Figure:
    """Position RMSE over time of every filter, and its ratio to the oracle's (log scale, the
    recovery band 1.2 drawn), with the change instants marked."""
    ref = sc.reference()
    others = [f for f in sc.filters if ref is not None and f.name != ref.name]
    fig = Figure(figsize=(9, 7.5), layout="constrained")
    ax_pos, ax_ratio = fig.subplots(2, 1, sharex=True)
    t_end = float(sc.filters[0].t[-1])
    for f in sc.filters:
        ax_pos.plot(f.t, f.pos.line, lw=1.1, label=f.name, gid=f"changing_rmse/{f.name}",
                    **filter_style(f.name, f.kind).line())  # fmt: skip
    _mark_changes(ax_pos, schedule, t_end, label=True)
    ax_pos.set_ylabel("position RMSE [m]")
    ax_pos.set_ylim(bottom=0)
    if others:
        with np.errstate(all="ignore"):
            for f in others:
                ratio = f.pos.line / ref.pos.line
                ax_ratio.plot(f.t, ratio, lw=1.0, gid=f"changing_ratio/{f.name}",
                              **filter_style(f.name, f.kind).line())  # fmt: skip
        ax_ratio.axhline(RECOVERY_TOLERANCE, color="black", lw=0.8, ls="--",
                         label=f"recovered below {RECOVERY_TOLERANCE:g}x")  # fmt: skip
        ax_ratio.axhline(1.0, color="0.6", lw=0.6)
        plain_log_axis(ax_ratio)
        ax_ratio.set_ylabel(f"position RMSE / {ref.name}'s (log)")
    _mark_changes(ax_ratio, schedule, t_end, label=False)
    ax_ratio.set_xlabel("time [s]")
    ax_pos.set_xlim(sc.filters[0].t[0], t_end)
    # one legend below the panels (outside the data): the filters, the changes, the recovery line
    handles, labels = legend_entries((ax_pos, ax_ratio))
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 5))
    fig.suptitle(f"{sc.name}: position RMSE over runs with the noise changes marked")
    return fig


def adapting(f: FilterSeries, col: str) -> bool:
    """Whether `f` changes its `col` variance during the runs (any filter kind: read from its
    recorded values; the oracle, told the schedule, is drawn as the truth instead)."""
    if role_of(f.kind) == "oracle":
        return False
    values = np.concatenate([f.noise[col].lo, f.noise[col].hi])
    values = values[np.isfinite(values)]
    return values.size > 0 and float(values.max() - values.min()) > 1e-9 * abs(float(values.max()))


def variances_figure(sc: ScenarioData, schedule: NoiseSchedule) -> Figure | None:
    """Every adapting filter's variances (mean over runs) against the true schedule, one panel
    per channel some filter adapts; None when no filter adapts any."""

    columns = [c for c in NOISE_COLUMNS if any(adapting(f, c) for f in sc.filters)]
    if not columns:
        return None
    t = sc.filters[0].t
    true = schedule.true_variances(sc.true_sigmas.radians(), t)
    nrows = math.ceil(len(columns) / 2)
    fig = Figure(figsize=(10, 3.8 * nrows + 1.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, 2, sharex=True, squeeze=False)).ravel()
    for ax, col in zip(axes, columns, strict=False):
        what, unit, factor = NOISE_COLUMNS[col]
        for f in sc.filters:
            if adapting(f, col):
                ax.plot(f.t, f.noise[col].line, lw=1.0, label=f.name,
                        gid=f"changing_noise/{col}/{f.name}",
                        **filter_style(f.name, f.kind).line())  # fmt: skip
        ax.plot(t, true[:, CHANNELS.index(_CHANNEL_OF[col])] * factor, color="black", lw=1.4,
                ls="--", label="true", gid=f"changing_true/{col}")  # fmt: skip
        _mark_changes(ax, schedule, float(t[-1]), label=False)
        plain_log_axis(ax)
        ax.set_title(f"{what} {col}", fontsize=9)
        ax.set_ylabel(f"{col} [{unit}] (log)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0, fontsize=7)
    for ax in axes[len(columns) :]:
        ax.set_visible(False)
    for ax in axes[max(len(columns) - 2, 0) : len(columns)]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"{sc.name}: adapted variances (mean over runs) against the true schedule"
                 " (dashed; outliers: the mixture's variance)", fontsize=9)  # fmt: skip
    return fig


PHASES_CAPTION = (
    "Per phase (between change points): position RMSE [m], its ratio to the oracle's over the"
    " phase (paired over runs, 95 % bootstrap interval), ANEES and share of steps with NEES in"
    " the 95 % bounds; *recovery*: seconds after the phase's change until the filter's position"
    f" RMSE is within {RECOVERY_TOLERANCE:g}x the oracle's for {RECOVERY_HOLD_S:g} s (or to the"
    " phase's end), '>' when it never is (censored at the phase's length); *track R* / *track Q*:"
    " mean |ln(filter's variance / true variance)| over the two channels of R / of Qu"
    " (0: exact; ln 2 = 0.69: a factor 2 off)."
)


def phases_table(phases: pd.DataFrame) -> TableBlock:
    """The per-phase table of report.md, from phases.parquet."""
    header = ["filter", "phase [s]", "RMSE pos", "RMSE / oracle", "ANEES", "in bounds",
              "recovery [s]", "track R", "track Q"]  # fmt: skip
    rows = []
    for _, r in phases.iterrows():
        if not math.isfinite(r["recovery_s"]):
            recovery = "-"
        else:
            recovery = (">" if r["recovery_censored"] else "") + format_sig(r["recovery_s"])
        track_r = float(np.mean([r["track_R_rr"], r["track_R_bb"]]))
        track_q = float(np.mean([r["track_Q_vv"], r["track_Q_gg"]]))
        ratio = float(r.get("rmse_vs_oracle", math.nan))
        if math.isfinite(ratio):
            lo, hi = float(r["rmse_vs_oracle_lo"]), float(r["rmse_vs_oracle_hi"])
            ratio_text = f"{format_sig(ratio)} [{format_sig(lo)}, {format_sig(hi)}]"
        else:
            ratio_text = "-"
        rows.append([
            str(r["filter"]),
            f"{r['t_start']:g}-{r['t_end']:.4g}",
            Cell(format_sig(r["rmse_pos"]), r["rmse_pos"]),
            Cell(ratio_text, ratio),
            Cell(format_sig(r["anees"]), r["anees"]),
            Cell(format_share(r["nees_in_bounds"]), r["nees_in_bounds"]),
            Cell(recovery, r["recovery_s"]),
            Cell(format_sig(track_r, 2), track_r),
            Cell(format_sig(track_q, 2), track_q),
        ])  # fmt: skip
    return TableBlock(header, rows, numeric=[False, False, *[True] * 7], caption=PHASES_CAPTION)
