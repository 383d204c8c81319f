"""The scenario file of a problem beyond the robot (`problem: linear`, `problem: tracking`;
SPEC 17), validated strictly like every scenario: unknown keys, wrong shapes and non-positive
covariances are one-line `ScenarioError`s naming the file and the field.

    name: survey
    problem: linear
    runs: 100
    system: {F: ..., H: ..., Q: ..., R: ..., steps: 1001}   # default: the survey's system
    filter_noise: {Q: [[1, 0], [0, 1]], R: [[1, 0], [0, 1]]}  # what the filters assume / start from
    filters: [{name: kf, kind: ekf}, {name: oracle, kind: ekf-oracle}, ...]

`system:` is validated by the model of the scenario's problem (`SYSTEMS`): `LinearSystem`,
`TrackingSystem` (problems.tracking_schema).

A user's own problem (`problem: module`) names its Python file instead of `system`:
`module: {file: pendulum.py}` (a path relative to the scenario file's folder, inside it;
`problems.module` reads and checks it; docs/CUSTOM_PROBLEMS.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from ..config import (  # is_problem_document: re-exported
    MAX_SEED,
    ScenarioError,
    check_unique_names,
    is_problem_document,  # noqa: F401
)
from ..filters.registry import supports_problem, unsupported_reason
from ..schema import StrictModel
from ..storage import scenario_name_problem
from .base import Problem
from .filters import Matrix
from .forms import PROBLEM_KINDS, AnyProblemFilter
from .linear import SURVEY_F, SURVEY_H, SURVEY_Q, SURVEY_R, SURVEY_STEPS, LinearProblem
from .module import ModuleProblem, ModuleProblemError
from .tracking_schema import TrackingSystem

# Problems a scenario may name besides the robot (the default, `problem: robot` or absent).
PROBLEMS = ("linear", "tracking", "module")
MAX_DIM = 50
MAX_STEPS = 10**6


def as_matrix(value, rows: int | None, cols: int | None, what: str) -> np.ndarray:
    """A rectangular finite matrix of the given shape, or ValueError saying what is wrong."""
    M = np.array(value, dtype=float)
    if M.ndim != 2 or M.size == 0:
        raise ValueError(f"{what}: expected a matrix (a list of equal-length rows)")
    if rows is not None and M.shape[0] != rows or cols is not None and M.shape[1] != cols:
        raise ValueError(f"{what}: expected {rows} x {cols}, got {M.shape[0]} x {M.shape[1]}")
    if max(M.shape) > MAX_DIM:
        raise ValueError(f"{what}: at most {MAX_DIM} rows and columns")
    return M


def check_covariance(M: np.ndarray, what: str) -> None:
    if not np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, np.abs(M).max())):
        raise ValueError(f"{what}: a covariance must be symmetric")
    if np.linalg.eigvalsh(M).min() <= 0:
        raise ValueError(f"{what}: a covariance must be positive definite")


class LinearSystem(StrictModel):
    """x(k+1) = F x(k) + G w(k), z(k) = H x(k) + v(k); default the survey's (Dunik et al.)."""

    F: Matrix = Field([list(r) for r in SURVEY_F], description="state transition (n x n)")
    H: Matrix = Field([list(r) for r in SURVEY_H], description="measurement matrix (nz x n)")
    G: Matrix | None = Field(None, description="noise input (n x nw); default I")
    Q: Matrix = Field([list(r) for r in SURVEY_Q], description="true process noise (nw x nw)")
    R: Matrix = Field([list(r) for r in SURVEY_R], description="true measurement noise")
    x0: list[float] | None = Field(
        None, description="mean of the true initial state and the filters' start (default 0)"
    )
    P0: Matrix | None = Field(
        None, description="covariance of the true initial state and the filters' P0 (default I)"
    )
    steps: int = Field(SURVEY_STEPS, ge=10, le=MAX_STEPS, description="measurements per run")
    position: list[int] | None = Field(
        None, description="state components scored as position (default all)"
    )

    @model_validator(mode="after")
    def _shapes(self) -> LinearSystem:
        F = as_matrix(self.F, None, None, "F")
        n = F.shape[0]
        as_matrix(self.F, n, n, "F")
        H = as_matrix(self.H, None, n, "H")
        G = np.eye(n) if self.G is None else as_matrix(self.G, n, None, "G")
        check_covariance(as_matrix(self.Q, G.shape[1], G.shape[1], "Q"), "Q")
        check_covariance(as_matrix(self.R, H.shape[0], H.shape[0], "R"), "R")
        if self.x0 is not None and len(self.x0) != n:
            raise ValueError(f"x0: expected {n} values")
        if self.P0 is not None:
            check_covariance(as_matrix(self.P0, n, n, "P0"), "P0")
        if self.position is not None and (
            len(set(self.position)) != len(self.position)
            or not all(0 <= i < n for i in self.position)
        ):
            raise ValueError(f"position: distinct state indices 0 .. {n - 1}")
        return self

    def problem(self, steps: int | None = None) -> LinearProblem:
        return LinearProblem(self.F, self.H, self.Q, self.R, G=self.G, x0=self.x0, P0=self.P0,
                             steps=self.steps if steps is None else steps,
                             position=self.position)  # fmt: skip


