"""A damped pendulum seen by an angle encoder and a camera: a user's own problem
(docs/CUSTOM_PROBLEMS.md). Plain numpy in the subset numba compiles, so the same functions run
on both engines.

State x = (theta, omega): the angle from the downward vertical (rad) and the angular rate
(rad/s). Motion over dt (explicit Euler):

    theta' = theta + dt omega
    omega' = omega - dt (g / L) sin(theta) - dt c omega + w,    w ~ N(0, Q)

The noise w is an angular-rate kick (one input: G = [0, 1]^T). Measurements: the encoder's
angle (angle-valued: its residual is wrapped) and the camera's horizontal position of the bob,
L sin(theta), with a full 2 x 2 R (the two share a vibration).
"""

import numpy as np

# p = (dt, g, L, c): the parameter vector every function receives; a scenario may override it.
params = np.array([0.05, 9.81, 1.0, 0.2])

Q = np.array([[0.04]])  # rate kick per step, (rad/s)^2
R = np.array([[0.01, 0.002], [0.002, 0.0025]])  # encoder (rad^2), camera (m^2)
x0 = np.array([1.0, 0.0])  # released at 1 rad, at rest
P0 = np.diag([0.1, 0.1])
steps = 400
angles = (0,)  # measurement 0 is an angle
position = (0,)  # theta is scored as "position", omega as the rest


def f(x, k, p):
    dt, g, L, c = p[0], p[1], p[2], p[3]
    return np.array([x[0] + dt * x[1], x[1] - dt * (g / L) * np.sin(x[0]) - dt * c * x[1]])


def F(x, k, p):
    dt, g, L, c = p[0], p[1], p[2], p[3]
    return np.array([[1.0, dt], [-dt * (g / L) * np.cos(x[0]), 1.0 - dt * c]])


def G(x, k, p):
    return np.array([[0.0], [1.0]])


def h(x, k, p):
    return np.array([x[0], p[2] * np.sin(x[0])])


def H(x, k, p):
    return np.array([[1.0, 0.0], [p[2] * np.cos(x[0]), 0.0]])
