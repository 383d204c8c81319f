"""Report figures and tables of real-data results (SPEC 9), from saved results only.

A real-data result folder (manifest `kind: recorded`, written by real_experiment) holds its
held-out segments (or, protocol drives, its whole drives) as runs. Its section of the one report
(`section`: document blocks; report.py writes them into report.md and report.html with the
simulated scenarios' sections, through the same figure writer) shows:

- `<name>_track`: the map, the Vicon path at the scored evaluation times and the estimates of
  ekf-tuned, of the naive EKF (x1) and of the adaptive instance with the lowest position RMSE;
- `<name>_errors`: position and heading error over the held-out part's time (segments placed at
  their log times, each starting from ground truth) for the same filters;
- `<name>_noise`: the adapted R (range, bearing) and Qu (speed, turn rate) standard deviations
  over time, of every adaptive filter started from the naive guess (x1), against the tuned ones;
- `<name>_ratios`: every instance's held-out position RMSE over ekf-tuned's, with the paired 95 %
  bootstrap interval (log scale), grouped by filter, one marker per naive start;
- a table: per instance its RMSE (the Monte Carlo statistic and pooled), the ratio with its
  interval, heading RMSE, NEES in bounds, gate rejections and the segments that lost lock.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..analysis.metrics import format_number, format_share
from ..config import FILTER_NAME_PATTERN
from ..filters.registry import role_of
from ..storage import (
    AUDIT_FILES,
    COMPARISONS_FILE,
    COORDINATE_LIMIT,
    MANIFEST_FILE,
    SUMMARY_JSON,
    ResultsError,
    check_manifest_text,
    check_one_batch,
    read_json,
    read_parquet,
    read_steps,
    scenario_name_problem,
)
from .audit import audit_blocks, nees_per_drive_blocks
from .data import NOISE_COLUMNS, RunSeries, adapts_of
from .document import Block, Cell, Heading, ListBlock, Paragraph, TableBlock
from .plots import (
    FigureSaver,
    draw_paths,
    draw_runs,
    filter_colour,
    filter_linestyle,
    filter_style,
    legend_entries,
    plain_log_axis,
    ratio_colourbar,
    ratio_image,
)
from .results import LoadedResult, load_result

LOST_LOCK_M = 1.0
# The track and error figures show three filters: the reference, the naive EKF, the best adaptive
# (each in its style of the whole report: plots.filter_style).


@dataclass(frozen=True)
class RealData:
    """One real-data result, as the figures use it."""

    name: str
    description: str
    folder: Path
    manifest: dict
    steps: pd.DataFrame
    summary: list[dict]
    comparisons: pd.DataFrame
    tables: tuple[str, ...] = ()  # the tables the folder holds (results.LoadedResult.tables)

    @property
    def slug(self) -> str:
        return self.name

    def has(self, table: str) -> bool:
        return table in self.tables

    @property
    def reference(self) -> str | None:
        """The filter every ratio is taken against (ekf-tuned): the one comparisons.parquet
        compares with, else the first fitted filter (the registry's role)."""
        vs = self.comparisons["vs"] if "vs" in self.comparisons else ()
        if len(vs):
            return str(vs.iloc[0])
        return next((f["name"] for f in self.manifest["filters"]
                     if role_of(f["kind"]) == "fitted"), None)  # fmt: skip

    def instances(self) -> list[dict]:
        return list(self.manifest["filters"])

    def record(self, name: str) -> dict:
        return next(r for r in self.summary if r["filter"] == name)


def _finite(value, limit: float = math.inf) -> bool:
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and abs(value) <= limit
    )


def _check_real_manifest(path: Path, manifest: dict) -> None:
    """ResultsError unless the parts of a real-data manifest the report draws are as `anfekf
    run` writes them (a hand-edited one is refused in one line, before any figure)."""
    check_manifest_text(path, manifest)
    filters = manifest["filters"]
    if not isinstance(filters, list) or not filters:
        raise ResultsError(f"{path}: filters: expected a non-empty list of filter instances")
    for i, f in enumerate(filters):
        ok = (
            isinstance(f, dict)
            and isinstance(f.get("name"), str)
            and FILTER_NAME_PATTERN.fullmatch(f["name"])
            and isinstance(f.get("kind"), str)
            and (f.get("start") is None or _finite(f.get("start")))
        )
        if not ok:
            raise ResultsError(f"{path}: filters.{i}: expected a plain name, a kind and a start")
    data = manifest["data"]
    if not isinstance(data, dict):
        raise ResultsError(f"{path}: data: expected an object")
    if manifest.get("protocol") == "drives":
        _check_drives(path, data)
        return
    segments = data.get("segments")
    if not isinstance(segments, list) or not all(
        isinstance(s, dict) and _finite(s.get("t0")) and type(s.get("index")) is int
        for s in segments
    ):
        raise ResultsError(f"{path}: data.segments: expected segments with an index and a t0")
    if not _landmarks_ok(data.get("landmarks"), ("id", "x", "y")):
        raise ResultsError(
            f"{path}: data.landmarks: expected id, x and y lists of one length, finite numbers"
            f" within {COORDINATE_LIMIT:g} m"
        )
    for key in ("held_out",):
        span = data.get(key)
        if not (isinstance(span, list) and len(span) == 2 and all(_finite(v) for v in span)):
            raise ResultsError(f"{path}: data.{key}: expected [start, end] in seconds")
    for key in ("misfits", "gaps"):
        spans = data.get(key)
        if not isinstance(spans, list) or not all(
            isinstance(v, list) and len(v) == 2 and all(_finite(t) for t in v) for v in spans
        ):
            raise ResultsError(f"{path}: data.{key}: expected a list of [start, end] in seconds")


