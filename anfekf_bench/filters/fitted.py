"""Filters fitted on training runs before the batch (SPEC 13): `ekf-ml` and `ekf-tuned`.

A `FittedSpec` declares `fitted_on_training`: the experiment (anfekf_bench.fitting.simulated)
simulates the scenario's training runs, from seeds disjoint from every evaluation run, calls `fit`
once, caches what it returns, and hands every worker a copy of the spec carrying those values
(`with_fit`); `filter_context` then builds the filter from them. The learned filter
(`kalmannet`, filters.kalmannet) uses the same mechanism: a `FittedSpec` whose `fit` trains the
network and returns its weights.

Both kinds here fit the four sigmas (sigma_v, sigma_gamma, sigma_range, sigma_bearing) of a
fixed EKF: `ekf-ml` maximises the innovation log-likelihood (no truth), `ekf-tuned` minimises the
position RMSE against the truth of the training runs. How they are fitted is chosen by the
training runs the source supplies (their `fit_noise`, anfekf_bench.fitting): Nelder-Mead from
`starts` on simulated training runs (engines.tuning), the grid search of the scenario's
`tuning:` on a recorded log's training segments or other drives (fitting.recorded), Nelder-Mead
on a recorded run's own innovations (fitting.own).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Literal

from pydantic import Field, PrivateAttr

from .ekf import RobotEKF
from .spec import FilterContext, FilterSpec, Role

Multiplier = Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)]
FITTED_SIGMAS = ("sigma_v", "sigma_gamma", "sigma_range", "sigma_bearing")  # `sigmas_rad` keys
# A fitted sigma read back from the fit cache: a number whose square is finite and positive
SIGMA_LIMITS = (1e-100, 1e100)


def sigmas_problem(doc: Any, keys: tuple[str, ...], where: str) -> str | None:
    """Why `doc` does not hold a usable sigma under every one of `keys` (a number within
    SIGMA_LIMITS: a string, a missing key, zero, a negative or an overflowing value is
    refused), or None; `where` prefixes the field named ("sigmas_rad.")."""
    if not isinstance(doc, dict):
        return f"{where.rstrip('.') or 'fit'}: must be a mapping of {', '.join(keys)}"
    lo, hi = SIGMA_LIMITS
    for key in keys:
        value = doc.get(key)
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not number or not (math.isfinite(value) and lo <= value <= hi):
            shown = "missing" if key not in doc else f"got {str(value)[:40]!r}"
            return f"{where}{key}: must be a number in [{lo:g}, {hi:g}] ({shown})"
    return None


class FilterNotFitted(RuntimeError):
    """A fitted filter was asked to run before its training (a bug, not a user error)."""


class FittedSpec(FilterSpec):
    """A filter kind whose parameters are fitted on the scenario's training runs."""

    fitted_on_training: ClassVar[bool] = True
    role: ClassVar[Role] = "fitted"
    _fit: dict | None = PrivateAttr(default=None)

    def with_fit(self, fitted: dict) -> FittedSpec:
        """A copy of this spec that builds its filter from `fitted`."""
        spec = self.model_copy()
        spec._fit = dict(fitted)
        return spec

    def training_problem(self, training_runs: int) -> str | None:
        """Why `training_runs` training runs cannot fit this filter ("<field>: <why>"), or None;
        checked before any work."""
        return None

    def noise_fit_request(self) -> tuple[str, list[float], int] | None:
        """(criterion, starts, max_evaluations) when `fit` is a `fit_noise` of the training
        set (so that several such fits can run their starts together), else None."""
        return None

    def fitted_sigmas(self) -> tuple[float, float, float, float] | None:
        """The fitted (sv, sg, sr, sb) in radians the filter starts from, or None: the
        scenario's assumed noise (a kind that fits something else)."""
        return None

    @property
    def fitted(self) -> dict:
        if self._fit is None:
            raise FilterNotFitted(f"filter {self.name!r} ({self.kind}) has not been fitted")
        return self._fit


class FittedNoiseSpec(FittedSpec):
    """A fixed EKF whose four sigmas are fitted (`fitting.simulated.TrainingSet.fit_noise`)."""

    criterion: ClassVar[str]
    starts: list[Multiplier] = Field(
        [1.0, 3.0, 10.0],
        min_length=1,
        max_length=10,
        description="Nelder-Mead starts: multipliers of the scenario's filter_noise sigmas (too"
        " small a start loses lock and stalls: start at or above the assumed noise)",
    )
    max_evaluations: int = Field(
        300, ge=10, le=100_000, description="objective evaluations per start at most"
    )

    def fit(self, training: Any) -> dict:
        # The training runs fit the sigmas on the tuning kernel (fitting.simulated.TrainingSet,
        # fitting.own.OwnInnovations): a spec never imports an engine.
        return training.fit_noise(*self.noise_fit_request())

    def noise_fit_request(self) -> tuple[str, list[float], int]:
        return self.criterion, list(self.starts), self.max_evaluations

    def fit_problem(self, fitted: Any) -> str | None:
        problem = super().fit_problem(fitted)
        return problem or sigmas_problem(fitted.get("sigmas_rad"), FITTED_SIGMAS, "sigmas_rad.")

    def fitted_sigmas(self) -> tuple[float, float, float, float]:
        """(sv, sg, sr, sb) in radians, as `NoiseSigmas.radians` gives them."""
        s = self.fitted["sigmas_rad"]
        return (s["sigma_v"], s["sigma_gamma"], s["sigma_range"], s["sigma_bearing"])

    def build(self, ctx: FilterContext) -> RobotEKF:
        return RobotEKF(**ctx.kwargs())


class EKFMLSpec(FittedNoiseSpec):
    """The EKF with the sigmas that maximise the innovation log-likelihood of the training runs
    (no truth): the fair "tuned without truth" reference. On a recorded log, of the run it is
    scored on (its own innovations, never its ground truth: fitting.own.OwnInnovations)."""

    kind: Literal["ekf-ml"]
    fast_family: ClassVar[str | None] = "anfekf"  # engines/families/anfekf.py
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "tracking", "module"})
    problem_form: ClassVar[str | None] = "ml:MLSpec"  # problems/ml.py
    criterion: ClassVar[str] = "likelihood"
    fit_sources: ClassVar[frozenset[str]] = frozenset({"simulated", "own"})


class EKFTunedSpec(FittedNoiseSpec):
    """The EKF with the sigmas that minimise the position RMSE of the training runs (truth):
    the fair "tuned with truth" reference of a simulated scenario, and of a recorded one (one
    instance, no naive starts), where the grid search of the scenario's `tuning:` on the
    training segments or the other datasets' drives chooses them (fitting.recorded: `starts`
    and `max_evaluations` are Nelder-Mead's, which a recorded scenario refuses)."""

    kind: Literal["ekf-tuned"]
    fast_family: ClassVar[str | None] = "anfekf"  # engines/families/anfekf.py
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "tracking", "module"})
    problem_form: ClassVar[str | None] = "tuned:TunedSpec"  # problems/tuned.py
    criterion: ClassVar[str] = "rmse"
    fit_sources: ClassVar[frozenset[str]] = frozenset({"simulated", "recorded"})
    # Fields of the simulated fit only: a recorded scenario refuses them when given
    simulated_only: ClassVar[tuple[str, ...]] = ("starts", "max_evaluations")
