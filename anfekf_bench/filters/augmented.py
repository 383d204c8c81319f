"""The augmented EKF (SPEC 18, kind `ekf-aug`): the robot's pose plus the odometry's scale
factors and turn bias (and optionally the range bias) as states.

Error model (the same form as the simulator's `error_sources.ErrorSources`):

    odometry   u_odo = (k_v * u0, k_w * u1 + b_w) + n,   n ~ N(0, Qu)
    range      z_r   = r + b_r + white noise

where (u0, u1) is the true control: (V, gamma) on the bicycle, (v, w) on the unicycle, so b_w is
a steering bias [rad] on the bicycle and a turn-rate bias [rad/s] on the unicycle. The filter
inverts it: the control it drives its motion model with is

    u_true = (u0_odo / k_v, (u1_odo - b_w) / k_w)

and the odometry's white noise, in true units, is n / k: Q = model.Q(G diag(1 / k_v, 1 / k_w),
Qu). Each estimated parameter is a state; those not estimated (`estimate`) are held at their
start values, so `estimate: []` with the injected values is the oracle that knows the errors
(an EKF on the corrected odometry). The parameters drift as random walks of `drift` per
square-root second (Q_theta = drift^2 dt). The state is (x, y, phi, then the estimated
parameters in the order speed_scale, turn_scale, turn_bias, range_bias); the scored pose and
the NEES are the pose block's.

Jacobians of one step: F = [[F_pose, G dU], [0, I]], dU = d u_true / d theta: -u0_true / k_v
for k_v, -u1_true / k_w for k_w, -1 / k_w for b_w; H = [H_pose, (1, 0) for b_r].

`ekf-aug-calibrated` (`CalibratedAugmentedSpec`, a fitted kind): which parameters to estimate,
and from what start and spread, learnt on the scenario's simulated training runs (ekf-aug from
a fixed grid of scale starts, the one of least training RMSE read by `calibrate`); the same
filter and kernels.

Combining with the adaptive families (`augment:` on `sage-husa` and `vb-r`, `Augmentable`):
their filter class runs on this state (`augmented_class`: this predict and innovation, then the
family's hooks). R-adapting rules read only nu, H P- H^T and H, so they apply unchanged; the VB
iteration's residual at an iterate adds the range bias (`residual_of`). The Q- and P-adapting
rules (Sage-Husa `adapt: RQ`, iae Q, vbakf, the banks' Qu hypotheses, so the default `vb-imm`)
project their estimates through the 3-state pose model and are not combined.
"""

from __future__ import annotations

import functools
import math
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from ..models import h
from ..models.range_bearing import H_jacobian, residual_z
from ..schema import StrictModel
from .ekf import Innovation, RobotEKF
from .fitted import FittedSpec
from .spec import FilterContext, FilterSpec, Role

PARAMETERS: tuple[str, ...] = ("speed_scale", "turn_scale", "turn_bias", "range_bias")
Parameter = Literal["speed_scale", "turn_scale", "turn_bias", "range_bias"]
# A scale estimate below this is used as this (the controls divide by it)
SCALE_FLOOR = 0.05
FourPositive = tuple[
    Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)],
]


class AugmentParams(StrictModel):
    """Which odometry and range errors are states, their start values, spreads and drift."""

    estimate: list[Parameter] = Field(
        ["speed_scale", "turn_scale", "turn_bias"],
        max_length=4,
        description="the parameters estimated as states (speed_scale, turn_scale, turn_bias,"
        " range_bias); the others are held at their start",
    )
    start: tuple[
        Annotated[float, Field(ge=0.1, le=10, allow_inf_nan=False)],
        Annotated[float, Field(ge=0.1, le=10, allow_inf_nan=False)],
        Annotated[float, Field(ge=-10, le=10, allow_inf_nan=False)],
        Annotated[float, Field(ge=-100, le=100, allow_inf_nan=False)],
    ] = Field(
        (1.0, 1.0, 0.0, 0.0),
        description="start values: speed scale, turn scale, turn bias [rad on the bicycle,"
        " rad/s on the unicycle], range bias [m]",
    )
    sigma0: FourPositive = Field(
        (0.1, 0.3, 0.05, 0.2),
        description="start standard deviations of the four parameters (those estimated)",
    )
    drift: FourPositive = Field(
        (1e-4, 1e-4, 1e-4, 1e-4),
        description="random-walk standard deviation of each parameter per square-root second"
        " (slow: constants of the wheels and the sensor)",
    )

    @field_validator("estimate")
    @classmethod
    def _distinct(cls, estimate: list[str]) -> list[str]:
        if len(set(estimate)) != len(estimate):
            raise ValueError("estimate: each parameter at most once")
        return estimate

    def estimated(self) -> tuple[int, ...]:
        """Indices into PARAMETERS of the estimated ones, in state order."""
        return tuple(i for i, p in enumerate(PARAMETERS) if p in self.estimate)