def _landmarks_ok(landmarks, keys: tuple[str, ...]) -> bool:
    """Whether a map's `keys` columns are lists of one length of finite numbers within
    COORDINATE_LIMIT."""
    columns = [landmarks.get(k) for k in keys] if isinstance(landmarks, dict) else []
    return (
        len(columns) == len(keys)
        and all(isinstance(c, list) for c in columns)
        and len({len(c) for c in columns}) == 1
        and all(_finite(v, COORDINATE_LIMIT) for c in columns for v in c)
    )


def _check_drives(path: Path, data: dict) -> None:
    """The drives of a cross-drive result as the report draws them: each a plain id and its
    dataset's landmarks (finite x and y lists of one length)."""
    drives = data.get("drives")
    if not isinstance(drives, list) or not drives:
        raise ResultsError(f"{path}: data.drives: expected a non-empty list of drives")
    for i, d in enumerate(drives):
        if (
            not isinstance(d.get("drive") if isinstance(d, dict) else None, str)
            or scenario_name_problem(d["drive"])
            or not _landmarks_ok(d.get("landmarks"), ("x", "y"))
        ):
            raise ResultsError(
                f"{path}: data.drives.{i}: expected a plain drive id and landmarks x, y (finite"
                f" numbers within {COORDINATE_LIMIT:g} m, lists of one length)"
            )


def load_real(result: Path | LoadedResult) -> RealData:
    """A recorded result (a folder, or as the one loader read it) with its manifest checked."""
    loaded = result if isinstance(result, LoadedResult) else load_result(Path(result))
    folder, manifest = loaded.folder, loaded.manifest
    for key in ("filters", "data", "scenario"):
        if key not in manifest:
            raise ResultsError(f"{folder}: manifest.json has no {key!r}: not a real-data result")
    if not isinstance(manifest["scenario"], dict):
        raise ResultsError(f"{folder / MANIFEST_FILE}: scenario: expected an object")
    name = manifest["scenario"].get("name", folder.name)
    problem = scenario_name_problem(name) if isinstance(name, str) else "expected a name"
    if problem:  # the figures are named after it: never a path out of the report folder
        raise ResultsError(f"{folder / MANIFEST_FILE}: scenario.name: {problem}")
    check_one_batch(folder, manifest)
    _check_real_manifest(folder / MANIFEST_FILE, manifest)
    summary = read_json(folder / SUMMARY_JSON)
    if not isinstance(summary, list):
        raise ResultsError(f"{folder / SUMMARY_JSON}: expected a list of records")
    return RealData(
        name=str(manifest["scenario"].get("name", folder.name)),
        description=str(manifest["scenario"].get("description", "")),
        folder=folder,
        manifest=manifest,
        steps=read_steps(folder),
        summary=summary,
        comparisons=read_parquet(folder / COMPARISONS_FILE),
        tables=loaded.tables,
    )


# --------------------------------------------------------------------------------------------
# Series


def _value(x) -> float:
    return math.nan if x is None else float(x)


def shown_filters(rd: RealData) -> list[str]:
    """ekf-tuned, the naive EKF from x1 (else its first start), and the best adaptive instance."""
    out = []
    if rd.reference:
        out.append(rd.reference)
    plain = [f for f in rd.instances() if role_of(f["kind"]) == "reference"]
    if plain:
        x1 = [f for f in plain if f["start"] == 1.0]
        out.append((x1 or plain)[0]["name"])
    adaptive = [f["name"] for f in rd.instances() if adapts(rd, f)]
    if adaptive:
        best = min(adaptive, key=lambda n: _nan_last(_value(rd.record(n)["rmse_pos"])))
        out.append(best)
    return out


def adapts(rd: RealData, instance: dict) -> frozenset[str]:
    """What a filter instance adapts (data.adapts_of, as for a simulated filter): as the
    registry says for the scenario's entry it was made from, else the noise whose recorded R/Qu
    vary."""
    specs = {s.get("name"): s for s in rd.manifest["scenario"].get("filters", [])}
    spec = specs.get(instance["base"], {"kind": instance["kind"]})
    one = rd.steps[rd.steps["filter"] == instance["name"]]
    return adapts_of(spec, lambda: {c: one[c].to_numpy(float) for c in NOISE_COLUMNS if c in one})


def _nan_last(x: float) -> float:
    return x if math.isfinite(x) else math.inf


def absolute_times(rd: RealData, sub: pd.DataFrame) -> np.ndarray:
    """Log times [s] of rows of the steps table: the segment's cold start plus t."""
    t0 = {int(s["index"]): float(s["t0"]) for s in rd.manifest["data"]["segments"]}
    return sub["run"].map(t0).to_numpy(dtype=float) + sub["t"].to_numpy(dtype=float)


