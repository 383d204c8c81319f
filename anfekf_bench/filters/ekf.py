"""The EKF on filterpy's ExtendedKalmanFilter (SPEC 3): the base of every filter of the zoo.

Attribute names follow filterpy and the textbook: x, P, F, Q (3x3 process noise in state space),
R, H, S, K, y. The control-noise covariance the paper calls Q is `Qu` (2x2, on the controls); the
state-space Q of one step comes from the motion model (bicycle: G Qu G^T, eq. 20).

A filter of the zoo differs from this EKF only in its adaptation, written in four hooks that the
engine calls in a fixed order (SPEC 7, multi-rate events):

    predict(u)                      every control step
    begin_scan()                    once per scan that saw a landmark, before its first update
    before_gain(inn)                every associated landmark (gated or not), before the gain:
                                    may change R (R events) or P- (P inflation)
    correct(z, landmark, inn)       the landmark update itself (VB filters iterate here)
    after_update(inn)               after an accepted update (residual-based rules)
    end_scan()                      once per scan that saw a landmark, after its updates (Q events)

`inn` is an `Innovation`: what the filter used (navlie style), so that adaptive logic and
diagnostics need no private access.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from ..models import MotionModel, h, residual_z, wrap_scalar
from ..models.range_bearing import H_jacobian
from .spec import FilterContext, FilterSpec, Role


def _given(value: np.ndarray, *args) -> np.ndarray:
    """filterpy calls HJacobian(x, *args) and Hx(x, *hx_args): hand back what we computed."""
    return args[0]


class FilterDiverged(RuntimeError):
    """The estimate or its covariance stopped being finite and positive definite."""


@dataclass
class Innovation:
    """One landmark measurement as the filter saw it before its gain (eqs. 22-24).

    z: measurement (range, bearing); z_hat = h(x-); nu = z - z_hat, bearing wrapped (eq. 23);
    H = dh/dX at x- (eq. 25); HPHt = H P- H^T; R: the R in force when the gain was computed
    (after `before_gain`); S = HPHt + R (eq. 24); nis = nu^T S^-1 nu; accepted: passed the gate.
    """

    z: np.ndarray
    landmark: np.ndarray
    z_hat: np.ndarray
    nu: np.ndarray
    H: np.ndarray
    HPHt: np.ndarray
    R: np.ndarray | None = None
    S: np.ndarray | None = None
    nis: float = math.nan
    accepted: bool = False


class RobotEKF(ExtendedKalmanFilter):
    """Robot localisation EKF with a known landmark map, on any `MotionModel`.

    Predict, eqs. (19)-(21): x- = f(x, u), P- = F P F^T + Q(G, Qu).
    Update, eqs. (22)-(29), one landmark at a time, filterpy's Joseph form, innovation bearing
    wrapped by `residual_z`, validation gate nu^T S^-1 nu <= gate (eq. 26).

    Subclasses declare what they adapt in `adapts` ({"R"}, {"Q"}, {"P"} or several) and override
    the hooks above; `params` holds their validated parameter block (the scenario's filter spec).
    """

    adapts: ClassVar[frozenset[str]] = frozenset()
    # False for a filter without a covariance (KalmanNet): its P is NaN, its NEES not available.
    has_covariance: ClassVar[bool] = True

    def __init__(
        self,
        x0: np.ndarray,
        P0: np.ndarray,
        Qu: np.ndarray,
        R: np.ndarray,
        model: MotionModel,
        dt: float,
        gate: float | None,
        params: Any = None,
    ):
        super().__init__(dim_x=3, dim_z=2)
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        self.Qu = np.array(Qu, dtype=float)
        self.R = np.array(R, dtype=float)
        self.R0 = self.R.copy()
        self.Qu0 = self.Qu.copy()
        self.model = model
        self.dt = dt
        self.gate = gate
        self.params = params
        self.G = np.zeros((3, 2))
        self.P_inflation = 1.0  # what `before_gain` scaled P- by last (1: no inflation)
        self.nis_sum = 0.0
        self.n_updates = 0
        self.n_rejected = 0

    # -- predict ------------------------------------------------------------------------------

    def predict_x(self, u=0):
        self.x = self.model.f(self.x, u, self.dt)

    def predict(self, u=0, dt: float | None = None):
        """Eqs. (19)-(21): F and G at the estimate and the received controls; `dt` for models
        with variable steps (recorded logs), else the filter's own step."""
        if dt is not None:
            self.dt = dt
        self.F, self.G = self.model.jacobians(self.x, u, self.dt)
        self.Q = self.model.Q(self.G, self.Qu, self.dt)
        super().predict(u)

    # -- hooks of the adaptive filters (the plain EKF changes nothing) -------------------------

    def begin_scan(self) -> None:
        """Once per scan that saw a landmark, before its first update (forgetting factors)."""

    def before_gain(self, inn: Innovation) -> None:
        """Every associated landmark, gated or not, before the gain: may set R or scale P."""

    def after_update(self, inn: Innovation) -> None:
        """After an accepted update: x and P are the posterior (residual-based rules)."""

    def end_scan(self) -> None:
        """Once per scan that saw a landmark, after its updates (Q events)."""

    # -- update -------------------------------------------------------------------------------

    def innovation(self, z: np.ndarray, landmark: np.ndarray) -> Innovation:
        """H (eq. 25), predicted z (eq. 22), innovation nu (eq. 23) and H P- H^T at x-."""
        H = H_jacobian(self.x, landmark)
        z_hat = h(self.x, landmark)
        nu = residual_z(np.asarray(z, dtype=float), z_hat)
        return Innovation(z=z, landmark=landmark, z_hat=z_hat, nu=nu, H=H, HPHt=H @ self.P @ H.T)

    def update_landmark(self, z: np.ndarray, landmark: np.ndarray) -> bool:
        """Adapt, gate and fuse one range-bearing measurement; False if the gate rejected it."""
        inn = self.innovation(z, landmark)
        self.before_gain(inn)
        if self.P_inflation != 1.0:  # the hook scaled P-: H P- H^T follows it
            inn.HPHt = inn.H @ self.P @ inn.H.T
        inn.R = self.R
        inn.S = inn.HPHt + self.R
        inn.nis = float(inn.nu @ np.linalg.solve(inn.S, inn.nu))
        if not math.isfinite(inn.nis):
            raise FilterDiverged(f"innovation or its covariance is not finite (NIS {inn.nis})")
        if self.gate is not None and not inn.nis <= self.gate:
            self.n_rejected += 1
            return False
        inn.accepted = True
        self.nis_sum += inn.nis
        self.n_updates += 1
        self.correct(z, landmark, inn)
        self.after_update(inn)
        return True

    def correct(self, z: np.ndarray, landmark: np.ndarray, inn: Innovation) -> None:
        """The measurement update with the gain of `inn` (filterpy's Joseph form, eqs. 26-29)."""
        self.update(
            z, HJacobian=_given, Hx=_given, args=(inn.H,), hx_args=(inn.z_hat,),
            residual=residual_z,
        )  # fmt: skip
        self.x[2] = wrap_scalar(self.x[2])
        # Joseph form keeps P symmetric only up to round-off; keep it exactly symmetric.
        self.P = 0.5 * (self.P + self.P.T)

    def update_scan(self, zs: np.ndarray, landmarks: np.ndarray) -> None:
        """One scan that saw at least one landmark: begin_scan, each landmark, end_scan."""
        self.begin_scan()
        for z, landmark in zip(zs, landmarks, strict=True):
            self.update_landmark(z, landmark)
        self.end_scan()


def gate_threshold(probability: float | None) -> float | None:
    """G of eq. (26): the chi-square(2) quantile, or None for no gate."""
    return None if probability is None else _chi2_2_quantile(float(probability))


@functools.lru_cache(maxsize=64)
def _chi2_2_quantile(probability: float) -> float:
    # scipy's ppf costs ~0.3 ms a call, paid for every filter of every run otherwise
    return float(chi2.ppf(probability, 2))


class EKFSpec(FilterSpec):
    """The plain EKF with the scenario's assumed noise (`filter_noise`)."""

    kind: Literal["ekf"] = "ekf"
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "tracking", "module"})
    problem_form: ClassVar[str | None] = "filters:EKFSpec"  # problems/filters.py
    role: ClassVar[Role] = "reference"
    fast_family: ClassVar[str | None] = "anfekf"

    def build(self, ctx: FilterContext) -> RobotEKF:
        return RobotEKF(**ctx.kwargs())


