"""`anfekf report`: the series behind every figure and table, computed from saved results only.

Nothing is re-run. A scenario folder's steps.parquet and manifest.json (read through storage's
readers) become plain arrays (`ScenarioData`): the same metric functions the runner uses
(`filter_arrays`, `rmse_curve`, `nees_bounds`, `summarize_filter`) compute them, so a figure's line
and the table's number can never disagree. plots.py draws these arrays; `write_report` writes the
figures and report.md.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
import pandas as pd
from pydantic import ValidationError
from rich import box
from rich.table import Table
from rich.text import Text

from ..analysis.metrics import (
    format_number,
    format_share,
    nees_bounds,
    rmse_curve,
    summarize_filter,
)
from ..analysis.tables import filter_arrays
from ..config import NoiseSigmas
from ..models import control_covariance, measurement_covariance
from ..storage import (
    MANIFEST_FILE,
    ResultsError,
    read_manifest,
    read_steps,
    scenario_dirs,
    write_atomic,
)
from . import plots

BAND_PERCENTILES = (10.0, 90.0)  # the shaded band: this spread of the per-run values over runs
ELLIPSE_COUNT = 8  # 3-sigma ellipses along run 0's path, evenly spaced in time
REPORT_FILE = "report.md"

# The adapted covariance diagonals in steps.parquet, with what they mean and their units.
NOISE_COLUMNS: dict[str, tuple[str, str]] = {
    "R_rr": ("R range variance", "m²"),
    "R_bb": ("R bearing variance", "rad²"),
    "Q_vv": ("Q speed variance", "(m/s)²"),
    "Q_gg": ("Q steering variance", "rad²"),
}
_ADAPTED = {"R": ("R_rr", "R_bb"), "Q": ("Q_vv", "Q_gg")}
_NEEDED_COLUMNS = {
    "t", "x_true", "y_true", "x_est", "y_est", "P_xx", "P_xy", "P_yy", "heading_err", "diverged",
    *NOISE_COLUMNS,
}  # fmt: skip


class ImageFormat(str, Enum):
    """Figure file formats `--format` accepts."""

    png = "png"
    svg = "svg"
    pdf = "pdf"


@dataclass(frozen=True)
class Band:
    """A curve over time with the spread over runs around it (all arrays of length steps)."""

    line: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


@dataclass(frozen=True)
class FilterSeries:
    """Everything the figures show about one filter of one scenario (diverged runs left out)."""

    name: str
    kind: str  # ekf, ekf-oracle, anfekf
    adapts: str | None  # "R" or "Q" for an adapting ANFEKF, else None
    runs: int
    runs_used: int
    t: np.ndarray  # [s]
    pos: Band  # line: RMSE over runs [m]; band: percentiles of the per-run position error
    heading: Band  # as pos, in degrees
    nees: np.ndarray  # run-averaged NEES
    bounds: tuple[float, float]  # two-sided 95 % chi-square bounds for runs_used runs
    noise: dict[str, Band]  # R/Q diagonal column -> mean over runs and percentiles
    summary: dict  # summarize_filter's record: rmse_pos, rmse_heading, anees, nees_in_bounds, ...


@dataclass(frozen=True)
class Track:
    """One run's true path and each filter's estimate with its position covariance."""

    run: int
    t: np.ndarray
    truth: np.ndarray  # (steps, 2) [m]
    estimate: dict[str, np.ndarray]  # filter -> (steps, 2) [m]
    cov: dict[str, np.ndarray]  # filter -> (steps, 2, 2) [m²]
    ellipse_index: np.ndarray  # the steps that get a 3-sigma ellipse


@dataclass(frozen=True)
class ScenarioData:
    """One result folder, reduced to the series the report draws."""

    name: str
    description: str
    folder: Path
    runs: int
    seed: int | None
    filters: list[FilterSeries]
    true_noise: dict[str, float]  # noise column -> true variance in that column's units
    landmarks: np.ndarray  # (n, 2) [m]
    waypoints: np.ndarray  # (m, 2) [m]
    track: Track

    @property
    def slug(self) -> str:
        """The scenario name made safe for file names."""
        return re.sub(r"[^A-Za-z0-9_.-]", "_", self.name) or "scenario"

    @property
    def adapted_columns(self) -> list[str]:
        """The R/Q diagonal columns some filter adapts, in NOISE_COLUMNS order."""
        wanted = {c for f in self.filters if f.adapts for c in _ADAPTED[f.adapts]}
        return [c for c in NOISE_COLUMNS if c in wanted]


@dataclass(frozen=True)
class SummaryRow:
    """One row of the summary table: a filter in a scenario."""

    scenario: str
    filter: str
    kind: str
    runs: int
    runs_used: int
    rmse_pos: float  # [m], time mean of the RMSE-over-runs curve
    rmse_heading_deg: float  # [deg], likewise
    anees: float
    nees_in_bounds: float  # share of steps, 0..1
    nees_lo: float
    nees_hi: float
    vs_ekf: float  # rmse_pos / the scenario's EKF's rmse_pos (nan without an EKF)
    vs_oracle: float  # rmse_pos / the oracle EKF's rmse_pos (nan without one)


@dataclass
class ReportResult:
    """What `write_report` produced."""

    out_dir: Path
    scenarios: list[ScenarioData]
    rows: list[SummaryRow]
    files: list[Path] = field(default_factory=list)


# --------------------------------------------------------------------------- finding results


def find_scenarios(results_dirs: Sequence[Path], out_dir: Path | None = None) -> list[Path]:
    """The scenario folders under the given folders, minus the report folder, each once."""
    found: dict[Path, Path] = {}
    skip = Path(out_dir).resolve() if out_dir is not None else None
    for results_dir in results_dirs:
        for folder in scenario_dirs(Path(results_dir)):
            resolved = folder.resolve()
            if skip is not None and (resolved == skip or skip in resolved.parents):
                continue
            found.setdefault(resolved, folder)
    if not found:
        shown = ", ".join(str(d) for d in results_dirs)
        raise ResultsError(f"{shown}: no results found outside the report folder {out_dir}")
    return list(found.values())


# --------------------------------------------------------------------------- series


def _manifest(folder: Path) -> dict:
    doc = read_manifest(folder)
    if not isinstance(doc.get("scenario"), dict):
        raise ResultsError(
            f"{folder / MANIFEST_FILE}: expected an object with a 'scenario' mapping"
        )
    return doc


def _points(manifest: dict, key: str, path: Path) -> np.ndarray:
    try:
        pts = np.asarray(manifest["world"][key], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise ResultsError(f"{path}: world.{key}: expected a list of [x, y] points") from None
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isfinite(pts)):
        raise ResultsError(f"{path}: world.{key}: expected a list of finite [x, y] points")
    return pts


def true_variances(sigmas: NoiseSigmas) -> dict[str, float]:
    """The true noise as the R/Q diagonal entries steps.parquet records (angles in radians)."""
    sv, sg, sr, sb = sigmas.radians()
    R, Qu = measurement_covariance(sr, sb), control_covariance(sv, sg)
    return {"R_rr": R[0, 0], "R_bb": R[1, 1], "Q_vv": Qu[0, 0], "Q_gg": Qu[1, 1]}


def _true_noise(manifest: dict, path: Path) -> dict[str, float]:
    try:
        sigmas = NoiseSigmas.model_validate(manifest["scenario"].get("true_noise") or {})
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise ResultsError(f"{path}: scenario.true_noise.{where}: {err['msg']}") from None
    return true_variances(sigmas)


def _filter_specs(manifest: dict, path: Path) -> dict[str, dict]:
    specs = manifest["scenario"].get("filters")
    if not isinstance(specs, list) or not all(isinstance(s, dict) and "name" in s for s in specs):
        raise ResultsError(f"{path}: scenario.filters: expected a list of filters with names")
    return {str(s["name"]): s for s in specs}


def _adapts(spec: dict) -> str | None:
    if spec.get("kind") != "anfekf" or spec.get("adaptation", True) is False:
        return None
    return spec.get("adapt", "R") if spec.get("adapt", "R") in _ADAPTED else None


def _band(values: np.ndarray) -> Band:
    """Mean over runs with the percentile band, for (runs, steps) values."""
    if len(values) == 0:
        empty = np.full(values.shape[1], np.nan)
        return Band(empty, empty, empty)
    lo, hi = np.percentile(values, BAND_PERCENTILES, axis=0)
    return Band(values.mean(axis=0), lo, hi)


def _error_band(err: np.ndarray) -> Band:
    """RMSE over runs (the paper's curve) with the percentile band of the per-run errors."""
    if len(err) == 0:
        return _band(err)
    lo, hi = np.percentile(err, BAND_PERCENTILES, axis=0)
    return Band(rmse_curve(err), lo, hi)


def filter_series(steps: pd.DataFrame, name: str, spec: dict) -> FilterSeries:
    """The series of one filter, from the steps table; diverged runs are left out like in tables."""
    a = filter_arrays(steps, name)
    ok = ~np.asarray(a["diverged"], dtype=bool)
    n = int(ok.sum())
    avg_nees = a["nees"][ok].mean(axis=0) if n else np.full(len(a["t"]), np.nan)
    return FilterSeries(
        name=name,
        kind=str(spec.get("kind", "?")),
        adapts=_adapts(spec),
        runs=len(ok),
        runs_used=n,
        t=np.asarray(a["t"], dtype=float),
        pos=_error_band(a["pos_err"][ok]),
        heading=_error_band(np.degrees(a["heading_err"][ok])),
        nees=avg_nees,
        bounds=nees_bounds(n) if n else (math.nan, math.nan),
        noise={col: _band(a[col][ok]) for col in NOISE_COLUMNS},
        summary=summarize_filter(a["pos_err"], a["heading_err"], a["nees"], a["diverged"]),
    )


def run_track(steps: pd.DataFrame, names: list[str], run: int | None = None) -> Track:
    """Run `run`'s (default: the first run's) truth and estimates, with ellipse instants."""
    run = int(steps["run"].min()) if run is None else run
    one = steps[steps["run"] == run]
    first = one[one["filter"] == names[0]].sort_values("step")
    estimate, cov = {}, {}
    for name in names:
        sub = one[one["filter"] == name].sort_values("step")
        estimate[name] = sub[["x_est", "y_est"]].to_numpy(dtype=float)
        pxx, pxy, pyy = (sub[c].to_numpy(dtype=float) for c in ("P_xx", "P_xy", "P_yy"))
        cov[name] = np.stack([np.stack([pxx, pxy], -1), np.stack([pxy, pyy], -1)], -2)
    n = len(first)
    # Evenly spaced in time, skipping the start where every ellipse is still a dot.
    index = np.unique(np.linspace(0, n - 1, ELLIPSE_COUNT + 1).round().astype(int)[1:])
    return Track(
        run=run,
        t=first["t"].to_numpy(dtype=float),
        truth=first[["x_true", "y_true"]].to_numpy(dtype=float),
        estimate=estimate,
        cov=cov,
        ellipse_index=index,
    )


def load_scenario_data(folder: Path) -> ScenarioData:
    """Read one scenario folder and compute every series the report draws."""
    folder = Path(folder)
    steps = read_steps(folder)
    steps_path = folder / "steps.parquet"
    missing = _NEEDED_COLUMNS - set(steps.columns)
    if missing:
        raise ResultsError(f"{steps_path}: missing columns {', '.join(sorted(missing))}")
    manifest = _manifest(folder)
    manifest_path = folder / MANIFEST_FILE
    specs = _filter_specs(manifest, manifest_path)
    names = [str(n) for n in steps["filter"].cat.categories if (steps["filter"] == n).any()]
    unknown = [n for n in names if n not in specs]
    if unknown:
        raise ResultsError(
            f"{steps_path}: filter {unknown[0]!r} is not in {manifest_path}; the two files"
            " come from different runs"
        )
    try:
        filters = [filter_series(steps, name, specs[name]) for name in names]
        track = run_track(steps, names)
    except ValueError as exc:  # ragged tables do not reshape into (runs, steps)
        raise ResultsError(
            f"{steps_path}: filters or runs have different numbers of steps ({exc})"
        ) from None
    scenario = manifest["scenario"]
    return ScenarioData(
        name=str(scenario.get("name", folder.name)),
        description=str(scenario.get("description", "")),
        folder=folder,
        runs=max(f.runs for f in filters),
        seed=manifest.get("seed"),
        filters=filters,
        true_noise=_true_noise(manifest, manifest_path),
        landmarks=_points(manifest, "landmarks", manifest_path),
        waypoints=_points(manifest, "waypoints", manifest_path),
        track=track,
    )


def _check_unique_names(scenarios: Sequence[ScenarioData]) -> None:
    """Figures are named after scenarios, so two results of one scenario would overwrite."""
    seen: dict[str, Path] = {}
    for sc in scenarios:
        if sc.slug in seen:
            raise ResultsError(
                f"{seen[sc.slug]} and {sc.folder} both hold scenario {sc.name!r};"
                " report them one at a time (with different --out folders)"
            )
        seen[sc.slug] = sc.folder


# --------------------------------------------------------------------------- tables


def _first_of_kind(sc: ScenarioData, kind: str) -> FilterSeries | None:
    return next((f for f in sc.filters if f.kind == kind), None)


def _ratio(value: float, reference: FilterSeries | None) -> float:
    if reference is None:
        return math.nan
    ref = reference.summary["rmse_pos"]
    return value / ref if ref and math.isfinite(ref) else math.nan


def summary_rows(scenarios: Sequence[ScenarioData]) -> list[SummaryRow]:
    """One row per filter and scenario, with the RMSE ratios against the EKF and the oracle."""
    rows = []
    for sc in scenarios:
        ekf, oracle = _first_of_kind(sc, "ekf"), _first_of_kind(sc, "ekf-oracle")
        for f in sc.filters:
            s = f.summary
            rows.append(
                SummaryRow(
                    scenario=sc.name,
                    filter=f.name,
                    kind=f.kind,
                    runs=s["runs"],
                    runs_used=s["runs_used"],
                    rmse_pos=s["rmse_pos"],
                    rmse_heading_deg=math.degrees(s["rmse_heading"]),
                    anees=s["anees"],
                    nees_in_bounds=s["nees_in_bounds"],
                    nees_lo=s["nees_lo"],
                    nees_hi=s["nees_hi"],
                    vs_ekf=_ratio(s["rmse_pos"], ekf),
                    vs_oracle=_ratio(s["rmse_pos"], oracle),
                )
            )
    return rows


TABLE_HEADER = (
    "scenario", "filter", "runs used", "diverged", "RMSE pos [m]", "RMSE heading [deg]", "ANEES",
    "NEES in 95 % bounds", "RMSE / ekf", "RMSE / oracle",
)  # fmt: skip


def table_cells(row: SummaryRow) -> list[str]:
    """The formatted cells of one summary row, shared by report.md and the terminal table."""
    return [
        row.scenario,
        row.filter,
        f"{row.runs_used}/{row.runs}",
        str(row.runs - row.runs_used),
        format_number(row.rmse_pos, 3),
        format_number(row.rmse_heading_deg, 3),
        format_number(row.anees, 2),
        format_share(row.nees_in_bounds),
        format_number(row.vs_ekf, 2),
        format_number(row.vs_oracle, 2),
    ]


# The terminal table: the same cells under two-line headers, so it fits 80 columns.
TERMINAL_HEADER = (
    "scenario", "filter", "runs\nused", "div-\nerged", "RMSE\npos [m]", "RMSE\nhead [deg]", "ANEES",
    "NEES in\nbounds", "RMSE\n/ ekf", "RMSE\n/ oracle",
)  # fmt: skip


def rich_table(rows: Sequence[SummaryRow]) -> Table:
    """The summary table for the terminal."""
    table = Table(
        title="Summary across scenarios (RMSE: time mean of the RMSE-over-runs curve)",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
        collapse_padding=True,
    )
    for i, col in enumerate(TERMINAL_HEADER):
        # Text, not str: "[m]" would be read as rich markup and vanish.
        table.add_column(Text(col), justify="left" if i < 2 else "right", no_wrap=i < 2)
    previous = None
    for row in rows:
        if previous is not None and row.scenario != previous:
            table.add_section()
        table.add_row(*table_cells(row))
        previous = row.scenario
    return table


def markdown_table(rows: Sequence[SummaryRow]) -> str:
    """The summary table as GitHub markdown."""
    lines = [
        "| " + " | ".join(TABLE_HEADER) + " |",
        "|" + "|".join(["---"] * 2 + ["---:"] * (len(TABLE_HEADER) - 2)) + "|",
    ]
    lines += ["| " + " | ".join(table_cells(r)) + " |" for r in rows]
    return "\n".join(lines)


# --------------------------------------------------------------------------- report.md


def figure_name(scenario: str, kind: str, fmt: ImageFormat) -> str:
    """File name of a scenario's figure (kind: rmse, nees, noise, map) or of the overview."""
    return f"{scenario}_{kind}.{fmt.value}" if scenario else f"{kind}.{fmt.value}"


def render_markdown(
    scenarios: Sequence[ScenarioData],
    rows: Sequence[SummaryRow],
    figures: dict[str, dict[str, str]],
    overview: str,
) -> str:
    """report.md: the summary table, the overview and every scenario's figures."""
    out = [
        "# anfekf-bench report",
        "",
        "Generated by `anfekf report` from saved results only (steps.parquet, manifest.json).",
        "RMSE: the time mean of the RMSE-over-runs curve `sqrt(mean_runs(ex² + ey²))`; ANEES: the",
        "time mean of the run-averaged NEES; *in bounds*: the share of recorded steps whose",
        "run-averaged NEES lies strictly inside the two-sided 95 % chi-square bounds for the runs",
        "used. Ratios divide a filter's position RMSE by the plain EKF's and by the oracle EKF's",
        "(the EKF given the true noise). Diverged runs are left out of every mean.",
        "",
        "## Summary",
        "",
        markdown_table(rows),
        "",
        f"![RMSE and consistency per filter across scenarios]({overview})",
        "",
    ]
    captions = {
        "rmse": "Position and heading RMSE over time",
        "nees": "Run-averaged NEES against the 95 % chi-square bounds",
        "noise": "Adapted noise covariance against the true value",
        "map": "Map, true path and run {run}'s estimates with 3-sigma ellipses",
    }
    for sc in scenarios:
        out += [f"## {sc.name}", ""]
        if sc.description:
            out += [sc.description, ""]
        seed = f", seed {sc.seed}" if sc.seed is not None else ""
        out += [f"{sc.runs} runs{seed}; results in `{sc.folder}`.", ""]
        for kind, caption in captions.items():
            name = figures[sc.slug].get(kind)
            caption = caption.format(run=sc.track.run)
            if name is None:
                out += [f"*{caption}: no filter of this scenario adapts R or Q.*", ""]
            else:
                out += [f"![{sc.name}: {caption}]({name})", ""]
    return "\n".join(out)


# --------------------------------------------------------------------------- the command


def write_report(
    results_dirs: Sequence[Path], out_dir: Path, fmt: ImageFormat = ImageFormat.png
) -> ReportResult:
    """Read every scenario under `results_dirs`, write its figures and report.md to `out_dir`.

    Everything is read (and checked) before anything is written, so bad input leaves no partial
    report behind.
    """
    out_dir = Path(out_dir)
    fmt = ImageFormat(fmt)
    folders = find_scenarios(results_dirs, out_dir)
    scenarios = [load_scenario_data(f) for f in folders]
    _check_unique_names(scenarios)
    rows = summary_rows(scenarios)
    result = ReportResult(out_dir=out_dir, scenarios=scenarios, rows=rows)
    out_dir.mkdir(parents=True, exist_ok=True)

    def save(fig, name: str) -> str:
        path = out_dir / name
        plots.save_figure(fig, path, fmt.value)
        result.files.append(path)
        return name

    figures: dict[str, dict[str, str]] = {}
    for sc in scenarios:
        made = figures[sc.slug] = {}
        made["rmse"] = save(plots.rmse_figure(sc), figure_name(sc.slug, "rmse", fmt))
        made["nees"] = save(plots.nees_figure(sc), figure_name(sc.slug, "nees", fmt))
        if sc.adapted_columns:
            made["noise"] = save(plots.noise_figure(sc), figure_name(sc.slug, "noise", fmt))
        made["map"] = save(plots.map_figure(sc), figure_name(sc.slug, "map", fmt))
    overview = save(plots.overview_figure(rows), figure_name("", "overview", fmt))
    text = render_markdown(scenarios, rows, figures, overview) + "\n"
    md = out_dir / REPORT_FILE
    write_atomic(md, lambda tmp: tmp.write_text(text, encoding="utf-8"))
    result.files.append(md)
    return result