def _one(rd: RealData, name: str) -> pd.DataFrame:
    sub = rd.steps[rd.steps["filter"] == name].sort_values(["run", "step"])
    sub = sub[np.isfinite(sub["t"].to_numpy(dtype=float))]
    return sub.assign(t_abs=absolute_times(rd, sub))


def _broken(sub: pd.DataFrame, columns: list[str]) -> list[np.ndarray]:
    """Columns with a NaN row between segments, so that lines do not join across runs."""
    parts = []
    for _, g in sub.groupby("run", sort=True):
        parts.append(g[columns].to_numpy(dtype=float))
        parts.append(np.full((1, len(columns)), np.nan))
    return np.vstack(parts) if parts else np.zeros((0, len(columns)))


# --------------------------------------------------------------------------------------------
# Figures


def _figure(rows: int, cols: int, size: tuple[float, float]):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    return fig, axes


def track_figure(rd: RealData):
    """The map, Vicon at the scored times of the held-out segments and the shown filters'
    estimates (plots.draw_paths: the map of every source)."""
    fig, axes = _figure(1, 1, (7.5, 6.5))
    ax = axes[0, 0]
    lm = rd.manifest["data"]["landmarks"]
    names = shown_filters(rd)
    truth = _broken(_one(rd, names[0]), ["x_true", "y_true"]) if names else np.zeros((0, 2))
    estimates = {name: _broken(_one(rd, name), ["x_est", "y_est"]) for name in names}
    draw_paths(ax, np.column_stack([lm["x"], lm["y"]]), truth, estimates, landmark_ids=lm["id"],
               truth_label="Vicon (scored times)", truth_alpha=0.45)  # fmt: skip
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{rd.name}: held-out segments against Vicon")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside right upper")  # off the map
    return fig


def _mark_segments(ax, rd: RealData) -> None:
    """Dotted lines at the cold starts, grey where nothing is scored; x limited to the part."""
    a, b = rd.manifest["data"]["held_out"]
    ax.set_xlim(a, b)
    for s in rd.manifest["data"]["segments"]:
        ax.axvline(float(s["t0"]), color="0.6", lw=0.6, ls=":")
    for a, b in rd.manifest["data"]["misfits"] + rd.manifest["data"]["gaps"]:
        ax.axvspan(a, b, color="0.85", lw=0)


def series(rd: RealData, name: str, column: str) -> RunSeries:
    """Column `column` of instance `name` over log time, segment by segment (ragged runs)."""
    return RunSeries.of_steps(_one(rd, name), column, time="t_abs")


def errors_figure(rd: RealData):
    fig, axes = _figure(2, 1, (9.5, 6.5))
    for name in shown_filters(rd):
        style = filter_style(name).line()
        draw_runs(axes[0, 0], series(rd, name, "pos_err"), f"pos/{name}", name, lw=0.8, **style)
        heading = series(rd, name, "heading_err").map(np.degrees)
        draw_runs(axes[1, 0], heading, f"heading/{name}", lw=0.8, **style)
    for ax, label in ((axes[0, 0], "position error [m]"), (axes[1, 0], "heading error [deg]")):
        _mark_segments(ax, rd)
        ax.set_yscale("log")
        ax.set_ylabel(label)
    axes[1, 0].set_xlabel("log time [s] (dotted: segment cold starts; grey: not scored)")
    axes[0, 0].legend(loc="upper left")
    axes[0, 0].set_title(f"{rd.name}: errors on the held-out part")
    return fig


NOISE = (
    ("R_rr", "range std [m]", "sigma_range"),
    ("R_bb", "bearing std [rad]", "sigma_bearing_rad"),
    ("Q_vv", "speed std [m/s]", "sigma_v"),
    ("Q_gg", "turn-rate std [rad/s]", "sigma_w_rad"),
)


def noise_figure(rd: RealData):
    """Adapted noise (as standard deviations) of the adaptive filters started at x1."""
    fig, axes = _figure(2, 2, (10, 6.5))
    tuned = rd.manifest.get("tuning") or {}
    naive = rd.manifest["scenario"]["naive"]
    starts = {f["start"] for f in rd.instances() if f["start"] is not None}
    start = 1.0 if 1.0 in starts else (min(starts) if starts else None)
    adaptive = {f["name"]: (f["base"], adapts(rd, f)) for f in rd.instances()
                if f["start"] == start and adapts(rd, f)}  # fmt: skip
    for ax, (col, label, key) in zip(axes.ravel(), NOISE, strict=True):
        for name, (base, what) in adaptive.items():
            if col[0] not in what:  # R_rr, R_bb: "R"; Q_vv, Q_gg: "Q"
                continue
            # the report's colour and line style of the filter: thirteen filters stay apart
            draw_runs(ax, series(rd, name, col).map(np.sqrt), f"{col}/{name}", name, lw=0.9,
                      color=filter_colour(base), ls=filter_linestyle(base))  # fmt: skip
        if key in tuned:
            ax.axhline(tuned[key], color="k", ls="--", lw=1, gid=f"{col}/tuned", label="ekf-tuned")
        if start is not None:
            ax.axhline(naive[key] * start, color="0.5", ls=":", lw=1, label=f"naive x{start:g}")
        _mark_segments(ax, rd)
        plain_log_axis(ax)
        ax.set_ylabel(label)
        ax.set_xlabel("log time [s]")
    handles, labels = legend_entries(axes.ravel())
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 5), fontsize=7)
    fig.suptitle(f"{rd.name}: adapted R and Q (start x{start:g}) against the tuned values")
    return fig


