"""The truth-tuned reference on a problem (`ekf-tuned`, SPEC 17): the (E)KF with the assumed Q
and R each multiplied by a factor fitted once on the scenario's training runs against their
truth (seeds disjoint from the evaluation runs), then used unchanged in every run. The fair
"tuned with truth" line beside `ekf-ml` ("tuned without truth").

Two one-dimensional fits (scipy.optimize.minimize_scalar, bounded Brent), because the state
estimate of a Kalman filter depends on Q and R almost only through their ratio (exactly, but for
P0 and the gate), so position RMSE cannot fix their common level:
1. the ratio: Q = a Q0 with R = R0, a minimising the position RMSE over the training runs;
2. the level: both multiplied by c, c making the training runs' average NEES equal to the state
   dimension (minimising (log(ANEES / n))^2): the filter's P believes its own errors.
Each factor is searched within [1 / bound, bound] on a log scale.
"""

from __future__ import annotations

import math
import time
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy.optimize import minimize_scalar

from .base import Problem
from .filters import GenericKF, ProblemFilterSpec


def training_errors(problem: Problem, runs: list, Q: np.ndarray, R: np.ndarray):
    """(position RMSE over every run and step, average NEES) of the (E)KF with Q, R (the
    problem's compiled filter where it has one: the same filter)."""
    squared, nees = 0.0, 0.0
    count = 0
    pos = list(problem.position)
    for t in runs:
        fast = problem.fast_filter(Q, R, t.z)
        if fast is None:
            trace = GenericKF(problem, Q, R).run(t.z)
            x, P = trace.x, trace.P
        else:
            x, P = fast[0], fast[1]
        e = t.x - x
        squared += float(np.sum(e[:, pos] ** 2))
        nees += float(np.sum(e * np.linalg.solve(P, e[..., None])[..., 0]))
        count += len(t.x)
    return math.sqrt(squared / count), nees / count


class TunedSpec(ProblemFilterSpec):
    """The (E)KF with the assumed Q and R scaled by factors fitted on training runs against
    their truth: the ratio for position RMSE, the level for NEES (module doc)."""

    kind: Literal["ekf-tuned"]
    estimates: ClassVar[frozenset[str]] = frozenset({"Q", "R"})
    bound: Annotated[float, Field(gt=1, le=1e8, allow_inf_nan=False)] = Field(
        1e4, description="each factor is searched within [1 / bound, bound]"
    )
    tolerance: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        1e-3, description="the search's tolerance on the log of a factor"
    )

    def fits_on_training(self) -> bool:
        return True

    def fit_training(self, problem, runs, Q0, R0):
        started = time.perf_counter()
        Q0, R0 = np.asarray(Q0, float), np.asarray(R0, float)
        span = (-math.log(self.bound), math.log(self.bound))
        options = {"xatol": self.tolerance}
        evaluations = 0

        def rmse(log_a):
            nonlocal evaluations
            evaluations += 1
            value = training_errors(problem, runs, math.exp(log_a) * Q0, R0)[0]
            return value if math.isfinite(value) else 1e300

        ratio = minimize_scalar(rmse, bounds=span, method="bounded", options=options)
        a = math.exp(ratio.x)

        def nees_gap(log_c):
            nonlocal evaluations
            evaluations += 1
            c = math.exp(log_c)
            anees = training_errors(problem, runs, c * a * Q0, c * R0)[1]
            return math.log(anees / problem.n) ** 2 if anees > 0 else 1e300

        level = minimize_scalar(nees_gap, bounds=span, method="bounded", options=options)
        c = math.exp(level.x)
        Q, R = c * a * Q0, c * R0
        train_rmse, train_anees = training_errors(problem, runs, Q, R)
        return Q, R, {
            "training_runs": len(runs), "Q": Q.tolist(), "R": R.tolist(),
            "Q_factor": c * a, "R_factor": c, "training_rmse_pos": train_rmse,
            "training_anees": train_anees, "evaluations": evaluations + 1,
            "converged": bool(ratio.success and level.success),
            "seconds": round(time.perf_counter() - started, 3),
        }  # fmt: skip

    def build(self, problem, Q, R):
        return GenericKF(problem, Q, R)
