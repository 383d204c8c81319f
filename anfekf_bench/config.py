"""Scenario files: strict, typed validation of the YAML a user writes.

Angles are written in DEGREES in YAML; every such key ends in `_deg`. The loader converts them to
radians once (`World`, `NoiseSigmas.radians`), so the rest of the code works in radians only.
"""

from __future__ import annotations

import difflib
import math
import re
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, ClassVar, Literal, TypeVar, Union

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .error_sources import ErrorSources
from .filters.ekf import EKFSpec
from .filters.registry import (
    KINDS,
    SPEC_BY_KIND,
    AnyFilterSpec,
    check_starts,
    expand_entry_points,
    instance_names,
    instances,
)
from .filters.spec import FilterSpec
from .schedule import NoiseSchedule
from .schema import NonNegativeFloat, PositiveFloat, StrictModel
from .storage import FileProblem, read_regular_bytes, scenario_name_problem
from .text import one_line  # noqa: F401  (re-exported: the one escaping helper)

# Bounds: every value that passes validation can run. A coordinate beyond 10,000 km, a noise
# sigma or P0 whose square overflows a float's range in the covariance algebra, or a map of more
# than MAX_POINTS points is refused here; memory against the machine is checked per batch
# (experiment.check_plan).
MAX_COORDINATE = 1e7  # [m]
MAX_POINTS = 100_000
MAX_RUNS = 100_000
MAX_JOBS = 1024
MAX_SEED = 2**63 - 1
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False)]
Point = tuple[float, float]
MapSource = Union[str, list[Point]]

BUILTIN_MAP = "bailey-webmap"

# Files a scenario names are read whole, only if regular files (a FIFO or device is refused).
SCENARIO_FILE_LIMIT = 2**20  # bytes
MAP_FILE_LIMIT = 16 * 2**20  # bytes
# YAML: nesting depth and the number of values after expanding aliases (a "billion laughs" file
# of a few hundred bytes expands to billions); a scenario needs a depth of 6 and a few hundred.
YAML_MAX_DEPTH = 32
YAML_MAX_VALUES = 3 * MAX_POINTS + 100_000  # an inline map of MAX_POINTS [x, y] and the rest
# Filter names appear in tables, figure legends and file contents: plain characters only.
FILTER_NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9 _.+-]{0,63}")


class ScenarioError(Exception):
    """A scenario cannot be used; `str()` is the one-line message shown to the user."""

    def __init__(self, path: str | Path, field: str, message: str):
        self.path = str(path)
        self.field = field
        self.message = message
        where = f"{self.path}: {field}: " if field else f"{self.path}: "
        super().__init__(one_line(where + message))


_Strict = StrictModel


class NoiseSigmas(_Strict):
    """Standard deviations of control noise (V, gamma) and measurement noise (range, bearing)."""

    sigma_v: PositiveFloat = Field(0.3, le=1e3, description="speed noise [m/s]")
    sigma_gamma_deg: PositiveFloat = Field(3.0, le=360, description="steering noise [deg]")
    sigma_range: PositiveFloat = Field(0.1, le=1e5, description="range noise [m]")
    sigma_bearing_deg: PositiveFloat = Field(1.0, le=360, description="bearing noise [deg]")

    def radians(self) -> tuple[float, float, float, float]:
        """(sv [m/s], sg [rad], sr [m], sb [rad])."""
        return (
            self.sigma_v,
            math.radians(self.sigma_gamma_deg),
            self.sigma_range,
            math.radians(self.sigma_bearing_deg),
        )


