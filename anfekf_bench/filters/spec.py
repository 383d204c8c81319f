"""Typed, declarative filter parameters (Stone Soup style) and what a filter is built from.

Each filter family declares its parameter block as a `FilterSpec` subclass beside its class, with
the papers' defaults; the registry collects them into the scenario schema. A spec builds its filter
from a `FilterContext`: the starting noise, the motion model and the gate, resolved once per run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal, get_args

import numpy as np
from pydantic import Field, model_validator

from ..models import MotionModel
from ..schema import StrictModel

Bounds = Annotated[
    tuple[Annotated[float, Field(gt=0, allow_inf_nan=False)], ...],
    Field(min_length=2, max_length=2),
]


# What a filter is in a comparison, declared on its spec class (`FilterSpec.role`):
# "reference": the plain EKF on the assumed noise, that every filter is compared with;
# "oracle": the EKF told the true noise, the other reference;
# "fitted": an EKF whose fixed settings are fitted on training runs or drives: its noise (ekf-ml,
# ekf-tuned), or which error states it estimates and from where (ekf-aug-calibrated);
# "trained": a learned filter trained on training runs or drives (no assumed noise to start from);
# "adaptive": a filter that adapts online from the assumed noise (a user's class included).
Role = Literal["reference", "oracle", "fitted", "trained", "adaptive"]
ROLES: tuple[str, ...] = get_args(Role)

# The training runs a fit reads, declared on a spec class (`FilterSpec.fit_sources`) and
# supplied by the source (anfekf_bench.fitting):
# "simulated": training runs of the scenario's world, seeds disjoint from every evaluation run;
# "recorded": a recorded log's training segments, or the other datasets' drives of a fold;
# "own": a recorded run's own innovations (its odometry and landmarks), never its ground truth.
FitSource = Literal["simulated", "recorded", "own"]
FIT_SOURCES: tuple[str, ...] = get_args(FitSource)


@dataclass(frozen=True)
class FilterContext:
    """Everything a filter starts from in one run (radians, SI units)."""

    x0: np.ndarray
    P0: np.ndarray
    Qu: np.ndarray  # assumed control-noise covariance (2x2), or the true one for the oracle
    R: np.ndarray  # assumed measurement-noise covariance (2x2), or the true one
    model: MotionModel
    dt: float
    gate: float | None
    # The oracle of a scenario with a noise schedule: the true noise at every step
    # (schedule.ScheduledNoise); None everywhere else.
    true_noise: object | None = None

    def kwargs(self) -> dict:
        return dict(
            x0=self.x0, P0=self.P0, Qu=self.Qu, R=self.R, model=self.model, dt=self.dt,
            gate=self.gate,
        )  # fmt: skip


class FilterSpec(StrictModel):
    """A filter of a scenario: a unique `name` and a `kind` that selects the family.

    A family's capabilities, read by every consumer through `registry.capabilities` (the
    report's noise figures, `anfekf kinds`, the docs), are declared here on its spec class:
    - the class docstring's first line: the kind's one-line description;
    - `adapts_noise`: what the family can adapt: "R" (measurement noise), "Q" (control noise
      Qu), "P" (the covariance); empty for a fixed-noise filter;
    - `adapted()`: what one instance adapts (override it when a parameter decides, as the
      adaptive families' `adapt` and `adaptation` do: `AdaptiveSpec` does that already);
    - which engines run it: the reference engine (filterpy) runs every kind; a faster engine
      registers its own `supports(spec)` with the registry (`registry.register_engine`);
    - `role`: what the filter is in a comparison (ROLES); consumers ask the registry
      (`registry.role_of`, `registry.kinds_with_role`), never compare a kind with a string;
    - `user_defined`: a user's class (kind `custom` and entry points), run only where it is named;
    - `problems`: the problems (SPEC 17) it runs on, and `robot_only_because`: why not the others
      (`registry.supports_problem`, `registry.unsupported_reason`); `problem_form`: its spec
      class on the problems beyond the robot (anfekf_bench.problems.forms reads it);
    - its fit, where it has one: `fit_sources`, the training runs it can be fitted on
      (FIT_SOURCES), and `fit(training)`, run by anfekf_bench.fitting's one entry point.
    """

    name: str = Field(min_length=1)
    kind: str
    uses_true_noise: ClassVar[bool] = False  # the oracle is given the TRUE Q and R
    fitted_on_training: ClassVar[bool] = False  # fitted before the batch (filters.fitted)
    adapts_noise: ClassVar[frozenset[str]] = frozenset()  # any of "R", "Q", "P" (see above)
    role: ClassVar[Role] = "adaptive"
    user_defined: ClassVar[bool] = False
    # Problems (SPEC 17) the kind has an implementation for (the robot: this package's EKFs;
    # the others: anfekf_bench.problems), and why not on the others.
    problems: ClassVar[frozenset[str]] = frozenset({"robot"})
    robot_only_because: ClassVar[str] = (
        "not yet written for the problem interface (anfekf_bench.problems)"
    )
    # Its form on the problems beyond the robot, where `problems` names one: the spec class of
    # its parameters there (full Q and R instead of the robot's sigmas) and its implementation,
    # as "<module>:<class>" in anfekf_bench.problems. Read there (problems.forms), as the fast
    # engine reads `fast_family`: the registry lists each kind once and imports no problem.
    problem_form: ClassVar[str | None] = None
    default_filter: ClassVar[bool] = False  # the one to use when nothing is known (SPEC 19)
    # The module under engines/families/ whose hooks run this kind on the fast engine's one loop
    # (engines/loop.py), or None. Read on the exact class (`fast_family_of`): a subclass that
    # does not name one (it may build another filter) runs on filterpy.
    fast_family: ClassVar[str | None] = None
    # The module under engines/ of the fast engine's kernel of its own for a kind that is not one
    # EKF on the loop (a bank's M members, swvb's passes over a scan, ...; engines/fast.py runs
    # it through `KERNEL_RUNNERS`), or None. Read on the exact class too (`fast_kernel_of`).
    fast_kernel: ClassVar[str | None] = None
    fit_sources: ClassVar[frozenset[str]] = frozenset()  # of FIT_SOURCES; empty: no fit

    def build(self, ctx: FilterContext):
        """A fresh filter for one run."""
        raise NotImplementedError

    def adapted(self) -> frozenset[str] | None:
        """What this filter adapts ("R", "Q", "P"), or None when the spec cannot tell (a user's
        class: the report then looks at whether its recorded R/Qu vary)."""
        return self.adapts_noise

    def fit(self, training) -> dict:
        """Fit on `training` (the training runs of one of `fit_sources`, a
        fitting.fit.TrainingRuns): a JSON-able dict of the fitted values and their cost."""
        raise NotImplementedError(f"kind {self.kind} declares no fit")

    def fit_record(self, fitted: dict) -> dict:
        """What the manifest records of `fitted` (all of it, unless bulky)."""
        return fitted

    def fit_problem(self, fitted: Any) -> str | None:
        """Why `fitted`, read back from the fit cache (outputs.read_cached_fit), cannot be
        used ("<field>: <why>"), or None: what a hand-edited or damaged cache file must never
        get past."""
        return None if isinstance(fitted, dict) else "fitted: must be a mapping"


def fast_family_of(spec) -> str | None:
    """The fast engine's family module of a spec (or spec class), declared on exactly its class
    (`FilterSpec.fast_family`); None: not on the fast engine's loop."""
    cls = spec if isinstance(spec, type) else type(spec)
    return cls.__dict__.get("fast_family")


def fast_kernel_of(spec) -> str | None:
    """The fast engine's kernel of its own for a spec (or spec class), declared on exactly its
    class (`FilterSpec.fast_kernel`); None: none (on the loop, or on filterpy only)."""
    cls = spec if isinstance(spec, type) else type(spec)
    return cls.__dict__.get("fast_kernel")


class FilterParams(StrictModel):
    """Base of a filter's own parameter block (a custom filter's `Params`)."""


class AdaptiveParams(FilterParams):
    """Rules common to every adaptive filter, ANFEKF included (SPEC 7)."""

    adaptation: bool = Field(
        True, description="false: never change R, Qu or P (then the filter equals the EKF)"
    )
    adapt_from: Literal["all", "accepted"] = Field(
        "all",
        description="innovations that feed adaptation: all associated ones (gated or not), or"
        " only those the gate accepted (can lose lock for good)",
    )
    bounds: Bounds = Field(
        (1e-4, 1e4),
        description="floor and ceiling of every adapted variance, as factors of its starting"
        " value (1e-4..1e4 in variance is 0.01x..100x in standard deviation)",
    )

    @model_validator(mode="after")
    def _floor_below_ceiling(self) -> AdaptiveParams:
        lo, hi = self.bounds
        if not lo <= 1.0 <= hi:
            raise ValueError("bounds: need floor <= 1 <= ceiling (factors of the starting value)")
        return self


class AdaptiveSpec(FilterSpec, AdaptiveParams):
    """A built-in adaptive filter's spec: a name and kind plus the common adaptive rules."""

    adapts_noise: ClassVar[frozenset[str]] = frozenset({"R"})

    def adapted(self) -> frozenset[str] | None:
        # `adaptation: false` freezes every variance; an `adapt` field ("R", "Q", "RQ") picks
        # among what the family can adapt.
        if self.adaptation is False:
            return frozenset()
        chosen = getattr(self, "adapt", None)
        return self.adapts_noise if not isinstance(chosen, str) else frozenset(chosen)