def ratio_rows(rd: RealData) -> list[dict]:
    """Per instance: its ratio of position RMSE to ekf-tuned's with the paired interval."""
    ref = rd.reference
    rows = []
    c = rd.comparisons
    for f in rd.instances():
        name = f["name"]
        rec = rd.record(name)
        hit = c[(c["filter"] == name) & (c["vs"] == ref) & (c["metric"] == "rmse_pos")]
        est, lo, hi = (
            (float(hit["estimate"].iloc[0]), float(hit["lo"].iloc[0]), float(hit["hi"].iloc[0]))
            if len(hit) else (1.0 if name == ref else math.nan, math.nan, math.nan)
        )  # fmt: skip
        rows.append({
            "filter": name, "base": f["base"], "kind": f["kind"], "start": f["start"],
            "reference": name == ref,
            "rmse_pos": _value(rec["rmse_pos"]), "rmse_pos_pooled": _value(rec["rmse_pos_pooled"]),
            "rmse_heading_deg": math.degrees(_value(rec["rmse_heading"])),
            "ratio": est, "lo": lo, "hi": hi, "anees": _value(rec["anees"]),
            "nees_in_bounds": _value(rec["nees_in_bounds"]),
            "gate_rejected": _value(rec.get("gate_rejected")),
            "lost_lock_runs": int(rec.get("lost_lock_runs", 0)), "runs": int(rec["runs"]),
            "diverged": int(rec["diverged"]),
        })  # fmt: skip
    return rows


def ratio_figure(rd: RealData):
    rows = [r for r in ratio_rows(rd) if r["filter"] != rd.reference]
    bases = list(dict.fromkeys(r["base"] for r in rows))
    # A trained filter (kalmannet) has one instance, start None: drawn after the naive starts.
    starts = sorted({r["start"] for r in rows}, key=lambda m: (m is None, m or 0.0))
    fig, axes = _figure(1, 1, (8, 0.35 * len(bases) * max(1, len(starts)) + 1.5))
    ax = axes[0, 0]
    markers = "os^Dv<>p"
    colours = {base: filter_colour(base) for base in bases}  # the report's one palette
    y = 0
    ticks, labels = [], []
    for base in bases:
        for k, m in enumerate(starts):
            r = next((r for r in rows if r["base"] == base and r["start"] == m), None)
            if r is None:
                continue
            err = None
            if math.isfinite(r["lo"]) and math.isfinite(r["hi"]):
                err = [[r["ratio"] - r["lo"]], [r["hi"] - r["ratio"]]]
            ax.errorbar([r["ratio"]], [y], xerr=err, fmt=markers[k % len(markers)],
                        color=colours[base], ms=5, capsize=2,
                        gid=f"ratio/{r['filter']}")  # fmt: skip
            ticks.append(y)
            shown = base if m is None else f"{base} x{m:g}"
            labels.append(shown + (" (lost lock)" if r["lost_lock_runs"] else ""))
            y -= 1
        y -= 0.5
    ax.axvline(1.0, color="k", lw=1)
    plain_log_axis(ax, "x")
    ax.set_yticks(ticks, labels, fontsize=7)
    ax.set_xlabel("held-out position RMSE / ekf-tuned's (95 % paired bootstrap interval)")
    ax.set_title(f"{rd.name}: every filter from every naive start")
    return fig


# --------------------------------------------------------------------------------------------
# The report's section (document blocks; report.py puts them in the one report)


def _start_text(r: dict) -> str:
    """A row's start: 'x1' (a naive start), 'tuned' (ekf-tuned), 'trained' (kalmannet)."""
    if r["start"] is not None:
        return f"x{r['start']:g}"
    return "tuned" if r["reference"] else "trained"


def _number(value: float, digits: int) -> Cell:
    return Cell(format_number(value, digits), value)


def _ratio_cell(r: dict) -> Cell:
    """'0.92 [0.85, 1.01]': a ratio to ekf-tuned with its interval (when it has one)."""
    text = format_number(r["ratio"], 2)
    if math.isfinite(r["lo"]):
        text += f" [{r['lo']:.2f}, {r['hi']:.2f}]"
    return Cell(text, r["ratio"])


def _count_cell(count: int, total: int) -> Cell:
    return Cell(f"{count}/{total}", count)


def results_table(rd: RealData) -> TableBlock:
    """Per instance (segments protocol): RMSE (Monte Carlo statistic and pooled), the ratio to
    ekf-tuned with its interval, heading RMSE, ANEES, NEES in bounds, gate rejections, lost lock."""
    header = (
        "filter", "start", "RMSE pos [m]", "pooled [m]", "ratio to ekf-tuned [95 %]",
        "RMSE head [deg]", "ANEES", "NEES in bounds", "gate rejected", "lost lock",
    )  # fmt: skip
    rows = [
        [
            Cell(r["base"]), Cell(_start_text(r)),
            _number(r["rmse_pos"], 3), _number(r["rmse_pos_pooled"], 3), _ratio_cell(r),
            _number(r["rmse_heading_deg"], 1), _number(r["anees"], 1),
            Cell(format_share(r["nees_in_bounds"]), r["nees_in_bounds"]),
            Cell(format_share(r["gate_rejected"]), r["gate_rejected"]),
            _count_cell(r["lost_lock_runs"], r["runs"]),
        ]
        for r in ratio_rows(rd)
    ]  # fmt: skip
    return TableBlock(header, rows, (False, False) + (True,) * (len(header) - 2))


