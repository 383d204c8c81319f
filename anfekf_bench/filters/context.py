"""What a filter starts from in a run, whatever the source (SPEC 12): its noise (the true, the
fitted or the assumed, times a naive start), the start state and covariance, the motion model
and the gate. `start_context` is the one constructor; `filter_context` says what a simulated
run starts from, `recorded_context` what a recorded segment or drive starts from. Below the
registry and every family, so that a spec may build its own context (a fit does) without
importing the registry."""

from __future__ import annotations

import numpy as np

from ..models import Bicycle, Unicycle, control_covariance, measurement_covariance
from ..schedule import ScheduledNoise
from .ekf import RobotEKF, gate_threshold
from .spec import FilterContext, FilterSpec

Sigmas = tuple[float, float, float, float]  # (control: sv, sg or sw; measurement: sr, sb)


def start_context(
    Qu: np.ndarray, R: np.ndarray, *, x0: np.ndarray, P0: np.ndarray, model, dt: float,
    gate_probability: float | None, true_noise: ScheduledNoise | None = None,
) -> FilterContext:  # fmt: skip
    """The one constructor of a filter's starting context, whatever the source."""
    return FilterContext(
        x0=x0,
        P0=P0,
        Qu=Qu,
        R=R,
        model=model,
        dt=dt,
        gate=gate_threshold(gate_probability),
        true_noise=true_noise,
    )


def filter_context(spec: FilterSpec, scenario, world, start: float | None = None) -> FilterContext:
    """What `spec`'s filter starts from in a run of `scenario` on the simulated `world`: the
    oracle gets the true noise, a filter fitted on training runs its fitted noise
    (filters.fitted), every other filter the assumed one, each standard deviation times `start`
    (a naive start, `instances`)."""
    noise = scenario.true_noise if spec.uses_true_noise else scenario.filter_noise
    fitted = spec.fitted_sigmas() if spec.fitted_on_training else None
    schedule = getattr(scenario, "noise_schedule", None)
    true_noise = None
    if spec.uses_true_noise and schedule is not None:  # SPEC 14: the true noise of every step
        true_noise = ScheduledNoise(schedule, noise.radians(), world.T)
    sv, sg, sr, sb = noise.radians() if fitted is None else fitted
    if start is not None:
        sv, sg, sr, sb = sv * start, sg * start, sr * start, sb * start
    return start_context(
        control_covariance(sv, sg),
        measurement_covariance(sr, sb),
        x0=world.x0,
        P0=np.eye(3) * scenario.p0,
        model=Bicycle(world.T, world.B),
        dt=world.T,
        gate_probability=scenario.gate_probability,
        true_noise=true_noise,
    )


def recorded_p0(scenario) -> np.ndarray:
    """P0 of every filter of a recorded scenario (its `p0_std_xy`, `p0_std_phi_rad`)."""
    return np.diag([scenario.p0_std_xy**2, scenario.p0_std_xy**2, scenario.p0_std_phi_rad**2])


def recorded_context(
    scenario, pose: np.ndarray, start: float | None, sigmas: Sigmas | None = None
) -> FilterContext:
    """What a filter starts from on a recorded segment or drive of `scenario`: ground truth's
    `pose`, the Unicycle of the odometry period, and `sigmas` (ekf-tuned's tuned noise, ekf-ml's
    fitted one) or else the naive guess times `start` (a trained filter, one instance, gets the
    naive x1)."""
    if sigmas is None:
        sigmas, start = scenario.naive.sigmas(), 1.0 if start is None else start
    sv, sw, sr, sb = np.asarray(sigmas, dtype=float) * (1.0 if start is None else start)
    # Squared by product, where `filter_context` squares by power (models' covariances): the
    # two differ in the last bit for about 0.1 % of values, and each source's tables were
    # committed with its own.
    return start_context(
        np.diag([sv * sv, sw * sw]),
        np.diag([sr * sr, sb * sb]),
        x0=np.array(pose, dtype=float),
        P0=recorded_p0(scenario),
        model=Unicycle(scenario.odometry_period_s),
        dt=scenario.odometry_period_s,
        gate_probability=scenario.gate_probability,
    )


def build_filter(spec: FilterSpec, scenario, world) -> RobotEKF:
    """A fresh filter for one run of `scenario` (see `filter_context`)."""
    return spec.build(filter_context(spec, scenario, world))
