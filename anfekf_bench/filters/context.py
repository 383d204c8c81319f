"""What a filter starts from in a simulated run: its noise (the true, the fitted or the assumed,
times a naive start), the start state and covariance, the motion model and the gate. Below the
registry and every family, so that a spec may build its own context (a fit does) without
importing the registry."""

from __future__ import annotations

import numpy as np

from ..models import Bicycle, control_covariance, measurement_covariance
from ..schedule import ScheduledNoise
from .ekf import RobotEKF, gate_threshold
from .spec import FilterContext, FilterSpec


def filter_context(spec: FilterSpec, scenario, world, start: float | None = None) -> FilterContext:
    """What `spec`'s filter starts from in a run of `scenario` on the simulated `world`: the
    oracle gets the true noise, a filter fitted on training runs its fitted noise
    (filters.fitted), every other filter the assumed one, each standard deviation times `start`
    (a naive start, `instances`)."""
    noise = scenario.true_noise if spec.uses_true_noise else scenario.filter_noise
    fitted = spec.fitted_sigmas() if spec.fitted_on_training else None
    sv, sg, sr, sb = noise.radians() if fitted is None else fitted
    if start is not None:
        sv, sg, sr, sb = sv * start, sg * start, sr * start, sb * start
    schedule = getattr(scenario, "noise_schedule", None)
    true_noise = None
    if spec.uses_true_noise and schedule is not None:  # SPEC 14: the true noise of every step
        true_noise = ScheduledNoise(schedule, noise.radians(), world.T)
    return FilterContext(
        x0=world.x0,
        P0=np.eye(3) * scenario.p0,
        Qu=control_covariance(sv, sg),
        R=measurement_covariance(sr, sb),
        model=Bicycle(world.T, world.B),
        dt=world.T,
        gate=gate_threshold(scenario.gate_probability),
        true_noise=true_noise,
    )


def build_filter(spec: FilterSpec, scenario, world) -> RobotEKF:
    """A fresh filter for one run of `scenario` (see `filter_context`)."""
    return spec.build(filter_context(spec, scenario, world))
