"""`anfekf report`: the series behind every figure and table, computed from saved results only.

Nothing is re-run (run, store and plot are separate steps). A scenario folder's steps.parquet and
manifest.json (read through storage's readers) become plain arrays (`ScenarioData`): the same
metric functions the runner uses (`filter_arrays`, `rmse_curve`, `nees_bounds`,
`summarize_filter`) compute them, so a figure's line and the table's number can never disagree.
The paired comparisons (comparisons.parquet: ratios with 95 % bootstrap intervals), the claims'
verdicts (claims.json) and the per-run metrics (runs.parquet) are shown as saved. plots.py draws
the arrays; `write_report` writes the figures, report.md and report.html (one self-contained
file, document.py).

One pipeline for every source: each result (a simulated scenario, a recorded log of either
protocol, a sweep) gives its section as document blocks (`section`: `scenario_section` here,
`real.section`, `sweep.section`), its figures saved through the one writer
(`plots.FigureSaver`); the one Document becomes report.md and report.html.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed
from pydantic import ValidationError

from ..analysis.metrics import (
    format_sig,
    nees_bounds,
    summarize_filter,
)
from ..analysis.statistics import Interval, interval_too_wide
from ..analysis.tables import filter_arrays
from ..config import NoiseSigmas
from ..filters.registry import role_of
from ..models import control_covariance, measurement_covariance
from ..problems.experiment import read_problem_result
from ..storage import (
    CLAIMS_FILE,
    COMPARISONS_FILE,
    MANIFEST_FILE,
    RUNS_FILE,
    STEPS_FILE,
    ResultsError,
    check_one_batch,
    check_simulated_manifest,
    read_json,
    read_manifest,
    read_parquet,
    read_steps,
    read_summary,
    write_atomic,
)
from ..workers import local_workers
from . import changing, plots, real, render, summary_figures
from . import suite as suite_report
from . import sweep as sweep_report
from .consistency import check_saved_result
from .data import (
    _NEEDED_COLUMNS,
    BAND_PERCENTILES,
    ELLIPSE_COUNT,
    FEW_RUNS,
    HTML_FILE,
    MAX_OUTLIERS_DRAWN,
    NOISE_COLUMNS,
    OUTLIER_FACTOR,
    REPORT_FILE,
    SIGMAS,
    Band,
    FilterSeries,
    Ratio,
    RunSeries,
    ScenarioData,
    SummaryRow,
    Track,
    adapts_of,
    first_with_role,
)
from .document import (
    Block,
    Cell,
    Contents,
    Document,
    FigureBlock,
    Heading,
    Paragraph,
    TableBlock,
    Warning,
    to_html,
    to_markdown,
)
from .problems import problem_blocks
from .results import (  # noqa: F401  (find_scenarios re-exported: it lived here)
    PROBLEM,
    RECORDED,
    SIMULATED,
    SWEEP,
    find_results,
    find_scenarios,
    load_result,
)
from .tables import (  # noqa: F401  (re-exported: the table API lived here)
    LEADERBOARD_CAPTION,
    TABLE_HEADER,
    TERMINAL_HEADER,
    format_ratio,
    leaderboard_table,
    markdown_table,
    rich_table,
    summary_rows,
    summary_table,
    table_cells,
    table_row,
)


class ImageFormat(str, Enum):
    """Figure file formats `--format` accepts."""

    png = "png"
    svg = "svg"
    pdf = "pdf"


@dataclass
class ReportResult:
    """What `write_report` produced."""

    out_dir: Path
    scenarios: list[ScenarioData]
    rows: list[SummaryRow]
    files: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    problems: int = 0  # problem results (SPEC 17) in the report
    figure_workers: int = 0  # processes that drew the figures beside this one (0: none)


# --------------------------------------------------------------------------- series


def _manifest(folder: Path) -> dict:
    doc, path = read_manifest(folder), folder / MANIFEST_FILE
    if not isinstance(doc.get("scenario"), dict):
        raise ResultsError(f"{path}: expected an object with a 'scenario' mapping")
    check_simulated_manifest(path, doc)  # valid Unicode, a map within range (hand-edited files)
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
    """The noise as the R/Q diagonal entries the noise figure shows (angles in deg²)."""
    sv, sg, sr, sb = sigmas.radians()
    R, Qu = measurement_covariance(sr, sb), control_covariance(sv, sg)
    stored = {"R_rr": R[0, 0], "R_bb": R[1, 1], "Q_vv": Qu[0, 0], "Q_gg": Qu[1, 1]}
    return {col: float(value * NOISE_COLUMNS[col][2]) for col, value in stored.items()}


def _sigmas(manifest: dict, key: str, path: Path) -> NoiseSigmas:
    try:
        return NoiseSigmas.model_validate(manifest["scenario"].get(key) or {})
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise ResultsError(f"{path}: scenario.{key}.{where}: {err['msg']}") from None


def _filter_specs(manifest: dict, path: Path) -> dict[str, dict]:
    specs = manifest["scenario"].get("filters")
    if not isinstance(specs, list) or not all(isinstance(s, dict) and "name" in s for s in specs):
        raise ResultsError(f"{path}: scenario.filters: expected a list of filters with names")
    by_name = {str(s["name"]): s for s in specs}
    # A scenario with naive starts: each instance '<filter> x<m>' is its base filter's spec.
    for instance in manifest.get("filters") or []:
        if isinstance(instance, dict) and instance.get("base") in by_name:
            by_name.setdefault(str(instance.get("name")), by_name[instance["base"]])
    return by_name


def outlier_runs(run_ids: np.ndarray, run_mean_nees: np.ndarray) -> tuple[int, ...]:
    """The runs whose time-mean NEES exceeds OUTLIER_FACTOR x the median run's, worst first."""
    values = np.asarray(run_mean_nees, dtype=float)
    if values.size < 3 or np.isnan(values).all():  # all NaN: no covariance, no NEES
        return ()
    with np.errstate(invalid="ignore"):
        median = float(np.nanmedian(np.where(np.isinf(values), np.nan, values)))
    if not math.isfinite(median) or median <= 0:
        return ()
    bad = np.flatnonzero(values > OUTLIER_FACTOR * median)
    order = bad[np.argsort(-values[bad], kind="stable")]
    return tuple(int(run_ids[i]) for i in order)


