"""A linear time-invariant problem: x(k+1) = F x(k) + G w(k), z(k) = H x(k) + v(k).

The default is the system of Dunik, Straka, Kost, Havlik (2017, "Noise covariance matrices in
state-space models: a survey and comparison of estimation methods", IJACSP 31(11)), the one their
public comparison script uses: F = [[0.9, 0], [-0.3, 0.8]], H = I, Q = [[2, -0.5], [-0.5, 1]],
R = [[3, 0], [0, 2]], 1001 steps, starting estimate 0 (SPEC 17).
"""

from __future__ import annotations

import numpy as np

from .base import Problem, Trajectory
from .kalman import linear_recursion

SURVEY_F = ((0.9, 0.0), (-0.3, 0.8))
SURVEY_H = ((1.0, 0.0), (0.0, 1.0))
SURVEY_Q = ((2.0, -0.5), (-0.5, 1.0))
SURVEY_R = ((3.0, 0.0), (0.0, 2.0))
SURVEY_STEPS = 1001


class LinearProblem(Problem):
    """A linear time-invariant system with full Q and R."""

    name = "linear"
    linear = True

    def __init__(self, F, H, Q, R, *, G=None, x0=None, P0=None, steps=SURVEY_STEPS,
                 position=None):  # fmt: skip
        self.Fm = np.array(F, dtype=float)
        self.Hm = np.array(H, dtype=float)
        self.n = self.Fm.shape[0]
        self.nz = self.Hm.shape[0]
        self.Gm = np.eye(self.n) if G is None else np.array(G, dtype=float)
        self.nw = self.Gm.shape[1]
        self.Q = np.array(Q, dtype=float)
        self.R = np.array(R, dtype=float)
        self.x0 = np.zeros(self.n) if x0 is None else np.array(x0, dtype=float)
        self.P0 = np.eye(self.n) if P0 is None else np.array(P0, dtype=float)
        self.steps = int(steps)
        self.position = tuple(range(self.n)) if position is None else tuple(position)

    def simulate(self, rng: np.random.Generator) -> Trajectory:
        """As `Problem.simulate` (the same draws in the same order), the recursion as one tight
        loop and the measurements in bulk."""
        x0 = rng.multivariate_normal(self.x0, self.P0)
        w = rng.multivariate_normal(np.zeros(self.nw), self.Q, size=self.steps)
        v = rng.multivariate_normal(np.zeros(self.nz), self.R, size=self.steps)
        x = linear_recursion(self.Fm, self.Gm, w, x0)
        return Trajectory(x=x, z=x @ self.Hm.T + v)

    def compiled_model(self):
        from .fast import linear_model

        return linear_model(self.Fm, self.Gm, self.Hm, self.angles)

    def f(self, x, k):
        return self.Fm @ x

    def F(self, x, k):
        return self.Fm

    def G(self, x, k):
        return self.Gm

    def h(self, x, k):
        return self.Hm @ x

    def H(self, x, k):
        return self.Hm


def survey_problem(steps: int = SURVEY_STEPS) -> LinearProblem:
    """The survey's system (Dunik et al. 2017) with `steps` measurements per run."""
    return LinearProblem(SURVEY_F, SURVEY_H, SURVEY_Q, SURVEY_R, steps=steps)
