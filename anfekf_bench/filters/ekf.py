"""The EKF on filterpy's ExtendedKalmanFilter (SPEC 3): the base of every filter of the zoo.

Attribute names follow filterpy and the textbook: x, P, F, Q (3x3 process noise in state space),
R, H, S, K, y. The control-noise covariance the paper calls Q is `Qu` (2x2, on (V, gamma)); the
state-space Q is G Qu G^T (eq. 20).
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from ..models import F_jacobian, G_jacobian, H_jacobian, f, h, residual_z, wrap_scalar


def _given(value: np.ndarray, *args) -> np.ndarray:
    """filterpy calls HJacobian(x, *args) and Hx(x, *hx_args): hand back what we computed."""
    return args[0]


class FilterDiverged(RuntimeError):
    """The estimate or its covariance stopped being finite and positive definite."""


class RobotEKF(ExtendedKalmanFilter):
    """Car-like robot localisation EKF with a known landmark map.

    Predict, eqs. (19)-(21): x- = f(x, u), P- = F P F^T + G Qu G^T.
    Update, eqs. (22)-(29), one landmark at a time, filterpy's Joseph form, innovation bearing
    wrapped by `residual_z`, validation gate nu^T S^-1 nu <= gate (eq. 26).
    """

    def __init__(
        self,
        x0: np.ndarray,
        P0: np.ndarray,
        Qu: np.ndarray,
        R: np.ndarray,
        T: float,
        B: float,
        gate: float | None,
    ):
        super().__init__(dim_x=3, dim_z=2)
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        self.Qu = np.array(Qu, dtype=float)
        self.R = np.array(R, dtype=float)
        self.T = T
        self.B = B
        self.gate = gate
        self.nis_sum = 0.0
        self.n_updates = 0
        self.n_rejected = 0

    def predict_x(self, u=0):
        self.x = f(self.x, u, self.T, self.B)

    def predict(self, u=0):
        """Eqs. (19)-(21): F and G at the estimate and the received controls."""
        self.F = F_jacobian(self.x, u, self.T, self.B)
        G = G_jacobian(self.x, u, self.T, self.B)
        self.Q = G @ self.Qu @ G.T
        super().predict(u)

    def innovation(self, z: np.ndarray, landmark: np.ndarray):
        """H (eq. 25), predicted z (eq. 22), innovation nu (eq. 23), S (eq. 24)."""
        H = H_jacobian(self.x, landmark)
        z_hat = h(self.x, landmark)
        nu = residual_z(np.asarray(z, dtype=float), z_hat)
        HPHt = H @ self.P @ H.T
        return H, z_hat, nu, HPHt

    def supervise(self, nu: np.ndarray, H: np.ndarray, HPHt: np.ndarray) -> None:
        """Hook called at every landmark before the gain; the plain EKF changes nothing."""

    def update_landmark(self, z: np.ndarray, landmark: np.ndarray) -> bool:
        """Gate and fuse one range-bearing measurement; False if the gate rejected it."""
        H, z_hat, nu, HPHt = self.innovation(z, landmark)
        self.supervise(nu, H, HPHt)
        S = HPHt + self.R
        nis = float(nu @ np.linalg.solve(S, nu))
        if not math.isfinite(nis):
            raise FilterDiverged(f"innovation or its covariance is not finite (NIS {nis})")
        if self.gate is not None and not nis <= self.gate:
            self.n_rejected += 1
            return False
        self.nis_sum += nis
        self.n_updates += 1
        self.update(
            z, HJacobian=_given, Hx=_given, args=(H,), hx_args=(z_hat,), residual=residual_z
        )
        self.x[2] = wrap_scalar(self.x[2])
        # Joseph form keeps P symmetric only up to round-off; keep it exactly symmetric.
        self.P = 0.5 * (self.P + self.P.T)
        return True


def gate_threshold(probability: float | None) -> float | None:
    """G of eq. (26): the chi-square(2) quantile, or None for no gate."""
    return None if probability is None else float(chi2.ppf(probability, 2))
