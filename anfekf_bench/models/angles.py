"""Angle wrapping, shared by the models, the filters and the metrics."""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(a):
    """Wrap angles to (-pi, pi] (scalar or array)."""
    return -((-np.asarray(a, dtype=float) + math.pi) % TWO_PI - math.pi)


def wrap_scalar(a: float) -> float:
    """Scalar `wrap_angle` without numpy overhead, for the simulation's inner loop."""
    return -((-a + math.pi) % TWO_PI - math.pi)
