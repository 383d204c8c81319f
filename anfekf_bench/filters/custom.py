"""Your own filter in the benchmark, without editing the package (docs/CUSTOM_FILTERS.md).

In a scenario file:

    filters:
      - {name: mine, kind: custom, class: "mypkg.filters:MyFilter", params: {gain: 0.5}}

or, once a package registers an entry point in the group `anfekf_bench.filters`
(`my-filter = "mypkg.filters:MyFilter"`), simply `{name: mine, kind: my-filter, gain: 0.5}`.

The class must subclass `anfekf_bench.filters.RobotEKF` (or `AdaptiveEKF`) and may declare a
`Params` class (a subclass of `anfekf_bench.filters.FilterParams`) that validates `params`; the
filter receives the validated instance as `self.params`.
"""

from __future__ import annotations

import importlib
import re
import warnings
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any, ClassVar, Literal, TypeVar

import numpy as np
from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from .ekf import RobotEKF
from .spec import FilterContext, FilterSpec

ENTRY_POINT_GROUP = "anfekf_bench.filters"
CLASS_PATH = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*$"


T = TypeVar("T")
_COMPLEX_WARNING = getattr(getattr(np, "exceptions", np), "ComplexWarning", Warning)


class CustomFilterFailed(Exception):
    """A user's filter raised while being built or run; `str()` is the one-line message.

    Raised in a worker, it reaches the command through joblib or Dask as itself (one argument,
    so it pickles), and ends the batch in one line, exit 2; the saved runs and any previous
    result stay."""


def _shown(exc: BaseException) -> str:
    text = str(exc).replace("\n", " ")
    return type(exc).__name__ + (f": {text[:200]}" if text else "")


def contained(name: str, class_path: str, hook: str, call: Callable[..., T], *args) -> T:
    """`call(*args)`, with anything a user's code raises (SystemExit and other BaseExceptions
    included) turned into CustomFilterFailed naming the filter and the hook. A plain
    KeyboardInterrupt passes: it is the user's Ctrl-C, and the batch stops as interrupted."""
    try:
        with warnings.catch_warnings():
            # A complex number cast to real: the filter's state is of the wrong type.
            warnings.simplefilter("error", _COMPLEX_WARNING)
            return call(*args)
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # noqa: BLE001 - a user's filter may raise anything
        raise CustomFilterFailed(
            f"filter {name!r} ({class_path}): {hook} raised {_shown(exc)}"
        ) from None


def load_filter_class(path: str) -> type[RobotEKF]:
    """The class named `module:Class`; ValueError (one line) if it cannot be used."""
    module_name, _, class_name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # the user's module may fail in any way (sys.exit too)
        raise ValueError(
            f"cannot import module {module_name!r} ({_shown(exc)}); is it"
            " installed or on PYTHONPATH?"
        ) from None
    cls = getattr(module, class_name, None)
    if cls is None:
        raise ValueError(f"module {module_name!r} has no {class_name!r}")
    if not (isinstance(cls, type) and issubclass(cls, RobotEKF)):
        raise ValueError(f"{path} is not a subclass of anfekf_bench.filters.RobotEKF")
    return cls


def entry_point_kinds() -> dict[str, str]:
    """Filter kinds registered by installed packages: kind -> 'module:Class'."""
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)}


class CustomSpec(FilterSpec):
    """A user's filter class, named by its import path, with its own parameters."""

    kind: Literal["custom"]
    robot_only_because: ClassVar[str] = "a user's class is written against the robot's EKF"
    user_defined: ClassVar[bool] = True
    class_path: str = Field(alias="class", description="module:Class, e.g. mypkg.filters:MyFilter")
    params: dict[str, Any] = Field(default_factory=dict, description="the class's Params")

    model_config = {**FilterSpec.model_config, "populate_by_name": True}

    def adapted(self) -> frozenset[str] | None:
        return None  # the user's class decides as it runs: the report reads the recorded R/Qu

    @field_validator("class_path")
    @classmethod
    def _looks_like_a_class_path(cls, value: str) -> str:
        if not re.fullmatch(CLASS_PATH, value):
            raise ValueError("expected module:Class, e.g. mypkg.filters:MyFilter")
        return value

    @model_validator(mode="after")
    def _class_and_params(self) -> CustomSpec:
        cls = load_filter_class(self.class_path)
        schema = getattr(cls, "Params", None)
        if schema is None:
            if self.params:
                raise ValueError(f"{self.class_path} declares no Params, so params must be empty")
            return self
        if not (isinstance(schema, type) and issubclass(schema, BaseModel)):
            raise ValueError(f"{self.class_path}.Params must be a pydantic model (FilterParams)")
        try:
            schema.model_validate(self.params)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err["loc"]) or "(params)"
            raise ValueError(f"params.{where}: {err['msg']}") from None
        return self

    def filter_class(self) -> type[RobotEKF]:
        return load_filter_class(self.class_path)

    def build(self, ctx: FilterContext) -> RobotEKF:
        """The user's filter, given its own copies of the context's arrays (x0 is the world's:
        a filter writing into it must not move every other filter's start)."""
        cls = self.filter_class()
        schema = getattr(cls, "Params", None)
        params = schema.model_validate(self.params) if schema is not None else None
        kwargs = {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in ctx.kwargs().items()}
        return contained(
            self.name, self.class_path, "__init__", lambda: cls(**kwargs, params=params)
        )