class WorldConfig(_Strict):
    """SPEC section 1; defaults are the paper's / Bailey's simulator settings."""

    landmarks: MapSource = Field(
        BUILTIN_MAP,
        description="CSV path (relative to the YAML file), list of [x, y], or the builtin map",
    )
    waypoints: MapSource = Field(BUILTIN_MAP, description="as `landmarks`")
    loops: int = Field(1, ge=1, le=100)
    x0: tuple[Coordinate, Coordinate, Annotated[float, Field(ge=-3600, le=3600)]] = Field(
        (0.0, 0.0, 0.0), description="x [m], y [m], phi [deg]"
    )
    speed: PositiveFloat = Field(3.0, le=1e3, description="V [m/s]")
    wheelbase: PositiveFloat = Field(4.0, le=1e3, description="B [m]")
    max_steer_deg: Annotated[float, Field(gt=0, le=90)] = 30.0
    max_steer_rate_deg: PositiveFloat = Field(20.0, le=1e5, description="[deg/s]")
    dt: PositiveFloat = Field(0.025, le=60, description="control period T [s]")
    sensor_every: int = Field(8, ge=1, le=10**6, description="control steps per sensor scan")
    max_range: PositiveFloat = Field(20.0, le=MAX_COORDINATE, description="[m]")
    fov_deg: Annotated[float, Field(gt=0, le=360)] = 180.0
    waypoint_tolerance: PositiveFloat = Field(
        1.0, le=MAX_COORDINATE, description="[m]: switch waypoint within this"
    )
    max_steps: int = Field(
        1_000_000, ge=1, le=10**7, description="safety stop for routes never completed"
    )


Engine = Literal["filterpy", "fast"]
ClaimMetric = Literal["rmse_pos", "rmse_heading", "anees", "nees_in_bounds"]


class FactorRange(_Strict):
    """`num` factors from `start` to `stop`, evenly spaced in log (the natural axis of a factor)."""

    start: PositiveFloat
    stop: PositiveFloat
    num: int = Field(ge=2, le=101)

    def values(self) -> list[float]:
        return [float(v) for v in np.geomspace(self.start, self.stop, self.num)]


class SweepAxis(_Strict):
    """One axis of a sweep: a scenario field (a dotted path such as filter_noise.sigma_range or
    filters.1.window) set to each value, or a scale factor on the assumed R or Qu (variances:
    both standard deviations of filter_noise multiplied by sqrt(factor))."""

    field: str | None = Field(None, min_length=1, description="dotted path of a scenario field")
    scale: Literal["R", "Qu"] | None = Field(None, description="scale the assumed R or Qu")
    values: list[float] | None = Field(None, min_length=1, max_length=101)
    factors: FactorRange | None = None

    @model_validator(mode="after")
    def _one_target_one_list(self) -> SweepAxis:
        if (self.field is None) == (self.scale is None):
            raise ValueError("an axis needs exactly one of field or scale")
        if (self.values is None) == (self.factors is None):
            raise ValueError("an axis needs exactly one of values or factors")
        if len(set(self.points())) != len(self.points()):
            raise ValueError("an axis lists a value twice")
        if not all(math.isfinite(v) for v in self.points()):
            raise ValueError("an axis value must be a finite number")
        least = min(self.points())
        if self.scale is not None and least <= 0:
            raise ValueError(
                f"scale factors multiply variances, so each must be > 0 (got {least:g})"
            )
        return self

    @property
    def label(self) -> str:
        return self.field if self.field is not None else f"{self.scale}_factor"

    def points(self) -> list[float]:
        return list(self.values) if self.values is not None else self.factors.values()


class SweepSpec(_Strict):
    """A grid over one or more axes (SPEC 10): every cell is the scenario with the axes' values
    set, the same seed in every cell (cells are paired too)."""

    axes: list[SweepAxis] = Field(min_length=1, max_length=3)
    cell_steps: bool = Field(False, description="write each cell's steps.parquet too")
    max_cells: int = Field(400, ge=1, le=10_000, description="refuse larger grids")

    @model_validator(mode="after")
    def _distinct_axes_and_size(self) -> SweepSpec:
        labels = [a.label for a in self.axes]
        if len(set(labels)) != len(labels):
            raise ValueError("two axes set the same field")
        cells = math.prod(len(a.points()) for a in self.axes)
        if cells > self.max_cells:
            raise ValueError(f"{cells} cells exceed max_cells = {self.max_cells}")
        return self