SEGMENTS_FIGURES = (
    ("ratios", ratio_figure, "every filter from every naive start against ekf-tuned"),
    ("track", track_figure, "the held-out segments against Vicon, with the map"),
    ("errors", errors_figure, "position and heading error over time"),
    ("noise", noise_figure, "adapted R and Q against the tuned values"),
)


def _figures(rd: RealData, save: FigureSaver, drawn: Sequence) -> list[Block]:
    """Each figure of `drawn` ((key, function, caption)) saved as `<name>_<key>.<format>`."""
    return [save(draw(rd), f"{rd.slug}_{key}.{save.fmt}", f"{rd.name}: {caption}")
            for key, draw, caption in drawn]  # fmt: skip


def segments_section(rd: RealData, save: FigureSaver, level: int = 3) -> list[Block]:
    """A result of the segments protocol (SPEC 9): the log and its held-out part, ekf-tuned's
    noise, the table of every instance and four figures."""
    m = rd.manifest
    data, tuned = m["data"], m.get("tuning")
    out: list[Block] = [Heading(f"{rd.name} (real data)", level, anchor=f"real-{rd.slug}")]
    if rd.description:
        out.append(Paragraph(rd.description))
    out.append(Paragraph(
        f"Log: {data['source']} ({data['log']}); held-out part {data['held_out'][0]:.1f}-"
        f"{data['held_out'][1]:.1f} s with {data['held_out_scorable_s']:.0f} s of scorable ground"
        f" truth, in {m['runs']} segments, each cold-started from ground truth (the runs of the"
        " statistics below: one robot, one sensor, consecutive stretches of one drive, so not"
        " independent repeats; docs/REAL_DATA.md)."
    ))  # fmt: skip
    if tuned:
        out.append(Paragraph(
            f"ekf-tuned: sigma_v {tuned['sigma_v']:.4g} m/s, sigma_w {tuned['sigma_w_rad']:.4g}"
            f" rad/s, sigma_range {tuned['sigma_range']:.4g} m, sigma_bearing"
            f" {tuned['sigma_bearing_rad']:.4g} rad, chosen among {tuned['settings']} settings on"
            f" {tuned['train_segments']} training segments (training RMSE"
            f" {tuned['train_rmse_pos']:.4f} m; {100 * tuned['coarse_lost_lock_share']:.0f} % of"
            " the coarse grid lost lock)."
        ))  # fmt: skip
    out.append(Paragraph(
        "RMSE pos: the time mean of the RMSE-over-segments curve (segments aligned by the rank of"
        " the evaluation time in the segment); pooled: over every scored time of every segment."
        f" Lost lock: segments whose position error exceeds {LOST_LOCK_M:g} m at a scored time."
    ))  # fmt: skip
    out.append(results_table(rd))
    return out


def section(rd: RealData, save: FigureSaver, level: int = 3) -> list[Block]:
    """A recorded result's part of the report: every part of `PARTS` whose test the result
    passes (its protocol, the tables it holds), in order; its figures saved through `save`
    (the report's one figure writer)."""
    try:
        return [block for _, wanted, build in PARTS if wanted(rd)
                for block in build(rd, save, level)]  # fmt: skip
    except (KeyError, TypeError, ValueError, IndexError, OverflowError, AttributeError) as exc:
        # A hand-edited manifest the checks above let through: one line, not a traceback.
        raise ResultsError(
            f"{rd.folder / MANIFEST_FILE}: not a real-data manifest written by anfekf run"
            f" ({type(exc).__name__})"
        ) from None


# --------------------------------------------------------------------------------------------
# Protocol drives (SPEC 15): every run is one whole drive; statistics over drives


def is_drives_result(rd: RealData) -> bool:
    return rd.manifest.get("protocol") == "drives"


def drive_ids(rd: RealData) -> list[str]:
    return [d["drive"] for d in rd.manifest["data"]["drives"]]


def drive_rmse(rd: RealData) -> pd.DataFrame:
    """Position RMSE of every instance on every drive (rows: instances in scenario order,
    columns: drives), pooled over the drive's scored evaluation times; NaN for a diverged run."""
    steps = rd.steps
    err = steps["pos_err"].to_numpy(dtype=float)
    frame = pd.DataFrame({"filter": steps["filter"].astype(str), "run": steps["run"],
                          "sq": err * err, "n": np.isfinite(err)})  # fmt: skip
    frame = frame[frame["n"]]
    g = frame.groupby(["filter", "run"], sort=False)
    rmse = np.sqrt(g["sq"].sum() / g["n"].sum()).unstack("run")
    names = [f["name"] for f in rd.instances()]
    ids = drive_ids(rd)
    out = rmse.reindex(index=names, columns=range(len(ids)))
    out.columns = ids
    return out


