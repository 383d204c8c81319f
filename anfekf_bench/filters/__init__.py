"""The filters: the EKF (the base of all), the adaptive filters, and the registry that builds them.

The public API for a filter of your own (docs/CUSTOM_FILTERS.md): subclass `RobotEKF` (or
`AdaptiveEKF` for the common adaptive rules), override its hooks, declare a `Params` class
deriving from `FilterParams` (or `AdaptiveParams`), and name it in a scenario file.
"""

from .adaptive import AdaptiveEKF, clip_to_bounds, qu_least_squares
from .anfekf import ANFEKF, ANFEKFSpec, mismatch, q_step, r_step
from .context import build_filter
from .ekf import EKFSpec, FilterDiverged, Innovation, OracleSpec, RobotEKF, gate_threshold
from .registry import KINDS, AnyFilterSpec
from .spec import AdaptiveParams, FilterContext, FilterParams, FilterSpec

__all__ = [
    "ANFEKF",
    "ANFEKFSpec",
    "KINDS",
    "AdaptiveEKF",
    "AdaptiveParams",
    "AnyFilterSpec",
    "EKFSpec",
    "FilterContext",
    "FilterDiverged",
    "FilterParams",
    "FilterSpec",
    "Innovation",
    "OracleSpec",
    "RobotEKF",
    "build_filter",
    "clip_to_bounds",
    "gate_threshold",
    "mismatch",
    "q_step",
    "qu_least_squares",
    "r_step",
]
