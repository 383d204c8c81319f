"""The filter registry: every filter family's spec, and the one place that builds a filter.

A family registers its `FilterSpec` subclass here; the scenario schema's `filters:` list is the
tagged union of all of them (discriminated by `kind`), so a new family needs no other edit.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Union

from pydantic import Field

from .akhlaghi import AkhlaghiSpec
from .als import ALSSpec
from .anfekf import ANFEKFSpec
from .augmented import AugmentedSpec, CalibratedAugmentedSpec
from .bank import IMMSpec, MMAESpec
from .cm_scale import CMScaleSpec
from .custom import CustomSpec, entry_point_kinds
from .ekf import EKFSpec, OracleSpec
from .fading import FadingSpec
from .fitted import EKFMLSpec, EKFTunedSpec
from .iae import IAESpec
from .kalmannet import KalmanNetSpec
from .sage_husa import SageHusaSpec
from .spec import ROLES, FilterSpec
from .swvb import SWVBSpec
from .vb import VBAKFSpec, VBRSpec
from .vb_bank import VBIMMSpec

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
    MMAESpec,
    IMMSpec,
    VBIMMSpec,
    FadingSpec,
    SWVBSpec,
    ALSSpec,
    EKFMLSpec,
    EKFTunedSpec,
    AugmentedSpec,
    CalibratedAugmentedSpec,
    KalmanNetSpec,
    CustomSpec,
)


def kind_of(spec_class: type[FilterSpec]) -> str:
    """The `kind` tag a spec class is selected by."""
    return spec_class.model_fields["kind"].annotation.__args__[0]


SPEC_BY_KIND: dict[str, type[FilterSpec]] = {kind_of(s): s for s in SPECS}
KINDS: tuple[str, ...] = tuple(SPEC_BY_KIND)


def role_of(kind: str) -> str | None:
    """The role (spec.ROLES) of the filters of `kind`; None for a kind this registry does not
    know (a stored result of a kind since removed)."""
    cls = SPEC_BY_KIND.get(str(kind))
    return None if cls is None else cls.role


def kinds_with_role(*roles: str) -> tuple[str, ...]:
    """The registered kinds whose role is one of `roles`, in registry order."""
    unknown = set(roles) - set(ROLES)
    if unknown:
        raise ValueError(f"unknown role(s) {sorted(unknown)}: roles are {', '.join(ROLES)}")
    return tuple(kind for kind, cls in SPEC_BY_KIND.items() if cls.role in roles)


def comparison_rank(kind: str) -> int:
    """Where a filter of `kind` stands in a group of filters compared side by side: the plain
    EKF (the reference) first, the paper's ANFEKF next, the other filters, the oracle last."""
    cls = SPEC_BY_KIND.get(str(kind))
    if cls is None:
        return 2
    if cls.role in ("reference", "oracle"):
        return 0 if cls.role == "reference" else 3
    return 1 if cls is ANFEKFSpec else 2


# ---------------------------------------------------------------------------------------------
# Capabilities: what each kind adapts, which engines run it, its doc. Every consumer (the report,
# `anfekf kinds`, the docs) reads them here; a family declares them on its spec class (see
# `FilterSpec`), so a new kind needs no edit in this file beyond its entry in SPECS.

# Engines other than the reference register `supports(spec) -> bool` here when imported
# (engines/fast.py does), so this module never imports an engine: no import circle.
_ENGINE_SUPPORTS: dict[str, Callable[[FilterSpec], bool]] = {}
REFERENCE_ENGINE = "filterpy"  # runs every kind


def register_engine(name: str, supports: Callable[[FilterSpec], bool]) -> None:
    """Record that engine `name` runs the specs for which `supports(spec)` is true."""
    _ENGINE_SUPPORTS[name] = supports


def engines_for(spec: FilterSpec) -> tuple[str, ...]:
    """The engines that run `spec` (of those imported so far): the reference engine first."""
    extra = [name for name, supports in _ENGINE_SUPPORTS.items() if supports(spec)]
    return (REFERENCE_ENGINE, *extra)


def spec_from_record(record: Mapping[str, Any]) -> FilterSpec | None:
    """A spec rebuilt from its stored form (a manifest's `scenario.filters` entry) without
    validating it: nothing is imported or checked (a custom class may be absent where a report
    is made). None for a kind this registry does not know."""
    cls = SPEC_BY_KIND.get(str(record.get("kind")))
    if cls is None:
        return None
    return cls.model_construct(**{k: v for k, v in record.items() if k in cls.model_fields})


def adapted_noise(spec: FilterSpec | Mapping[str, Any]) -> frozenset[str] | None:
    """What a filter adapts ("R", "Q" for the control noise Qu, "P"), from its spec or its
    stored record; None when the spec cannot tell (a custom filter, an unknown kind)."""
    if isinstance(spec, Mapping):
        spec = spec_from_record(spec)
        if spec is None:
            return None
    try:
        return spec.adapted()
    except (AttributeError, TypeError):  # a stored record missing a field the rule reads
        return type(spec).adapts_noise


