"""Car-like (bicycle) vehicle model of the paper (Havangi et al., Section 4).

State X = (x, y, phi), control u = (V, gamma). Every function is pure and works on plain float
arrays; equation numbers refer to the paper.
"""

from __future__ import annotations

import numpy as np

from .motion_terms import MOTION_BICYCLE, jacobian_arrays, next_pose, step_terms


def f(x: np.ndarray, u: np.ndarray, T: float, B: float) -> np.ndarray:
    """Discrete motion model, eq. (17) with zero noise: X+ = f(X, u) (models.motion_terms:
    the formulas the fast engine compiles)."""
    return next_pose(x, step_terms(u[0], u[1], T, MOTION_BICYCLE, B))


def jacobians(x: np.ndarray, u: np.ndarray, T: float, B: float) -> tuple[np.ndarray, np.ndarray]:
    """F = df/dX (3x3) and G = df/du (3x2) at (X, u), eqs. (9), (10) and (21): one call, because
    both need the same angle (and a filter always wants both)."""
    return jacobian_arrays(x[2], step_terms(u[0], u[1], T, MOTION_BICYCLE, B))


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
