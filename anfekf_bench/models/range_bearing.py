"""Range-bearing sensor of a known landmark (Havangi et al., eqs. 18, 22, 25).

State X = (x, y, phi), measurement z = (range, bearing); the same for every motion model.
"""

from __future__ import annotations

import math

import numpy as np

from .angles import wrap_scalar


def h(x: np.ndarray, landmark: np.ndarray) -> np.ndarray:
    """Range-bearing measurement of one landmark, eq. (18) / (22), bearing wrapped."""
    dx = landmark[0] - x[0]
    dy = landmark[1] - x[1]
    return np.array([math.hypot(dx, dy), wrap_scalar(math.atan2(dy, dx) - x[2])])


def H_jacobian(x: np.ndarray, landmark: np.ndarray) -> np.ndarray:
    """H = dh/dX for one landmark, eq. (25)."""
    dx = landmark[0] - x[0]
    dy = landmark[1] - x[1]
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    return np.array(
        [
            [-dx / r, -dy / r, 0.0],
            [dy / q, -dx / q, -1.0],
        ]
    )


def residual_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Innovation a - b with the bearing component wrapped to (-pi, pi] (filterpy residual hook)."""
    y = a - b
    y[1] = wrap_scalar(y[1])
    return y


def measurement_covariance(sigma_range: float, sigma_bearing: float) -> np.ndarray:
    """R = diag(sr^2, sb^2), radians."""
    return np.diag([sigma_range**2, sigma_bearing**2])