def module_path(file: str, folder: Path) -> Path:
    """The module file `file` names, relative to the scenario's folder and inside it (a scenario
    and the code it runs travel together), or ValueError."""
    relative = Path(file)
    if relative.is_absolute():
        raise ValueError(f"{file}: give a path relative to the scenario file's folder")
    if relative.suffix != ".py":
        raise ValueError(f"{file}: expected a Python file (.py)")
    path = (folder / relative).resolve()
    if not path.is_relative_to(folder.resolve()):
        raise ValueError(f"{file}: outside the scenario file's folder ({folder}); keep the"
                         " module beside the scenario or below it")  # fmt: skip
    if not path.is_file():
        raise ValueError(f"{file}: no such file in {folder}")
    return path


def scenario_folder(info: ValidationInfo) -> Path:
    folder = (info.context or {}).get("folder")
    return Path(".") if folder is None else Path(folder)


class ModuleSystem(StrictModel):
    """A user's own problem: a Python file defining f, F, G, h, H, Q, R, x0, P0, steps."""

    file: str = Field(
        min_length=1, description="the module (.py), relative to the scenario file's folder"
    )
    params: list[Annotated[float, Field(allow_inf_nan=False)]] | None = Field(
        None, description="the parameter vector p its functions receive (default its `params`)"
    )
    steps: int | None = Field(
        None, ge=10, le=MAX_STEPS, description="measurements per run (default its `steps`)"
    )
    _path: Path | None = PrivateAttr(None)

    @field_validator("file")
    @classmethod
    def _readable_module(cls, file: str, info: ValidationInfo) -> str:
        try:
            ModuleProblem(module_path(file, scenario_folder(info)))
        except ModuleProblemError as exc:
            raise ValueError(f"{file}: {exc}") from None
        return file

    @model_validator(mode="after")
    def _overrides(self, info: ValidationInfo) -> ModuleSystem:
        self._path = module_path(self.file, scenario_folder(info))
        self.problem()  # params and steps fit the module
        return self

    def problem(self, steps: int | None = None) -> ModuleProblem:
        return ModuleProblem(self._path, params=self.params,
                             steps=self.steps if steps is None else steps)  # fmt: skip


class AssumedNoise(StrictModel):
    """The noise the filters assume, and where the adaptive ones start."""

    Q: Matrix | None = Field(
        None, description="assumed Q (default: the problem's; linear: I, tracking: the true Q)"
    )
    R: Matrix | None = Field(
        None, description="assumed R (default: the problem's; linear: I, tracking: the true R)"
    )
    Q_scale: Annotated[float, Field(gt=0, le=1e12, allow_inf_nan=False)] | None = Field(
        None, description="assumed Q = this factor x the true Q (instead of Q)"
    )
    R_scale: Annotated[float, Field(gt=0, le=1e12, allow_inf_nan=False)] | None = Field(
        None, description="assumed R = this factor x the true R (instead of R)"
    )

    @model_validator(mode="after")
    def _one_way_each(self) -> AssumedNoise:
        for key in ("Q", "R"):
            if getattr(self, key) is not None and getattr(self, f"{key}_scale") is not None:
                raise ValueError(f"{key} and {key}_scale: give one of them")
        return self


class ProblemTraining(StrictModel):
    runs: int = Field(20, ge=1, le=10_000, description="training runs of the fitted filters")


