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


def jacobians(x: np.ndarray, u: np.ndarray, T: float, B: float) -> tuple[np.ndarray, np.ndarray]:
    """F = df/dX (3x3) and G = df/du (3x2) at (X, u), eqs. (9), (10) and (21): one call, because
    both need the same angle (and a filter always wants both)."""
    V, gamma = u[0], u[1]
    a = x[2] + gamma
    ca, sa = math.cos(a), math.sin(a)
    TV = T * V
    F = np.array(
        [
            [1.0, 0.0, -TV * sa],
            [0.0, 1.0, TV * ca],
            [0.0, 0.0, 1.0],
        ]
    )
    G = np.array(
        [
            [T * ca, -TV * sa],
            [T * sa, TV * ca],
            [T * math.sin(gamma) / B, TV * math.cos(gamma) / B],
        ]
    )
    return F, G


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

    def jacobians(self, x: np.ndarray, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return jacobians(x, u, dt, self.B)

    def Q(self, G: np.ndarray, Qu: np.ndarray, dt: float) -> np.ndarray:
        """Eq. (20): G Qu G^T."""
        return G @ Qu @ G.T