class ClaimSpec(_Strict):
    """A claim about one filter, decided on its paired interval (SPEC 8).

    With `vs`: the ratio filter / vs of the metric (rmse_pos, rmse_heading, anees), or for
    nees_in_bounds the difference of the shares; without: the filter's own metric. Exactly one
    of `at_most` / `at_least` is the threshold.
    """

    filter: str = Field(min_length=1)
    vs: str | None = Field(None, description="the filter compared with (paired over runs)")
    metric: ClaimMetric
    at_most: Annotated[float, Field(allow_inf_nan=False)] | None = None
    at_least: Annotated[float, Field(allow_inf_nan=False)] | None = None
    source: str = Field("", description="where the claim comes from, e.g. the paper's figure")

    @model_validator(mode="after")
    def _one_threshold(self) -> ClaimSpec:
        if (self.at_most is None) == (self.at_least is None):
            raise ValueError("a claim needs exactly one of at_most or at_least")
        if self.vs == self.filter:
            raise ValueError("a claim compares a filter with another one: vs equals filter")
        return self


DASK_ADDRESS = r"^(tcp|tls|ws|wss|ucx)://\S+:\d{1,5}$"


class BackendConfig(_Strict):
    """Where the runs execute: local joblib processes, or an existing Dask distributed cluster.

    The backend never changes a run's numbers (run i only depends on its seed), so it is left out
    of the resume fingerprint; `anfekf run --backend/--scheduler` override it.
    """

    kind: Literal["local", "dask"] = "local"
    scheduler: Annotated[str, Field(pattern=DASK_ADDRESS)] | None = Field(
        None, description="Dask scheduler address tcp://HOST:PORT (kind dask only)"
    )
    connect_timeout_s: PositiveFloat = Field(
        10.0,
        le=3600,
        description="give up reaching the scheduler (or finding workers) after this [s]",
    )

    @model_validator(mode="after")
    def _scheduler_iff_dask(self) -> BackendConfig:
        if self.kind == "dask" and self.scheduler is None:
            raise ValueError("kind dask needs a scheduler address tcp://HOST:PORT")
        if self.kind == "local" and self.scheduler is not None:
            raise ValueError("scheduler is only used with kind dask")
        return self


def check_plain_names(filters: list) -> list:
    """The filters, or ValueError for a name that is not plain text (it appears in tables,
    legends, TeX-like figure text and file metadata: a scenario's or a recorded log's)."""
    for i, spec in enumerate(filters):
        if not FILTER_NAME_PATTERN.fullmatch(spec.name):
            raise ValueError(
                f"entry {i}: filter name {spec.name!r}: 1 to 64 characters, letters, digits,"
                " space and _ . + - (starting with a letter or digit)"
            )
    return filters


def check_unique_names(filters: list) -> list:
    """The filters, or ValueError naming the repeated names (a scenario's or a recorded log's)."""
    names = [f.name for f in filters]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"filter names must be unique; repeated: {', '.join(dupes)}")
    return filters


def check_named_filters(items: list, names: set[str]) -> list:
    """Claims or compare pairs, or ValueError for one that names no filter of the scenario."""
    for i, item in enumerate(items):
        wanted = (item.filter, item.vs) if isinstance(item, ClaimSpec) else item
        for value in wanted:
            if value is not None and value not in names:
                known = ", ".join(sorted(names))
                raise ValueError(f"entry {i}: no filter named {value!r} (filters: {known})")
    return items


ENGINE_DESCRIPTION = (
    "filterpy (the reference) or fast (numeric kernels, numba when installed); filters the fast"
    " engine does not implement run on filterpy (`--engine` overrides)"
)
Start = Annotated[PositiveFloat, Field(le=1e3)]