class AugmentedSpec(FilterSpec, AugmentParams):
    """The EKF with the odometry's scale factors and turn bias (optionally the range bias) as
    states: errors that are not white noise (SPEC 18)."""

    kind: Literal["ekf-aug"]
    fast_kernel: ClassVar[str | None] = "kernels_augmented"
    role: ClassVar[Role] = "adaptive"

    @property
    def augment(self) -> AugmentParams:
        return self

    def build(self, ctx: FilterContext) -> AugmentedEKF:
        return AugmentedEKF(**ctx.kwargs(), params=self, augment=self)


# The convergence tolerances docs/results/bias.md states (fixed before any scored run): 0.03 on a
# scale factor, 0.25 deg on the turn bias (a steering angle on the bicycle), 0.05 m on the range
# bias. `ekf-aug-calibrated` counts a parameter as present beyond them.
TOLERANCE: tuple[float, float, float, float] = (0.03, 0.03, math.radians(0.25), 0.05)
SIGMA0_FLOOR = 1e-9  # a present parameter's start standard deviation: at least this


def calibrate(ends, estimate, start, tolerance) -> dict:
    """`ekf-aug-calibrated`'s rule (fixed on training and development seeds before any scored
    run was looked at: examples/bias/calibrated.py, docs/results/bias.md). From each training
    run's parameter estimates at its end, `ends` (runs x 4, PARAMETERS' order; a row with a NaN,
    a run that lost its covariance, is left out): their mean m and between-run standard
    deviation s; a parameter of `estimate` is present when |m - start| > tolerance; the present
    ones are estimated from m with start standard deviation s (at least SIGMA0_FLOOR), the
    others held at `start`. ValueError when fewer than 2 runs are left."""
    ends = np.asarray(ends, dtype=float).reshape(-1, len(PARAMETERS))
    kept = ends[np.all(np.isfinite(ends), axis=1)]
    if len(kept) < 2:
        raise ValueError(
            f"{len(kept)} of {len(ends)} training runs ended with finite estimates: the"
            " calibration needs 2 or more (training.runs)"
        )
    m, s = kept.mean(axis=0), kept.std(axis=0, ddof=1)
    present = [
        p for i, p in enumerate(PARAMETERS)
        if p in estimate and abs(m[i] - start[i]) > tolerance[i]
    ]  # fmt: skip
    return {
        "estimate": present,
        "start": [
            float(m[i]) if p in present else float(start[i]) for i, p in enumerate(PARAMETERS)
        ],
        "sigma0": [
            max(float(s[i]), SIGMA0_FLOOR) if p in present else 0.0
            for i, p in enumerate(PARAMETERS)
        ],  # fmt: skip
        "training_mean": [float(v) for v in m],
        "training_sd": [float(v) for v in s],
        "training_runs_used": len(kept),
    }


# The candidate starts of a scale factor on the training runs, as multiples of its nominal start
# (fixed before any run with them was looked at). ekf-aug started at nominal loses lock when a
# scale is far off (a 1.6x steering scale; a 1.3x one it finds): from the nearest of these
# starts a scale within 0.4-2.5x is at most about 15 % off (neighbours 1.2-1.33x apart), well
# inside what it finds. Symmetric in log scale about 1, which it includes (the start that
# `calibrate` alone would use).
SCALE_STARTS: tuple[float, ...] = (0.5, 0.67, 0.8, 1.0, 1.25, 1.5, 2.0)
SCALE_INDICES = (0, 1)  # speed_scale, turn_scale in PARAMETERS


def start_candidates(estimate, start, factors) -> list[tuple[float, float, float, float]]:
    """The training runs' candidate starts: every combination of `factors` x `start` for the
    scale factors in `estimate` (speed outer, turn inner), the other parameters at `start`."""
    axes = [
        [start[i] * f for f in factors] if PARAMETERS[i] in estimate else [start[i]]
        for i in SCALE_INDICES
    ]
    return [(v, w, float(start[2]), float(start[3])) for v in axes[0] for w in axes[1]]


