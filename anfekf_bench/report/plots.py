"""The report's matplotlib figures, drawn only from the series report.py computes.

Every function returns a `matplotlib.figure.Figure` (no pyplot state), so tests can read back the
plotted data: each data artist carries a gid such as "rmse_pos/anfekf" or "nees_bound_hi/50".
One colour per filter in every figure (`filter_colour`).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")  # files only; never open a window

import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Ellipse, Rectangle  # noqa: E402

from ..analysis.metrics import format_number, format_share  # noqa: E402
from ..storage import write_atomic  # noqa: E402

if TYPE_CHECKING:  # report.py imports this module; these names are for annotations only
    from .report import Band, FilterSeries, ScenarioData, SummaryRow

DPI = 110
ELLIPSE_SIGMA = 3.0
FILTER_COLOURS = {
    "ekf": "#d62728",  # red
    "anfekf": "#1f77b4",  # blue
    "anfekf-q": "#2ca02c",  # green
    "ekf-oracle": "#4d4d4d",  # dark grey: the reference
}
# Other filter names get one of these, chosen by a stable hash of the name (not Python's hash(),
# which changes between processes), so a name keeps its colour in every figure and every report.
FALLBACK_COLOURS = ("#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
_RC = {
    "font.size": 9,
    "axes.titlesize": 10,
    "legend.fontsize": 8,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "svg.hashsalt": "anfekf-report",  # reproducible SVG ids
}
_METADATA = {"png": {}, "svg": {"Date": None}, "pdf": {"CreationDate": None}}


def filter_colour(name: str) -> str:
    """The colour of filter `name`, the same in every figure."""
    if name in FILTER_COLOURS:
        return FILTER_COLOURS[name]
    return FALLBACK_COLOURS[zlib.crc32(name.encode()) % len(FALLBACK_COLOURS)]


def _style(f: FilterSeries) -> dict:
    # The oracle is a reference, not a contender: dashed, in every figure.
    return {"color": filter_colour(f.name), "linestyle": "--" if f.kind == "ekf-oracle" else "-"}


def save_figure(fig: Figure, path: Path, fmt: str = "png") -> None:
    """Write `fig` atomically in format png, svg or pdf (no timestamps: reproducible files)."""
    with matplotlib.rc_context(_RC):
        write_atomic(
            Path(path),
            lambda tmp: fig.savefig(tmp, format=fmt, dpi=DPI, metadata=_METADATA.get(fmt, {})),
        )


def _band(
    ax: Axes, t: np.ndarray, band: Band, f: FilterSeries, key: str, label: str | None
) -> None:
    style = _style(f)
    ax.fill_between(
        t, band.lo, band.hi, color=style["color"], alpha=0.12, lw=0, gid=f"{key}_band/{f.name}"
    )
    ax.plot(t, band.line, lw=1.2, label=label, gid=f"{key}/{f.name}", **style)


def _lost(f: FilterSeries) -> str:
    """Legend note for a filter that lost runs to divergence (they are left out of its curves)."""
    lost = f.runs - f.runs_used
    return f" ({lost} of {f.runs} runs diverged, left out)" if lost else ""


def _ends(est: np.ndarray, t: np.ndarray) -> str:
    """Legend note for an estimate that stops: the filter diverged in this run."""
    bad = np.flatnonzero(~np.all(np.isfinite(est), axis=1))
    return f" (diverged by t = {t[bad[0]]:.1f} s)" if len(bad) else ""


def _runs_text(sc: ScenarioData) -> str:
    """'50 runs', with a pointer to the legend when some filter lost runs to divergence."""
    lost = any(f.runs_used < f.runs for f in sc.filters)
    return f"{sc.runs} runs" + (" (diverged runs left out: see legend)" if lost else "")


@matplotlib.rc_context(_RC)
def rmse_figure(sc: ScenarioData) -> Figure:
    """Position and heading RMSE over time per filter, with the spread over runs shaded."""
    fig = Figure(figsize=(9, 6), layout="constrained")
    ax_pos, ax_head = fig.subplots(2, 1, sharex=True)
    lo, hi = _percentiles()
    for f in sc.filters:
        s = f.summary
        head = math.degrees(s["rmse_heading"]) if math.isfinite(s["rmse_heading"]) else math.nan
        label = (
            f"{f.name}: {format_number(s['rmse_pos'], 3)} m, {format_number(head, 3)} deg{_lost(f)}"
        )
        _band(ax_pos, f.t, f.pos, f, "rmse_pos", label)
        _band(ax_head, f.t, f.heading, f, "rmse_heading", None)
    ax_pos.set_ylabel("position RMSE [m]")
    ax_head.set_ylabel("heading RMSE [deg]")
    ax_head.set_xlabel("time [s]")
    for ax in (ax_pos, ax_head):
        ax.set_ylim(bottom=0)
        ax.set_xlim(sc.filters[0].t[0], sc.filters[0].t[-1])
    # Below the axes: error spikes reach any corner, a legend inside would hide some.
    fig.legend(
        *ax_pos.get_legend_handles_labels(),
        loc="outside lower center",
        ncols=min(len(sc.filters), 4),
        title="filter: time mean of the position and heading lines",
    )
    fig.suptitle(f"{sc.name}: RMSE over time, {_runs_text(sc)}")
    ax_pos.set_title(
        f"line: RMSE over runs sqrt(mean(ex² + ey²)) at each step;"
        f" band: {lo:g}-{hi:g} % of the runs' errors",
        fontsize=8,
    )
    return fig


@matplotlib.rc_context(_RC)
def nees_figure(sc: ScenarioData) -> Figure:
    """Run-averaged NEES per filter (log scale) with the two-sided 95 % chi-square bounds."""
    fig = Figure(figsize=(9, 5.2), layout="constrained")
    ax = fig.subplots()
    for f in sc.filters:
        s = f.summary
        share = format_share(s["nees_in_bounds"])
        label = f"{f.name}: ANEES {format_number(s['anees'], 2)}, {share} in bounds{_lost(f)}"
        ax.plot(f.t, f.nees, lw=1.0, label=label, gid=f"nees/{f.name}", **_style(f))
    # Filters that lost runs to divergence average fewer runs: their bounds are wider.
    for n, (lo, hi) in sorted({(f.runs_used, f.bounds) for f in sc.filters if f.runs_used}):
        label = f"95 % bounds, {n} runs: [{lo:.2f}, {hi:.2f}]"
        ax.axhspan(lo, hi, color="#2ca02c", alpha=0.08, lw=0)
        ax.axhline(lo, color="black", lw=0.9, ls=":", label=label, gid=f"nees_bound_lo/{n}")
        ax.axhline(hi, color="black", lw=0.9, ls=":", gid=f"nees_bound_hi/{n}")
    ax.axhline(3.0, color="#2ca02c", lw=0.8, alpha=0.6, label="expected value 3 (pose dim.)")
    ax.set_yscale("log")
    ax.set_xlim(sc.filters[0].t[0], sc.filters[0].t[-1])
    ax.set_xlabel("time [s]")
    ax.set_ylabel("run-averaged NEES [-] (log)")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncols=2)
    fig.suptitle(f"{sc.name}: consistency, NEES averaged over {_runs_text(sc)}")
    return fig


@matplotlib.rc_context(_RC)
def noise_figure(sc: ScenarioData) -> Figure:
    """The adapted R/Q diagonal over time (mean over runs and spread) against the true value."""
    from .report import NOISE_COLUMNS

    columns = sc.adapted_columns
    ncols = 2
    nrows = math.ceil(len(columns) / ncols)
    fig = Figure(figsize=(9, 3.4 * nrows + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, ncols, sharex=True, squeeze=False)).ravel()
    lo, hi = _percentiles()
    ekf = next((f for f in sc.filters if f.kind == "ekf"), None)
    for ax, col in zip(axes, columns, strict=False):
        what, unit = NOISE_COLUMNS[col]
        for f in sc.filters:
            if f.adapts and col.startswith(f.adapts):
                _band(ax, f.t, f.noise[col], f, f"noise/{col}", f"{f.name} (adapted)")
        if ekf is not None:
            ax.plot(
                ekf.t,
                ekf.noise[col].line,
                lw=1.2,
                ls=":",
                color=filter_colour(ekf.name),
                label=f"{ekf.name} (fixed)",
                gid=f"noise_fixed/{col}/{ekf.name}",
            )
        true = sc.true_noise[col]
        ax.axhline(
            true,
            color="black",
            lw=1.0,
            ls="--",
            label=f"true: {true:.3g} {unit}",
            gid=f"noise_true/{col}",
        )
        ax.set_yscale("log")
        ax.set_title(f"{what} {col}", fontsize=9)
        ax.set_ylabel(f"{col} [{unit}] (log)")
        ax.legend(loc="best")
    for ax in axes[len(columns) :]:
        ax.set_visible(False)
    for ax in axes[max(len(columns) - ncols, 0) : len(columns)]:
        ax.set_xlabel("time [s]")
    fig.suptitle(
        f"{sc.name}: adapted noise covariance, mean over {_runs_text(sc)} "
        f"(band: {lo:g}-{hi:g} % of runs); ekf-oracle uses the true value"
    )
    return fig


def ellipse(centre: np.ndarray, cov: np.ndarray, sigma: float = ELLIPSE_SIGMA, **kw) -> Ellipse:
    """The `sigma`-sigma ellipse of a 2x2 covariance around `centre`."""
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    angle = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
    width, height = 2 * sigma * np.sqrt(vals[::-1])
    return Ellipse(tuple(centre), width=width, height=height, angle=angle, fill=False, **kw)


def _ellipse_ok(est: np.ndarray, cov: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(est)) and np.all(np.isfinite(cov)))


def _zoom_index(sc: ScenarioData) -> int:
    """The ellipse instant with the largest ellipse of any filter: the most telling close-up."""
    tr = sc.track
    best, best_size = int(tr.ellipse_index[-1]), -1.0
    for k in tr.ellipse_index:
        for name in tr.cov:
            if _ellipse_ok(tr.estimate[name][k], tr.cov[name][k]):
                size = float(np.linalg.eigvalsh(tr.cov[name][k])[-1])
                if size > best_size:
                    best, best_size = int(k), size
    return best


def _zoom_half_width(sc: ScenarioData, k: int) -> float:
    tr = sc.track
    reach = 1.0
    for name in tr.cov:
        est, cov = tr.estimate[name][k], tr.cov[name][k]
        if _ellipse_ok(est, cov):
            radius = ELLIPSE_SIGMA * math.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0))
            reach = max(reach, radius + float(np.hypot(*(est - tr.truth[k]))))
    return 1.4 * reach


@matplotlib.rc_context(_RC)
def map_figure(sc: ScenarioData) -> Figure:
    """Landmarks, waypoints, the true path, one run's estimates and 3-sigma ellipses, a zoom."""
    fig = Figure(figsize=(12, 5.6), layout="constrained")
    ax_map, ax_zoom = fig.subplots(1, 2, width_ratios=[1.6, 1])
    tr = sc.track
    styles = {f.name: _style(f) for f in sc.filters}
    k = _zoom_index(sc)
    half = _zoom_half_width(sc, k)
    centre = tr.truth[k]
    for ax in (ax_map, ax_zoom):
        main = ax is ax_map  # gids on the full map only: tests read the data back from there
        ax.scatter(*sc.landmarks.T, marker="*", s=60, color="#b8860b", label="landmarks",
                   zorder=3, gid="map_landmarks" if main else None)  # fmt: skip
        ax.plot(*tr.truth.T, color="black", lw=1.4, label="true path",
                gid="map_truth" if main else None)  # fmt: skip
        for name, est in tr.estimate.items():
            ax.plot(*est.T, lw=0.9, label=f"{name} estimate{_ends(est, tr.t)}",
                    gid=f"map_est/{name}" if main else None, **styles[name])  # fmt: skip
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    ax_map.scatter(*sc.waypoints.T, marker="o", s=30, facecolors="none", edgecolors="#7f7f7f",
                   label="waypoints", zorder=3, gid="map_waypoints")  # fmt: skip
    for name in tr.estimate:
        style = {"edgecolor": styles[name]["color"], "linestyle": styles[name]["linestyle"]}
        for j in tr.ellipse_index:
            est, cov = tr.estimate[name][j], tr.cov[name][j]
            if not _ellipse_ok(est, cov):
                continue  # this filter had diverged by then
            ax_map.add_patch(ellipse(est, cov, lw=1.0, gid=f"map_ellipse/{name}/{j}", **style))
            if j == k:
                ax_zoom.add_patch(ellipse(est, cov, lw=1.4, **style))
                ax_zoom.plot(*est, marker="o", ms=4, color=style["edgecolor"])
    ax_zoom.plot(*centre, marker="x", ms=8, mew=2, ls="none", color="black", label="true pose")
    ax_map.set_aspect("equal", adjustable="datalim")
    ax_zoom.set_aspect("equal", adjustable="box")
    ax_zoom.set_xlim(centre[0] - half, centre[0] + half)
    ax_zoom.set_ylim(centre[1] - half, centre[1] + half)
    ax_map.add_patch(Rectangle(tuple(centre - half), 2 * half, 2 * half, fill=False,
                               edgecolor="black", lw=0.8, linestyle=":"))  # fmt: skip
    ax_map.legend(loc="best", ncols=2)
    ax_zoom.legend(handles=ax_zoom.get_lines()[-1:], loc="upper left")
    ax_map.set_title(f"run {tr.run}: {ELLIPSE_SIGMA:g}-sigma position ellipses every "
                     f"{_spacing(tr):.0f} s (true size; dotted box: zoom)", fontsize=9)  # fmt: skip
    ax_zoom.set_title(f"zoom at t = {tr.t[k]:.1f} s: estimates (dots) and their "
                      f"{ELLIPSE_SIGMA:g}-sigma ellipses", fontsize=9)  # fmt: skip
    fig.suptitle(f"{sc.name}: map and run {tr.run} of {sc.runs}")
    return fig


