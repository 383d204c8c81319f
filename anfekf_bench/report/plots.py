"""The report's matplotlib figures, drawn only from the series report.py computes.

Every function returns a `matplotlib.figure.Figure` (no pyplot state), so tests can read back the
plotted data: each data artist carries a gid such as "rmse_pos/anfekf" or "nees_bound_hi/50".
One colour per filter in every figure (`filter_colour`).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Iterable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import matplotlib

matplotlib.use("Agg")  # files only; never open a window

import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Ellipse, Rectangle  # noqa: E402
from matplotlib.ticker import (  # noqa: E402
    FuncFormatter,
    LogLocator,
    NullFormatter,  # noqa: E402
    NullLocator,
)

from ..analysis.metrics import format_share, format_sig  # noqa: E402
from ..filters.registry import role_of  # noqa: E402
from ..storage import write_atomic  # noqa: E402
from .data import (  # noqa: E402
    _ADAPTED,
    BAND_PERCENTILES,
    NOISE_COLUMNS,
    OUTLIER_FACTOR,
    Band,
    FilterSeries,
    RunSeries,
    ScenarioData,
)
from .document import Block, FigureBlock  # noqa: E402
from .ranking import (  # noqa: E402
    CONSISTENT_SHARE,  # noqa: F401  (the tables read it here)
)
from .render import (  # noqa: E402, F401  (the figures' modules read these here)
    DPI,
    RATIO_MAX,
    RATIO_MIN,
    RATIO_TICK_PRIORITY,
    RC,
    PlainLogLocator,
    RatioBarLocator,
    Rendering,
    RenderPool,
    figure_bytes,
    figure_files,
    plain_number,
    plain_power_of_ten,
    ratio_bar_ticks,
    ratio_norm,
)

ELLIPSE_SIGMA = 3.0
# Filters get colours by their order within a report (`palette`), not from their names: names
# hashed onto colours collide, and a zoo of 30 filters needs every pairing told apart. A
# qualitative palette (matplotlib's tab10 without its grey) cycles through the colours first,
# then again with the next line style: 9 colours x 4 styles = 36 distinct (colour, style) pairs.
PALETTE = (
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#bcbd22",
    "#17becf",
)  # fmt: skip
LINE_STYLES = ("-", (0, (5, 1.5)), (0, (3, 1, 1, 1)), (0, (1, 1)))
ORACLE_COLOUR = "#4d4d4d"  # dark grey, dashed: the reference, in every figure
_ORDER: dict[str, int] = {}  # filter name -> its place in the report being drawn
_ORACLES: frozenset[str] = frozenset()  # the names of its filters whose kind is the oracle


@contextmanager
def palette(names: Sequence[str], oracles: Sequence[str] = ()):
    """Within this block, filter `names` (in this order, duplicates ignored) take the palette's
    entries one after another; a name outside the list is appended as it is first drawn.
    `oracles`: the names among them of a kind whose role is the oracle (registry.role_of), drawn
    in the oracle's style also where a figure knows a filter by its name only."""
    global _ORDER, _ORACLES
    saved = _ORDER, _ORACLES
    _ORDER = {n: i for i, n in enumerate(dict.fromkeys(names))}
    _ORACLES = frozenset(oracles)
    try:
        yield
    finally:
        _ORDER, _ORACLES = saved


def palette_state() -> tuple[list[str], list[str]]:
    """The filter names in their palette order now, and the oracles' names
    (`palette(*palette_state())` restores it, in a worker process that draws part of a
    report)."""
    return list(_ORDER), sorted(_ORACLES)


def _place(name: str) -> int:
    return _ORDER.setdefault(name, len(_ORDER))


MARKERS = ("o", "s", "^", "D")
HATCHES = ("", "////", "....", "xxxx")  # bars: in step with the line style


@dataclass(frozen=True)
class FilterStyle:
    """How one filter is drawn in every figure of a report: a colour, and beside it a line style,
    a point marker and a bar hatch of the same round of the palette, so no two filters look
    alike in any kind of figure (lines, points or bars) for up to 36 filters."""

    colour: str
    linestyle: object
    marker: str
    hatch: str

    def line(self) -> dict:
        """matplotlib keywords of a line in this style."""
        return {"color": self.colour, "linestyle": self.linestyle}


ORACLE_STYLE = FilterStyle(ORACLE_COLOUR, "--", "o", "")


