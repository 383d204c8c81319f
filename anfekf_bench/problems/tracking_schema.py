"""The `system:` keys of `problem: tracking` (SPEC 17; the model: problems.tracking), validated
strictly: unknown keys, non-positive noise, a turn outside the run are one-line errors.

    system:
      T: 1.0                      # sampling period [s]
      steps: 200
      q: 0.5                      # white-acceleration intensity [m^2/s^3], per axis
      sigma_range: 10.0           # [m]
      sigma_bearing: 0.002        # [rad]
      radar: [0, 0]               # [m]
      x0: [2000, 10, 5000, -15]   # (x, vx, y, vy): mean of the true start, the filters' start
      P0_sd: [50, 5, 50, 5]       # standard deviations of the true start, the filters' P0
      gate: 0.999                 # chi-square probability of the gate (null: no gate)
      manoeuvre: {omega: 0.05, start: 80, end: 120, known: false}   # optional
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from ..schema import StrictModel
from .tracking import TrackingProblem, Turn

Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
MAX_STEPS = 10**6


class Manoeuvre(StrictModel):
    """A coordinated turn of the truth at a constant rate over the steps [start, end)."""

    omega: Annotated[float, Field(ge=-1, le=1, allow_inf_nan=False)] = Field(
        description="turn rate [rad/s], not 0 (positive: counter-clockwise)"
    )
    start: int = Field(ge=0, le=MAX_STEPS, description="first step of the turn")
    end: int = Field(ge=1, le=MAX_STEPS, description="first step after the turn")
    known: bool = Field(
        False, description="whether the filters are told of the turn (their f is the truth's)"
    )

    @model_validator(mode="after")
    def _a_turn(self) -> Manoeuvre:
        if self.omega == 0:
            raise ValueError("omega: a turn rate other than 0")
        if self.end <= self.start:
            raise ValueError("end: after start")
        return self


class TrackingSystem(StrictModel):
    """A nearly-constant-velocity target (x, vx, y, vy) seen by a range-bearing radar."""

    T: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = Field(
        1.0, description="sampling period [s]"
    )
    steps: int = Field(200, ge=10, le=MAX_STEPS, description="measurements per run")
    q: Annotated[float, Field(gt=0, le=1e8, allow_inf_nan=False)] = Field(
        0.5, description="white-acceleration intensity per axis [m^2/s^3]: Q = q blockdiag(B, B),"
        " B = [[T^3/3, T^2/2], [T^2/2, T]]",
    )  # fmt: skip
    sigma_range: Positive = Field(10.0, description="range noise standard deviation [m]")
    sigma_bearing: Annotated[float, Field(gt=0, le=3, allow_inf_nan=False)] = Field(
        0.002, description="bearing noise standard deviation [rad]"
    )
    radar: list[Finite] = Field([0.0, 0.0], description="the radar's position (x, y) [m]")
    x0: list[Finite] = Field(
        [2000.0, 10.0, 5000.0, -15.0],
        description="mean of the true start (x, vx, y, vy) [m, m/s], the filters' start",
    )
    P0_sd: list[Positive] = Field(
        [50.0, 5.0, 50.0, 5.0],
        description="standard deviations of the true start, the filters' P0 (diagonal)",
    )
    gate: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] | None = Field(
        0.999, description="chi-square probability (2 dof) of the measurement gate; null: none"
    )
    manoeuvre: Manoeuvre | None = Field(None, description="a coordinated-turn segment")

    @model_validator(mode="after")
    def _shapes(self) -> TrackingSystem:
        for key, size in (("radar", 2), ("x0", 4), ("P0_sd", 4)):
            if len(getattr(self, key)) != size:
                raise ValueError(f"{key}: expected {size} values")
        if np.hypot(self.x0[0] - self.radar[0], self.x0[2] - self.radar[1]) <= 0:
            raise ValueError("x0: the target starts at the radar (its bearing is undefined)")
        if self.manoeuvre is not None and self.manoeuvre.end > self.steps:
            raise ValueError(f"manoeuvre.end: at most steps ({self.steps})")
        return self

    def problem(self, steps: int | None = None) -> TrackingProblem:
        m = self.manoeuvre
        turn = None if m is None else Turn(m.omega, m.start, m.end, m.known)
        return TrackingProblem(
            T=self.T, q=self.q, sigma_range=self.sigma_range, sigma_bearing=self.sigma_bearing,
            radar=self.radar, x0=self.x0, P0=np.diag(np.square(self.P0_sd)),
            steps=self.steps if steps is None else steps, gate=self.gate, turn=turn,
        )  # fmt: skip
