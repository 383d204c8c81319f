"""The filter registry: every filter family's spec, and the one place that builds a filter.

A family registers its `FilterSpec` subclass here; the scenario schema's `filters:` list is the
tagged union of all of them (discriminated by `kind`), so a new family needs no other edit.
"""

from __future__ import annotations

from typing import Annotated, Union

import numpy as np
from pydantic import Field

from ..models import Bicycle, control_covariance, measurement_covariance
from .akhlaghi import AkhlaghiSpec
from .anfekf import ANFEKFSpec
from .cm_scale import CMScaleSpec
from .custom import CustomSpec, entry_point_kinds
from .ekf import EKFSpec, OracleSpec, RobotEKF, gate_threshold
from .iae import IAESpec
from .kalmannet import KalmanNetSpec
from .sage_husa import SageHusaSpec
from .spec import FilterContext, FilterSpec
from .vb import VBAKFSpec, VBRSpec

SPECS: tuple[type[FilterSpec], ...] = (
    EKFSpec,
    OracleSpec,
    ANFEKFSpec,
    SageHusaSpec,
    AkhlaghiSpec,
    IAESpec,
    CMScaleSpec,
    VBRSpec,
    VBAKFSpec,
    KalmanNetSpec,
    CustomSpec,
)


def kind_of(spec_class: type[FilterSpec]) -> str:
    """The `kind` tag a spec class is selected by."""
    return spec_class.model_fields["kind"].annotation.__args__[0]


SPEC_BY_KIND: dict[str, type[FilterSpec]] = {kind_of(s): s for s in SPECS}
KINDS: tuple[str, ...] = tuple(SPEC_BY_KIND)

AnyFilterSpec = Annotated[Union[SPECS], Field(discriminator="kind")]  # noqa: UP007


def expand_entry_points(item: object) -> object:
    """A filter entry whose kind an installed package registered becomes a `custom` entry."""
    kind = item.get("kind") if isinstance(item, dict) else None
    if not isinstance(kind, str) or kind in KINDS:
        return item
    registered = entry_point_kinds()
    if kind not in registered:
        return item
    params = {k: v for k, v in item.items() if k not in ("name", "kind")}
    return {"name": item.get("name"), "kind": "custom", "class": registered[kind], "params": params}


def filter_context(spec: FilterSpec, scenario, world) -> FilterContext:
    """What `spec`'s filter starts from in a run of `scenario` on the simulated `world`: the
    oracle gets the true noise, every other filter the assumed one."""
    noise = scenario.true_noise if spec.uses_true_noise else scenario.filter_noise
    sv, sg, sr, sb = noise.radians()
    return FilterContext(
        x0=world.x0,
        P0=np.eye(3) * scenario.p0,
        Qu=control_covariance(sv, sg),
        R=measurement_covariance(sr, sb),
        model=Bicycle(world.T, world.B),
        dt=world.T,
        gate=gate_threshold(scenario.gate_probability),
    )


def build_filter(spec: FilterSpec, scenario, world) -> RobotEKF:
    """A fresh filter for one run of `scenario` (see `filter_context`)."""
    return spec.build(filter_context(spec, scenario, world))