def filter_style(name: str, kind: str | None = None) -> FilterStyle:
    """THE style map of a report: filter `name`'s colour, line style, marker and hatch, from its
    place in the report (see `palette`); the oracle (by its `kind`'s role, or its name among the
    palette's oracles) grey and dashed, the reference, in every figure. Every figure draws
    filters through this function only."""
    if role_of(kind) == "oracle" or name in _ORACLES:
        return ORACLE_STYLE
    place = _place(name)
    turn = (place // len(PALETTE)) % len(LINE_STYLES)
    return FilterStyle(PALETTE[place % len(PALETTE)], LINE_STYLES[turn], MARKERS[turn],
                       HATCHES[turn])  # fmt: skip


def filter_colour(name: str) -> str:
    """The colour of filter `name`, the same in every figure of a report (`filter_style`)."""
    return filter_style(name).colour


def filter_linestyle(name: str):
    """The line style beside the colour (`filter_style`): the palette's second round is dashed."""
    return filter_style(name).linestyle


def filter_marker(name: str) -> str:
    """The point marker beside the colour (overview, leaderboard), in step with the line style."""
    return filter_style(name).marker


# Value labels beside points and bars only while a scenario's group is this small; beyond, the
# labels would overlap (the numbers are in the tables and the leaderboard).
MAX_LABELLED_GROUP = 5


def _style(f: FilterSeries) -> dict:
    # The oracle is a reference, not a contender: grey and dashed, in every figure.
    return filter_style(f.name, f.kind).line()


def save_figure(fig: Figure, path: Path | BinaryIO, fmt: str = "png", dpi: int = DPI) -> None:
    """Write `fig` in format png, svg or pdf (no timestamps: reproducible files,
    `render.figure_bytes`): to a path atomically, or into an open binary file."""
    data = figure_bytes(fig, fmt, dpi)
    if isinstance(path, (str, Path)):
        write_atomic(Path(path), lambda tmp: tmp.write_bytes(data))
    else:
        path.write(data)


@dataclass
class FigureSaver:
    """The one place a report's figures are written: each section builder hands it a figure,
    its file name and its caption; it saves the file into `out_dir` (remembered in `files`) and
    returns the document's block, with the image report.html embeds (a PDF gets a PNG copy: a
    browser does not show a PDF in <img>).

    With a `pool` (render.RenderPool) a figure is drawn in a worker process while the report
    builds the next one: its block comes back without its image, and `finish` waits for the
    drawings, writes their files and puts the images into the document's blocks. The files are
    the same bytes either way."""

    out_dir: Path
    fmt: str = "png"
    dpi: int = DPI
    html: bool = True
    files: list[Path] = field(default_factory=list)
    pool: RenderPool | None = None
    _drawing: dict[str, Rendering] = field(default_factory=dict, repr=False)

    def __call__(self, fig: Figure, name: str, caption: str) -> FigureBlock:
        path = Path(self.out_dir) / name
        self.files.append(path)
        png_copy = self.html and self.fmt == "pdf"
        drawing = None if self.pool is None else self.pool.submit(fig, self.fmt, self.dpi, png_copy)
        if drawing is not None:
            self._drawing[name] = drawing
            return self._block(name, caption, b"", b"")
        data, png = figure_files(fig, self.fmt, self.dpi, png_copy)
        write_atomic(path, lambda tmp: tmp.write_bytes(data))
        return self._block(name, caption, data, png)

    def finish(self, blocks: Sequence[Block]) -> list[Block]:
        """`blocks` with the images of the figures the pool drew, once their files are written
        (every block as it is without a pool)."""
        # While the workers draw from the first, this process draws from the last, one at a
        # time, each only if no worker has started it: it would otherwise wait idle.
        drawn: dict[str, tuple[bytes, bytes]] = {}
        for name, drawing in reversed(self._drawing.items()):
            if not drawing.take_back():
                break
            drawn[name] = drawing.result()
        for name, drawing in self._drawing.items():
            if name not in drawn:
                drawn[name] = drawing.result()
            data = drawn[name][0]
            write_atomic(Path(self.out_dir) / name, lambda tmp, data=data: tmp.write_bytes(data))
        self._drawing.clear()
        return [
            self._block(b.file, b.caption, *drawn[b.file])
            if isinstance(b, FigureBlock) and b.file in drawn else b
            for b in blocks
        ]  # fmt: skip

    def cancel(self) -> None:
        """Drop the drawings the pool has not started (the report failed or was interrupted:
        its process would otherwise wait for them on its way out)."""
        for drawing in self._drawing.values():
            drawing.take_back()
        self._drawing.clear()

    def _block(self, name: str, caption: str, data: bytes, png: bytes) -> FigureBlock:
        if not self.html:
            image, mime = b"", "image/png"
        elif self.fmt == "pdf":
            image, mime = png, "image/png"
        else:
            image = data
            mime = "image/svg+xml" if self.fmt == "svg" else "image/png"
        return FigureBlock(name, caption, image, mime, link_only=self.fmt == "pdf")


def legend_entries(axes: Iterable[Axes]) -> tuple[list, list[str]]:
    """The legend handles and labels of several axes, each label once (its first handle): one
    legend for a figure whose panels share filters."""
    handles, labels = [], []
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    return handles, labels


def plain_log_axis(ax: Axes, which: str = "y", minor: bool = True) -> None:
    """Log scale with plain tick labels (2, 3, 4, 6, 10) and unlabelled minor ticks (none
    without `minor`)."""
    axis = ax.yaxis if which == "y" else ax.xaxis
    (ax.set_yscale if which == "y" else ax.set_xscale)("log")
    axis.set_major_locator(PlainLogLocator())
    axis.set_major_formatter(FuncFormatter(plain_number))
    if minor:
        axis.set_minor_locator(LogLocator(base=10, subs=tuple(range(2, 10))))
    else:
        axis.set_minor_locator(NullLocator())
    axis.set_minor_formatter(NullFormatter())


def draw_band(ax: Axes, t: np.ndarray, band: Band, colour, gid: str) -> None:
    """The spread over runs of a series over time (its `RunSeries.band`), shaded."""
    ax.fill_between(t, band.lo, band.hi, color=colour, alpha=0.12, lw=0, gid=gid)


def draw_runs(ax: Axes, series: RunSeries, gid: str, label: str | None = None, **line) -> None:
    """Every run of a series over time, each on its own time axis, as one line broken between
    runs (recorded segments at their log times, drives from their cold starts)."""
    ax.plot(*series.joined(), gid=gid, label=label, **line)


def _band(
    ax: Axes, t: np.ndarray, band: Band, f: FilterSeries, key: str, label: str | None
) -> None:
    style = _style(f)
    draw_band(ax, t, band, style["color"], f"{key}_band/{f.name}")
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


def rmse_ratio_curve(f: FilterSeries, ref: FilterSeries) -> np.ndarray:
    """Position RMSE over runs of `f` divided by `ref`'s, at each step (NaN where undefined)."""
    with np.errstate(all="ignore"):
        ratio = f.pos.line / ref.pos.line
    return np.where(np.isfinite(ratio) & (ratio > 0), ratio, np.nan)


# The ratio panel zooms on the filters whose time-mean ratio lies within this factor of 1: the
# lines that coincide with the reference above. Farther filters leave the zoomed axis (their gap
# is plain in the panels above); the legend gives every ratio with its interval.
NEAR_FACTOR = 1.25


def _ratio_panel(ax: Axes, sc: ScenarioData, ref: FilterSeries, others: list) -> None:
    near = []
    for f in others:
        ratio = sc.ratio(f.name, ref)
        style = _style(f)
        curve = rmse_ratio_curve(f, ref)
        interval = (
            f" [{format_sig(ratio.lo)}, {format_sig(ratio.hi)}]" if ratio.has_interval else ""
        )
        is_near = 1 / NEAR_FACTOR <= ratio.estimate <= NEAR_FACTOR
        ax.plot(f.t, curve, lw=1.0, gid=f"rmse_ratio/{f.name}", alpha=1.0 if is_near else 0.35,
                label=f"{f.name}: {format_sig(ratio.estimate)}{interval}", **style)  # fmt: skip
        # The table's ratio (time-mean RMSE over time-mean RMSE) as a level line.
        ax.axhline(ratio.estimate, color=style["color"], lw=1.6, ls=(0, (6, 2)), alpha=0.8,
                   gid=f"rmse_ratio_mean/{f.name}")  # fmt: skip
        if is_near:
            near.append(curve)
    ax.axhline(1.0, color="black", lw=0.8)
    plain_log_axis(ax)
    zoomed = ""
    if near and len(near) < len(others):
        values = np.concatenate(near)
        values = values[np.isfinite(values)]
        if values.size:
            lo, hi = np.percentile(values, (0.5, 99.5))
            lo, hi = min(lo, 0.98), max(hi, 1.02)
            ax.set_ylim(lo / 1.03, hi * 1.03)
            zoomed = f"; axis zoomed on the filters within {NEAR_FACTOR:g} x of {ref.name}"
    ax.set_ylabel(f"position RMSE / {ref.name} (log)")
    # beside the panel: inside, it covered the lines it labels
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0, fontsize=7,
              title=f"RMSE / {ref.name},\ntime means [95 % interval]",
              title_fontsize=7)  # fmt: skip
    ax.set_title(
        f"ratio to {ref.name} at each step (dashed level: the ratio of the time means){zoomed}",
        fontsize=8,
    )


