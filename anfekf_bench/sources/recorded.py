"""Real-data scenarios (SPEC 9): a scenario file that names a recorded log instead of a world.

A document with a `data:` key is a `RecordedScenario`, the recorded member of the scenario's
source union (`config.Scenario` declares the keys every scenario has; `scenarios.load_scenario`
validates and resolves it):

    name: mrclam-d9
    data: {kind: mrclam, path: builtin}       # or {kind: log, path: my-log/} (docs/REAL_DATA.md)
    split_fraction: 0.5                        # training part | held-out part
    segment_s: 60                              # held-out (and training) segments [s]
    naive: {sigma_v: 0.1, sigma_w_rad: 0.1, sigma_range: 0.1, sigma_bearing_rad: 0.05}
    starts: [0.25, 1, 4]                       # each filter runs once per start
    filters:
      - {name: ekf, kind: ekf}
      - {name: ekf-tuned, kind: ekf-tuned}
      - {name: anfekf, kind: anfekf, adapt: RQ}

Angles of this block are in radians, as their keys say (`_rad`): the unit of the data and of the
research notes. Every filter but `ekf-tuned` and `ekf-ml` runs once per naive start m, as the
instance `"<name> x<m>"` (e.g. `anfekf x0.25`), starting from the naive standard deviations times m
(the variances times m^2). `ekf-tuned` is the fixed EKF whose noise the grid search on the training
part chose (`TuningConfig`, fitting.recorded.tune); `ekf-ml` the fixed EKF whose noise maximises the
innovation likelihood of the very run it is scored on (its own odometry and landmarks, never its
ground truth: fitting.own.fit_on_own_innovations); both run once, without naive starts.
Resolving the file reads the log and cuts it (`Recording`): nothing is run here.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, ClassVar, Literal, Union

import numpy as np
from pydantic import Field, field_serializer, field_validator, model_validator

from ..config import Scenario, ScenarioError, Start, validate_as
from ..filters.fitted import EKFTunedSpec
from ..filters.registry import SPECS
from ..filters.spec import FilterSpec
from ..schema import PositiveFloat, StrictModel
from . import mrclam, user_log

BUILTIN = "builtin"
# The noise a recorded fit of a fixed EKF gives (the grid search, a run's own innovations)
NOISE_KEYS = ("sigma_v", "sigma_w_rad", "sigma_range", "sigma_bearing_rad")


# The kinds a recorded log can run: every kind not fitted before the batch, and the fitted and
# trained kinds whose spec declares a fit on recorded runs (fitting.fit): ekf-tuned by the grid
# search on the training segments or other drives ("recorded"), ekf-ml on each run's own
# innovations ("own": no truth needed, fitting.own.fit_on_own_innovations), KalmanNet trained on
# the training drives or segments ("recorded", fitting.recorded).
RECORDED_FITS = frozenset({"recorded", "own"})
REAL_SPECS: tuple[type[FilterSpec], ...] = tuple(
    s for s in SPECS if not s.fitted_on_training or s.fit_sources & RECORDED_FITS
)
REAL_KINDS = tuple(s.model_fields["kind"].annotation.__args__[0] for s in REAL_SPECS)
RealFilterSpec = Annotated[Union[REAL_SPECS], Field(discriminator="kind")]  # noqa: UP007


class DataConfig(StrictModel):
    """Where the log comes from."""

    kind: Literal["mrclam", "log"] = Field(
        "mrclam",
        description="mrclam: UTIAS MRCLAM (the built-in copy, or a folder of its .dat files);"
        " log: a folder in the user-log schema (docs/REAL_DATA.md)",
    )
    path: str = Field(
        BUILTIN, min_length=1, description="'builtin' (mrclam only) or a folder, relative to the"
        " scenario file",
    )  # fmt: skip
    robot: Annotated[int, Field(ge=1, le=5)] | None = Field(
        None, description="mrclam folder of the whole dataset: read Robot<k>_*.dat"
    )
    drive: str | None = Field(
        None, description="path builtin: which built-in drive (d6-r1 .. d7-r5, d9-r3; default"
        " d9-r3)",
    )  # fmt: skip
    drives: list[str] | None = Field(
        None, min_length=2, description="path builtin, protocol drives: the built-in drives,"
        " each one run scored whole (d6-r1 .. d7-r5, d9-r3)",
    )  # fmt: skip

    @model_validator(mode="after")
    def _builtin_is_mrclam(self) -> DataConfig:
        if self.path == BUILTIN and self.kind != "mrclam":
            raise ValueError("path 'builtin' is the MRCLAM copy: use kind mrclam, or a folder")
        if self.robot is not None and (self.kind != "mrclam" or self.path == BUILTIN):
            raise ValueError("robot selects Robot<k>_*.dat in an MRCLAM folder only")
        if (self.drive is not None or self.drives is not None) and self.path != BUILTIN:
            raise ValueError("drive and drives name built-in drives: use path builtin")
        if self.drive is not None and self.drives is not None:
            raise ValueError("give drive (one log) or drives (the cross-drive protocol), not both")
        for d in [self.drive] if self.drive is not None else self.drives or []:
            if d not in mrclam.DRIVES:
                raise ValueError(f"unknown drive {d!r} (built-in: {', '.join(mrclam.DRIVES)})")
        if self.drives is not None and len(set(self.drives)) != len(self.drives):
            raise ValueError("a drive is listed twice")
        return self


class NaiveNoise(StrictModel):
    """The naive guess every start scales (research notes: the prototype's values).

    sigma_v [m/s] and sigma_w_rad [rad/s] are per odometry step of `odometry_period_s` (the
    Unicycle's rate-consistent Qu); sigma_range [m], sigma_bearing_rad [rad].
    """

    sigma_v: Annotated[PositiveFloat, Field(le=1e3)] = 0.1
    sigma_w_rad: Annotated[PositiveFloat, Field(le=1e3)] = 0.1
    sigma_range: Annotated[PositiveFloat, Field(le=1e3)] = 0.1
    sigma_bearing_rad: Annotated[PositiveFloat, Field(le=1e3)] = 0.05

    def sigmas(self) -> np.ndarray:
        """(sv, sw, sr, sb)."""
        return np.array([self.sigma_v, self.sigma_w_rad, self.sigma_range, self.sigma_bearing_rad])


Exponents = tuple[Annotated[float, Field(ge=-20, le=20)], Annotated[float, Field(ge=-20, le=20)]]


class TuningConfig(StrictModel):
    """The grid search behind `ekf-tuned` (fitting.recorded.tune).

    Coarse stage: every combination of multipliers 2^e of the naive standard deviations, e from
    the first to the last exponent of each range in steps of 1 (the research notes' grid:
    10 x 10 x 6 x 6 = 3,600 settings). Refinement (`refine`): the 3^4 settings around the best
    one with steps of 2^(1/2), then again with 2^(1/4). Criterion: the position RMSE over every
    scorable evaluation time of the training segments (pooled); a setting that loses lock scores
    high and one whose estimate stops being finite scores infinite.
    """

    sigma_v: Exponents = (-4, 5)
    sigma_w: Exponents = (-4, 5)
    sigma_range: Exponents = (-3, 2)
    sigma_bearing: Exponents = (-3, 2)
    refine: bool = True

    @model_validator(mode="after")
    def _ordered(self) -> TuningConfig:
        for key in ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing"):
            lo, hi = getattr(self, key)
            if lo > hi:
                raise ValueError(f"{key}: the first exponent must not exceed the last")
            if hi - lo > 40:
                raise ValueError(f"{key}: at most 41 exponents")
        return self

    def axes(self) -> list[np.ndarray]:
        """The exponent values of each of (sv, sw, sr, sb)."""
        return [
            np.arange(lo, hi + 0.5)
            for lo, hi in (self.sigma_v, self.sigma_w, self.sigma_range, self.sigma_bearing)
        ]

    def size(self) -> int:
        return int(np.prod([len(a) for a in self.axes()]))


MAX_GRID = 20_000


class RecordedScenario(Scenario):
    """A scenario whose runs come from a recorded log (see the module doc): the held-out
    segments of one log (protocol segments) or whole drives (protocol drives)."""

    source: ClassVar[Literal["recorded"]] = "recorded"
    spec_by_kind: ClassVar[dict[str, type[FilterSpec]]] = dict(
        zip(REAL_KINDS, REAL_SPECS, strict=True)
    )
    sweep: ClassVar[None] = None  # a recorded scenario is not a sweep (config.SweepSpec)

    # Narrowed: the kinds a recorded log can run, and other defaults (`config.Scenario`).
    filters: list[RealFilterSpec] = Field(
        default_factory=lambda: [EKFTunedSpec(name="ekf-tuned", kind="ekf-tuned")], min_length=1
    )
    starts: list[Start] = Field(
        [0.25, 1.0, 4.0], min_length=1, max_length=20,
        description="multipliers of the naive standard deviations each filter starts from",
    )  # fmt: skip
    data: DataConfig
    split_fraction: Annotated[float, Field(gt=0, lt=1)] = Field(
        0.5, description="training part: this share of the ground-truth span, from its start"
    )
    split_at_s: PositiveFloat | None = Field(
        None, description="split this many seconds after the first ground-truth stamp instead"
    )
    segment_s: PositiveFloat = Field(
        60.0,
        ge=1.0,  # shorter segments are mostly cold start, and their count would explode
        le=1e6,
        description="segment length [s] of both parts; each segment is cold-started",
    )
    min_scorable_s: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(
        10.0, description="segments with less scorable ground truth are left out"
    )
    max_gap_s: PositiveFloat = Field(0.5, description="Vicon gaps longer than this are not scored")
    misfit_detection: bool = Field(
        True, description="leave out detected Vicon mis-fits (mrclam.MisfitRule); false for a"
        " robot that reverses",
    )  # fmt: skip
    odometry_period_s: PositiveFloat = Field(
        0.12, description="T0 of the Unicycle: the step the naive sigma_v, sigma_w refer to"
    )
    naive: NaiveNoise = NaiveNoise()
    tuning: TuningConfig = TuningConfig()
    # Bounded so that the variances (squares, then times the starts) stay finite.
    p0_std_xy: PositiveFloat = Field(0.05, le=1e4, description="initial std of x and y [m]")
    p0_std_phi_rad: PositiveFloat = Field(
        0.05, le=1e3, description="initial std of the heading [rad]"
    )
    protocol: Literal["segments", "drives"] = Field(
        "segments", description="segments: one log split into training and held-out segments;"
        " drives: every drive of data.drives is one run, scored whole from its ground-truth"
        " start, ekf-tuned tuned on the drives of other datasets (tune_on)",
    )  # fmt: skip
    tune_on: dict[int, list[int]] | None = Field(
        None, description="protocol drives: dataset -> the datasets whose drives tune its"
        " ekf-tuned (default: every other dataset of data.drives)",
    )  # fmt: skip
    eval_period_s: PositiveFloat | None = Field(
        None, description="score at odometry stamps at least this far apart (null: every"
        " stamp); the filters still run on every event",
    )  # fmt: skip

    @model_validator(mode="after")
    def _drives_protocol(self) -> RecordedScenario:
        drives = self.data.drives
        if self.protocol == "segments":
            if drives is not None or self.tune_on is not None:
                raise ValueError("data.drives and tune_on belong to protocol drives")
            return self
        if drives is None:
            raise ValueError("protocol drives needs data.drives (the built-in drives to run)")
        datasets = {mrclam.drive_dataset(d) for d in drives}
        for ds, sources in (self.tune_on or {}).items():
            if ds not in datasets or not set(sources) <= datasets or not sources:
                raise ValueError(
                    f"tune_on: {ds}: datasets must be among data.drives'"
                    f" ({', '.join(map(str, sorted(datasets)))})"
                )
            if ds in sources:
                raise ValueError(f"tune_on: {ds}: a dataset is never tuned on its own drives")
        if self.reference() is not None and any(not self.tuning_sources(ds) for ds in datasets):
            raise ValueError("protocol drives: ekf-tuned needs drives of another dataset")
        return self

    def tuning_sources(self, dataset: int) -> list[int]:
        """protocol drives: the datasets whose drives tune `dataset`'s ekf-tuned."""
        if self.tune_on is not None and dataset in self.tune_on:
            return sorted(self.tune_on[dataset])
        datasets = {mrclam.drive_dataset(d) for d in self.data.drives or []}
        return sorted(datasets - {dataset})

    @field_validator("tuning")
    @classmethod
    def _grid_size(cls, tuning: TuningConfig) -> TuningConfig:
        if tuning.size() > MAX_GRID:
            raise ValueError(f"the coarse grid has {tuning.size()} settings; at most {MAX_GRID}")
        return tuning

    @field_validator("filters")
    @classmethod
    def _filters(cls, filters: list) -> list:
        if any(f.role == "oracle" for f in filters):
            raise ValueError("ekf-oracle needs the true noise, which a recorded log does not have")
        if sum(isinstance(f, EKFTunedSpec) for f in filters) > 1:
            raise ValueError("at most one ekf-tuned filter (the reference)")
        for i, f in enumerate(filters):
            for key in sorted(set(getattr(f, "simulated_only", ())) & f.model_fields_set):
                raise ValueError(
                    f"filters.{i}.{key}: not for a recorded log: its {f.kind} is fitted by the"
                    " grid search of `tuning:`"
                )
        return filters

    @field_serializer("filters", mode="wrap")
    def _without_simulated_fields(self, filters: list, handler) -> list:
        """The filters as written, less the fields of a simulated fit (refused above, so
        only their defaults): the manifest and the run store's fingerprint hold what a
        recorded log's filters use."""
        out = handler(filters)
        for spec, doc in zip(filters, out, strict=True):
            for key in getattr(spec, "simulated_only", ()):
                doc.pop(key, None)
        return out

    def reference(self) -> str | None:
        """The instance every other is compared with: the ekf-tuned filter, if any."""
        return next((f.name for f in self.filters if isinstance(f, EKFTunedSpec)), None)


# --------------------------------------------------------------------------------------------
# Validation with one-line errors


def parse_real_scenario(data: dict, path: str | Path = "<scenario>") -> RecordedScenario:
    """Validate a recorded scenario's document; ScenarioError (one line) if it is not valid."""
    return validate_as(RecordedScenario, data, path)


# --------------------------------------------------------------------------------------------
# The resolved log: spans, segments, cold starts


@dataclass(frozen=True)
class Segment:
    """One part of the log run on its own: [start, end], cold-started from ground truth at t0
    (the first scorable time at or after `start`) with `pose`."""

    index: int
    start: float
    end: float
    t0: float
    pose: np.ndarray
    scorable_s: float

    def as_dict(self) -> dict:
        return {
            "index": self.index, "start": self.start, "end": self.end, "t0": self.t0,
            "pose": [float(v) for v in self.pose], "scorable_s": self.scorable_s,
        }  # fmt: skip


@dataclass(frozen=True, eq=False)
class Recording:
    """A real-data scenario's log, resolved: where scoring is allowed, the two parts, segments.

    `landmarks` (the map, (n, 2)) and `waypoints` (empty) stand where a simulated world has them.
    """

    log: mrclam.RobotLog
    source: str
    exclusions: mrclam.Exclusions
    misfit: mrclam.MisfitRule | None
    train: mrclam.Span
    held_out: mrclam.Span
    train_segments: list[Segment]
    test_segments: list[Segment]
    digest: str

    @property
    def landmarks(self) -> np.ndarray:
        return np.column_stack([self.log.landmark_x, self.log.landmark_y])

    @property
    def waypoints(self) -> np.ndarray:
        return np.zeros((0, 2))

    def scorable(self, t) -> np.ndarray:
        return self.exclusions.scorable(t)

    def summary(self) -> dict:
        """What the manifest says about the data."""
        ex = self.exclusions
        return {
            "source": self.source,
            "log": self.log.name,
            "digest": self.digest,
            "t_origin": self.log.t_origin,
            "span": [self.log.t_start, self.log.t_end],
            "counts": self.log.counts(),
            "gaps": ex.gaps.tolist(),
            "misfits": ex.misfits.tolist(),
            "train": [self.train.start, self.train.end],
            "held_out": [self.held_out.start, self.held_out.end],
            "train_scorable_s": ex.scorable_seconds(self.train.start, self.train.end),
            "held_out_scorable_s": ex.scorable_seconds(self.held_out.start, self.held_out.end),
            "train_segments": [s.as_dict() for s in self.train_segments],
            "segments": [s.as_dict() for s in self.test_segments],
            "landmarks": {
                "id": self.log.landmark_id.tolist(),
                "x": self.log.landmark_x.tolist(),
                "y": self.log.landmark_y.tolist(),
            },
        }


def log_digest(log: mrclam.RobotLog) -> str:
    """SHA-256 (16 hex digits) of a log's arrays: a resumed batch must see the same data."""
    h = hashlib.sha256()
    for name in (
        "odo_t odo_v odo_w meas_t meas_landmark meas_range meas_bearing landmark_id landmark_x "
        "landmark_y truth_t truth_x truth_y truth_phi"
    ).split():
        a = np.ascontiguousarray(getattr(log, name))
        h.update(name.encode() + str(a.dtype).encode() + a.tobytes())
    return h.hexdigest()[:16]


def read_log(cfg: DataConfig, scenario_path: Path) -> tuple[mrclam.RobotLog, str]:
    """The log a scenario names, and a description of where it came from."""
    if cfg.path == BUILTIN and cfg.drive is not None:
        return mrclam.load_drive(cfg.drive), f"built-in drive {cfg.drive}"
    if cfg.path == BUILTIN:
        return mrclam.load_builtin(), f"built-in {mrclam.BUILTIN_NAME}"
    folder = Path(cfg.path)
    if not folder.is_absolute():
        folder = scenario_path.parent / folder
    if cfg.kind == "mrclam":
        return mrclam.read_mrclam(folder, robot=cfg.robot), f"MRCLAM folder {cfg.path}"
    return user_log.read_user_log(folder), f"log folder {cfg.path}"


def cut_segments(
    log: mrclam.RobotLog,
    span: mrclam.Span,
    length_s: float,
    ex: mrclam.Exclusions,
    misfit: mrclam.MisfitRule | None,
    min_scorable_s: float,
) -> list[Segment]:
    """`mrclam.segments` of a span, each with its cold start; segments with less than
    `min_scorable_s` of scorable ground truth (or none after their start) are left out."""
    out = []
    for seg in mrclam.segments(span.start, span.end, length_s):
        scorable_s = ex.scorable_seconds(seg.start, seg.end)
        if scorable_s < max(min_scorable_s, 1e-9):
            continue
        try:
            t0, pose = mrclam.cold_start(log, seg.start, ex.max_gap_s, misfit)
        except ValueError:
            continue
        if t0 >= seg.end:
            continue
        out.append(Segment(len(out), seg.start, seg.end, t0, pose, scorable_s))
    return out


def resolve_recording(scenario: RecordedScenario, scenario_path: Path) -> Recording:
    """Read the log and cut it; ScenarioError (one line) if it cannot be used."""
    try:
        log, source = read_log(scenario.data, scenario_path)
    except mrclam.LogError as exc:
        raise ScenarioError(scenario_path, "data", str(exc)) from None
    misfit = mrclam.MisfitRule() if scenario.misfit_detection else None
    ex = mrclam.exclusions(log, scenario.max_gap_s, misfit)
    if scenario.split_at_s is not None:
        at = log.t_start + scenario.split_at_s
        field = "split_at_s"
    else:
        at = log.t_start + scenario.split_fraction * (log.t_end - log.t_start)
        field = "split_fraction"
    try:
        train, held_out = mrclam.split(log, at)
    except ValueError as exc:
        raise ScenarioError(scenario_path, field, str(exc)) from None
    parts = {}
    for name, span in (("training", train), ("held-out", held_out)):
        parts[name] = cut_segments(
            log, span, scenario.segment_s, ex, misfit, scenario.min_scorable_s
        )
        if not parts[name]:
            raise ScenarioError(
                scenario_path,
                "segment_s",
                f"the {name} part ({span.start:.1f}-{span.end:.1f} s) has no segment with"
                f" {scenario.min_scorable_s:g} s of scorable ground truth",
            )
    return Recording(
        log=log,
        source=source,
        exclusions=ex,
        misfit=misfit,
        train=train,
        held_out=held_out,
        train_segments=parts["training"],
        test_segments=parts["held-out"],
        digest=log_digest(log),
    )


def resolve_scenario_log(scenario: RecordedScenario, path: str | Path) -> Recording | DriveSet:
    """The log a recorded scenario names, read and cut: its segments (protocol segments) or its
    drives (protocol drives); ScenarioError (one line) if it cannot be used."""
    if scenario.protocol == "drives":
        return resolve_drives(scenario)
    return resolve_recording(scenario, Path(path))


# --------------------------------------------------------------------------------------------
# The cross-drive protocol (SPEC 15): every drive one run, scored whole


@dataclass(frozen=True, eq=False)
class Drive:
    """One built-in drive as one run: cold-started from ground truth at its first scorable time,
    scored over its whole ground-truth span (never after its last ground-truth stamp: Dataset 6
    Robot 1's Vicon ends 128 s before its odometry). `log` and `scorable` stand where a
    `Recording` has them, so `real_experiment.segment_inputs` reads either."""

    id: str
    dataset: int
    log: mrclam.RobotLog
    exclusions: mrclam.Exclusions
    segment: Segment

    def scorable(self, t) -> np.ndarray:
        return self.exclusions.scorable(t)


@dataclass(frozen=True, eq=False)
class DriveSet:
    """A cross-drive scenario's drives, resolved (the runs, in `data.drives` order)."""

    drives: list[Drive]
    misfit: mrclam.MisfitRule | None
    digest: str

    @property
    def test_segments(self) -> list[Segment]:
        return [d.segment for d in self.drives]

    @property
    def landmarks(self) -> np.ndarray:
        """The first drive's map (each dataset has its own: see `maps`)."""
        lg = self.drives[0].log
        return np.column_stack([lg.landmark_x, lg.landmark_y])

    @property
    def waypoints(self) -> np.ndarray:
        return np.zeros((0, 2))

    def summary(self) -> dict:
        """What the manifest says about the data: per drive, its log, span, counts, gaps and
        its dataset's map."""
        out = {"protocol": "drives", "digest": self.digest, "drives": []}
        for d in self.drives:
            ex, lg = d.exclusions, d.log
            out["drives"].append(
                {
                    "drive": d.id, "dataset": d.dataset, "log": lg.name, "run": d.segment.index,
                    "t_origin": lg.t_origin, "span": [lg.t_start, lg.t_end],
                    "odometry_end": float(lg.odo_t[-1]) if len(lg.odo_t) else None,
                    "counts": lg.counts(), "gaps": ex.gaps.tolist(),
                    "misfits": ex.misfits.tolist(), "segment": d.segment.as_dict(),
                    "landmarks": {"id": lg.landmark_id.tolist(), "x": lg.landmark_x.tolist(),
                                  "y": lg.landmark_y.tolist()},
                }
            )  # fmt: skip
        return out


def resolve_drives(scenario: RecordedScenario) -> DriveSet:
    """Load every drive of `data.drives` and make it one run, whole, from its ground truth."""
    misfit = mrclam.MisfitRule() if scenario.misfit_detection else None
    drives = []
    digest = hashlib.sha256()
    for index, drive in enumerate(scenario.data.drives or []):
        log = mrclam.load_drive(drive)
        ex = mrclam.exclusions(log, scenario.max_gap_s, misfit)
        t0, pose = mrclam.cold_start(log, log.t_start, ex.max_gap_s, misfit)
        seg = Segment(index, log.t_start, log.t_end, t0, pose, ex.scorable_seconds())
        drives.append(Drive(drive, mrclam.drive_dataset(drive), log, ex, seg))
        digest.update(f"{drive}:{log_digest(log)};".encode())
    return DriveSet(drives=drives, misfit=misfit, digest=digest.hexdigest()[:16])