class Scenario(_Strict):
    """One scenario file, whatever its source (SPEC 12): the keys every scenario has, declared
    once here. Its `source` is one member of a union that adds what describes the runs:
    `SimulatedScenario` (below: a simulated world, one run per seed) or
    `sources.recorded.RecordedScenario` (a recorded log: held-out segments, or whole drives).
    A document with a `data:` key is recorded, any other simulated (`source_of`);
    `scenarios.parse_any_scenario` validates either with the same one-line errors."""

    source: ClassVar[Literal["simulated", "recorded"]]
    # The filter kinds this source accepts (kind -> spec): the error messages' allowed keys.
    spec_by_kind: ClassVar[dict[str, type[FilterSpec]]] = SPEC_BY_KIND

    name: str = Field(min_length=1, description="the result folder's name: OUT/<name>/")
    description: str = Field("", max_length=10_000, description="free text, shown in the report")
    seed: int = Field(
        0,
        ge=0,
        le=MAX_SEED,
        description="root seed; run i draws from SeedSequence(seed).spawn(runs)[i] (recorded:"
        " the seed of the bootstrap intervals)",
    )
    jobs: int = Field(
        2, ge=1, le=MAX_JOBS, description="local worker processes (`--jobs` overrides)"
    )
    steps_table: bool = Field(
        True, description="write steps.parquet (false: summaries and per-run tables only)"
    )
    engine: Engine = Field("filterpy", description=ENGINE_DESCRIPTION)
    gate_probability: Annotated[float, Field(gt=0, lt=1)] | None = Field(
        0.999, description="chi-square validation gate (eq. 26); null switches it off"
    )
    # The kinds differ by source (a recorded log has no truth to fit on or oracle noise): each
    # member narrows `filters` to its kinds, and sets its default and its `starts`' default.
    filters: list[AnyFilterSpec] = Field(
        default_factory=lambda: [EKFSpec(name="ekf")],
        min_length=1,
        description="the filters to run on the same data (kinds: `anfekf kinds`, Filter kinds)",
    )
    starts: list[Start] | None = Field(
        None,
        min_length=1,
        max_length=20,
        description="naive starts: each filter runs once per multiplier m of every standard"
        " deviation of filter_noise (variances times m^2), named '<filter> x<m>'; the oracle and"
        " the fitted and trained filters run once; absent: every filter once, as named",
    )
    backend: BackendConfig = Field(
        BackendConfig(),
        description="where the runs execute (`--backend`, `--scheduler` override; recorded:"
        " tuning and fits stay in this process)",
    )
    claims: list[ClaimSpec] = Field(
        default_factory=list, description="claims checked on every run and by `anfekf check`"
    )
    compare: list[tuple[str, str]] = Field(
        default_factory=list,
        description="extra (filter, vs) pairs to compare, besides each filter vs the reference"
        " (simulated: ekf and oracle; recorded: ekf-tuned)",
    )

    @field_validator("name")
    @classmethod
    def _safe_name(cls, name: str) -> str:
        # The result folder is OUT/<name>: never '.', '..', a path, or a name of the layout.
        problem = scenario_name_problem(name)
        if problem:
            raise ValueError(problem)
        return name

    @field_validator("filters")
    @classmethod
    def _plain_unique_filter_names(cls, filters: list) -> list:
        return check_unique_names(check_plain_names(filters))

    @field_validator("starts")
    @classmethod
    def _distinct_starts(cls, starts: list[float] | None) -> list[float] | None:
        return None if starts is None else check_starts(starts)

    @field_validator("claims", "compare")
    @classmethod
    def _name_filters_of_the_scenario(cls, items: list, info: ValidationInfo) -> list:
        if "filters" not in info.data or "starts" not in info.data:
            return items  # their own error says what is wrong
        names = instance_names(info.data["filters"], info.data["starts"])
        return check_named_filters(items, set(names))

    def instances(self) -> list[tuple[str, FilterSpec, float | None]]:
        """(instance name, spec, start multiplier or None), in scenario order: each filter once
        per naive start (`filters.registry.instances`), the fitted, trained and oracle ones
        once."""
        return instances(self.filters, self.starts)

    def instance_names(self) -> list[str]:
        return [name for name, _, _ in self.instances()]


def is_problem_document(data: object) -> bool:
    """Whether a scenario document names a problem other than the robot (SPEC 17: validated by
    `problems.schema`, which a robot's scenario never needs to import)."""
    return isinstance(data, dict) and data.get("problem", "robot") != "robot"


