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

Bounds: on every channel, each factor and the product of the factors in force at any instant
(changes and the outliers' inflation) lie in [1e-6, 1e6] (`factor_range_problem`), refused up
front otherwise: beyond, the true variance overflows or vanishes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from .schema import StrictModel

CHANNELS: tuple[str, ...] = ("speed", "steering", "range", "bearing")  # the order of u and z
GROUPS: dict[str, tuple[str, ...]] = {"Qu": ("speed", "steering"), "R": ("range", "bearing")}
Channel = Literal["speed", "steering", "range", "bearing", "R", "Qu"]
# The TRUE variance of a channel over true_noise's, at any instant: every factor, and the
# product of the factors in force at once (changes and the outliers' variance inflation), lies
# in [VARIANCE_FACTOR_MIN, VARIANCE_FACTOR_MAX]. Outside, the variances leave what a filter can
# use (52 factors of 1e6 overflow to inf; 1e-300 makes the oracle's R vanish).
VARIANCE_FACTOR_MIN = 1e-6
VARIANCE_FACTOR_MAX = 1e6
Seconds = Annotated[float, Field(ge=0, le=1e7, allow_inf_nan=False)]
# (each factor's lower bound is the product's: a factor is in force at some instant; `gt=0`
# here keeps the schema's text)
Factor = Annotated[float, Field(gt=0, le=VARIANCE_FACTOR_MAX, allow_inf_nan=False)]
MAX_ITEMS = 100
SEARCH_STEPS = 48  # golden-section steps for a maximum inside a segment (0.618^48: 1e-10)


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

    @model_validator(mode="after")
    def _factors_in_range(self) -> NoiseSchedule:
        problem = self.factor_range_problem()
        if problem:
            raise ValueError(problem)
        return self

    def factor_range_problem(self) -> str | None:
        """Why the product of the variance factors in force at some instant (the changes and
        the outliers' inflation) leaves [VARIANCE_FACTOR_MIN, VARIANCE_FACTOR_MAX] on a
        channel, or None. Exact: between two consecutive change points the steps and outliers
        are constant and each ramp is affine, so the log of the product is a constant plus a
        sum of logs of affine functions, concave: its minimum is at an end of the segment, its
        maximum found by golden-section search (logs throughout: no overflow)."""
        ends = self.change_points()
        a = np.array([0.0, *ends])  # segments [a, b); the last one runs on with all constant
        b = np.array([*ends, ends[-1] + 1.0 if ends else 1.0])
        middle = (a + b) / 2
        held = self._log_held(middle)  # (segments, 4): steps and outliers in force on [a, b)
        ramps = _LogRamps([change for change in self.changes if change.shape == "ramp"])
        lo = held + np.minimum(ramps(a), ramps(b))
        hi = held + np.maximum(ramps(a), ramps(b))
        # Inside a segment the product can only pass its ends where each ramp's own maximum
        # would (a bound): search only there.
        search = (held + ramps.upper(a, b) > np.log(VARIANCE_FACTOR_MAX)).any(axis=1)
        if search.any():
            hi[search] = held[search] + _concave_max(ramps, a[search], b[search])
        for extreme, bound, beyond in (
            (hi, VARIANCE_FACTOR_MAX, np.greater), (lo, VARIANCE_FACTOR_MIN, np.less),
        ):  # fmt: skip
            bad = beyond(extreme, np.log(bound) + (1e-9 if bound > 1 else -1e-9))
            if bad.any():
                seg, ch = np.argwhere(bad)[0]
                return (
                    f"the variance factors in force at once on {CHANNELS[ch]} (from"
                    f" {a[seg]:g} s) multiply to {_power(extreme[seg, ch])}; allowed: every"
                    f" factor and the product of those in force at any instant (changes and"
                    f" outliers) within [{VARIANCE_FACTOR_MIN:g}, {VARIANCE_FACTOR_MAX:g}]"
                )
        return None

    def _log_held(self, t: np.ndarray) -> np.ndarray:
        """log of the steps' factors and the outliers' inflation at t, per channel."""
        out = np.zeros((len(t), len(CHANNELS)))
        for change in self.changes:
            if change.shape == "step":
                f = np.log(change.factor_at(t))
                for c in change.affected():
                    out[:, CHANNELS.index(c)] += f
        if self.outliers is not None:
            f = np.where(self.outliers.active(t), np.log(self.outliers.variance_inflation()), 0.0)
            for c in self.outliers.affected():
                out[:, CHANNELS.index(c)] += f
        return out

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


class _LogRamps:
    """t -> log of the ramps' factors at t, per channel (continuous in t): one matrix product
    over all ramps, as the range search calls it often."""

    def __init__(self, ramps: list[NoiseChange]):
        self.start = np.array([r.start_s for r in ramps])
        self.length = np.array([r.end_s - r.start_s for r in ramps])
        self.factor = np.array([r.factor for r in ramps])
        member = [[c in r.affected() for c in CHANNELS] for r in ramps]
        self.member = np.array(member, dtype=float).reshape(len(ramps), len(CHANNELS))

    def each(self, t: np.ndarray) -> np.ndarray:
        share = np.clip((np.asarray(t)[:, None] - self.start) / self.length, 0.0, 1.0)
        # (1 - share) + factor * share: exact at both ends, whatever the factor's size
        return np.log((1.0 - share) + self.factor * share)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return self.each(t) @ self.member

    def upper(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """A bound of the maximum on [a, b]: each ramp at its own largest end."""
        return np.maximum(self.each(a), self.each(b)) @ self.member


def _concave_max(f: Callable[[np.ndarray], np.ndarray], a: np.ndarray, b: np.ndarray):
    """The maximum over [a, b] of f (t -> (len(t), channels), each column concave in t on every
    segment), per segment and channel: golden-section search, the channels side by side."""
    best = np.maximum(f(a), f(b))
    n, channels = best.shape
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.repeat(a[:, None], channels, 1), np.repeat(b[:, None], channels, 1)
    own = np.arange(channels)

    def g(t: np.ndarray) -> np.ndarray:  # (n, channels) times -> each channel's own value
        return f(t.ravel()).reshape(n, channels, channels)[:, own, own]

    for _ in range(SEARCH_STEPS):
        m1, m2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        right = g(m2) >= g(m1)
        lo, hi = np.where(right, m1, lo), np.where(right, hi, m2)
    return np.maximum(best, g((lo + hi) / 2))


def _power(log_value: float) -> str:
    """exp(log_value) as text, also where it is beyond the float range ('1e+312')."""
    if not np.isfinite(log_value):
        return "0" if log_value < 0 else "inf"
    exponent = log_value / np.log(10.0)
    if abs(exponent) < 300:
        return f"{np.exp(log_value):.3g}"
    whole = int(np.floor(exponent))
    mantissa = f"{10 ** (exponent - whole):.3g}"
    if mantissa == "10":  # 9.9996 rounded
        mantissa, whole = "1", whole + 1
    return f"{mantissa}e{whole:+d}"


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