def drive_lost_lock(rd: RealData) -> pd.DataFrame:
    """Whether an instance lost lock on a drive: its position error exceeded LOST_LOCK_M at a
    scored time, or it diverged (True/False, same shape as `drive_rmse`)."""
    steps = rd.steps
    big = steps.assign(big=steps["pos_err"].to_numpy(dtype=float) > LOST_LOCK_M)
    lost = big.groupby([big["filter"].astype(str), "run"], sort=False)["big"].any().unstack("run")
    rm = drive_rmse(rd)
    lost = lost.reindex(index=rm.index, columns=range(rm.shape[1])).fillna(True).astype(bool)
    lost.columns = rm.columns
    return lost | rm.isna()


def drive_ratio_rows(rd: RealData, confidence: float = 0.95, resamples: int = 9999) -> list[dict]:
    """Per instance: the geometric mean over drives of its RMSE over ekf-tuned's on the same
    drive, with a paired BCa bootstrap interval over drives (drives are the independent repeats:
    resampled whole, each with both filters' RMSE), the Wilcoxon signed-rank p of the log ratios,
    the drives it beat ekf-tuned on, and the drives on which it lost lock."""
    from scipy import stats

    ref = rd.reference
    rm = drive_rmse(rd)
    lost = drive_lost_lock(rd)
    seed = int(rd.manifest.get("seed", 0))
    rows = []
    for f in rd.instances():
        name = f["name"]
        row = {"filter": name, "base": f["base"], "kind": f["kind"], "start": f["start"],
               "reference": name == ref,
               "lost_lock": int(lost.loc[name].sum()), "drives": int(rm.shape[1]),
               "rmse_median": float(np.nanmedian(rm.loc[name]))}  # fmt: skip
        if ref is None or name == ref:
            row.update(ratio=1.0 if name == ref else math.nan, lo=math.nan, hi=math.nan,
                       p_value=math.nan, better=0, used=int(rm.shape[1]))  # fmt: skip
            rows.append(row)
            continue
        log_ratio = np.log(rm.loc[name].to_numpy(float) / rm.loc[ref].to_numpy(float))
        log_ratio = log_ratio[np.isfinite(log_ratio)]
        est = float(np.exp(log_ratio.mean())) if len(log_ratio) else math.nan
        lo = hi = p = math.nan
        if len(log_ratio) >= 3 and np.ptp(log_ratio) > 0:
            boot = stats.bootstrap((log_ratio,), np.mean, confidence_level=confidence,
                                   n_resamples=resamples, method="BCa",
                                   random_state=np.random.default_rng(seed))  # fmt: skip
            lo, hi = (float(np.exp(v)) for v in (boot.confidence_interval.low,
                                                  boot.confidence_interval.high))  # fmt: skip
            p = float(stats.wilcoxon(log_ratio).pvalue)
        row.update(ratio=est, lo=lo, hi=hi, p_value=p, better=int((log_ratio < 0).sum()),
                   used=len(log_ratio))  # fmt: skip
        rows.append(row)
    return rows


def drives_heatmap_figure(rd: RealData):
    """Filters x drives: each instance's RMSE over ekf-tuned's on that drive, on the report's
    one ratio scale (plots.ratio_image, as the leaderboard and the sweeps)."""
    rm = drive_rmse(rd)
    ref = rd.reference
    ratio = rm.div(rm.loc[ref], axis=1) if ref else rm
    ratio = ratio.drop(index=ref) if ref else ratio
    # at least the title's width and the colour bar's ticks' height, however few the drives
    size = (max(6.0, 2.6 + 0.62 * ratio.shape[1]), max(3.2, 1.4 + 0.24 * ratio.shape[0]))
    fig, axes = _figure(1, 1, size)
    ax = axes[0, 0]
    image = ratio_image(ax, ratio.to_numpy(float), gid="drives_heatmap")
    for (i, j), v in np.ndenumerate(ratio.to_numpy(float)):
        text = "div." if not math.isfinite(v) else (f"{v:.2f}" if v < 10 else f"{v:.0f}")
        ax.text(j, i, text, ha="center", va="center", fontsize=5.5)
    ax.set_xticks(range(ratio.shape[1]), list(ratio.columns), rotation=45, fontsize=7)
    ax.set_yticks(range(ratio.shape[0]), list(ratio.index), fontsize=6)
    ax.grid(False)
    ratio_colourbar(fig, image, ax, f"RMSE / {ref or 'the reference'}'s (log)")
    ax.set_title(f"{rd.name}: position RMSE over ekf-tuned's, per drive")
    return fig


def _drive_grid(rd: RealData, size_per: tuple[float, float]):
    ids = drive_ids(rd)
    cols = min(4, len(ids))
    rows = math.ceil(len(ids) / cols)
    fig, axes = _figure(rows, cols, (size_per[0] * cols, size_per[1] * rows))
    for ax in axes.ravel()[len(ids) :]:
        ax.set_visible(False)
    return ids, fig, axes.ravel()


