"""What a report is drawn from: the data classes read from saved results and the constants the
figures and tables share. The lowest module of the report package: `report`, `plots` and
`changing` import it, it imports none of them (no import circle).
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..analysis.metrics import rmse_curve
from ..analysis.statistics import too_few_runs
from ..config import NoiseSigmas
from ..filters.registry import adapted_noise, role_of
from ..schedule import NoiseSchedule

BAND_PERCENTILES = (10.0, 90.0)  # the shaded band: this spread of the per-run values over runs
ELLIPSE_COUNT = 8  # 3-sigma ellipses along run 0's path, evenly spaced in time
REPORT_FILE = "report.md"
HTML_FILE = "report.html"
# An outlier run: its time-mean NEES exceeds this many times the median run's (of the same
# filter). One such run can move the run-averaged NEES (and the mean adapted noise) far from
# where the other runs are; the figures mark them and show the median beside the mean.
OUTLIER_FACTOR = 5.0
MAX_OUTLIERS_DRAWN = 3  # per filter, the worst ones
FEW_RUNS = 10  # below this, intervals are wide and the NEES bounds hardly discriminate

_DEG2 = (180.0 / math.pi) ** 2
# The adapted covariance diagonals in steps.parquet: what they mean, the unit they are shown in,
# and the factor from the stored unit (angles are stored in rad², shown in deg² like every other
# angle of the report).
NOISE_COLUMNS: dict[str, tuple[str, str, float]] = {
    "R_rr": ("R range variance", "m²", 1.0),
    "R_bb": ("R bearing variance", "deg²", _DEG2),
    "Q_vv": ("Q speed variance", "(m/s)²", 1.0),
    "Q_gg": ("Q steering variance", "deg²", _DEG2),
}
# What each adapted noise (registry.adapted_noise: "R", "Q"; "P" has no column) shows as.
_ADAPTED = {"R": ("R_rr", "R_bb"), "Q": ("Q_vv", "Q_gg")}
_NEEDED_COLUMNS = {
    "t", "x_true", "y_true", "x_est", "y_est", "P_xx", "P_xy", "P_yy", "heading_err", "diverged",
    *NOISE_COLUMNS,
}  # fmt: skip
# The noise a scenario states, in the units of its YAML keys.
SIGMAS = (
    ("sigma_v", "speed σv", "m/s"),
    ("sigma_gamma_deg", "steering σγ", "deg"),
    ("sigma_range", "range σr", "m"),
    ("sigma_bearing_deg", "bearing σb", "deg"),
)


@dataclass(frozen=True)
class Band:
    """A curve over time with the spread over runs around it (all arrays of length steps)."""

    line: np.ndarray  # the mean over runs (RMSE over runs for errors)
    lo: np.ndarray
    hi: np.ndarray
    median: np.ndarray  # the median over runs: what a typical run does


@dataclass(frozen=True)
class RunSeries:
    """One quantity of one filter over time, run by run, each run on its own time axis: the
    series type of every figure over time, whatever the source. A simulated scenario's runs
    share one time axis (`aligned`); a recorded result's segments and drives are ragged (of
    different lengths, at different log times: `of_steps`). `band` gives the per-step
    statistics over the runs present at each step; `joined` every run as one line, broken
    between runs."""

    runs: tuple[int, ...]
    t: tuple[np.ndarray, ...]  # per run [s]
    values: tuple[np.ndarray, ...]  # per run, the same length as its t
    axis: np.ndarray | None = None  # the time axis the runs share (`aligned`), even with no run

    @classmethod
    def aligned(cls, t: np.ndarray, values: np.ndarray, runs=None) -> RunSeries:
        """(runs, steps) `values` on one time axis `t` (a simulated scenario's runs)."""
        values = np.asarray(values, dtype=float)
        runs = range(len(values)) if runs is None else runs
        t = np.asarray(t, dtype=float)
        return cls(tuple(int(r) for r in runs), (t,) * len(values), tuple(values), t)

    @classmethod
    def of_steps(cls, steps: pd.DataFrame, column: str, time: str = "t") -> RunSeries:
        """Column `column` of one filter's rows of a steps table, run by run, over its column
        `time` (rows in step order; rows with no time left out)."""
        runs, ts, vs = [], [], []
        for run, g in steps.groupby("run", sort=True):
            runs.append(int(run))
            ts.append(g[time].to_numpy(dtype=float))
            vs.append(g[column].to_numpy(dtype=float))
        return cls(tuple(runs), tuple(ts), tuple(vs))

    def map(self, fn) -> RunSeries:
        """The same runs with `fn` applied to their values (a unit, a square root)."""
        return RunSeries(self.runs, self.t, tuple(fn(v) for v in self.values), self.axis)

    def run(self, run: int) -> RunSeries:
        """Run `run` alone."""
        i = self.runs.index(run)
        return RunSeries((run,), (self.t[i],), (self.values[i],))

    @property
    def ragged(self) -> bool:
        return len({len(v) for v in self.values}) > 1

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(t, (runs, steps) values) by step index: the longest run's time axis, shorter runs
        padded with NaN (no value there)."""
        if self.axis is not None:
            t = self.axis
        else:
            t = max(self.t, key=len, default=np.zeros(0))
        out = np.full((len(self.values), len(t)), np.nan)
        for i, v in enumerate(self.values):
            out[i, : len(v)] = v
        return t, out

    def present(self) -> np.ndarray:
        """How many runs have a value at each step."""
        return np.sum(~np.isnan(self.grid()[1]), axis=0)

    def band(self, rms: bool = False) -> Band:
        """Per step, over the runs present there: the mean (`rms`: the root mean square, the
        RMSE over runs of an error) with the BAND_PERCENTILES band and the median. Runs of one
        length: numpy's plain statistics (a NaN value stays NaN); ragged runs: the padding is
        left out (a step's statistics are over the runs that reach it)."""
        _, values = self.grid()
        if len(values) == 0:
            empty = np.full(values.shape[1], np.nan)
            return Band(empty, empty, empty, empty)
        if self.ragged:
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a step no run reaches
                lo, hi = np.nanpercentile(values, BAND_PERCENTILES, axis=0)
                median = np.nanmedian(values, axis=0)
                line = rmse_curve(values) if rms else np.nanmean(values, axis=0)
            return Band(line, lo, hi, median)
        lo, hi = np.percentile(values, BAND_PERCENTILES, axis=0)
        line = rmse_curve(values) if rms else values.mean(axis=0)
        return Band(line, lo, hi, np.median(values, axis=0))

    def joined(self) -> tuple[np.ndarray, np.ndarray]:
        """(t, values) of every run in order, a NaN after each run, so that a line drawn
        through them does not join one run to the next."""
        gap = np.full(1, np.nan)
        t = [a for ti in self.t for a in (ti, gap)]
        v = [a for vi in self.values for a in (vi, gap)]
        return (np.concatenate(t), np.concatenate(v)) if t else (np.zeros(0), np.zeros(0))


@dataclass(frozen=True)
class FilterSeries:
    """Everything the figures show about one filter of one scenario (diverged runs left out)."""

    name: str
    kind: str  # ekf, ekf-oracle, anfekf, ...
    adapts: frozenset[str]  # noise it adapts: "R", "Q" (Qu), "P" (registry.adapted_noise)
    runs: int
    runs_used: int
    t: np.ndarray  # [s]
    pos: Band  # line: RMSE over runs [m]; band: percentiles of the per-run position error
    heading: Band  # as pos, in degrees
    nees: np.ndarray  # run-averaged NEES
    nees_median: np.ndarray  # median over runs of the NEES at each step
    bounds: tuple[float, float]  # two-sided 95 % chi-square bounds for runs_used runs
    noise: dict[str, Band]  # R/Q diagonal column -> mean over runs and percentiles (shown unit)
    summary: dict  # summarize_filter's record: rmse_pos, rmse_heading, anees, nees_in_bounds, ...
    run_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))  # kept runs
    run_mean_nees: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per kept run
    outliers: tuple[int, ...] = ()  # run ids, worst first (see OUTLIER_FACTOR)
    outlier_nees: dict[int, np.ndarray] = field(default_factory=dict)  # drawn outliers' NEES
    outlier_noise: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)


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
class Ratio:
    """A paired ratio of comparisons.parquet: filter / vs with its 95 % bootstrap interval."""

    estimate: float
    lo: float
    hi: float
    runs_used: int
    p_value: float = math.nan

    @property
    def has_interval(self) -> bool:
        return math.isfinite(self.lo) and math.isfinite(self.hi)