def _ratio_heatmap(fig: Figure, ax: Axes, sc: ScenarioData, ref: FilterSeries, others: list):
    """Many filters: each filter's position RMSE over the reference's at each step as one row
    of colour (the report's one ratio scale), rows sorted by the time-mean ratio: 26 lines in
    one log panel hid one another."""
    ratios = {f.name: sc.ratio(f.name, ref) for f in others}
    order = sorted(others, key=lambda f: (not math.isfinite(ratios[f.name].estimate),
                                          ratios[f.name].estimate))  # fmt: skip
    t = others[0].t
    grid = np.vstack([rmse_ratio_curve(f, ref) for f in order])
    image = ratio_image(ax, grid, gid="rmse_ratio_heatmap",
                        extent=(t[0], t[-1], len(order) - 0.5, -0.5))  # fmt: skip
    ax.set_yticks(np.arange(len(order)),
                  [f"{f.name} {format_sig(ratios[f.name].estimate)}" for f in order],
                  fontsize=6.5)  # fmt: skip
    ax.grid(False)
    ratio_colourbar(fig, image, ax, f"RMSE / {ref.name}'s (log)")
    ax.set_title(f"position RMSE / {ref.name}'s at each step, one row a filter (its time-mean"
                 " ratio beside its name), best first", fontsize=8)  # fmt: skip