class ProblemScenario(StrictModel):
    """A scenario of a problem beyond the robot (SPEC 17)."""

    name: str = Field(min_length=1, description="the result folder's name: OUT/<name>/")
    description: str = Field("", max_length=10_000)
    problem: Literal["linear", "tracking", "module"] = Field(
        description="the problem (robot: the default pipeline; module: a user's own, `module`)"
    )
    seed: int = Field(0, ge=0, le=MAX_SEED)
    runs: int = Field(100, ge=1, le=100_000)
    jobs: int = Field(1, ge=1, le=1024, description="local worker processes")
    engine: Literal["filterpy", "fast"] = Field(
        "filterpy",
        description="filterpy: the filters as Python (the reference); fast: their loops compiled"
        " by numba (`--engine` overrides)",
    )
    system: LinearSystem | TrackingSystem | None = Field(
        None, validate_default=True,
        description="the true system, keys by problem (absent: the problem's default)",
    )  # fmt: skip
    module: ModuleSystem | None = Field(None, description="problem: module's file")
    filter_noise: AssumedNoise = AssumedNoise()
    training: ProblemTraining = ProblemTraining()
    filters: list[AnyProblemFilter] = Field(min_length=1)

    @field_validator("name")
    @classmethod
    def _safe_name(cls, name: str) -> str:
        problem = scenario_name_problem(name)
        if problem:
            raise ValueError(problem)
        return name

    @field_validator("system", mode="wrap")
    @classmethod
    def _system_of_the_problem(cls, value, handler, info: ValidationInfo):
        model = SYSTEMS.get(info.data.get("problem"))
        if model is None:  # the problem itself is wrong: that is the error reported
            return value
        if isinstance(value, model):
            return value
        return model.model_validate({} if value is None else value)

    @field_validator("filters")
    @classmethod
    def _unique_names(cls, filters: list) -> list:
        return check_unique_names(filters)

    @model_validator(mode="after")
    def _noise_shapes_and_support(self) -> ProblemScenario:
        if (self.problem == "module") != (self.module is not None):
            raise ValueError("problem: module names its file in `module: {file: ...}`; `module`"
                             " is for problem: module only")  # fmt: skip
        if self.module is not None and "system" in self.model_fields_set:
            raise ValueError("system: the linear problem's; a module defines its own system")
        try:
            problem = self.build_problem()
        except ModuleProblemError as exc:
            raise ValueError(f"module: {exc}") from None
        for key, m in (("Q", problem.nw), ("R", problem.nz)):
            value = getattr(self.filter_noise, key)
            if value is not None:
                check_covariance(as_matrix(value, m, m, f"filter_noise.{key}"), key)
        for i, spec in enumerate(self.filters):
            if not supports_problem(spec.kind, self.problem):
                raise ValueError(f"filters.{i}: {unsupported_reason(spec.kind, self.problem)}")
            for key, m in (("Q", problem.nw), ("R", problem.nz), ("start_Q", problem.nw),
                           ("start_R", problem.nz)):  # fmt: skip
                value = getattr(spec, key, None)
                if value is not None:
                    check_covariance(as_matrix(value, m, m, f"filters.{i}.{key}"), key)
            try:
                spec.check(problem)
            except ValueError as exc:
                raise ValueError(f"filters.{i} ({spec.name}): {exc}") from None
        return self

    def build_problem(self, steps: int | None = None) -> Problem:
        if self.module is not None:
            return self.module.problem(steps)
        return self.system.problem(steps)

    def assumed_noise(self) -> tuple[np.ndarray, np.ndarray]:
        """(Q, R) the filters assume: filter_noise's matrices, or its factors on the true
        ones, or the problem's default."""
        p, noise = self.build_problem(), self.filter_noise
        out = list(p.default_assumed())
        for i, (key, true) in enumerate((("Q", p.Q), ("R", p.R))):
            if getattr(noise, key) is not None:
                out[i] = np.array(getattr(noise, key), float)
            elif getattr(noise, f"{key}_scale") is not None:
                out[i] = getattr(noise, f"{key}_scale") * true
        return out[0], out[1]


SYSTEMS: dict[str, type[StrictModel]] = {"linear": LinearSystem, "tracking": TrackingSystem}


def parse_problem_scenario(data: dict, path: str | Path) -> ProblemScenario:
    """Validate a problem scenario's document; ScenarioError (one line) otherwise."""
    try:
        return ProblemScenario.model_validate(data, context={"folder": Path(path).parent})
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = [str(p) for p in err["loc"]]
        if len(loc) >= 3 and loc[0] == "filters" and loc[2] in PROBLEM_KINDS:
            loc.pop(2)
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "literal_error" and loc == ["problem"]:
            msg = f"unknown problem (known: robot, {', '.join(PROBLEMS)})"
        elif err["type"] == "union_tag_invalid":
            tag = str(err.get("ctx", {}).get("tag", ""))
            why = unsupported_reason(tag, str(data.get("problem")))
            msg = why or f"unknown kind {tag!r}"
            msg += f" (kinds for this problem: {', '.join(PROBLEM_KINDS)})"
        more = len(exc.errors()) - 1
        if more:
            msg += f" [+{more} more error{'s' if more > 1 else ''}]"
        raise ScenarioError(path, ".".join(loc), msg) from None