def source_of(document: dict) -> Literal["simulated", "recorded"]:
    """Which member of the source union a scenario document is: a recorded log names its
    `data:` (SPEC 9), a simulated world needs nothing (every world key has a default)."""
    return "recorded" if "data" in document else "simulated"


class TrainingConfig(_Strict):
    """Training runs for the filters fitted before the batch (`ekf-ml`, `ekf-tuned`,
    `kalmannet`: see anfekf_bench.fitting.simulated). Their seeds come from a branch of the root
    seed that no evaluation run draws from; unused when no filter of the scenario is fitted."""

    runs: int = Field(20, ge=1, le=10_000, description="training runs simulated for fitting")


ScenarioT = TypeVar("ScenarioT", bound=Scenario)


class SimulatedScenario(Scenario):
    """A scenario whose runs the simulator draws from its world, one per seed (SPEC 1, 6)."""

    source: ClassVar[Literal["simulated"]] = "simulated"

    runs: int = Field(50, ge=1, le=MAX_RUNS, description="Monte Carlo runs (`--runs` overrides)")
    record_every: int = Field(1, ge=1, le=10**7, description="record every n-th control step")
    world: WorldConfig = Field(
        WorldConfig(), description="the simulated world (defaults: the paper's, SPEC section 1)"
    )
    true_noise: NoiseSigmas = Field(
        NoiseSigmas(), description="the noise the simulation draws (standard deviations)"
    )
    filter_noise: NoiseSigmas = Field(
        NoiseSigmas(),
        description="the noise the filters assume (the oracle EKF gets `true_noise`)",
    )
    p0: NonNegativeFloat = Field(1e-9, le=1e6, description="P0 = p0 * I")
    sweep: SweepSpec | None = Field(
        None,
        description="a grid of cells (anfekf run writes a sweep)",
    )
    training: TrainingConfig = Field(
        TrainingConfig(), description="training runs of the filters fitted before the batch"
    )
    noise_schedule: NoiseSchedule | None = Field(
        None,
        description="true noise that changes over time: R/Qu steps and ramps, outliers,"
        " blackouts (SPEC 14); absent: constant true noise",
    )
    error_sources: ErrorSources | None = Field(
        None,
        description="odometry scale factors and steering bias, range bias of the simulated"
        " robot (SPEC 18); absent: white noise only",
    )

    @model_validator(mode="after")
    def _starts_not_in_sweeps(self) -> SimulatedScenario:
        if self.starts is not None and self.sweep is not None:
            raise ValueError(
                "starts: not with sweep (a sweep's cells compare filters by name; run the"
                " starts as separate scenarios)"
            )
        return self


@dataclass(frozen=True)
class World:
    """The resolved world, SI units and radians, with the map loaded."""

    landmarks: np.ndarray  # (n, 2)
    waypoints: np.ndarray  # (m, 2)
    loops: int
    x0: np.ndarray  # (3,) radians
    V: float
    B: float
    max_steer: float
    max_steer_rate: float
    T: float
    sensor_every: int
    max_range: float
    half_fov: float
    waypoint_tolerance: float
    max_steps: int


def _builtin_csv(kind: str) -> Path:
    return Path(str(resources.files("anfekf_bench") / "data" / BUILTIN_MAP / f"{kind}.csv"))