@matplotlib.rc_context(RC)
def rmse_figure(sc: ScenarioData) -> Figure:
    """Position and heading RMSE over time per filter, with the spread over runs shaded, and
    (log scale) each filter's position RMSE divided by the reference's, where lines that
    coincide in the top panel come apart."""
    ref = sc.reference()
    others = [f for f in sc.filters if ref is not None and f.name != ref.name]
    rows = 3 if others else 2
    # Many filters: one legend in one column beside the panels (below them, it was cut at both
    # edges; in the ratio panel, it covered two thirds of the data), each entry with the ratio.
    many = len(sc.filters) > MANY_FILTERS
    width = 12.5 if many else 9
    height = (6 + 0.16 * len(others) if many else 8.4) if others else 6
    fig = Figure(figsize=(width, height), layout="constrained")
    ratio_share = 0.065 * len(others) if many else 1
    axes = fig.subplots(rows, 1, sharex=True, height_ratios=[1.2, 1, ratio_share][:rows])
    ax_pos, ax_head = axes[0], axes[1]
    lo, hi = _percentiles()
    for f in sc.filters:
        s = f.summary
        head = math.degrees(s["rmse_heading"]) if math.isfinite(s["rmse_heading"]) else math.nan
        label = f"{f.name}: {format_sig(s['rmse_pos'])} m, {format_sig(head)} deg{_lost(f)}"
        if many and ref is not None and f.name != ref.name:
            r = sc.ratio(f.name, ref)
            ci = f" [{format_sig(r.lo)}, {format_sig(r.hi)}]" if r.has_interval else ""
            label += f"; {format_sig(r.estimate)}{ci} x {ref.name}"
        _band(ax_pos, f.t, f.pos, f, "rmse_pos", label)
        _band(ax_head, f.t, f.heading, f, "rmse_heading", None)
    ax_pos.set_ylabel("position RMSE [m]")
    ax_head.set_ylabel("heading RMSE [deg]")
    for ax in (ax_pos, ax_head):
        ax.set_ylim(bottom=0)
    if others and many:
        _ratio_heatmap(fig, axes[2], sc, ref, others)
    elif others:
        _ratio_panel(axes[2], sc, ref, others)
    axes[-1].set_xlabel("time [s]")
    for ax in axes:
        ax.set_xlim(sc.filters[0].t[0], sc.filters[0].t[-1])
    # Below the axes: error spikes reach any corner, a legend inside would hide some.
    if many:
        title = "filter: time means of the position\nand heading RMSE; position RMSE /\n"
        title += f"{ref.name}'s [95 % interval]" if ref else ""
        fig.legend(*ax_pos.get_legend_handles_labels(), loc="outside right upper", ncols=1,
                   fontsize=7, title=title, title_fontsize=7)  # fmt: skip
    else:
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


def _outlier_label(f: FilterSeries, run: int) -> str:
    i = int(np.flatnonzero(f.run_ids == run)[0])
    return f"{f.name} run {run}: outlier, mean NEES {format_sig(float(f.run_mean_nees[i]))}"


# More filters than this in one panel and their lines hide one another: the NEES figure draws
# them as small multiples, families (kinds) packed into panels of at most PANEL_FILTERS, the
# reference in every panel, each panel's legend beside it (outside the data).
MANY_FILTERS = 8
PANEL_FILTERS = 4


def family_panels(filters: Sequence[FilterSeries], size: int = PANEL_FILTERS) -> list[list]:
    """`filters` in panels of at most `size`: whole families (kind) together where they fit,
    consecutive families sharing a panel, a family larger than `size` split."""
    kinds = dict.fromkeys(f.kind for f in filters)
    panels: list[list] = []
    for kind in kinds:
        family = [f for f in filters if f.kind == kind]
        while family:
            if panels and len(panels[-1]) + len(family) <= size:
                panels[-1] += family
                family = []
            else:
                panels.append(family[:size])
                family = family[size:]
    return panels


def _nees_label(f: FilterSeries) -> str:
    s = f.summary
    share = format_share(s["nees_in_bounds"])
    if f.runs_used and np.isnan(f.nees).all():  # no covariance (KalmanNet): no NEES
        return f"{f.name}: NEES not available (no covariance)"
    return f"{f.name}: ANEES {format_sig(s['anees'])}, {share} in bounds{_lost(f)}"


def _nees_limits(sc: ScenarioData) -> tuple[float, float] | None:
    # Limits from the averages, medians and bounds: a single run's NEES swings over decades and
    # would squeeze them (outlier runs may leave the axis).
    shown = [f.nees for f in sc.filters] + [f.nees_median for f in sc.filters]
    shown.append(np.array([b for f in sc.filters for b in f.bounds]))
    values = np.concatenate(shown)
    values = values[np.isfinite(values) & (values > 0)]
    return (values.min() / 1.5, values.max() * 1.5) if values.size else None


