"""What a filter needs of a motion model: the step f, its Jacobians, and the step's process noise.

Every model works on the pose X = (x, y, phi) and a 2-vector control u; `dt` is the step's length
[s]. The simulator's bicycle has a fixed dt (the control period); recorded logs have varying ones.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class MotionModel(Protocol):
    """A discrete motion model X+ = f(X, u, dt) with additive control noise of covariance Qu."""

    def f(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """The noise-free step, heading wrapped to (-pi, pi]."""

    def jacobians(self, x: np.ndarray, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """F = df/dX (3x3) and G = df/du (3x2) at (X, u)."""

    def Q(self, G: np.ndarray, Qu: np.ndarray, dt: float) -> np.ndarray:
        """The step's state-space process noise from the control-noise covariance Qu (2x2)."""