def filter_series(steps: pd.DataFrame, name: str, spec: dict) -> FilterSeries:
    """The series of one filter, from the steps table; diverged runs are left out like in tables."""
    a = filter_arrays(steps, name)
    ok = ~np.asarray(a["diverged"], dtype=bool)
    n = int(ok.sum())
    nees = a["nees"][ok]
    steps_n = len(a["t"])
    with np.errstate(all="ignore"):
        avg_nees = nees.mean(axis=0) if n else np.full(steps_n, np.nan)
        med_nees = np.median(nees, axis=0) if n else np.full(steps_n, np.nan)
        run_mean = nees.mean(axis=1) if n else np.zeros(0)
    run_ids = np.asarray(a["run"])[ok]
    outliers = outlier_runs(run_ids, run_mean)
    drawn = outliers[:MAX_OUTLIERS_DRAWN]
    row_of = {int(r): i for i, r in enumerate(run_ids)}
    noise = {col: a[col][ok] * NOISE_COLUMNS[col][2] for col in NOISE_COLUMNS}
    t = np.asarray(a["t"], dtype=float)

    def series(values: np.ndarray) -> RunSeries:
        return RunSeries.aligned(t, values, run_ids)

    return FilterSeries(
        name=name,
        kind=str(spec.get("kind", "?")),
        adapts=adapts_of(spec, noise),
        runs=len(ok),
        runs_used=n,
        t=t,
        pos=series(a["pos_err"][ok]).band(rms=True),
        heading=series(np.degrees(a["heading_err"][ok])).band(rms=True),
        nees=avg_nees,
        nees_median=med_nees,
        bounds=nees_bounds(n) if n else (math.nan, math.nan),
        noise={col: series(values).band() for col, values in noise.items()},
        summary=summarize_filter(a["pos_err"], a["heading_err"], a["nees"], a["diverged"]),
        run_ids=run_ids,
        run_mean_nees=run_mean,
        outliers=outliers,
        outlier_nees={r: nees[row_of[r]] for r in drawn},
        outlier_noise={col: {r: noise[col][row_of[r]] for r in drawn} for col in NOISE_COLUMNS},
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


def _float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def read_comparisons(folder: Path) -> dict[tuple[str, str, str], Ratio]:
    """comparisons.parquet as (filter, vs, metric) -> Ratio; empty when the file is absent
    (results written before comparisons existed)."""
    path = Path(folder) / COMPARISONS_FILE
    if not os.path.lexists(path):
        return {}
    df = read_parquet(path)
    needed = {"filter", "vs", "metric", "estimate", "lo", "hi", "runs_used"}
    if not needed <= set(df.columns):
        missing = ", ".join(sorted(needed - set(df.columns)))
        raise ResultsError(f"{path}: missing columns {missing}")
    out = {}
    for r in df.itertuples(index=False):
        if getattr(r, "kind", "ratio") != "ratio":
            continue
        out[(str(r.filter), str(r.vs), str(r.metric))] = Ratio(
            _float(r.estimate),
            _float(r.lo),
            _float(r.hi),
            int(r.runs_used),
            _float(getattr(r, "p_value", math.nan)),
        )
    return out


def read_claims(folder: Path) -> list[dict]:
    """claims.json (a list of verdict records); empty when absent."""
    path = Path(folder) / CLAIMS_FILE
    if not os.path.lexists(path):
        return []
    doc = read_json(path)
    if not isinstance(doc, list) or not all(isinstance(c, dict) for c in doc):
        raise ResultsError(f"{path}: expected a list of claim records")
    return doc


def read_per_run(folder: Path) -> pd.DataFrame | None:
    """runs.parquet, or None when absent."""
    path = Path(folder) / RUNS_FILE
    if not os.path.lexists(path):
        return None
    df = read_parquet(path)
    missing = {"filter", "run", "rmse_pos", "mean_nees", "diverged"} - set(df.columns)
    if missing:
        raise ResultsError(f"{path}: missing columns {', '.join(sorted(missing))}")
    df["filter"] = df["filter"].astype(str)
    return df


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
    check_saved_result(folder, steps, manifest)  # one batch's steps, whole, under plain names
    check_one_batch(folder, manifest)
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
    return _scenario_data(folder, manifest, manifest_path, filters, track, read_per_run(folder))


NO_STEPS_NOTE = (
    "*No figures over time: this result has no steps.parquet (its scenario sets"
    " `steps_table: false`). The rows above come from summary.parquet, the ratios from"
    " comparisons.parquet, the per-run spread and outlier runs from runs.parquet.*"
)
_NO_SERIES = np.zeros(0)


# Steps files adding up to at least this many bytes are read in worker processes, one scenario
# each (the zoo: 6 x 140 MB, 1.3-1.9 s each); below, starting the workers costs more than it saves.
PARALLEL_MIN_STEPS_BYTES = 100 * 2**20


def load_scenarios(folders: Sequence[Path]) -> list[ScenarioData]:
    """Every simulated result's report data, in `folders` order: `load_scenario_data` where a
    steps table was written, else `load_summary_only`; read (and checked) in parallel when the
    steps tables are large (`PARALLEL_MIN_STEPS_BYTES`), the same data either way."""
    folders = [Path(f) for f in folders]
    sizes = [_steps_bytes(f) for f in folders]
    calls = [(_load_one, f, size is not None) for f, size in zip(folders, sizes, strict=True)]
    large = sum(size or 0 for size in sizes) >= PARALLEL_MIN_STEPS_BYTES
    loaded = _in_workers(calls, large, sum(size is not None for size in sizes))
    return [func(*args) for func, *args in calls] if loaded is None else loaded


def _in_workers(calls: list[tuple], large: bool, heavy: int) -> list | None:
    """The results of `calls` (func, *args), in order, computed in worker processes when the
    work is `large` and at least two of the calls are `heavy` and there are two CPUs; None
    otherwise (the caller does the work itself: starting workers would cost more)."""
    jobs = min(heavy, os.cpu_count() or 1)
    if jobs < 2 or not large:
        return None
    with local_workers():
        return Parallel(n_jobs=jobs)(delayed(func)(*args) for func, *args in calls)


def _steps_bytes(folder: Path) -> int | None:
    """The size of `folder`'s steps table as listed (a link's own), None when there is none."""
    try:
        return os.lstat(folder / STEPS_FILE).st_size
    except OSError:  # missing or unreadable: as os.path.lexists, the summary-only reader says why
        return None


def _load_one(folder: Path, has_steps: bool) -> ScenarioData:
    return load_scenario_data(folder) if has_steps else load_summary_only(folder)


def load_summary_only(folder: Path) -> ScenarioData:
    """A result without steps.parquet (`steps_table: false`), as the tables need it: each
    filter's summary record (summary.parquet), its runs (runs.parquet), no series over time."""
    folder = Path(folder)
    manifest = _manifest(folder)
    manifest_path = folder / MANIFEST_FILE
    check_one_batch(folder, manifest)
    load_result(folder)  # the tables a summary-only result needs (steps.parquet if written)
    specs = _filter_specs(manifest, manifest_path)
    summary = read_summary(folder)
    where = folder / "summary.parquet"
    needed = {"filter", "runs", "runs_used", "rmse_pos", "rmse_heading", "anees",
              "nees_in_bounds", "nees_lo", "nees_hi"}  # fmt: skip
    if not needed <= set(summary.columns):
        raise ResultsError(
            f"{where}: missing columns {', '.join(sorted(needed - set(summary.columns)))}"
        )
    per_run = read_per_run(folder)
    empty = Band(_NO_SERIES, _NO_SERIES, _NO_SERIES, _NO_SERIES)
    filters = []
    for rec in summary.to_dict(orient="records"):
        name = str(rec["filter"])
        if name not in specs:
            raise ResultsError(f"{where}: filter {name!r} is not in {manifest_path}")
        record = {k: (_float(v) if k not in ("filter", "scenario") else v) for k, v in rec.items()}
        record["runs"], record["runs_used"] = int(rec["runs"]), int(rec["runs_used"])
        ids, means = np.zeros(0, dtype=int), np.zeros(0)
        if per_run is not None:
            mine = per_run[(per_run["filter"] == name) & ~per_run["diverged"].astype(bool)]
            ids, means = mine["run"].to_numpy(int), mine["mean_nees"].to_numpy(float)
        filters.append(
            FilterSeries(
                name=name,
                kind=str(specs[name].get("kind", "?")),
                adapts=adapts_of(specs[name]),
                runs=record["runs"],
                runs_used=record["runs_used"],
                t=_NO_SERIES,
                pos=empty,
                heading=empty,
                nees=_NO_SERIES,
                nees_median=_NO_SERIES,
                bounds=(record["nees_lo"], record["nees_hi"]),
                noise={},
                summary=record,
                run_ids=ids,
                run_mean_nees=means,
                outliers=outlier_runs(ids, means),
            )  # fmt: skip
        )
    if not filters:
        raise ResultsError(f"{where}: holds no filters")
    return _scenario_data(folder, manifest, manifest_path, filters, None, per_run)


def _check_unique_names(scenarios: Sequence[ScenarioData | real.RealData]) -> None:
    """Figures are named after scenarios (simulated or recorded), so two results of one
    scenario would overwrite."""
    seen: dict[str, Path] = {}
    for sc in scenarios:
        if sc.slug in seen:
            raise ResultsError(
                f"{seen[sc.slug]} and {sc.folder} both hold scenario {sc.name!r};"
                " report them one at a time (with different --out folders)"
            )
        seen[sc.slug] = sc.folder


# --------------------------------------------------------------------------- tables


def noise_table(sc: ScenarioData) -> TableBlock:
    """The true noise against what the filters assume (the oracle EKF is given the truth)."""
    rows = []
    for key, what, unit in SIGMAS:
        true, assumed = getattr(sc.true_sigmas, key), getattr(sc.assumed_sigmas, key)
        rows.append(
            [
                Cell(f"{what} [{unit}]"),
                Cell(format_sig(true), true),
                Cell(format_sig(assumed), assumed),
                Cell(format_sig(assumed / true), assumed / true),
            ]
        )
    return TableBlock(("noise", "true", "assumed by the filters", "assumed / true"), rows,
                      (False, True, True, True))  # fmt: skip


def mismatch_sentence(sc: ScenarioData) -> str:
    """One sentence naming each sigma the filters get wrong, and by what factor."""
    wrong = []
    for key, what, unit in SIGMAS:
        true, assumed = getattr(sc.true_sigmas, key), getattr(sc.assumed_sigmas, key)
        if not math.isclose(true, assumed, rel_tol=1e-9):
            wrong.append(
                f"{what} {format_sig(assumed)} {unit} for a true {format_sig(true)} {unit}"
                f" ({format_sig(assumed / true)} x)"
            )
    oracle = first_with_role(sc, "oracle")
    given = f" `{oracle.name}` is given the true noise." if oracle else ""
    if not wrong:
        return "**Noise:** the filters assume the true noise (no mismatch)." + given
    return "**Noise mismatch:** the filters assume " + "; ".join(wrong) + "." + given


def per_run_table(sc: ScenarioData) -> TableBlock | None:
    """runs.parquet summarised per filter: the spread of the runs' own RMSE and mean NEES."""
    df = sc.per_run
    if df is None or len(df) == 0:
        return None
    rows = []
    lo_p, hi_p = BAND_PERCENTILES
    for f in sc.filters:
        sub = df[(df["filter"] == f.name) & ~df["diverged"].astype(bool)]
        if len(sub) == 0:
            continue
        rmse, nees = sub["rmse_pos"].to_numpy(float), sub["mean_nees"].to_numpy(float)
        lo, hi = np.percentile(rmse, BAND_PERCENTILES)
        worst = sub.iloc[int(np.nanargmax(nees))] if np.isfinite(nees).any() else None
        worst_text = (
            "-" if worst is None else f"{format_sig(float(worst.mean_nees))} (run {worst.run})"
        )
        outliers = ", ".join(str(r) for r in f.outliers[:8]) + (
            f" (+{len(f.outliers) - 8})" if len(f.outliers) > 8 else ""
        )
        rows.append(
            [
                Cell(f.name),
                Cell(format_sig(float(np.median(rmse))), float(np.median(rmse))),
                Cell(f"{format_sig(lo)} - {format_sig(hi)}", lo),
                Cell(format_sig(float(np.median(nees))), float(np.median(nees))),
                Cell(worst_text, None if worst is None else float(worst.mean_nees)),
                Cell(outliers or "none", len(f.outliers)),
            ]
        )
    header = (
        "filter", "run RMSE pos [m]: median", f"{lo_p:g}-{hi_p:g} % of runs",
        "run mean NEES: median", "worst run",
        f"outlier runs (mean NEES > {OUTLIER_FACTOR:g} x median)",
    )  # fmt: skip
    return TableBlock(header, rows, (False, True, True, True, True, False))


def claims_table(sc: ScenarioData) -> TableBlock | None:
    if not sc.claims:
        return None
    rows = []
    for c in sc.claims:
        r = Ratio(_float(c.get("estimate")), _float(c.get("lo")), _float(c.get("hi")), 0)
        rows.append(
            [
                Cell(str(c.get("claim", "?"))),
                Cell(format_ratio(r), r.estimate),
                Cell(str(c.get("verdict", "?"))),
                Cell(str(c.get("runs_used", "-")), _float(c.get("runs_used"))),
                Cell(str(c.get("source") or "")),
                Cell(str(c.get("warning") or "")),
            ]
        )
    header = ("claim", "estimate [95 % CI]", "verdict", "runs", "source", "warning")
    return TableBlock(header, rows, (False, True, False, True, False, False))


def scenario_warnings(sc: ScenarioData) -> list[str]:
    """What the reader must know before trusting this scenario's numbers."""
    out = []
    used = min(f.runs_used for f in sc.filters)
    if sc.few_runs:
        lo, hi = nees_bounds(used) if used else (math.nan, math.nan)
        out.append(
            f"{sc.name}: only {used} runs (fewer than {FEW_RUNS}): the 95 % NEES bounds"
            f" [{format_sig(lo)}, {format_sig(hi)}] are so wide that 'NEES in bounds' hardly"
            " discriminates, and the ratio intervals are wide; use more runs for conclusions."
        )
    for c in sc.claims:
        problem = claim_interval_problem(c)
        if problem:
            out.append(f"{sc.name}: claim '{c.get('claim', '?')}' ({c.get('verdict', '?')}):"
                       f" {problem}.")  # fmt: skip
    return out


def claim_interval_problem(claim: dict) -> str | None:
    """Why a claim's interval cannot support it (too wide: it straddles the threshold, or
    undefined), else None. A share decided on its point estimate has no interval to judge."""
    if claim.get("method") == "point":
        return None
    threshold = claim.get("at_most") if claim.get("at_most") is not None else claim.get("at_least")
    if threshold is None:
        return claim.get("warning") or None
    interval = Interval(_float(claim.get("estimate")), _float(claim.get("lo")),
                        _float(claim.get("hi")), 0.95, 0, str(claim.get("method", "")))  # fmt: skip
    return interval_too_wide(interval, float(threshold))


# --------------------------------------------------------------------------- the document


def figure_name(scenario: str, kind: str, fmt: ImageFormat) -> str:
    """File name of a scenario's figure (kind: rmse, nees, noise, map) or of the overview."""
    return f"{scenario}_{kind}.{fmt.value}" if scenario else f"{kind}.{fmt.value}"


INTRO = (
    "Generated by `anfekf report` from saved results only (steps.parquet, runs.parquet,"
    " comparisons.parquet, claims.json, manifest.json); nothing was re-run. RMSE: the time mean"
    " of the RMSE-over-runs curve `sqrt(mean_runs(ex² + ey²))`; ANEES: the time mean of the"
    " run-averaged NEES; *NEES in bounds*: the share of recorded steps whose run-averaged NEES"
    " lies strictly inside the two-sided 95 % chi-square bounds for the runs used. Ratios divide"
    " a filter's metric by the plain EKF's or by the oracle EKF's (the EKF given the true noise),"
    " paired over the runs neither diverged in, with a 95 % paired bootstrap interval in"
    " brackets (BCa, over runs). Diverged runs are left out of every mean. Angles are in degrees"
    " throughout. Numbers have 3 significant digits. An *outlier run* is one whose time-mean NEES"
    f" exceeds {OUTLIER_FACTOR:g} times the median run's; the figures mark them and show the"
    " median over runs beside the mean."
)

CAPTIONS = {
    "rmse": "Position and heading RMSE over time, and each filter's position RMSE divided by"
    " {ref}'s (log scale: the gap between lines that coincide above)",
    "nees": "Run-averaged NEES (solid) and median over runs (dotted) against the 95 % chi-square"
    " bounds{outliers}",
    "noise": "Adapted noise covariance (mean over runs solid, median dashed, 10-90 % band) against"
    " the true and the assumed value{outliers}",
    "map": "Map, true path and run {run}'s estimates with 3-sigma ellipses",
}


def _outlier_note(sc: ScenarioData) -> str:
    marked = [(f.name, f.outliers) for f in sc.filters if f.outliers]
    if not marked:
        return "; no outlier runs"
    parts = []
    for name, runs in marked:
        shown = ", ".join(str(r) for r in runs[:MAX_OUTLIERS_DRAWN])
        more = len(runs) - MAX_OUTLIERS_DRAWN
        parts.append(f"{name} run{'s' if len(runs) > 1 else ''} {shown}"
                     + (f" and {more} more" if more > 0 else ""))  # fmt: skip
    return "; outlier runs drawn thin: " + "; ".join(parts)


def caption(sc: ScenarioData, kind: str) -> str:
    ref = sc.reference()
    return CAPTIONS[kind].format(
        run=sc.track.run if sc.track is not None else "-",
        ref=f"`{ref.name}`" if ref else "the reference",
        outliers=_outlier_note(sc),
    )


OVERVIEW_CAPTION = (
    "Per scenario: each filter's position RMSE and ANEES divided by the oracle EKF's (log"
    " scale, 95 % paired bootstrap intervals as error bars) and its share of steps with NEES in"
    " the 95 % bounds"
)


def summary_blocks(
    scenarios: Sequence[ScenarioData], rows: Sequence[SummaryRow], save: plots.FigureSaver
) -> list[Block]:
    """The simulated scenarios side by side: warnings, the summary table, the leaderboard (when
    there is an oracle) and the overview figure."""
    fmt = ImageFormat(save.fmt)
    out: list[Block] = [Heading("Summary", anchor="summary")]
    out += [Warning(text) for sc in scenarios for text in scenario_warnings(sc)]
    out.append(summary_table(rows))
    if any(role_of(r.kind) == "oracle" for r in rows):
        name = figure_name("", "leaderboard", fmt)
        out += [Heading("Leaderboard", level=3, anchor="leaderboard"),
                save(summary_figures.leaderboard_figure(rows), name, LEADERBOARD_CAPTION),
                leaderboard_table(rows)]  # fmt: skip
    out.append(save(summary_figures.overview_figure(rows), figure_name("", "overview", fmt),
                    OVERVIEW_CAPTION))  # fmt: skip
    return out


def scenario_section(sc: ScenarioData, save: plots.FigureSaver, out_dir: Path) -> list[Block]:
    """A simulated scenario's part of the report: its noise, claims, runs, phases (a noise
    schedule, SPEC 14) and figures."""
    out: list[Block] = [Heading(sc.name, anchor=f"scenario-{sc.slug}")]
    if sc.description:
        out.append(Paragraph(sc.description))
    seed = f", seed {sc.seed}" if sc.seed is not None else ""
    link = Path(os.path.relpath(sc.folder.resolve(), Path(out_dir).resolve())).as_posix()
    out.append(Paragraph(f"{sc.runs} runs{seed}; results in [{link}]({link})."))
    out += [Paragraph(mismatch_sentence(sc)), noise_table(sc)]
    out += [Warning(text) for text in scenario_warnings(sc)]
    claims = claims_table(sc)
    if claims is not None:
        out += [Paragraph("**Claims** declared by the scenario, decided on the interval:"), claims]
    per_run = per_run_table(sc)
    if per_run is not None:
        out += [Paragraph("**Per run** (runs.parquet; diverged runs left out):"), per_run]
    if sc.phases is not None:  # the true noise changes (SPEC 14)
        out += [Paragraph("**Per phase** (phases.parquet; diverged runs left out):"),
                changing.phases_table(sc.phases)]  # fmt: skip
    if not sc.has_steps:
        return [*out, Paragraph(NO_STEPS_NOTE)]
    figures = scenario_figures(sc, save)
    for kind in ("rmse", "nees", "noise", "map"):
        block = figures.get(kind)
        if block is None and kind == "noise" and sc.schedule is not None:
            continue  # drawn against the true schedule below ("variances")
        if block is None:
            out.append(Paragraph(f"*{CAPTIONS[kind].split(' (')[0]}: no filter of this scenario"
                                 " adapts R or Q.*"))  # fmt: skip
        else:
            out.append(block)
    # a scenario with a noise schedule
    return out + [figures[kind] for kind in ("changes", "variances") if kind in figures]


ResultData = ScenarioData | real.RealData | sweep_report.SweepData


def section(result: ResultData, save: plots.FigureSaver, out_dir: Path) -> list[Block]:
    """One result folder's blocks, from the section builder of its source kind: a simulated
    scenario (with a noise schedule or not), a recorded log (segments or drives protocol) or a
    sweep."""
    if isinstance(result, real.RealData):
        return real.section(result, save)
    if isinstance(result, sweep_report.SweepData):
        return sweep_report.section(result, save)
    return scenario_section(result, save, out_dir)


# The groups after the simulated scenarios: their heading (text, anchor) before the first one.
GROUPS = ((real.RealData, "Real data", "real-data"), (sweep_report.SweepData, "Sweeps", "sweeps"))


def build_document(
    scenarios: Sequence[ScenarioData],
    rows: Sequence[SummaryRow],
    others: Sequence[ResultData],
    save: plots.FigureSaver,
    out_dir: Path,
    worst_case: Sequence[Block] = (),
) -> Document:
    """The report's content, once, for report.md and report.html: the simulated scenarios'
    summary, then one loop over the result folders (simulated, then recorded, then sweeps),
    each giving its section; the figures are saved through `save` on the way."""
    doc = Document("anfekf-bench report")
    doc.add(Paragraph(INTRO), Contents())
    if scenarios:
        doc.add(*summary_blocks(scenarios, rows, save))
    doc.add(*worst_case)  # the worst case over the scenarios (report/suite.py)
    drawn = _scenario_sections_in_workers(scenarios, save, out_dir)
    started = set()
    for i, result in enumerate([*scenarios, *others]):
        for kind, text, anchor in GROUPS:
            if isinstance(result, kind) and kind not in started:
                doc.add(Heading(text, anchor=anchor))
                started.add(kind)
        if i in drawn:
            blocks, files = drawn[i]
            save.files += files
            doc.add(*blocks)
        else:
            doc.add(*section(result, save, out_dir))
    return doc


# A report whose simulated scenarios hold at least this many (run, filter) series draws their
# sections in worker processes, one scenario each (the zoo: 6 x 1350, about 25 s of figures
# each); below, starting the workers would cost more than it saves.
PARALLEL_MIN_SERIES = 2000


def _series(sc: ScenarioData) -> int:
    return sc.runs * len(sc.filters)


def _scenario_sections_in_workers(
    scenarios: Sequence[ScenarioData], save: plots.FigureSaver, out_dir: Path
) -> dict[int, tuple[list[Block], list[Path]]]:
    """The sections of the simulated scenarios with steps (index -> (blocks, files saved)),
    drawn in parallel when the report is large (`PARALLEL_MIN_SERIES`); empty otherwise (then
    `build_document` draws every section itself). Each worker draws with this process's
    palette order (every scenario's filters are in it), so the files are the same bytes."""
    todo = [i for i, sc in enumerate(scenarios) if sc.has_steps]
    names, oracles = plots.palette_state()
    calls = [
        (_draw_section, scenarios[i], names, oracles, save.fmt, save.dpi, save.html, out_dir)
        for i in todo
    ]
    large = sum(_series(scenarios[i]) for i in todo) >= PARALLEL_MIN_SERIES
    drawn = _in_workers(calls, large, len(todo))
    return {} if drawn is None else dict(zip(todo, drawn, strict=True))


def _draw_section(
    sc: ScenarioData,
    names: list[str],
    oracles: list[str],
    fmt: str,
    dpi: int,
    html: bool,
    out_dir: Path,
) -> tuple[list[Block], list[Path]]:
    """A worker's part of `_scenario_sections_in_workers`: one scenario's section and files."""
    save = plots.FigureSaver(out_dir, fmt, dpi, html)
    with plots.palette(names, oracles):
        blocks = scenario_section(sc, save, out_dir)
    return blocks, save.files


# --------------------------------------------------------------------------- the command


def write_report(
    results_dirs: Sequence[Path],
    out_dir: Path,
    fmt: ImageFormat = ImageFormat.png,
    *,
    dpi: int = plots.DPI,
    html: bool = True,
    sweeps: Sequence[Path] = (),
    jobs: int = 1,
) -> ReportResult:
    """Read every result under `results_dirs` (scenarios, real data) and the `sweeps` folders,
    write their figures, and one report.md and report.html to `out_dir` covering all of them,
    with a table of contents.

    Everything is read (and checked) before anything is written, so bad input leaves no partial
    report behind. `jobs` > 1: the figures are drawn in up to that many worker processes
    (`render.figure_workers`), the same files; they are spawned, so a script that asks for
    them runs its work under `if __name__ == "__main__":`, as multiprocessing requires.
    """
    out_dir = Path(out_dir)
    fmt = ImageFormat(fmt)
    pool = render.render_pool(render.figure_workers(jobs))  # starts while the results load
    workers = 0 if pool is None else pool.workers  # none: every figure drawn here
    # Every result read (and checked) before anything is written: one loader for every kind.
    loaded = find_results(results_dirs, out_dir, sweeps)
    swept = [sweep_report.read_sweep(r.folder) for r in loaded if r.kind == SWEEP]
    problem_results = [read_problem_result(r.folder) for r in loaded if r.kind == PROBLEM]
    recorded = [real.load_real(r) for r in loaded if r.kind == RECORDED]
    folders = [r.folder for r in loaded if r.kind == SIMULATED]
    scenarios = load_scenarios(folders)
    _check_unique_names([*scenarios, *recorded])
    rows = summary_rows(scenarios)
    result = ReportResult(out_dir=out_dir, scenarios=scenarios, rows=rows, figure_workers=workers)
    result.warnings = [w for sc in scenarios for w in scenario_warnings(sc)]
    out_dir.mkdir(parents=True, exist_ok=True)
    save = plots.FigureSaver(out_dir, fmt.value, dpi, html, pool=pool)
    # Colours by the filters' order in this report: the same filter, the same colour throughout
    # (a recorded result's instances by the filter they were made from).
    names = [f.name for sc in scenarios for f in sc.filters]
    names += [f["base"] for rd in recorded for f in rd.instances()]
    oracles = [f.name for sc in scenarios for f in sc.filters if role_of(f.kind) == "oracle"]
    oracles += [f["base"] for rd in recorded for f in rd.instances()
                if role_of(f.get("kind")) == "oracle"]  # fmt: skip
    worst = suite_report.worst_case(scenarios, recorded)
    worst_blocks = () if worst is None else suite_report.blocks(worst, len(scenarios))
    try:
        with plots.palette(names, oracles):  # a sweep's filters in the scenarios' colours
            doc = build_document(scenarios, rows, [*recorded, *swept], save, out_dir, worst_blocks)
        doc.add(*problem_blocks(problem_results, save, fmt.value))
        doc.blocks = save.finish(doc.blocks)
    except KeyboardInterrupt:
        if pool is not None:
            pool.stop()  # the command ends: so do its workers, now
        raise
    except BaseException:
        save.cancel()  # the workers drop this report's figures
        raise
    result.problems = len(problem_results)
    result.files += save.files
    if worst is not None:
        result.files += suite_report.write_tables(worst, out_dir)
    outputs = {REPORT_FILE: to_markdown(doc)}
    if html:
        outputs[HTML_FILE] = to_html(doc)
    for name, text in outputs.items():
        path = out_dir / name
        write_atomic(path, lambda tmp, text=text: tmp.write_text(text, encoding="utf-8"))
        result.files.append(path)
    return result


def scenario_figures(sc: ScenarioData, save: plots.FigureSaver) -> dict[str, FigureBlock]:
    """A scenario's figures (kind -> block), saved with `save`."""
    fmt = ImageFormat(save.fmt)
    made: dict[str, FigureBlock] = {}
    label = f"{sc.name}: "
    made["rmse"] = save(plots.rmse_figure(sc), figure_name(sc.slug, "rmse", fmt),
                        label + caption(sc, "rmse"))  # fmt: skip
    made["nees"] = save(plots.nees_figure(sc), figure_name(sc.slug, "nees", fmt),
                        label + caption(sc, "nees"))  # fmt: skip
    # With a schedule the true noise is not one line: the variances figure draws it instead.
    if sc.adapted_columns and sc.schedule is None:
        made["noise"] = save(plots.noise_figure(sc), figure_name(sc.slug, "noise", fmt),
                             label + caption(sc, "noise"))  # fmt: skip
    made["map"] = save(plots.map_figure(sc), figure_name(sc.slug, "map", fmt),
                       label + caption(sc, "map"))  # fmt: skip
    if sc.schedule is not None:  # the true noise changes (SPEC 14)
        made["changes"] = save(
            changing.changes_figure(sc, sc.schedule),
            figure_name(sc.slug, "changes", fmt),
            label + "Position RMSE over time and its ratio to the oracle's, with the noise"
            " changes marked (dotted; blackouts shaded)",
        )
        fig = changing.variances_figure(sc, sc.schedule)
        if fig is not None:
            made["variances"] = save(
                fig,
                figure_name(sc.slug, "variances", fmt),
                label + "Variances of every filter that adapts them (mean over runs) against"
                " the true schedule (dashed)",
            )
    return made


def _scenario_data(
    folder: Path, manifest: dict, manifest_path: Path, filters: list, track, per_run
) -> ScenarioData:
    """A scenario's report data from its manifest and what was read of its tables."""
    scenario = manifest["scenario"]
    true_sigmas = _sigmas(manifest, "true_noise", manifest_path)
    return ScenarioData(
        name=str(scenario.get("name", folder.name)),
        description=str(scenario.get("description", "")),
        folder=folder,
        runs=max(f.runs for f in filters),
        seed=manifest.get("seed"),
        filters=filters,
        true_noise=true_variances(true_sigmas),
        landmarks=_points(manifest, "landmarks", manifest_path),
        waypoints=_points(manifest, "waypoints", manifest_path),
        track=track,
        true_sigmas=true_sigmas,
        assumed_sigmas=_sigmas(manifest, "filter_noise", manifest_path),
        comparisons=read_comparisons(folder),
        claims=read_claims(folder),
        per_run=per_run,
        schedule=changing.read_schedule(manifest, manifest_path),
        phases=changing.read_phases(folder),
    )