def _outlier_lines(ax: Axes, f: FilterSeries, colour, top: float | None) -> None:
    """`f`'s outlier runs as thin lines; one that leaves the axis (above `top`) gets a triangle
    at the top where it leaves, and its peak in its legend entry: never a text on the plot,
    which printed over the others' when several left the axis."""
    for run, values in f.outlier_nees.items():
        label = _outlier_label(f, run)
        above = np.flatnonzero(np.nan_to_num(values, nan=0.0) > top) if top else []
        if len(above):
            label += f", off scale (peak {format_sig(float(np.nanmax(values)))}, ▲)"
            ax.plot([f.t[above[0]]], [top], marker="^", ms=6, color=colour, ls="none",
                    clip_on=False, gid=f"nees_off_scale/{f.name}/{run}")  # fmt: skip
        ax.plot(f.t, values, lw=0.5, alpha=0.45, color=colour, label=label,
                gid=f"nees_outlier/{f.name}/{run}")  # fmt: skip


def _nees_panel(ax: Axes, sc: ScenarioData, filters: list, top: float | None) -> None:
    """One panel of the small multiples: `filters`' NEES, medians and outlier runs (an outlier
    that leaves the axis: a triangle at the top, its peak in its legend entry, never a text
    that could print over another), the bounds; the legend beside the panel."""
    for f in filters:
        colour = filter_colour(f.name) if role_of(f.kind) != "oracle" else ORACLE_COLOUR
        ax.plot(f.t, f.nees, lw=1.1, label=_nees_label(f), gid=f"nees/{f.name}", **_style(f))
        ax.plot(f.t, f.nees_median, lw=0.8, ls=":", color=colour, gid=f"nees_median/{f.name}")
        _outlier_lines(ax, f, colour, top)
    for n, (lo, hi) in sorted({(f.runs_used, f.bounds) for f in filters if f.runs_used}):
        ax.axhspan(lo, hi, color="#2ca02c", alpha=0.08, lw=0)
        ax.axhline(lo, color="black", lw=0.8, ls=(0, (1, 2)), gid=f"nees_bound_lo/{n}")
        ax.axhline(hi, color="black", lw=0.8, ls=(0, (1, 2)), gid=f"nees_bound_hi/{n}")
    plain_log_axis(ax)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0, fontsize=7)


def _nees_small_multiples(sc: ScenarioData) -> Figure:
    ref = sc.reference()
    panels = family_panels([f for f in sc.filters if f is not ref])
    cols = 2
    rows = math.ceil(len(panels) / cols)
    fig = Figure(figsize=(15, 2.5 * rows + 1.4), layout="constrained")
    axes = fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False).ravel()
    limits = _nees_limits(sc)
    for ax, group in zip(axes, panels, strict=False):
        _nees_panel(ax, sc, ([ref] if ref else []) + group, limits[1] if limits else None)
        if limits:
            ax.set_ylim(*limits)
        ax.set_xlim(sc.filters[0].t[0], sc.filters[0].t[-1])
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    for ax in axes[::cols]:
        ax.set_ylabel("NEES [-] (log)")
    for ax in axes[max(len(panels) - cols, 0) : len(panels)]:
        ax.set_xlabel("time [s]")
        ax.xaxis.set_tick_params(labelbottom=True)
    bounds = "; ".join(
        f"{n} runs: [{format_sig(lo)}, {format_sig(hi)}]"
        for n, (lo, hi) in sorted({(f.runs_used, f.bounds) for f in sc.filters if f.runs_used})
    )
    fig.suptitle(f"{sc.name}: NEES averaged over {_runs_text(sc)}, filters by family")
    reference = f"{ref.name} (grey, dashed) in every panel; " if ref else ""
    note = (
        f"{reference}solid: run-averaged NEES; dotted: median over runs; thin: outlier runs (mean"
        f" NEES > {OUTLIER_FACTOR:g} x the median run's); shaded: 95 % bounds ({bounds}); a"
        " consistent filter's NEES averages 3 (pose dim.)"
    )
    fig.supxlabel("\n".join(textwrap.wrap(note, 170)), fontsize=8)  # laid out below the panels
    return fig