def _spacing(tr) -> float:
    idx = tr.ellipse_index
    return float(np.median(np.diff(tr.t[idx]))) if len(idx) > 1 else float(tr.t[idx[0]])


@matplotlib.rc_context(_RC)
def overview_figure(rows: Sequence[SummaryRow]) -> Figure:
    """Position RMSE and the share of steps with NEES in bounds, per filter and scenario."""
    scenarios = list(dict.fromkeys(r.scenario for r in rows))
    # In every group: the plain EKF first, then the adaptive filters, the oracle (reference) last.
    rank = {"ekf": 0, "anfekf": 1, "ekf-oracle": 3}
    ordered = sorted(rows, key=lambda r: rank.get(r.kind, 2))
    groups = {s: [r for r in ordered if r.scenario == s] for s in scenarios}
    width = 0.8 / max(len(g) for g in groups.values())
    fig = Figure(figsize=(max(8.0, 2.6 * len(scenarios) + 3), 4.6), layout="constrained")
    ax_rmse, ax_cons = fig.subplots(1, 2)
    panels = ((ax_rmse, "rmse_pos", 1.0, "%.2f"), (ax_cons, "nees_in_bounds", 100.0, "%.0f"))
    labelled: set[tuple[str, str]] = set()
    for j, (scen, group) in enumerate(groups.items()):
        for i, row in enumerate(group):
            centre = j + (i - (len(group) - 1) / 2) * width
            for ax, key, scale, fmt in panels:
                value = getattr(row, key) * scale
                bars = ax.bar(
                    centre,
                    value if math.isfinite(value) else 0.0,  # all runs diverged: an empty slot
                    width,
                    color=filter_colour(row.filter),
                    label=None if (key, row.filter) in labelled else row.filter,
                    gid=f"overview_{key}/{scen}/{row.filter}",
                )
                labelled.add((key, row.filter))
                ax.bar_label(bars, fmt=fmt, fontsize=6, padding=1)
    for ax in (ax_rmse, ax_cons):
        ax.set_xticks(np.arange(len(scenarios)), scenarios)
        ax.grid(axis="x", visible=False)
    ax_rmse.set_ylabel("position RMSE [m] (time mean of RMSE curve)")
    ax_rmse.set_title("accuracy: lower is better")
    ax_cons.set_ylabel("steps with run-averaged NEES in 95 % bounds [%]")
    ax_cons.set_ylim(0, 105)
    ax_cons.set_title("consistency: higher is better")
    handles, labels = ax_rmse.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=len(labels))
    runs = "/".join(str(n) for n in sorted({r.runs for r in rows}))
    fig.suptitle(f"Overview: {len(scenarios)} scenarios, {runs} runs each")
    return fig


def _percentiles() -> tuple[float, float]:
    from .report import BAND_PERCENTILES

    return BAND_PERCENTILES