def drives_track_figure(rd: RealData):
    """Every drive: its dataset's map, Vicon at the scored times, and the shown filters
    (plots.draw_paths: the map of every source)."""
    ids, fig, axes = _drive_grid(rd, (3.6, 3.4))
    names = shown_filters(rd)
    for run, (drive, ax) in enumerate(zip(ids, axes, strict=False)):
        lm = rd.manifest["data"]["drives"][run]["landmarks"]
        subs = {name: _one_run(rd, name, run) for name in names}
        truth = subs[names[0]][["x_true", "y_true"]].to_numpy(float) if names else np.zeros((0, 2))
        draw_paths(ax, np.column_stack([lm["x"], lm["y"]]), truth,
                   {n: sub[["x_est", "y_est"]].to_numpy(float) for n, sub in subs.items()},
                   gid=lambda what, drive=drive: f"{what}/{drive}", truth_label="Vicon",
                   truth_alpha=0.4, lw=0.6, marker_size=20)  # fmt: skip
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(drive, fontsize=8)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("")
        ax.set_ylabel("")
    axes[0].legend(loc="best", fontsize=6)
    fig.suptitle(f"{rd.name}: every drive against Vicon, with its dataset's map")
    return fig


def _one_run(rd: RealData, name: str, run: int) -> pd.DataFrame:
    steps = rd.steps
    sub = steps[(steps["filter"] == name) & (steps["run"] == run)].sort_values("step")
    return sub[np.isfinite(sub["t"].to_numpy(dtype=float))]


def drives_errors_figure(rd: RealData):
    """Every drive: position error over time of the shown filters (log scale)."""
    ids, fig, axes = _drive_grid(rd, (3.6, 2.4))
    for run, (drive, ax) in enumerate(zip(ids, axes, strict=False)):
        for name in shown_filters(rd):
            one = RunSeries.of_steps(_one_run(rd, name, run), "pos_err")
            draw_runs(ax, one, f"pos/{drive}/{name}", name, lw=0.5, **filter_style(name).line())
        ax.set_yscale("log")
        ax.set_title(drive, fontsize=8)
        ax.tick_params(labelsize=6)
    axes[0].legend(loc="best", fontsize=6)
    axes[0].set_ylabel("position error [m]")
    fig.suptitle(f"{rd.name}: position error over time from the cold start [s]")
    return fig


