"""One step of each motion model as plain scalar formulas, written once for both engines.

The bicycle (models.bicycle, the paper's eq. 17) and the unicycle (models.unicycle, midpoint
Euler) share one form: from heading x2, with controls (u0, u1) over dt,

    a   = x2 + turn
    x+  = x + f12,  y+ = y - f02,  phi+ = wrap(x2 + dh)
    F   = [[1, 0, f02], [0, 1, f12], [0, 0, 1]],  f02 = cf0 sin(a),  f12 = cf1 cos(a)
    G   = [[cg0 cos(a), cg1 sin(a)], [cg0 sin(a), cg3 cos(a)], [g20, g21]]

where `step_terms` gives what does not depend on the heading (turn, cf0, cf1, cg0, cg1, cg3,
g20, g21, dh) and `jacobians_at` the rest. The models' `f` and `jacobians` (the filterpy engine,
the simulator) build their arrays from these two functions; the fast engine's kernels compile
the very same functions with numba (engines.kernels), so the products are the same, in the same
order, on both engines. `step_terms` and `jacobians_at` take plain floats and tuples only, so
that numba can compile them; `next_pose` and `jacobian_arrays` make the models' arrays.
"""

from __future__ import annotations

import math

import numpy as np

from .angles import wrap_scalar

MOTION_BICYCLE = 0  # u = (V, gamma), B the wheelbase, Q = G Qu G^T (dt is the control period)
MOTION_UNICYCLE = 1  # u = (v, w), midpoint Euler, Q = (T0 / dt) G Qu G^T (rate-consistent)


def step_terms(u0, u1, dt, motion, B):
    """What the Jacobians and the predicted heading of one step share whatever the heading:
    (turn, cf0, cf1, cg0, cg1, cg3, g20, g21, dh), computed once for a bank's M members.
    Bicycle: a = x2 + gamma, F and G from T = dt, V = u0 (eqs. 9, 10, 21); unicycle:
    a = x2 + w dt / 2."""
    if motion == MOTION_UNICYCLE:
        half = 0.5 * u0 * dt * dt
        vdt = u0 * dt
        return 0.5 * u1 * dt, -vdt, vdt, dt, -half, half, 0.0, dt, u1 * dt
    T, V, g = dt, u0, u1
    TV = T * V
    nTV = -T * V
    return (
        g,
        nTV,
        TV,
        T,
        nTV,
        TV,
        T * math.sin(g) / B,
        TV * math.cos(g) / B,
        (dt * u0 * math.sin(u1) / B),
    )


def jacobians_at(x2, terms):
    """F and G from heading x2 and the step's `step_terms`: (f02, f12, G), G = (g00, g01, g10,
    g11, g20, g21) row-major. The position step is (f12, -f02), bit for bit: negation is exact."""
    turn, cf0, cf1, cg0, cg1, cg3, g20, g21, _ = terms
    a = x2 + turn
    ca = math.cos(a)
    sa = math.sin(a)
    return cf0 * sa, cf1 * ca, (cg0 * ca, cg1 * sa, cg0 * sa, cg3 * ca, g20, g21)


# The filterpy engine's and the simulator's arrays, from the same two functions


def next_pose(x: np.ndarray, terms: tuple) -> np.ndarray:
    """The noise-free step from pose x: (x + f12, y - f02, wrap(x2 + dh))."""
    f02, f12, _ = jacobians_at(x[2], terms)
    return np.array([x[0] + f12, x[1] - f02, wrap_scalar(x[2] + terms[8])])


def jacobian_arrays(x2: float, terms: tuple) -> tuple[np.ndarray, np.ndarray]:
    """F (3x3) and G (3x2) from heading x2 and the step's `step_terms`."""
    f02, f12, (g00, g01, g10, g11, g20, g21) = jacobians_at(x2, terms)
    F = np.array([[1.0, 0.0, f02], [0.0, 1.0, f12], [0.0, 0.0, 1.0]])
    G = np.array([[g00, g01], [g10, g11], [g20, g21]])
    return F, G
