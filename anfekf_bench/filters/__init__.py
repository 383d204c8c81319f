"""The filters: the EKF (the base of all), the ANFEKF, and the registry that builds them."""

from .anfekf import ANFEKF, mismatch, q_step, r_step
from .ekf import FilterDiverged, RobotEKF, gate_threshold
from .registry import build_filter

__all__ = [
    "ANFEKF",
    "FilterDiverged",
    "RobotEKF",
    "build_filter",
    "gate_threshold",
    "mismatch",
    "q_step",
    "r_step",
]