def drives_noise_figure(rd: RealData):
    """Adapted noise per drive: the time median of each adaptive filter's (start x1) adapted
    standard deviations on every drive, against the values ekf-tuned was tuned to there."""
    ids = drive_ids(rd)
    fig, axes = _figure(2, 2, (11, 6.5))
    starts = {f["start"] for f in rd.instances() if f["start"] is not None}
    start = 1.0 if 1.0 in starts else (min(starts) if starts else None)
    adaptive = {f["name"]: f["base"] for f in rd.instances()
                if role_of(f["kind"]) != "reference" and f["start"] == start}  # fmt: skip
    tuning = rd.manifest.get("tuning") or {}
    per_drive = {d["drive"]: d for d in tuning.get("per_drive", [])}
    tunings = tuning.get("tunings", {})
    steps = rd.steps
    for ax, (col, label, key) in zip(axes.ravel(), NOISE, strict=True):
        for name, base in adaptive.items():
            sub = steps[steps["filter"] == name]
            med = sub.groupby("run")[col].median().reindex(range(len(ids)))
            ax.plot(range(len(ids)), np.sqrt(med.to_numpy(float)), "o-", ms=3, lw=0.6,
                    color=filter_colour(base), gid=f"{col}/{name}", label=name)  # fmt: skip
        tuned = [tunings.get("+".join(map(str, _sources(per_drive.get(d)))), {}).get(key)
                 for d in ids]  # fmt: skip
        if any(v is not None for v in tuned):
            ax.plot(range(len(ids)), [math.nan if v is None else v for v in tuned], "k_", ms=14,
                    mew=2, gid=f"{col}/tuned", label="ekf-tuned")  # fmt: skip
        ax.set_xticks(range(len(ids)), ids, rotation=45, fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel(label)
    axes[0, 0].legend(loc="best", fontsize=6, ncol=2)
    fig.suptitle(f"{rd.name}: adapted noise (median over each drive, start x{start:g}) against"
                 " ekf-tuned's values")  # fmt: skip
    return fig


def _sources(entry: dict | None) -> list[int]:
    if not entry:
        return []
    return sorted({int(d[1]) for d in entry["tuned_on"]})


def drives_table(rd: RealData) -> TableBlock:
    """Per instance (drives protocol): the ratio to ekf-tuned over drives with its interval, the
    Wilcoxon p, the drives it beat ekf-tuned on, its median RMSE, the drives it lost lock on and
    its NEES in bounds (each drive's own NEES against single-run bounds, pooled)."""
    header = ("filter", "start", "ratio to ekf-tuned [95 %]", "p", "better on", "median RMSE [m]",
              "lost lock", "NEES in bounds")  # fmt: skip
    rows = [
        [
            Cell(r["base"]), Cell(_start_text(r)), _ratio_cell(r),
            _number(r["p_value"], 3), _count_cell(r["better"], r["used"]),
            _number(r["rmse_median"], 3), _count_cell(r["lost_lock"], r["drives"]),
            Cell(format_share(_value(rd.record(r["filter"]).get("nees_in_bounds"))),
                 _value(rd.record(r["filter"]).get("nees_in_bounds"))),
        ]
        for r in drive_ratio_rows(rd)
    ]  # fmt: skip
    return TableBlock(header, rows, (False, False) + (True,) * (len(header) - 2))


def drives_section(rd: RealData, save: FigureSaver, level: int = 3) -> list[Block]:
    """A result of the drives protocol (SPEC 15): the ratios over drives, ekf-tuned's tuning per
    drive, the per-drive RMSE and four figures."""
    m = rd.manifest
    tuning = m.get("tuning") or {}
    rm = drive_rmse(rd)
    heading = f"{rd.name} (real data, {m['runs']} drives)"
    out: list[Block] = [Heading(heading, level, anchor=f"real-{rd.slug}")]
    if rd.description:
        out.append(Paragraph(rd.description))
    out.append(Paragraph(
        "Each drive is one run, cold-started from Vicon at its first stamp and scored over its"
        " whole ground-truth span (docs/REAL_DATA.md section 6). Ratios: the geometric mean"
        " over drives of each drive's position RMSE over ekf-tuned's on that drive, with a"
        " paired 95 % BCa bootstrap interval over drives (the independent repeats) and the"
        f" Wilcoxon p. Lost lock: drives with a position error above {LOST_LOCK_M:g} m at a"
        " scored time (or diverged). NEES in bounds: the share of every scored step of every"
        " drive whose own NEES lies inside the single-run 95 % chi-square(3) bounds [0.216,"
        " 9.35] (a step index is a different time on each drive: nothing is averaged across"
        " drives)."
    ))  # fmt: skip
    out.append(drives_table(rd))
    if tuning.get("per_drive"):
        out.append(Paragraph(
            "ekf-tuned per drive: tuned on the drives of the other dataset(s) (cross), against"
            " values tuned on its own dataset's drives, itself included (in-dataset, in-sample:"
            " what tuning on that map could give). RMSE of the plain EKF with each on the drive."
        ))  # fmt: skip
        rows = []
        for d in tuning["per_drive"]:
            c, i = d["cross_rmse_pos"], d["in_dataset_rmse_pos"]
            ratio = c / i if i else math.nan
            rows.append([Cell(d["drive"]), Cell(f"datasets {'+'.join(map(str, _sources(d)))}"),
                         _number(c, 3), _number(i, 3), _number(ratio, 2)])  # fmt: skip
        header = ("drive", "tuned on", "cross RMSE [m]", "in-dataset RMSE [m]",
                  "cross / in-dataset")  # fmt: skip
        out.append(TableBlock(header, rows, (False, False, True, True, True)))
        out.append(ListBlock([
            f"tuned on dataset(s) {key}: sigma_v {t['sigma_v']:.4g} m/s, sigma_w"
            f" {t['sigma_w_rad']:.4g} rad/s, sigma_range {t['sigma_range']:.4g} m,"
            f" sigma_bearing {t['sigma_bearing_rad']:.4g} rad (training RMSE"
            f" {t['train_rmse_pos']:.4f} m, {t['settings']} settings, {t['seconds']:.1f} s)"
            for key, t in tuning.get("tunings", {}).items()
        ]))  # fmt: skip
    rows = [[Cell(str(name)), *(_number(v, 3) for v in row)] for name, row in rm.iterrows()]
    out.append(TableBlock(("filter", *rm.columns), rows, (False,) + (True,) * rm.shape[1],
                          caption="Per drive position RMSE [m]:"))  # fmt: skip
    return out + nees_per_drive_blocks(rd.folder, [f["name"] for f in rd.instances()],
                                       drive_ids(rd))  # fmt: skip


def audit_section(rd: RealData, save: FigureSaver, level: int = 3) -> list[Block]:
    """The drives audited against Vicon (SPEC 18: its tables, audit_*.parquet)."""
    audit = audit_blocks(rd.folder)
    if not audit:
        return []
    return [Heading(f"{rd.name}: the drives audited against Vicon", level + 1,
                    anchor=f"real-{rd.slug}-audit"), *audit]  # fmt: skip


DRIVES_FIGURES = (
    ("heatmap", drives_heatmap_figure, "filters x drives, RMSE over ekf-tuned's"),
    ("tracks", drives_track_figure, "every drive against Vicon"),
    ("errors", drives_errors_figure, "position error over time per drive"),
    ("noise", drives_noise_figure, "adapted noise per drive against the tuned values"),
)


def _has_audit(rd: RealData) -> bool:
    return any(rd.has(name) for name in AUDIT_FILES.values())


def _is_segments(rd: RealData) -> bool:
    return not is_drives_result(rd)


# A recorded result's section, part by part: (name, whether the result has what it draws, its
# blocks). Chosen by what the result holds, not by a module per source.
PARTS = (
    ("segments", _is_segments, segments_section),
    ("drives", is_drives_result, drives_section),
    ("audit", _has_audit, audit_section),
    ("segment figures", _is_segments, lambda rd, save, _: _figures(rd, save, SEGMENTS_FIGURES)),
    ("drive figures", is_drives_result, lambda rd, save, _: _figures(rd, save, DRIVES_FIGURES)),
)