def choose_candidate(candidates, scores, start) -> int:
    """The index of the candidate of least training score (mean position RMSE over the
    training runs; NaN: a run lost its covariance, never chosen while another is finite); equal
    scores go to the candidate nearest `start` (sum over the scales of |log(candidate /
    start)|), then to the first."""
    scores = np.where(np.isfinite(scores), np.asarray(scores, dtype=float), np.inf)

    def distance(c):
        return sum(abs(math.log(c[i] / start[i])) for i in SCALE_INDICES)

    return min(range(len(candidates)), key=lambda k: (scores[k], distance(candidates[k]), k))


class CalibratedAugmentedSpec(FittedSpec, AugmentedSpec):
    """ekf-aug whose error states are chosen and started on the scenario's training runs: the
    parameters of `estimate` whose training estimates differ from `start` by more than
    `tolerance` are estimated, from their training mean with the training spread as start
    standard deviation; the others are held at `start` (SPEC 18, docs/results/bias.md).
    `start`, `sigma0` and `drift` are ekf-aug's on the training runs (`start`: the nominal
    values too); the scored runs keep `drift`.

    The fit (`fit_sources`: simulated training runs only; a recorded scenario refuses the kind:
    a vehicle's constants are its own, another drive's robot has others): ekf-aug with this
    spec's `estimate`, `sigma0` and `drift` on each training run (the fast engine's kernel)
    from each candidate start (`start_candidates`: the estimated scale factors at
    `scale_starts` x `start`, SCALE_STARTS by default; ekf-aug from the nominal start loses
    lock on a large scale error and would teach the rule a wrong one); the candidate of least
    mean position RMSE over the training runs (their truth; `choose_candidate`) gives the four
    estimates at each run's last record, and `calibrate` reads them against `start`. The
    manifest records which parameters are present, their start and spread, the training
    means, the chosen candidate start and every candidate's training RMSE."""

    kind: Literal["ekf-aug-calibrated"]
    fast_kernel: ClassVar[str | None] = "kernels_augmented"
    role: ClassVar[Role] = "fitted"
    fit_sources: ClassVar[frozenset[str]] = frozenset({"simulated"})
    estimate: list[Parameter] = Field(
        list(PARAMETERS),
        max_length=4,
        description="the candidates: the parameters estimated on the training runs, of which"
        " those found present are estimated in the scored runs (the others held at their start)",
    )
    tolerance: FourPositive = Field(
        TOLERANCE,
        description="a parameter is present when its training mean differs from its start by"
        " more than this: scales, turn bias [rad on the bicycle, rad/s on the unicycle], range"
        " bias [m] (default: the stated convergence tolerances, 0.03, 0.03, 0.25 deg, 0.05 m)",
    )
    scale_starts: list[Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)]] = Field(
        list(SCALE_STARTS),
        min_length=1,
        max_length=12,
        description="the training runs' candidate starts of each scale factor estimated, as"
        " multiples of its start: ekf-aug runs from every combination, and the one of least"
        " training RMSE gives the end estimates the rule reads ([1]: from the start only)",
    )

    def training_spec(self) -> AugmentedSpec:
        """The `ekf-aug` the training runs are filtered with: this spec's candidates, start,
        spreads and drift."""
        fields = self.model_dump(include=set(AugmentParams.model_fields))
        return AugmentedSpec(name=self.name, kind="ekf-aug", **fields)

    def training_problem(self, training_runs: int) -> str | None:
        if training_runs < 2:
            return (
                f"kind: {self.kind} needs training.runs of 2 or more (got {training_runs}): the"
                " training runs' spread is its start standard deviation"
            )
        return None

    def fit(self, training: Any) -> dict:
        # The training runs filter with ekf-aug from each candidate start
        # (fitting.simulated.TrainingSet.augmented_runs): a spec never imports an engine.
        base = self.training_spec()
        candidates = start_candidates(self.estimate, self.start, self.scale_starts)
        runs = [training.augmented_runs(base.model_copy(update={"start": c})) for c in candidates]
        scores = [float(np.mean(rmse)) for _, rmse in runs]
        best = choose_candidate(candidates, scores, self.start)
        fitted = calibrate(runs[best][0], self.estimate, self.start, self.tolerance)
        fitted["training_start"] = [float(v) for v in candidates[best]]
        fitted["candidates"] = [
            {"start": [float(v) for v in c[:2]],
             "training_rmse": s if math.isfinite(s) else None}
            for c, s in zip(candidates, scores, strict=True)
        ]  # fmt: skip
        problem = self.fit_problem(fitted)
        if problem:
            raise ValueError(f"the training runs give no usable calibration: {problem}")
        return fitted

    def fit_problem(self, fitted: Any) -> str | None:
        problem = super().fit_problem(fitted)
        if problem:
            return problem
        if not set(fitted.get("estimate") or []) <= set(self.estimate):
            return "estimate: a parameter that is not one of the candidates"
        try:
            self._params(fitted)
        except ValidationError as exc:
            err = exc.errors()[0]
            return f"{'.'.join(map(str, err['loc']))}: {err['msg']}"
        return None

    def _params(self, fitted: dict) -> AugmentParams:
        return AugmentParams(
            estimate=fitted.get("estimate"), start=fitted.get("start"),
            sigma0=fitted.get("sigma0"), drift=self.drift,
        )  # fmt: skip

    @property
    def augment(self) -> AugmentParams:
        """The fitted error states: those present, their start and spread."""
        return self._params(self.fitted)

    def build(self, ctx: FilterContext) -> AugmentedEKF:
        return AugmentedEKF(**ctx.kwargs(), params=self, augment=self.augment)


