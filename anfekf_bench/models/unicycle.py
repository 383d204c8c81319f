"""Unicycle (differential-drive) model for recorded logs: control u = (v, w), variable steps.

State X = (x, y, phi), control u = (v [m/s], w [rad/s]) held constant over the step (zero-order
hold), step length dt [s]. One step is the midpoint-Euler integration

    a    = phi + w dt / 2
    x+   = x + v dt cos(a)
    y+   = y + v dt sin(a)
    phi+ = wrap(phi + w dt)

which is exact for a straight line (w = 0) and for a pure rotation (v = 0), and second-order
accurate along an arc. `F` and `G` are the exact Jacobians of this step.

Process noise (rate-consistent)
-------------------------------
The control noise is white in time. `Qu = diag(sv^2, sw^2)` is the covariance of the control
noise of ONE NOMINAL STEP of length `T0` (default 0.12 s, the MRCLAM odometry period), so sv [m/s]
and sw [rad/s] read as "std per odometry sample". The step's state-space noise is

    Q = (T0 / dt) G Qu G^T.

Since G is proportional to dt, Q grows like dt (not dt^2): splitting an interval into two steps
(for instance at a measurement time) gives, to first order in dt, the same total noise as one step,
and a step of exactly T0 gives the textbook G Qu G^T. Equivalently, the control noise n(t) has the
intensity Qu T0, E[n(t) n(s)^T] = Qu T0 delta(t - s), in (m/s)^2 s and (rad/s)^2 s; with
`Unicycle(T0=1.0)`, `Qu` is that spectral density per second. The textbook per-step form
G Qu G^T alone scales with dt^2 and silently halves the noise of an interval split in two.
This is the form of the Dataset 9 research notes (T0 = 0.12 s): their sv, sw values apply as is.
"""

from __future__ import annotations

import math

import numpy as np

from .motion_terms import MOTION_UNICYCLE, jacobian_arrays, next_pose, step_terms


class Unicycle:
    """Midpoint-Euler unicycle as a `MotionModel`, for variable step lengths (see module doc).

    `T0` [s] is the reference step of `Qu`: Q = (T0 / dt) G Qu G^T (rate-consistent).
    """

    def __init__(self, T0: float = 0.12):
        if not (math.isfinite(T0) and T0 > 0):
            raise ValueError(f"T0 must be a positive number of seconds, got {T0!r}")
        self.T0 = float(T0)

    def f(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """The noise-free step, heading wrapped to (-pi, pi] (models.motion_terms)."""
        return next_pose(x, step_terms(float(u[0]), float(u[1]), dt, MOTION_UNICYCLE, 0.0))

    def jacobians(self, x: np.ndarray, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """F = df/dX (3x3) and G = df/du (3x2); G's w column includes the midpoint's
        d a / d w = dt / 2."""
        terms = step_terms(float(u[0]), float(u[1]), dt, MOTION_UNICYCLE, 0.0)
        return jacobian_arrays(x[2], terms)

    def Q(self, G: np.ndarray, Qu: np.ndarray, dt: float) -> np.ndarray:
        """Rate-consistent step noise (T0 / dt) G Qu G^T; zero for a zero-length step."""
        if dt <= 0.0:
            return np.zeros((G.shape[0], G.shape[0]))
        return (self.T0 / dt) * (G @ Qu @ G.T)
