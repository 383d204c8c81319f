"""Vehicle and sensor models of the paper (Havangi et al., Section 4).

State X = (x, y, phi), control u = (V, gamma), measurement z = (range, bearing).
Every function is pure and works on plain float arrays; equation numbers refer to the paper.
"""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(a):
    """Wrap angles to (-pi, pi] (scalar or array)."""
    return -((-np.asarray(a, dtype=float) + math.pi) % TWO_PI - math.pi)


def wrap_scalar(a: float) -> float:
    """Scalar `wrap_angle` without numpy overhead, for the simulation's inner loop."""
    return -((-a + math.pi) % TWO_PI - math.pi)


def f(x: np.ndarray, u: np.ndarray, T: float, B: float) -> np.ndarray:
    """Discrete motion model, eq. (17) with zero noise: X+ = f(X, u)."""
    V, gamma = u[0], u[1]
    a = x[2] + gamma
    return np.array(
        [
            x[0] + T * V * math.cos(a),
            x[1] + T * V * math.sin(a),
            wrap_scalar(x[2] + T * V * math.sin(gamma) / B),
        ]
    )


def F_jacobian(x: np.ndarray, u: np.ndarray, T: float, B: float) -> np.ndarray:
    """F = df/dX at (X, u), eqs. (9) and (21)."""
    V, gamma = u[0], u[1]
    a = x[2] + gamma
    return np.array(
        [
            [1.0, 0.0, -T * V * math.sin(a)],
            [0.0, 1.0, T * V * math.cos(a)],
            [0.0, 0.0, 1.0],
        ]
    )


def G_jacobian(x: np.ndarray, u: np.ndarray, T: float, B: float) -> np.ndarray:
    """G = df/du at (X, u), eqs. (10) and (21)."""
    V, gamma = u[0], u[1]
    a = x[2] + gamma
    ca, sa = math.cos(a), math.sin(a)
    return np.array(
        [
            [T * ca, -T * V * sa],
            [T * sa, T * V * ca],
            [T * math.sin(gamma) / B, T * V * math.cos(gamma) / B],
        ]
    )


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


def control_covariance(sigma_v: float, sigma_gamma: float) -> np.ndarray:
    """Q = diag(sv^2, sg^2): covariance of the CONTROL noise (SPEC 3), radians."""
    return np.diag([sigma_v**2, sigma_gamma**2])


def measurement_covariance(sigma_range: float, sigma_bearing: float) -> np.ndarray:
    """R = diag(sr^2, sb^2), radians."""
    return np.diag([sigma_range**2, sigma_bearing**2])