class Augmentable(StrictModel):
    """The `augment:` option of an adaptive family's spec (SPEC 18): its filter on the
    augmented state. The family's rule must adapt R only (a rule that adapts Qu or P- projects
    through the 3-state pose model)."""

    augment: AugmentParams | None = Field(
        None,
        description="estimate odometry scale factors, turn bias and range bias as states"
        " (ekf-aug's fields: estimate, start, sigma0, drift); {} for ekf-aug's defaults;"
        " null: the 3-state filter",
    )

    @model_validator(mode="after")
    def _r_only(self):
        if self.augment is not None and "Q" in str(getattr(self, "adapt", "R")):
            raise ValueError("augment: combines with R adaptation only (adapt: R)")
        return self

    def build_augmented(self, base: type, ctx: FilterContext):
        """The family's filter class `base` on the augmented state (`augmented_class`)."""
        return augmented_class(base)(**ctx.kwargs(), params=self, augment=self.augment)


def augment_of(spec) -> AugmentParams | None:
    """The augmentation a spec asks for: ekf-aug's own, an adaptive family's `augment:`, or
    None (the 3-state filter)."""
    return getattr(spec, "augment", None)


def true_controls(u0: float, u1: float, theta) -> tuple[float, float, float, float]:
    """(u0_true, u1_true, k_v, k_w) from the odometry and the parameters (scales floored)."""
    kv = max(theta[0], SCALE_FLOOR)
    kw = max(theta[1], SCALE_FLOOR)
    return u0 / kv, (u1 - theta[2]) / kw, kv, kw


def control_derivative(p: int, ut0: float, ut1: float, kv: float, kw: float) -> tuple[float, float]:
    """d u_true / d theta_p (a 2-vector)."""
    if p == 0:
        return -ut0 / kv, 0.0
    if p == 1:
        return 0.0, -ut1 / kw
    if p == 2:
        return 0.0, -1.0 / kw
    return 0.0, 0.0


