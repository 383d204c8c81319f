"""How the regression gate (analysis.gate) shows a metric: its name with its unit, and its
values in that unit."""

from __future__ import annotations

import math

# How the gate shows a metric: its name with its unit, and the factor from the stored unit. The
# files keep radians; every table a user reads shows angles in degrees (one unit per surface).
SHOWN_UNITS: dict[str, tuple[str, float]] = {
    "rmse_pos": ("rmse_pos [m]", 1.0),
    "rmse_heading": ("rmse_heading [deg]", 180.0 / math.pi),
}


def shown_metric(metric: str) -> str:
    """`metric` with the unit it is shown in ('rmse_heading [deg]')."""
    return SHOWN_UNITS.get(metric, (metric, 1.0))[0]


def in_shown_unit(metric: str, x: float | None) -> float | None:
    """A stored value in the unit it is shown in."""
    if x is None or isinstance(x, int) or metric not in SHOWN_UNITS:
        return x
    return x * SHOWN_UNITS[metric][1]


def fmt_value(x: float | None) -> str:
    if x is None:
        return "-"
    if isinstance(x, int):  # seed and runs
        return str(x)
    if math.isnan(x):
        return "null"
    return f"{x:.4g}"