@matplotlib.rc_context(RC)
def nees_figure(sc: ScenarioData) -> Figure:
    """Run-averaged NEES per filter (log scale) with the two-sided 95 % chi-square bounds, the
    median over runs (dotted) and the outlier runs (thin) that pull the average up. More than
    MANY_FILTERS filters: small multiples by family (`family_panels`)."""
    if len(sc.filters) > MANY_FILTERS:
        return _nees_small_multiples(sc)
    fig = Figure(figsize=(9, 5.6), layout="constrained")
    ax = fig.subplots()
    limits = _nees_limits(sc)
    for f in sc.filters:
        s = f.summary
        share = format_share(s["nees_in_bounds"])
        label = f"{f.name}: ANEES {format_sig(s['anees'])}, {share} in bounds{_lost(f)}"
        if f.runs_used and np.isnan(f.nees).all():  # no covariance (KalmanNet): no NEES
            label = f"{f.name}: NEES not available (no covariance)"
        ax.plot(f.t, f.nees, lw=1.2, label=label, gid=f"nees/{f.name}", **_style(f))
        ax.plot(f.t, f.nees_median, lw=0.9, ls=":", color=filter_colour(f.name),
                gid=f"nees_median/{f.name}")  # fmt: skip
        _outlier_lines(ax, f, filter_colour(f.name), limits[1] if limits else None)
    # Filters that lost runs to divergence average fewer runs: their bounds are wider.
    for n, (lo, hi) in sorted({(f.runs_used, f.bounds) for f in sc.filters if f.runs_used}):
        label = f"95 % bounds, {n} runs: [{format_sig(lo)}, {format_sig(hi)}]"
        ax.axhspan(lo, hi, color="#2ca02c", alpha=0.08, lw=0)
        ax.axhline(lo, color="black", lw=0.9, ls=(0, (1, 2)), label=label, gid=f"nees_bound_lo/{n}")
        ax.axhline(hi, color="black", lw=0.9, ls=(0, (1, 2)), gid=f"nees_bound_hi/{n}")
    ax.axhline(3.0, color="#2ca02c", lw=0.8, alpha=0.6, label="expected value 3 (pose dim.)")
    ax.plot([], [], color="grey", ls=":", lw=0.9,
            label="dotted: median over runs (a consistent filter's: 2.37)")  # fmt: skip
    plain_log_axis(ax)
    if limits:
        ax.set_ylim(*limits)
    ax.set_xlim(sc.filters[0].t[0], sc.filters[0].t[-1])
    ax.set_xlabel("time [s]")
    ax.set_ylabel("NEES [-] (log)")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncols=2)
    outliers = sum(len(f.outliers) for f in sc.filters)
    note = (
        f"; thin: outlier runs (mean NEES > {OUTLIER_FACTOR:g} x the median run's)"
        if outliers
        else "; no outlier runs"
    )
    fig.suptitle(f"{sc.name}: NEES averaged over {_runs_text(sc)}")
    ax.set_title(f"solid: run-averaged NEES; dotted: median over runs{note}", fontsize=8)
    return fig


# Up to this many adaptive filters share one row of noise panels; more are drawn as small
# multiples, one row per family (kind), so ten filters' bands do not hide one another.
NOISE_FILTERS_PER_ROW = 4


def noise_groups(sc: ScenarioData) -> list[list[FilterSeries]]:
    """The adaptive filters of `sc` in the rows of the noise figure: one row when they are few,
    else one row per family (kind), in order of appearance."""
    adaptive = [f for f in sc.filters if _adapted(f.adapts)]
    if len(adaptive) <= NOISE_FILTERS_PER_ROW:
        return [adaptive] if adaptive else []
    kinds = dict.fromkeys(f.kind for f in adaptive)
    return [[f for f in adaptive if f.kind == k] for k in kinds]


