"""How the regression gate (analysis.gate) shows a metric: its name with its unit, and its
values in that unit."""

from __future__ import annotations

import math

# How the gate shows a metric: its unit, and the factor from the stored unit. The files keep
# radians; every table a user reads shows angles in degrees (one unit per surface). The robot's
# units; a problem beyond the robot gives its own position unit (its manifest's
# `position_unit`: the tracking radar's m, none for the linear system), as the `units` of its
# `gate.ScenarioSummary`.
SHOWN_UNITS: dict[str, tuple[str, float]] = {
    "rmse_pos": ("m", 1.0),
    "rmse_heading": ("deg", 180.0 / math.pi),
}


def shown_metric(metric: str, units: dict[str, str] | None = None) -> str:
    """`metric` with the unit it is shown in ('rmse_heading [deg]'; `units`: a scenario's own
    unit of a metric, '' for none: 'rmse_pos')."""
    unit = (units or {}).get(metric, SHOWN_UNITS.get(metric, ("", 1.0))[0])
    return f"{metric} [{unit}]" if unit else metric


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