@dataclass(frozen=True)
class ScenarioData:
    """One result folder, reduced to the series the report draws."""

    name: str
    description: str
    folder: Path
    runs: int
    seed: int | None
    filters: list[FilterSeries]
    true_noise: dict[str, float]  # noise column -> true variance in that column's shown unit
    landmarks: np.ndarray  # (n, 2) [m]
    waypoints: np.ndarray  # (m, 2) [m]
    track: Track | None  # None: the result has no steps.parquet (steps_table: false)
    true_sigmas: NoiseSigmas = NoiseSigmas()
    assumed_sigmas: NoiseSigmas = NoiseSigmas()
    # (filter, vs, metric) -> ratio, from comparisons.parquet (empty for results without it)
    comparisons: dict[tuple[str, str, str], Ratio] = field(default_factory=dict)
    claims: list[dict] = field(default_factory=list)  # claims.json
    per_run: pd.DataFrame | None = None  # runs.parquet, when the results have it
    schedule: NoiseSchedule | None = None  # the true noise's schedule (SPEC 14), if any
    phases: pd.DataFrame | None = None  # phases.parquet, when the results have it

    @property
    def slug(self) -> str:
        """The scenario name made safe for file names."""
        return re.sub(r"[^A-Za-z0-9_.-]", "_", self.name) or "scenario"

    @property
    def adapted_columns(self) -> list[str]:
        """The R/Q diagonal columns some filter adapts, in NOISE_COLUMNS order."""
        wanted = {c for f in self.filters for a in f.adapts for c in _ADAPTED.get(a, ())}
        return [c for c in NOISE_COLUMNS if c in wanted]

    def reference(self) -> FilterSeries | None:
        """The filter ratios are taken against: the oracle EKF, else the plain EKF."""
        return first_with_role(self, "oracle") or first_with_role(self, "reference")

    def ratio(self, name: str, ref: FilterSeries | None, metric: str = "rmse_pos") -> Ratio | None:
        """filter `name` / `ref` on `metric`: the saved paired comparison (with its interval),
        else the ratio of the two summaries (no interval); None without a reference."""
        if ref is None or ref.name == name:
            return None
        saved = self.comparisons.get((name, ref.name, metric))
        if saved is not None:
            return saved
        f = next(f for f in self.filters if f.name == name)
        num, den = f.summary.get(metric, math.nan), ref.summary.get(metric, math.nan)
        value = num / den if den and math.isfinite(den) else math.nan
        return Ratio(value, math.nan, math.nan, min(f.runs_used, ref.runs_used))

    @property
    def has_steps(self) -> bool:
        """Whether the result has steps.parquet (the figures over time need it)."""
        return self.track is not None

    @property
    def few_runs(self) -> bool:
        return too_few_runs(min(f.runs_used for f in self.filters), FEW_RUNS)


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
    # Paired ratios with their 95 % intervals (comparisons.parquet); None for the reference
    # itself or without that reference.
    rmse_vs_ekf: Ratio | None = None
    rmse_vs_oracle: Ratio | None = None
    anees_vs_oracle: Ratio | None = None
    outliers: tuple[int, ...] = ()
    ekf_name: str = "ekf"
    oracle_name: str = "ekf-oracle"


def first_with_role(sc: ScenarioData, role: str) -> FilterSeries | None:
    """The scenario's first filter whose kind has `role` (registry.role_of: "reference", the
    plain EKF; "oracle"), or None."""
    return next((f for f in sc.filters if role_of(f.kind) == role), None)


def adapts_of(spec: dict, noise=None) -> frozenset[str]:
    """What a filter adapts ("R", "Q", "P"), for every source: as the registry says for its
    kind and parameters; for a filter the spec cannot tell about (a custom class, a kind this
    version does not know), the noise whose recorded R/Qu columns vary (`noise`: column ->
    values over its runs and steps, or a function giving them, called only then)."""
    declared = adapted_noise(spec)
    if declared is not None:
        return frozenset(declared)
    noise = noise() if callable(noise) else noise
    return frozenset(a for a, cols in _ADAPTED.items() if any(_varies(noise, c) for c in cols))


def _varies(noise: dict[str, np.ndarray] | None, col: str) -> bool:
    values = None if noise is None else noise.get(col)
    if values is None or np.size(values) == 0:
        return False
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    # a relative change well above rounding: a fixed filter stores one value for every step
    return finite.size > 1 and float(finite.max() - finite.min()) > 1e-9 * float(
        np.abs(finite).max()
    )
