"""Noise that changes while the robot drives (SPEC 14): the scenario's `noise_schedule` block.

A schedule scales the TRUE noise of the simulator over time; the filters' assumed noise is not
touched. Everything is written as VARIANCE factors of the scenario's `true_noise`:

- `changes`: a factor on one or more channels (range, bearing, speed, steering; `R` is range and
  bearing, `Qu` speed and steering) between `start_s` and `end_s`. `shape: step` holds the factor
  on [start_s, end_s) and is 1 outside (degrade and recover); `shape: ramp` goes linearly from 1 at
  start_s to the factor at end_s and holds it afterwards (a slow drift; a second ramp with the
  inverse factor brings it back). Factors of changes on the same channel multiply.
- `outliers`: measurement outliers on [start_s, end_s) (default: the whole run). `contaminated`:
  each landmark measurement is, with `probability`, drawn with its variance times
  `variance_factor` (both components); `student_t`: each component's Gaussian noise is turned into
  a Student-t of `dof` degrees of freedom with the same scale (Z / sqrt(W / dof), W ~ chi2(dof)).
- `blackouts`: intervals [start_s, end_s) in which no landmark is measured at all.

Times are those of the control steps: step k (its odometry u_odo[k-1] and its scan, when it has
one) is at t = k * dt, the time the steps table records.

The TRUE variance of a channel at t (`true_variances`) is the nominal variance times the product
of the changes' factors; where outliers are active, the measurement channels' variance is that of
the outlier distribution (moment matched: (1 - p + p f) sigma^2 for the contaminated Gaussian,
sigma^2 dof / (dof - 2) for Student-t, which is why dof > 2). That is the R the oracle is told and
the reference of the noise-tracking error. Blackouts change no variance (there is just nothing to
measure).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from .schema import StrictModel

CHANNELS: tuple[str, ...] = ("speed", "steering", "range", "bearing")  # the order of u and z
GROUPS: dict[str, tuple[str, ...]] = {"Qu": ("speed", "steering"), "R": ("range", "bearing")}
Channel = Literal["speed", "steering", "range", "bearing", "R", "Qu"]
Seconds = Annotated[float, Field(ge=0, le=1e7, allow_inf_nan=False)]
Factor = Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)]
MAX_ITEMS = 100


def _window_ok(start: float, end: float | None, what: str) -> None:
    if end is not None and not end > start:
        raise ValueError(f"{what}: end_s must be later than start_s")


class NoiseChange(StrictModel):
    """A variance factor on some channels, as a step or a ramp (see the module docstring)."""

    channels: list[Channel] = Field(
        min_length=1,
        max_length=6,
        description="range, bearing, speed, steering; R (range and bearing), Qu (both controls)",
    )
    factor: Factor = Field(description="variance factor (4: the standard deviation doubles)")
    start_s: Seconds = Field(description="when the change starts [s]")
    end_s: Seconds | None = Field(
        None, description="step: back to 1 here (null: never); ramp: the factor is reached here"
    )
    shape: Literal["step", "ramp"] = Field(
        "step", description="step: the factor on [start_s, end_s); ramp: linear from 1 to it"
    )

    @model_validator(mode="after")
    def _valid_window(self) -> NoiseChange:
        _window_ok(self.start_s, self.end_s, "change")
        if self.shape == "ramp" and self.end_s is None:
            raise ValueError("a ramp needs end_s (the time its factor is reached)")
        return self

    def affected(self) -> set[str]:
        return {c for name in self.channels for c in GROUPS.get(name, (name,))}

    def factor_at(self, t: np.ndarray) -> np.ndarray:
        if self.shape == "step":
            inside = t >= self.start_s
            if self.end_s is not None:
                inside &= t < self.end_s
            return np.where(inside, self.factor, 1.0)
        share = np.clip((t - self.start_s) / (self.end_s - self.start_s), 0.0, 1.0)
        return 1.0 + (self.factor - 1.0) * share


class Outliers(StrictModel):
    """Measurement outliers: a contaminated Gaussian or Student-t noise (module docstring)."""

    model: Literal["contaminated", "student_t"] = Field(
        description="contaminated Gaussian (probability, variance_factor) or Student-t (dof)"
    )
    probability: Annotated[float, Field(gt=0, le=1)] | None = Field(
        None, description="contaminated: share of landmark measurements that are outliers"
    )
    variance_factor: Annotated[float, Field(gt=1, le=1e6, allow_inf_nan=False)] | None = Field(
        None, description="contaminated: an outlier's variance over the nominal one"
    )
    dof: Annotated[float, Field(gt=2, le=1e6, allow_inf_nan=False)] | None = Field(
        None, description="student_t: degrees of freedom (> 2, so that the variance exists)"
    )
    channels: list[Literal["range", "bearing", "R"]] = Field(
        ["R"], min_length=1, max_length=3, description="the measurement components hit"
    )
    start_s: Seconds = Field(0.0, description="outliers from this time [s]")
    end_s: Seconds | None = Field(None, description="until this time [s] (null: the run's end)")

    @model_validator(mode="after")
    def _parameters_of_the_model(self) -> Outliers:
        _window_ok(self.start_s, self.end_s, "outliers")
        if self.model == "contaminated":
            if self.probability is None or self.variance_factor is None:
                raise ValueError("contaminated outliers need probability and variance_factor")
            if self.dof is not None:
                raise ValueError("dof is for student_t outliers only")
        else:
            if self.dof is None:
                raise ValueError("student_t outliers need dof")
            if self.probability is not None or self.variance_factor is not None:
                raise ValueError("probability and variance_factor are for contaminated outliers")
        return self

    def affected(self) -> set[str]:
        return {c for name in self.channels for c in GROUPS.get(name, (name,))}

    def active(self, t: np.ndarray) -> np.ndarray:
        inside = t >= self.start_s
        if self.end_s is not None:
            inside &= t < self.end_s
        return inside

    def variance_inflation(self) -> float:
        """The outlier distribution's variance over the nominal Gaussian's (moment matched)."""
        if self.model == "contaminated":
            return 1.0 - self.probability + self.probability * self.variance_factor
        return self.dof / (self.dof - 2.0)


class Blackout(StrictModel):
    """No landmark measurement at all on [start_s, end_s)."""

    start_s: Seconds = Field(description="no measurement from this time [s]")
    end_s: Seconds = Field(description="until this time [s] (exclusive)")

    @model_validator(mode="after")
    def _valid_window(self) -> Blackout:
        _window_ok(self.start_s, self.end_s, "blackout")
        return self


class NoiseSchedule(StrictModel):
    """The scenario's `noise_schedule`: changes, outliers and blackouts of the TRUE noise."""

    changes: list[NoiseChange] = Field(
        default_factory=list,
        max_length=MAX_ITEMS,
        description="variance factors of R / Qu channels over time (steps and ramps; multiply)",
    )
    outliers: Outliers | None = Field(None, description="measurement outliers")
    blackouts: list[Blackout] = Field(
        default_factory=list, max_length=MAX_ITEMS, description="intervals without any landmark"
    )

    @model_validator(mode="after")
    def _not_empty(self) -> NoiseSchedule:
        if not self.changes and self.outliers is None and not self.blackouts:
            raise ValueError("an empty schedule: give changes, outliers or blackouts (or drop it)")
        return self

    def change_points(self, t_end: float | None = None) -> list[float]:
        """Every time at which the true noise (or the sensor's presence) changes, sorted, those
        after 0 and (with `t_end`) before it: the phases' boundaries."""
        points = set()
        for item in [*self.changes, *self.blackouts, *([self.outliers] if self.outliers else [])]:
            points.add(float(item.start_s))
            if item.end_s is not None:
                points.add(float(item.end_s))
        return sorted(p for p in points if p > 0 and (t_end is None or p < t_end))

    def variance_factors(self, t: np.ndarray) -> np.ndarray:
        """(len(t), 4) variance factors of (speed, steering, range, bearing) at times t, changes
        only (no outliers)."""
        t = np.asarray(t, dtype=float)
        out = np.ones((len(t), len(CHANNELS)))
        for change in self.changes:
            f = change.factor_at(t)
            for c in change.affected():
                out[:, CHANNELS.index(c)] *= f
        return out

    def blacked_out(self, t: np.ndarray) -> np.ndarray:
        """Whether each time t lies in a blackout."""
        t = np.asarray(t, dtype=float)
        out = np.zeros(len(t), dtype=bool)
        for b in self.blackouts:
            out |= (t >= b.start_s) & (t < b.end_s)
        return out

    def true_variances(self, nominal_sigmas, t: np.ndarray) -> np.ndarray:
        """(len(t), 4) TRUE variances of (speed, steering, range, bearing) at t [(m/s)^2, rad^2,
        m^2, rad^2]: the nominal sigmas (radians) squared times the changes' factors, and the
        outliers' variance inflation where they are active (the oracle's R and Qu)."""
        t = np.asarray(t, dtype=float)
        var = np.square(np.asarray(nominal_sigmas, dtype=float))[None, :] * self.variance_factors(t)
        if self.outliers is not None:
            on = self.outliers.active(t)
            inflation = self.outliers.variance_inflation()
            for c in self.outliers.affected():
                var[on, CHANNELS.index(c)] *= inflation
        return var


class ScheduledNoise:
    """The true noise of a scheduled scenario as the oracle reads it, step by step: Qu and R
    (diagonal, radians) at control step k (t = k dt), computed in blocks and cached."""

    BLOCK = 4096

    def __init__(self, schedule: NoiseSchedule, nominal_sigmas, dt: float):
        self.schedule = schedule
        self.nominal = tuple(float(s) for s in nominal_sigmas)
        self.dt = float(dt)
        self._var = np.zeros((0, 4))

    def variances(self, k: int) -> np.ndarray:
        """(speed, steering, range, bearing) true variances at control step k >= 1."""
        if k > len(self._var):
            n = (k // self.BLOCK + 1) * self.BLOCK
            self._var = self.schedule.true_variances(self.nominal, np.arange(1, n + 1) * self.dt)
        return self._var[k - 1]