class AugmentedState(RobotEKF):
    """A `RobotEKF` (or an adaptive subclass: `augmented_class`) on the augmented state (module
    docstring): predict and innovation replaced; filterpy's update as it is."""

    def __init__(self, x0, P0, Qu, R, model, dt, gate, params, augment: AugmentParams):
        super().__init__(x0, P0, Qu, R, model, dt, gate, params=params)
        self.est = augment.estimated()
        n = 3 + len(self.est)
        self.dim_x = n
        self.theta0 = np.array(augment.start, dtype=float)
        self.drift2 = np.array(augment.drift, dtype=float) ** 2
        x = np.zeros(n)
        x[:3] = x0
        P = np.zeros((n, n))
        P[:3, :3] = P0
        for i, p in enumerate(self.est):
            x[3 + i] = self.theta0[p]
            P[3 + i, 3 + i] = augment.sigma0[p] ** 2
        self.x, self.P = x, P
        self._I = np.eye(n)
        self.F = np.eye(n)
        self.Q = np.zeros((n, n))
        self._ut = (0.0, 0.0)

    @property
    def parameters(self) -> np.ndarray:
        """The four parameters now: the estimated ones from the state, the others as started."""
        theta = self.theta0.copy()
        for i, p in enumerate(self.est):
            theta[p] = self.x[3 + i]
        return theta

    def predict_x(self, u=0):
        self.x = self.x.copy()
        self.x[:3] = self.model.f(self.x[:3], np.array(self._ut), self.dt)

    def predict(self, u=0, dt: float | None = None):
        if dt is not None:
            self.dt = dt
        ut0, ut1, kv, kw = true_controls(float(u[0]), float(u[1]), self.parameters)
        self._ut = (ut0, ut1)
        Fp, Gp = self.model.jacobians(self.x[:3], np.array(self._ut), self.dt)
        G = Gp * np.array([1.0 / kv, 1.0 / kw])
        n = self.dim_x
        F = np.eye(n)
        F[:3, :3] = Fp
        Q = np.zeros((n, n))
        Q[:3, :3] = self.model.Q(G, self.Qu, self.dt)
        for i, p in enumerate(self.est):
            F[:3, 3 + i] = Gp @ np.array(control_derivative(p, ut0, ut1, kv, kw))
            Q[3 + i, 3 + i] = self.drift2[p] * self.dt
        self.F, self.G, self.Q = F, G, Q
        super(RobotEKF, self).predict(u)  # filterpy: predict_x, then P = F P F^T + Q

    def innovation(self, z: np.ndarray, landmark: np.ndarray) -> Innovation:
        pose = self.x[:3]
        H = np.zeros((2, self.dim_x))
        H[:, :3] = H_jacobian(pose, landmark)
        z_hat = h(pose, landmark)
        z_hat[0] += self.parameters[3]
        if 3 in self.est:
            H[0, 3 + self.est.index(3)] = 1.0
        nu = residual_z(np.asarray(z, dtype=float), z_hat)
        return Innovation(z=z, landmark=landmark, z_hat=z_hat, nu=nu, H=H, HPHt=H @ self.P @ H.T)

    def residual_of(self, inn: Innovation):
        """e(x) = wrap(z - h(x)) at an augmented iterate, the range bias included (the VB
        rules' residual)."""
        z = np.asarray(inn.z, dtype=float)
        landmark = inn.landmark

        def residual(x: np.ndarray) -> np.ndarray:
            return residual_z(z, augmented_z(x, landmark, self.est, self.theta0[3]))

        return residual


class AugmentedEKF(AugmentedState):
    """`ekf-aug`: the EKF on the augmented state."""


@functools.cache
def augmented_class(base: type) -> type:
    """`base` (an adaptive family's filter class) on the augmented state: the state's predict
    and innovation come first in the method order, the family's hooks after. Used only with
    rules that read nu, H P- H^T and H (R-adapting ones)."""
    return type(f"Augmented{base.__name__}", (AugmentedState, base), {})


def augmented_z(x: np.ndarray, landmark: np.ndarray, est: tuple[int, ...], range_bias0: float):
    """h of the augmented state: the pose's range and bearing, the range bias added."""
    z = h(x[:3], landmark)
    z[0] += x[3 + est.index(3)] if 3 in est else range_bias0
    return z


def augmented_f(model, x: np.ndarray, u: np.ndarray, dt: float, spec: AugmentedSpec) -> np.ndarray:
    """The augmented state's noise-free step (for the Jacobian checks): the pose by the model
    on the corrected controls, the parameters unchanged."""
    theta = np.array(spec.start, dtype=float)
    for i, p in enumerate(spec.estimated()):
        theta[p] = x[3 + i]
    ut0, ut1, _, _ = true_controls(float(u[0]), float(u[1]), theta)
    out = np.array(x, dtype=float)
    out[:3] = model.f(x[:3], np.array([ut0, ut1]), dt)
    return out


def augmented_h(x: np.ndarray, landmark: np.ndarray, spec: AugmentedSpec) -> np.ndarray:
    """The augmented state's measurement (for the Jacobian checks)."""
    return augmented_z(x, landmark, spec.estimated(), spec.start[3])