@matplotlib.rc_context(RC)
def noise_figure(sc: ScenarioData) -> Figure:
    """The adapted R/Q diagonal over time of every filter that adapts it (the registry says
    which, or its recorded values vary): the median over runs with the spread over runs and
    the mean, against the true and the assumed value."""

    columns = sc.adapted_columns
    groups = noise_groups(sc)
    ncols = len(columns) if len(groups) > 1 else min(len(columns), 2)
    per_group = math.ceil(len(columns) / ncols)
    nrows = per_group * len(groups)
    height = (3.4 if len(groups) == 1 else 2.5) * nrows + 1.4
    fig = Figure(figsize=(max(9.0, 3.2 * ncols), height), layout="constrained")
    # Not sharex: every panel spans the same times anyway, and matplotlib's shared axes cost
    # O(panels^2) in their limit checks (a quarter of a 48-panel figure's drawing)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes[:-1].ravel():
        ax.tick_params(labelbottom=False)
    lo, hi = _percentiles()
    ekf = next((f for f in sc.filters if role_of(f.kind) == "reference"), None)
    for g, group in enumerate(groups):
        for j, col in enumerate(columns):
            ax = axes[g * per_group + j // ncols, j % ncols]
            what, unit, _ = NOISE_COLUMNS[col]
            if not any(col in _adapted(f.adapts) for f in group):
                ax.set_visible(False)  # a family's row shows only what it adapts
                continue
            for f in group:
                if col not in _adapted(f.adapts):
                    continue
                style = _style(f)
                band = f.noise[col]
                draw_band(ax, f.t, band, style["color"], f"noise/{col}_band/{f.name}")
                ax.plot(f.t, band.median, lw=1.4, label=f.name,
                        gid=f"noise_median/{col}/{f.name}", **style)  # fmt: skip
                ax.plot(f.t, band.line, lw=0.7, alpha=0.8, color=style["color"], ls=":",
                        gid=f"noise/{col}/{f.name}")  # fmt: skip
                for run, values in f.outlier_noise.get(col, {}).items():
                    ax.plot(f.t, values, lw=0.5, alpha=0.45, color=style["color"],
                            label=f"{f.name} run {run} (outlier)",
                            gid=f"noise_outlier/{col}/{f.name}/{run}")  # fmt: skip
            if ekf is not None:
                assumed = float(ekf.noise[col].line[0])
                ax.plot(ekf.t, ekf.noise[col].line, lw=1.0, ls=(0, (1, 2)), color="#7f7f7f",
                        label=f"assumed ({ekf.name}, fixed)",
                        gid=f"noise_fixed/{col}/{ekf.name}")  # fmt: skip
                if not math.isclose(assumed, sc.true_noise[col], rel_tol=0.05):  # else one label
                    ax.annotate(format_sig(assumed), (1, assumed),
                                xycoords=("axes fraction", "data"), xytext=(-2, 2),
                                textcoords="offset points", ha="right", va="bottom",
                                fontsize=6.5, color="#7f7f7f")  # fmt: skip
            true = sc.true_noise[col]
            ax.axhline(true, color="black", lw=1.0, ls="--", label="true value",
                       gid=f"noise_true/{col}")  # fmt: skip
            ax.annotate(format_sig(true), (0, true), xycoords=("axes fraction", "data"),
                        xytext=(2, 2), textcoords="offset points", ha="left", va="bottom",
                        fontsize=6.5)  # fmt: skip
            # Small multiples (one row per family) go without minor ticks: the plain labels
            # already mark 1-2-5 steps, and the ticks of 40 panels cost half of the figure's time.
            plain_log_axis(ax, minor=len(groups) == 1)
            family = f" ({group[0].kind})" if len(groups) > 1 else ""
            # y given: no panel has labels above it, and the automatic title position checks
            # every panel's ticks for them (an eighth of the figure's drawing)
            ax.set_title(f"{what} {col}{family}", fontsize=8, y=1.0)
            ax.set_ylabel(f"{col} [{unit}]", fontsize=8)
    for ax in axes.ravel()[len(groups) * per_group * ncols :]:
        ax.set_visible(False)
    # One time axis for all, as sharex gave: the union of the panels' own (a panel with no finite
    # value, its runs all diverged, would span 0..1 on its own)
    spans = [ax.get_xlim() for ax in axes.ravel()
             if ax.get_visible() and np.isfinite(ax.dataLim.intervalx).all()]  # fmt: skip
    if spans:
        start, end = min(a for a, _ in spans), max(b for _, b in spans)
        for ax in axes.ravel():
            ax.set_xlim(start, end)
    for g in range(len(groups)):  # unused cells of a group's last row
        for j in range(len(columns), per_group * ncols):
            axes[g * per_group + j // ncols, j % ncols].set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    handles, labels = legend_entries(axes.ravel())
    # Outside the data: with ten filters a legend inside would cover the lines.
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 5),
               fontsize=7)  # fmt: skip
    fig.suptitle(
        f"{sc.name}: adapted noise covariance over {_runs_text(sc)} (log scale)\nsolid: median"
        f" over runs, band: {lo:g}-{hi:g} % of runs, dotted: mean, thin: outlier runs;"
        " ekf-oracle uses the true value",
        fontsize=9,
    )
    return fig


def _adapted(adapts: frozenset[str]) -> tuple[str, ...]:
    """The noise columns a filter that adapts `adapts` ("R", "Q", "P") changes."""

    return tuple(c for a in sorted(adapts) for c in _ADAPTED.get(a, ()))


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


