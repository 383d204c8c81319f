"""The filters: the EKF on filterpy's ExtendedKalmanFilter (SPEC 3) and the ANFEKF (SPEC 4).

Attribute names follow filterpy and the textbook: x, P, F, Q (3x3 process noise in state space),
R, H, S, K, y. The control-noise covariance the paper calls Q is `Qu` (2x2, on (V, gamma)); the
state-space Q is G Qu G^T (eq. 20).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from . import anfis
from .config import ANFEKFSpec, EKFSpec, OracleSpec
from .models import F_jacobian, G_jacobian, H_jacobian, f, h, residual_z


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

    def supervise(self, nu: np.ndarray, HPHt: np.ndarray) -> None:
        """Hook called at every landmark before the gain; the plain EKF changes nothing."""

    def update_landmark(self, z: np.ndarray, landmark: np.ndarray) -> bool:
        """Gate and fuse one range-bearing measurement; False if the gate rejected it."""
        H, z_hat, nu, HPHt = self.innovation(z, landmark)
        self.supervise(nu, HPHt)
        S = HPHt + self.R
        nis = float(nu @ np.linalg.solve(S, nu))
        if self.gate is not None and not nis <= self.gate:
            self.n_rejected += 1
            return False
        self.nis_sum += nis
        self.n_updates += 1
        self.update(
            z, HJacobian=_given, Hx=_given, args=(H,), hx_args=(z_hat,), residual=residual_z
        )
        # Joseph form keeps P symmetric only up to round-off; keep it exactly symmetric.
        self.P = 0.5 * (self.P + self.P.T)
        return True


class ANFEKF(RobotEKF):
    """EKF plus an ANFIS supervisor that adapts R (two ANFIS, Sec. 5.1) or Qu (one, Sec. 5.2).

    At each landmark, before the gain (SPEC 4): covariance matching over the last N innovations,
    C = (1/N) sum nu nu^T (eq. 30), theoretical S = H P- H^T + R (eq. 24), normalised mismatch
    d_ii = (S_ii - C_ii) / (S_ii + C_ii) and its change; ANFIS output o; then
    R_ii <- R_ii exp(o_i) (eq. 33) or Qu <- Qu exp(o) (eq. 44); then one steepest-descent step on
    E = e^2 / 2, e the mismatch left after the adaptation (eqs. 39-42).
    """

    def __init__(self, *args, spec: ANFEKFSpec, **kwargs):
        super().__init__(*args, **kwargs)
        self.spec = spec
        self.window: deque[np.ndarray] = deque(maxlen=spec.window)
        self.C_sum = np.zeros((2, 2))
        self.d_prev: np.ndarray | None = None
        self.eta = tuple(spec.learning_rate)
        if spec.adapt == "R":
            init = dict(
                centres0=spec.centres_d,
                centres1=spec.centres_dd,
                width0=spec.width_d,
                width1=spec.width_dd,
                singleton_scale=spec.singleton_scale,
            )
            self.anfis_params = [anfis.init_params(**init), anfis.init_params(**init)]
        else:
            self.anfis_params = [
                anfis.init_params(
                    centres0=spec.centres_d,
                    centres1=spec.centres_d,
                    width0=spec.width_d,
                    width1=spec.width_d,
                    singleton_scale=spec.singleton_scale,
                )
            ]
        # Process noise G Qu G^T added since the last scan: first-order dS/dQ model (SPEC 4).
        self.Q_interval = np.zeros((3, 3))
        self._scan_open = False

    def predict(self, u=0):
        super().predict(u)
        if self._scan_open:
            self.Q_interval = np.zeros((3, 3))
            self._scan_open = False
        self.Q_interval += self.Q

    def supervise(self, nu: np.ndarray, HPHt: np.ndarray) -> None:
        self._scan_open = True
        outer = np.outer(nu, nu)
        if len(self.window) == self.window.maxlen:
            self.C_sum -= self.window[0]
        self.window.append(outer)
        self.C_sum += outer
        if len(self.window) < self.window.maxlen or not self.spec.adaptation:
            return
        C = np.diag(self.C_sum) / len(self.window)
        S = np.diag(HPHt) + np.diag(self.R)
        d = (S - C) / (S + C)
        dd = np.zeros(2) if self.d_prev is None else d - self.d_prev
        self.d_prev = d
        if self.spec.adapt == "R":
            self._adapt_R(d, dd, C, np.diag(HPHt))
        else:
            self._adapt_Q(d, C, S, nu)

    def _clipped(self, o: float) -> tuple[float, float]:
        """o clipped to +-output_clip, and do_clipped/do (0 where the clip is active)."""
        c = self.spec.output_clip
        return (o, 1.0) if -c <= o <= c else (math.copysign(c, o), 0.0)

    def _adapt_R(self, d: np.ndarray, dd: np.ndarray, C: np.ndarray, HPH: np.ndarray) -> None:
        """Eq. (33) with DeltaR_ii = R_ii (exp(o) - 1), then SD on e = (S'-C)/(S'+C)."""
        R_diag = np.diag(self.R).copy()
        for i in range(2):
            params = self.anfis_params[i]
            o_raw, do_dW = anfis.output_and_gradient(params, (d[i], dd[i]))
            o, slope = self._clipped(o_raw)
            R_diag[i] *= math.exp(o)
            if self.spec.learning and slope:
                S_new = HPH[i] + R_diag[i]
                e = (S_new - C[i]) / (S_new + C[i])
                dE_do = e * 2.0 * C[i] / (S_new + C[i]) ** 2 * R_diag[i]
                self.anfis_params[i] = anfis.sgd_step(params, _scaled(do_dW, dE_do), self.eta)
        self.R = np.diag(R_diag)

    def _adapt_Q(self, d: np.ndarray, C: np.ndarray, S: np.ndarray, nu: np.ndarray) -> None:
        """Eq. (44): Qu <- Qu exp(o); SD with S'(o) = S + (e^o - 1) diag(H Q_interval H^T)."""
        params = self.anfis_params[0]
        o_raw, do_dW = anfis.output_and_gradient(params, (d[0], d[1]))
        o, slope = self._clipped(o_raw)
        scale = math.exp(o)
        self.Qu = self.Qu * scale
        if self.spec.learning and slope:
            H = self._H_last
            # After earlier landmarks of the same scan P has shrunk, so the interval's process
            # noise can exceed what is left of H P H^T; capping it there keeps S' > 0 and bounds
            # |dE/do| by sum |e_i| / 2.
            dS_dscale = np.minimum(
                np.einsum("ij,jk,ik->i", H, self.Q_interval, H), S - np.diag(self.R)
            )
            S_new = S + (scale - 1.0) * dS_dscale
            e = (S_new - C) / (S_new + C)
            dE_do = float(np.sum(e * 2.0 * C / (S_new + C) ** 2 * scale * dS_dscale))
            self.anfis_params[0] = anfis.sgd_step(params, _scaled(do_dW, dE_do), self.eta)
        self.Q_interval = self.Q_interval * scale

    def innovation(self, z, landmark):
        H, z_hat, nu, HPHt = super().innovation(z, landmark)
        self._H_last = H
        return H, z_hat, nu, HPHt


def _scaled(g: anfis.ANFISParams, k: float) -> anfis.ANFISParams:
    return anfis.ANFISParams(m=g.m * k, delta=g.delta * k, w=g.w * k)


def gate_threshold(probability: float | None) -> float | None:
    """G of eq. (26): the chi-square(2) quantile, or None for no gate."""
    return None if probability is None else float(chi2.ppf(probability, 2))


def build_filter(spec, scenario, world, true_sigmas, filter_sigmas) -> RobotEKF:
    """A fresh filter for one run, from its spec and the scenario (sigmas in radians)."""
    sigmas = true_sigmas if isinstance(spec, OracleSpec) else filter_sigmas
    sv, sg, sr, sb = sigmas
    kwargs = dict(
        x0=world.x0,
        P0=np.eye(3) * scenario.p0,
        Qu=np.diag([sv**2, sg**2]),
        R=np.diag([sr**2, sb**2]),
        T=world.T,
        B=world.B,
        gate=gate_threshold(scenario.gate_probability),
    )
    if isinstance(spec, (EKFSpec, OracleSpec)):
        return RobotEKF(**kwargs)
    return ANFEKF(**kwargs, spec=spec)