NOISE_NAMES = {"R": "R (measurement noise)", "Q": "Qu (control noise)", "P": "P (covariance)"}


def noise_names(letters: frozenset[str] | None) -> str:
    """'R (measurement noise), Qu (control noise)' for {"R", "Q"}; 'nothing' for none."""
    if letters is None:
        return "what its class adapts (the report reads the recorded R/Qu)"
    return ", ".join(NOISE_NAMES[a] for a in "RQP" if a in letters) or "nothing (fixed noise)"


def adapts_line(info: KindInfo) -> str:
    """What a kind adapts, as `anfekf kinds` and the README say it."""
    if info.default_adapts is None:
        return noise_names(None)
    text = noise_names(info.adapts)
    if info.adapts and info.default_adapts != info.adapts:
        text += f" (by default: {noise_names(info.default_adapts)})"
    return text


@dataclass(frozen=True)
class KindInfo:
    """One filter kind as `anfekf kinds` and the docs show it."""

    kind: str
    doc: str  # the spec class docstring's first line
    adapts: frozenset[str]  # what the family can adapt
    default_adapts: frozenset[str] | None  # what an instance with the defaults adapts
    params: tuple[tuple[str, str, str], ...]  # (name, default, description); `name` left out
    engines: tuple[str, ...]  # engines that run an instance with the defaults


def _default_of(field) -> str:
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True)
    return repr(value) if isinstance(value, str) else str(value)


def capabilities(kind: str) -> KindInfo:
    """What kind `kind` is: doc, parameters with defaults, what it adapts, which engines."""
    cls = SPEC_BY_KIND[kind]
    doc = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())
    params = tuple(
        (field.alias or name, _default_of(field), field.description or "")
        for name, field in cls.model_fields.items()
        if name not in ("name", "kind")
    )
    probe = cls.model_construct(name=kind, kind=kind)
    return KindInfo(
        kind=kind,
        doc=doc,
        adapts=cls.adapts_noise,
        default_adapts=adapted_noise(probe),
        params=params,
        engines=engines_for(probe),
    )


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


# Naive starts (any scenario's `starts`): each filter runs once per multiplier of every standard
# deviation of its assumed noise, as the instance "<name> x<m>"; a filter whose noise is not
# assumed runs once under its own name.


def start_label(m: float) -> str:
    """'0.25', '1', '4': a start multiplier as it appears in instance names."""
    return f"{m:.3g}"


def runs_once(spec: FilterSpec) -> bool:
    """Whether `spec` has no assumed noise to start from: fitted, learned, or told the truth."""
    return spec.role in ("fitted", "trained", "oracle")


def instances(filters, starts) -> list[tuple[str, FilterSpec, float | None]]:
    """(instance name, spec, start multiplier or None), in scenario order; `starts` None: every
    filter once under its own name."""
    out = []
    for spec in filters:
        if starts is None or runs_once(spec):
            out.append((spec.name, spec, None))
        else:
            out += [(f"{spec.name} x{start_label(m)}", spec, float(m)) for m in starts]
    return out


def instance_names(filters, starts) -> list[str]:
    return [name for name, _, _ in instances(filters, starts)]


def check_starts(starts: list[float]) -> list[float]:
    """The starts, or ValueError when two print alike in instance names."""
    labels = [start_label(m) for m in starts]
    if len(set(labels)) != len(labels):
        raise ValueError("starts must differ (as printed with 3 significant digits)")
    return starts


# ---------------------------------------------------------------------------------------------
# Problems (SPEC 17): which problems each kind runs on, declared on its spec class (`problems`,
# `robot_only_because`), and its form beyond the robot (`problem_form`: the spec class of its
# parameters there and its implementation, in anfekf_bench.problems, which reads it by name).


def problem_forms() -> tuple[tuple[str, str | None], ...]:
    """(kind, its form: "<module>:<class>" in anfekf_bench.problems, or None where it names
    none) of every kind that runs on a problem beyond the robot, in registry order; the
    problems' schema, docs and tests derive their kinds from it (problems.forms)."""
    return tuple(
        (kind, cls.problem_form) for kind, cls in SPEC_BY_KIND.items() if cls.problems - {"robot"}
    )


def problems_of(kind: str) -> frozenset[str]:
    """The problems `kind` runs on (empty for a kind this registry does not know)."""
    cls = SPEC_BY_KIND.get(str(kind))
    return frozenset() if cls is None else cls.problems


def supports_problem(kind: str, problem: str) -> bool:
    return problem in problems_of(kind)


def unsupported_reason(kind: str, problem: str) -> str | None:
    """Why `kind` does not run on `problem` (one line), or None where it does."""
    cls = SPEC_BY_KIND.get(str(kind))
    if cls is None:
        return f"unknown kind {kind!r}"
    if problem in cls.problems:
        return None
    return f"kind {kind!r} does not run on problem {problem!r}: {cls.robot_only_because}"
