"""Filter construction: one place maps a scenario's filter spec to a fresh filter."""

from __future__ import annotations

import numpy as np

from ..config import EKFSpec, OracleSpec
from ..models import control_covariance, measurement_covariance
from .anfekf import ANFEKF
from .ekf import RobotEKF, gate_threshold


def build_filter(spec, scenario, world) -> RobotEKF:
    """A fresh filter for one run: the oracle gets the true noise, every other the assumed one."""
    noise = scenario.true_noise if isinstance(spec, OracleSpec) else scenario.filter_noise
    sv, sg, sr, sb = noise.radians()
    kwargs = dict(
        x0=world.x0,
        P0=np.eye(3) * scenario.p0,
        Qu=control_covariance(sv, sg),
        R=measurement_covariance(sr, sb),
        T=world.T,
        B=world.B,
        gate=gate_threshold(scenario.gate_probability),
    )
    if isinstance(spec, (EKFSpec, OracleSpec)):
        return RobotEKF(**kwargs)
    return ANFEKF(**kwargs, spec=spec)
