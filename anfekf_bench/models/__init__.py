"""Motion and sensor models: the car-like bicycle of the paper and the range-bearing sensor."""

from .angles import TWO_PI, wrap_angle, wrap_scalar
from .base import MotionModel
from .bicycle import Bicycle, control_covariance, f, jacobians
from .range_bearing import H_jacobian, h, measurement_covariance, residual_z
from .unicycle import Unicycle

__all__ = [
    "Bicycle",
    "MotionModel",
    "TWO_PI",
    "Unicycle",
    "H_jacobian",
    "control_covariance",
    "f",
    "h",
    "jacobians",
    "measurement_covariance",
    "residual_z",
    "wrap_angle",
    "wrap_scalar",
]