def read_points_csv(path: Path, *, scenario_path: str | Path, field: str) -> np.ndarray:
    """Read `x,y` lines (comments with #; an optional first line `x,y` is a header) into an
    (n, 2) array, with a clean error on failure.

    Only a regular file is read (a FIFO, device or folder is refused at once), and an error
    names the line, never quotes it: the path may point at any file.
    """

    def bad(message: str) -> ScenarioError:
        return ScenarioError(scenario_path, field, f"{path}: {message}")

    try:
        data = read_regular_bytes(path, MAP_FILE_LIMIT)
    except FileProblem as exc:
        if str(exc) == "file not found":
            raise ScenarioError(scenario_path, field, f"map file not found: {path}") from None
        raise ScenarioError(scenario_path, field, f"map file {path}: {exc}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise bad("not a text file (expected UTF-8 lines 'x,y')") from None
    points = []
    header_allowed = True
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        cells = line.split(",")
        first, header_allowed = header_allowed, False
        if first and [c.strip().lower() for c in cells] == ["x", "y"]:
            continue  # the column names, as spreadsheets and pandas write them
        if len(cells) != 2:
            raise bad(f"line {number}: expected 2 columns 'x,y', found {len(cells)}")
        try:
            x, y = float(cells[0]), float(cells[1])
        except ValueError:
            raise bad(f"line {number}: expected lines 'x,y' of numbers") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise bad(f"line {number}: coordinates must be finite numbers")
        points.append((x, y))
        if len(points) > MAX_POINTS:
            raise bad(f"more than {MAX_POINTS} points")
    if not points:
        raise bad("no points (need lines 'x,y')")
    pts = np.array(points, dtype=float)
    if np.abs(pts).max() > MAX_COORDINATE:
        raise bad(f"coordinates must lie within ±{MAX_COORDINATE:g} m")
    return pts


def _resolve_points(source: MapSource, kind: str, scenario_path: Path) -> np.ndarray:
    field = f"world.{kind}"
    if isinstance(source, str):
        path = _builtin_csv(kind) if source == BUILTIN_MAP else scenario_path.parent / source
        return read_points_csv(path, scenario_path=scenario_path, field=field)
    if len(source) == 0:
        raise ScenarioError(scenario_path, field, "needs at least one [x, y] point")
    if len(source) > MAX_POINTS:
        raise ScenarioError(scenario_path, field, f"more than {MAX_POINTS} points")
    pts = np.asarray(source, dtype=float)
    if not np.all(np.isfinite(pts)):
        raise ScenarioError(scenario_path, field, "coordinates must be finite numbers")
    if np.abs(pts).max() > MAX_COORDINATE:
        raise ScenarioError(
            scenario_path, field, f"coordinates must lie within ±{MAX_COORDINATE:g} m"
        )
    return pts


def resolve_world(cfg: WorldConfig, scenario_path: Path) -> World:
    """Load the map and convert degrees to radians."""
    return World(
        landmarks=_resolve_points(cfg.landmarks, "landmarks", scenario_path),
        waypoints=_resolve_points(cfg.waypoints, "waypoints", scenario_path),
        loops=cfg.loops,
        x0=np.array([cfg.x0[0], cfg.x0[1], math.radians(cfg.x0[2])]),
        V=cfg.speed,
        B=cfg.wheelbase,
        max_steer=math.radians(cfg.max_steer_deg),
        max_steer_rate=math.radians(cfg.max_steer_rate_deg),
        T=cfg.dt,
        sensor_every=cfg.sensor_every,
        max_range=cfg.max_range,
        half_fov=math.radians(cfg.fov_deg) / 2.0,
        waypoint_tolerance=cfg.waypoint_tolerance,
        max_steps=cfg.max_steps,
    )


def _shown_loc(err: dict) -> list[str]:
    """The field path a user wrote, without the union members pydantic adds to `loc`."""
    loc = [str(p) for p in err["loc"]]
    if err["type"] == "bool_as_number":  # raised for the whole mapping: name the key
        loc.append(str(err["ctx"]["key"]))
    # Drop the discriminator tag pydantic inserts for tagged unions (filters.0.anfekf.window).
    if len(loc) >= 3 and loc[0] == "filters" and loc[2] in KINDS:
        loc.pop(2)
    # A failed map source names both members (world.waypoints.str, world.waypoints.list[...]).
    if len(loc) >= 3 and loc[0] == "world" and loc[1] in ("landmarks", "waypoints"):
        loc = loc[:2]
    return loc


SHOWN_ERRORS = 4  # errors of a scenario shown after the first one; the rest are counted


def _format_validation_error(exc: ValidationError, model: type[Scenario]) -> tuple[str, str]:
    """The first error's field and message, followed by the other fields' errors (one each, at
    most SHOWN_ERRORS, then how many more) on the same line: `[+2 more errors: seed: ...;
    jobs: ...]`."""
    errors = exc.errors()
    field, msg = _error_field_message(errors[0], model)
    others: dict[str, str] = {}
    for err in errors[1:]:
        other, text = _error_field_message(err, model)
        if other != field:
            others.setdefault(other, text)
    if others:
        shown = [f"{name}: {text}" for name, text in list(others.items())[:SHOWN_ERRORS]]
        rest = len(others) - len(shown)
        if rest:
            shown.append(f"and {rest} more")
        msg += f" [+{len(others)} more error{'s' if len(others) > 1 else ''}: {'; '.join(shown)}]"
    return field, msg


def _error_field_message(err: dict, model: type[Scenario]) -> tuple[str, str]:
    """One pydantic error as (the field a user wrote, what is allowed there)."""
    loc = _shown_loc(err)
    field = ".".join(loc) or "(top level)"
    msg = err["msg"]
    if loc[:1] == ["world"] and loc[1:] in (["landmarks"], ["waypoints"]) and len(err["loc"]) > 2:
        msg = f"expected '{BUILTIN_MAP}', a CSV path, or a list of [x, y] number pairs"
    elif err["type"] in ("value_error", "bool_as_number"):  # ours: the message says it all
        msg = msg.removeprefix("Value error, ")
    elif err["type"] == "extra_forbidden":
        msg = "unknown key"
        parent = err["loc"][:-1]
        allowed = _allowed_keys(model, parent)
        if allowed:
            msg += f" (allowed: {', '.join(allowed)})"
        msg += _did_you_mean(str(err["loc"][-1]), allowed)
    elif "input" in err and err["type"] not in ("missing",):
        shown = repr(err["input"])
        if len(shown) > 60:
            shown = shown[:57] + "..."
        msg += f" (got {shown})"
    if err["type"] == "union_tag_invalid":
        tag = str(err.get("ctx", {}).get("tag", ""))
        if tag in SPEC_BY_KIND and tag not in model.spec_by_kind:  # a kind of the other source
            msg = f"kind {tag!r} is not available in a {model.source} scenario"
            sources = SPEC_BY_KIND[tag].fit_sources
            if sources:
                msg += f": it is fitted on {' or '.join(sorted(sources))} training runs only"
        else:
            msg += _did_you_mean(tag, model.spec_by_kind)
    return field, msg


def _did_you_mean(word: str, choices) -> str:
    """' (did you mean 'x'?)' for the closest of `choices` to a mistyped `word`, else ''."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.75)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _allowed_keys(scenario: type[Scenario], parent_loc: tuple) -> list[str]:
    model: type[BaseModel] | None = scenario
    for part in parent_loc:
        if isinstance(part, int):  # a list index: same model as the list's items
            continue
        if part in scenario.spec_by_kind:  # the filter spec a `kind` selected
            model = scenario.spec_by_kind[part]
            continue
        if model is None:
            return []
        field = model.model_fields.get(part)
        if field is None:
            return []
        model = _model_of(field.annotation)
    return sorted(model.model_fields) if model is not None else []


def _model_of(ann) -> type[BaseModel] | None:
    """The one pydantic model an annotation holds (Model, Model | None, list[Model]), or None."""
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return ann
    models = [m for m in map(_model_of, typing.get_args(ann)) if m is not None]
    return models[0] if len(models) == 1 else None


def check_document(data: object, path: str | Path) -> dict:
    """A scenario document is a mapping; ScenarioError (one line) otherwise."""
    if data is None:
        raise ScenarioError(path, "", "empty file: expected a mapping of scenario keys")
    if not isinstance(data, dict):
        raise ScenarioError(
            path, "", f"expected a mapping of scenario keys, found a {type(data).__name__}"
        )
    return data


def validate_as(model: type[ScenarioT], data: dict, path: str | Path) -> ScenarioT:
    """`data` validated as one member of the source union (filters' entry points expanded);
    ScenarioError (one line: the file, the field, what is allowed) if it is not valid."""
    if isinstance(data.get("filters"), list):
        data = {**data, "filters": [expand_entry_points(item) for item in data["filters"]]}
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        field, msg = _format_validation_error(exc, model)
        raise ScenarioError(path, field, msg) from None


def parse_scenario(data: object, path: str | Path = "<scenario>") -> SimulatedScenario:
    """Validate an already-parsed YAML document of a simulated scenario (a recorded one:
    `scenarios.parse_any_scenario`)."""
    return validate_as(SimulatedScenario, check_document(data, path), path)


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader, stricter: a key may appear once in a mapping (PyYAML keeps the last
    silently). Nesting depth and alias expansion are bounded in `load_yaml`, before anything is
    constructed."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: set = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # `<<: *base` merges; its keys may be overridden on purpose
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                except TypeError:
                    continue  # unhashable: PyYAML reports it itself
                if duplicate:
                    raise yaml.constructor.ConstructorError(
                        None,
                        None,
                        f"key {one_line(str(key))[:60]!r} appears twice (each key once)",
                        key_node.start_mark,
                    )
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _StrictLoader.construct_mapping
)


class _YAMLTooLarge(Exception):
    pass


def _expanded_size(node, depth: int, sizes: dict[int, int], active: set[int]) -> int:
    """Values `node` holds once aliases are expanded (memoised per node, so this is linear in
    the file, while the expansion itself may be exponential)."""
    if depth > YAML_MAX_DEPTH:
        raise _YAMLTooLarge(f"nested deeper than {YAML_MAX_DEPTH} levels")
    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in active:
        raise _YAMLTooLarge("an alias refers to the node that holds it")
    if isinstance(node, yaml.SequenceNode):
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [n for pair in node.value for n in pair]
    else:
        children = []
    active.add(key)
    total = 1
    for child in children:
        total += _expanded_size(child, depth + 1, sizes, active)
        if total > YAML_MAX_VALUES:
            raise _YAMLTooLarge(
                f"holds more than {YAML_MAX_VALUES} values (counting each alias's expansion)"
            )
    active.discard(key)
    sizes[key] = total
    return total


def load_yaml(text: str) -> object:
    """One YAML document, strictly (see _StrictLoader); yaml.YAMLError or _YAMLTooLarge."""
    loader = _StrictLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node, 0, {}, set())
        return loader.construct_document(node)
    finally:
        loader.dispose()


def read_scenario_document(path: str | Path) -> object:
    """A scenario file's YAML document (not yet validated); raises ScenarioError with a one-line
    message. `scenarios.load_scenario` validates and resolves it, whatever its source."""
    path = Path(path)
    try:
        raw = read_regular_bytes(path, SCENARIO_FILE_LIMIT)
    except FileProblem as exc:
        message = str(exc)
        if message == "file not found":
            message = "scenario file does not exist"
        elif "folder" in message:
            message = "not a file (a folder)"
        raise ScenarioError(path, "", message) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(path, "", "cannot read: not UTF-8 text") from None
    try:
        data = load_yaml(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        kind = "YAML error" if "appears twice" in problem else "YAML syntax error"
        raise ScenarioError(path, "", f"{kind}{where}: {problem}") from None
    except _YAMLTooLarge as exc:
        raise ScenarioError(path, "", f"YAML {exc}; not a scenario") from None
    except RecursionError:
        raise ScenarioError(path, "", "YAML nested too deeply") from None
    return data


def scenario_files(target: str | Path) -> list[Path]:
    """A scenario file, or every *.yaml / *.yml in a folder (sorted)."""
    target = Path(target)
    try:
        if target.is_dir():
            files = sorted(p for p in target.iterdir() if p.suffix in (".yaml", ".yml"))
            if not files:
                raise ScenarioError(target, "", "folder holds no *.yaml scenario files")
            return files
        if not target.exists():
            raise ScenarioError(target, "", "scenario file does not exist")
    except OSError as exc:  # a name or path too long (ENAMETOOLONG), no permission, ...
        raise ScenarioError(target, "", f"cannot be read ({exc.strerror or exc})") from None
    return [target]