class ScheduledOracle(RobotEKF):
    """The oracle of a scenario whose true noise changes (SPEC 14): at every control step k it
    takes that step's true Qu and R (`schedule.ScheduledNoise`, t = k dt) before its predict, so
    the scan of step k is fused with the R in force at k. Otherwise the plain EKF."""

    def __init__(self, *, true_noise, **kwargs):
        super().__init__(**kwargs)
        self.true_noise = true_noise
        self.k = 0  # control steps predicted so far

    def predict(self, u=0, dt: float | None = None):
        self.k += 1
        v = self.true_noise.variances(self.k)
        self.Qu = np.diag(v[:2])
        self.R = np.diag(v[2:])
        super().predict(u, dt)


class OracleSpec(FilterSpec):
    """The EKF given the TRUE noise: the best fixed-noise EKF, a reference; with a noise
    schedule, the true noise of every step (`ScheduledOracle`)."""

    kind: Literal["ekf-oracle"]
    problems: ClassVar[frozenset[str]] = frozenset({"robot", "linear", "tracking", "module"})
    problem_form: ClassVar[str | None] = "filters:OracleSpec"  # problems/filters.py
    uses_true_noise: ClassVar[bool] = True
    role: ClassVar[Role] = "oracle"
    fast_family: ClassVar[str | None] = "anfekf"

    def build(self, ctx: FilterContext) -> RobotEKF:
        if ctx.true_noise is not None:
            return ScheduledOracle(true_noise=ctx.true_noise, **ctx.kwargs())
        return RobotEKF(**ctx.kwargs())
