"""Errors that are not white noise (SPEC 18): the scenario's `error_sources` block.

A simulated robot's odometry and range sensor with the errors real ones have, on top of the
white noise of `true_noise` (and of a `noise_schedule`):

    odometry   u_odo = (speed_scale * V, steering_scale * gamma + steering_bias) + white noise
    range      z_range = r + range_bias + white noise

so `speed_scale` 1.1 is an odometry that reads 10 % fast and `steering_scale` 1.6 one that
overstates the steering (the bicycle's turn) 1.6x, as Dataset 9's commanded turn rate overstates
the true one. The parameters are constant over a run and the same in every run; they take no
random draw, so a scenario's runs draw exactly what they draw without them. Heavy-tailed bearing
errors are the noise schedule's Student-t outliers on the bearing channel (`schedule.Outliers`,
`channels: [bearing]`): one place per concept.

The augmented EKF (`filters.augmented`, kind `ekf-aug`) estimates the same four numbers in the
same form, so its estimates compare with these directly.
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from .schema import StrictModel

Scale = Annotated[float, Field(ge=0.1, le=10, allow_inf_nan=False)]


class ErrorSources(StrictModel):
    """Odometry scale factors and biases of the simulated robot (module docstring)."""

    speed_scale: Scale = Field(1.0, description="odometry speed over the true speed")
    steering_scale: Scale = Field(
        1.0, description="odometry steering angle over the true one (the turn's scale factor)"
    )
    steering_bias_deg: float = Field(
        0.0, ge=-30, le=30, allow_inf_nan=False, description="added to the odometry steering [deg]"
    )
    range_bias: float = Field(
        0.0, ge=-100, le=100, allow_inf_nan=False, description="added to every range [m]"
    )

    @model_validator(mode="after")
    def _not_empty(self) -> ErrorSources:
        if self.parameters() == (1.0, 1.0, 0.0, 0.0):
            raise ValueError("error_sources: every source is off (drop the block)")
        return self

    def parameters(self) -> tuple[float, float, float, float]:
        """(speed scale, steering scale, steering bias [rad], range bias [m]): the order of the
        augmented EKF's parameter states."""
        return (
            self.speed_scale,
            self.steering_scale,
            math.radians(self.steering_bias_deg),
            self.range_bias,
        )

    def odometry(self, u_true: np.ndarray, u_odo: np.ndarray) -> np.ndarray:
        """The odometry with these errors, from the true controls and the white-noise odometry
        u_odo = u_true + n: scale * u_true + bias + n."""
        kv, kg, bg, _ = self.parameters()
        out = np.array(u_odo, dtype=float)
        out[:, 0] += (kv - 1.0) * u_true[:, 0]
        out[:, 1] += (kg - 1.0) * u_true[:, 1] + bg
        return out

    def ranges(self, z_range: np.ndarray) -> np.ndarray:
        """Measured ranges with the range bias added."""
        return z_range + self.range_bias