def draw_paths(
    ax: Axes,
    landmarks: np.ndarray,
    truth: np.ndarray,
    estimates: dict[str, np.ndarray],
    *,
    labels: dict[str, str] | None = None,
    kinds: dict[str, str] | None = None,
    gid=lambda what: what,
    truth_label: str = "true path",
    truth_alpha: float = 1.0,
    lw: float = 0.9,
    marker_size: float = 60,
    landmark_ids: Sequence | None = None,
) -> None:
    """THE map of every source's figures (simulated runs, recorded segments, each drive): the
    landmarks (stars; `landmark_ids` beside them), the true path (black; NaN rows break it, as
    between segments) and each filter's estimate in its report style, on `ax` in metres.
    `gid(what)` names the artists ('landmarks', 'truth', 'est/<filter>'; None: unnamed)."""
    labels = labels or {}
    kinds = kinds or {}
    ax.scatter(*np.asarray(landmarks, dtype=float).reshape(-1, 2).T, marker="*", s=marker_size,
               color="#b8860b", label="landmarks", zorder=3, gid=gid("landmarks"))  # fmt: skip
    if landmark_ids is not None:
        for i, (x, y) in zip(landmark_ids, landmarks, strict=True):
            ax.annotate(str(i), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    if len(truth):
        ax.plot(*np.asarray(truth).T, color="black", lw=1.4, alpha=truth_alpha,
                label=truth_label, gid=gid("truth"))  # fmt: skip
    for name, est in estimates.items():
        ax.plot(*np.asarray(est).T, lw=lw, label=labels.get(name, name), gid=gid(f"est/{name}"),
                **filter_style(name, kinds.get(name)).line())  # fmt: skip
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


@matplotlib.rc_context(RC)
def map_figure(sc: ScenarioData) -> Figure:
    """Landmarks, waypoints, the true path, one run's estimates and 3-sigma ellipses, a zoom."""
    fig = Figure(figsize=(12, 5.6), layout="constrained")
    ax_map, ax_zoom = fig.subplots(1, 2, width_ratios=[1.6, 1])
    tr = sc.track
    styles = {f.name: _style(f) for f in sc.filters}
    k = _zoom_index(sc)
    half = _zoom_half_width(sc, k)
    centre = tr.truth[k]
    labels = {name: f"{name} estimate{_ends(est, tr.t)}" for name, est in tr.estimate.items()}
    kinds = {f.name: f.kind for f in sc.filters}
    for ax in (ax_map, ax_zoom):
        main = ax is ax_map  # gids on the full map only: tests read the data back from there
        draw_paths(ax, sc.landmarks, tr.truth, tr.estimate, labels=labels, kinds=kinds,
                   gid=(lambda what: f"map_{what}") if main else (lambda what: None))  # fmt: skip
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
    # Below the panels: inside, a legend covers part of the map (and a landmark).
    handles, labels = ax_map.get_legend_handles_labels()
    zoom_handles, zoom_labels = ax_zoom.get_legend_handles_labels()
    fig.legend([*handles, zoom_handles[-1]], [*labels, zoom_labels[-1]],
               loc="outside lower center", ncols=min(len(labels) + 1, 4))  # fmt: skip
    ax_map.set_title(f"run {tr.run}: {ELLIPSE_SIGMA:g}-sigma position ellipses every "
                     f"{_spacing(tr):.0f} s (true size; dotted box: zoom)", fontsize=9)  # fmt: skip
    ax_zoom.set_title(f"zoom at t = {tr.t[k]:.1f} s: estimates (dots) and their "
                      f"{ELLIPSE_SIGMA:g}-sigma ellipses", fontsize=9)  # fmt: skip
    fig.suptitle(f"{sc.name}: map and run {tr.run} of {sc.runs}")
    return fig


def _spacing(tr) -> float:
    idx = tr.ellipse_index
    return float(np.median(np.diff(tr.t[idx]))) if len(idx) > 1 else float(tr.t[idx[0]])


def _percentiles() -> tuple[float, float]:

    return BAND_PERCENTILES


# ---------------------------------------------------------------------------------------------
# The ratio scale's colours (its norm, its ends and the bar's ticks are in render: figures hold
# them by reference)
RATIO_CMAP = "RdBu_r"


NO_RATIO_COLOUR = (0.85, 0.85, 0.85, 1.0)  # light grey: no value (all runs diverged, no oracle)


def ratio_cmap():
    """The colour map of the ratio scale, light grey where there is no value."""
    from matplotlib import colormaps

    return colormaps[RATIO_CMAP].with_extremes(bad=NO_RATIO_COLOUR)


def ratio_colour(ratio: float) -> tuple[float, float, float, float]:
    """The RGBA colour of `ratio` on the ratio scale (NaN: light grey)."""
    if not (math.isfinite(ratio) and ratio > 0):
        return NO_RATIO_COLOUR
    value = min(max(math.log10(ratio), math.log10(RATIO_MIN)), math.log10(RATIO_MAX))
    return tuple(float(c) for c in ratio_cmap()(ratio_norm()(value)))


def ratio_image(ax: Axes, values: np.ndarray, **kw):
    """THE ratio heatmap of every report (the leaderboard, the RMSE figure's many filters, the
    sweeps, the drives): `values` (ratios; NaN or <= 0: no value, light grey) coloured by their
    log10 on the ratio scale, clipped to its ends; `kw` to imshow (gid, extent, origin, ...)."""
    with np.errstate(all="ignore"):
        logs = np.log10(np.where(np.asarray(values, dtype=float) > 0, values, np.nan))
    shown = np.ma.masked_invalid(np.clip(logs, math.log10(RATIO_MIN), math.log10(RATIO_MAX)))
    kw = {"aspect": "auto", "interpolation": "nearest", **kw}
    return ax.imshow(shown, cmap=ratio_cmap(), norm=ratio_norm(), **kw)


def ratio_colourbar(fig: Figure, mappable, ax, label: str) -> None:
    """A colour bar for a log10-ratio image, ticked in plain numbers at as many of
    RATIO_TICK_PRIORITY as its height fits (RatioBarLocator)."""
    bar = fig.colorbar(mappable, ax=ax, shrink=0.9, pad=0.02)
    from matplotlib.font_manager import FontProperties

    points = FontProperties(size=matplotlib.rcParams["ytick.labelsize"]).get_size_in_points()
    bar.ax.yaxis.set_major_locator(RatioBarLocator(points))
    bar.ax.yaxis.set_major_formatter(FuncFormatter(plain_power_of_ten))
    bar.ax.yaxis.set_minor_locator(NullLocator())
    bar.set_label(label)
