"""Car-like (bicycle) vehicle model of the paper (Havangi et al., Section 4).

State X = (x, y, phi), control u = (V, gamma). Every function is pure and works on plain float
arrays; equation numbers refer to the paper.
"""

from __future__ import annotations

import math

import numpy as np

from .angles import wrap_scalar


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


def control_covariance(sigma_v: float, sigma_gamma: float) -> np.ndarray:
    """Q = diag(sv^2, sg^2): covariance of the CONTROL noise (SPEC 3), radians."""
    return np.diag([sigma_v**2, sigma_gamma**2])


class Bicycle:
    """The paper's car-like model (eq. 17) as a `MotionModel`; one step is one control period.

    `dt` must equal the control period T the model was made with: the paper's noise Qu is per
    control step (Q = G Qu G^T, eq. 20), so this model is not for variable steps.
    """

    def __init__(self, T: float, B: float):
        self.T = T
        self.B = B

    def f(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        return f(x, u, dt, self.B)

    def F(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        return F_jacobian(x, u, dt, self.B)

    def G(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        return G_jacobian(x, u, dt, self.B)

    def Q(self, G: np.ndarray, Qu: np.ndarray, dt: float) -> np.ndarray:
        """Eq. (20): G Qu G^T."""
        return G @ Qu @ G.T
