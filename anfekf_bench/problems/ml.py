"""Maximum likelihood of the full Q and R (SPEC 17; research notes, section 3): maximise the
Gaussian likelihood of the (E)KF's innovations, -1/2 sum_k [log|S_k| + nu_k^T S_k^-1 nu_k], over
Cholesky factors with log diagonals (every value is a positive definite Q, R), by L-BFGS
(scipy.optimize) from one start. `fit_on: training` fits once on training runs whose seeds no
evaluation run draws from (the fair "tuned without truth" line: the same Q, R in every run);
`fit_on: run` fits on the evaluation run's own measurements (the survey's identification
setting: an estimate per run, then the filter with it; not causal).
"""

from __future__ import annotations

import math
import time
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy.optimize import minimize

from .base import Problem
from .filters import GenericKF, Matrix, ProblemFilterSpec, Trace
from .kalman import ekf_nll, linear_nll


def cholesky_params(M: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor of M with its diagonal's logarithms, row by row."""
    L = np.linalg.cholesky(M)
    idx = np.tril_indices(len(M))
    out = L[idx].copy()
    diag = idx[0] == idx[1]
    out[diag] = np.log(out[diag])
    return out


def from_cholesky_params(theta: np.ndarray, m: int) -> np.ndarray:
    L = np.zeros((m, m))
    idx = np.tril_indices(m)
    values = np.array(theta, dtype=float)
    diag = idx[0] == idx[1]
    values[diag] = np.exp(np.clip(values[diag], -50, 50))
    L[idx] = values
    return L @ L.T


def negative_log_likelihood(problem: Problem, runs: list[np.ndarray], Q, R) -> float:
    """Sum over runs of -log p(z | Q, R) (compiled for a linear problem and where the problem
    has a compiled filter). The gate is not applied: every measurement's likelihood counts (a
    gated likelihood rewards noise small enough to drop every measurement)."""
    if problem.linear:
        args = (problem.Fm, problem.Gm, problem.Hm, Q, R, problem.x0, problem.P0)
        return float(sum(linear_nll(*args, z) for z in runs))
    total = 0.0
    for z in runs:
        fast = problem.fast_filter(Q, R, z, gated=False)
        total += ekf_nll(problem, z, Q, R) if fast is None else fast[2]
    return float(total)


def fit_noise(problem: Problem, runs: list[np.ndarray], Q0, R0, maxiter: int = 200):
    """(Q, R, result) maximising the likelihood of `runs` from (Q0, R0)."""
    nq = problem.nw * (problem.nw + 1) // 2
    start = np.concatenate([cholesky_params(np.asarray(Q0, float)),
                            cholesky_params(np.asarray(R0, float))])  # fmt: skip
    scale = sum(len(z) for z in runs)

    def objective(theta):
        Q = from_cholesky_params(theta[:nq], problem.nw)
        R = from_cholesky_params(theta[nq:], problem.nz)
        value = negative_log_likelihood(problem, runs, Q, R) / scale
        return value if math.isfinite(value) else 1e300

    result = minimize(objective, start, method="L-BFGS-B", options={"maxiter": maxiter})
    return (from_cholesky_params(result.x[:nq], problem.nw),
            from_cholesky_params(result.x[nq:], problem.nz), result)  # fmt: skip


class MLSpec(ProblemFilterSpec):
    """Maximum likelihood of the full Q and R, on training runs or on each run's own data."""

    kind: Literal["ekf-ml"]
    estimates: ClassVar[frozenset[str]] = frozenset({"Q", "R"})
    fit_on: Literal["training", "run"] = Field(
        "training",
        description="training: one fit on the scenario's training runs (disjoint seeds), used"
        " in every run; run: a fit on each evaluation run's own measurements (offline)",
    )
    start_Q: Matrix | None = Field(None, description="the fit's start (default filter_noise)")
    start_R: Matrix | None = Field(None, description="the fit's start (default filter_noise)")
    maxiter: int = Field(200, ge=1, le=10_000, description="L-BFGS iterations at most")

    def fits_on_training(self) -> bool:
        return self.fit_on == "training"

    def fit_training(self, problem, runs, Q0, R0):
        started = time.perf_counter()
        Q, R, result = fit_noise(problem, [t.z for t in runs], *self.start(Q0, R0),
                                 maxiter=self.maxiter)  # fmt: skip
        return Q, R, {
            "training_runs": len(runs), "Q": Q.tolist(), "R": R.tolist(),
            "iterations": int(result.nit), "converged": bool(result.success),
            "seconds": round(time.perf_counter() - started, 3),
        }  # fmt: skip

    def start(self, Q, R):
        return (Q if self.start_Q is None else np.array(self.start_Q, float),
                R if self.start_R is None else np.array(self.start_R, float))  # fmt: skip

    def build(self, problem, Q, R):
        return MLKF(problem, Q, R, self)


class MLKF(GenericKF):
    """The KF with the fitted Q, R: built with the training fit's (`fit_on: training`), or
    fitted on the run's own measurements first (`fit_on: run`, from the Q, R it is built with)."""

    def __init__(self, problem, Q, R, spec: MLSpec):
        super().__init__(problem, Q, R)
        self.spec = spec

    def run(self, z) -> Trace:
        started = time.perf_counter()
        if not self.spec.fits_on_training():
            self.Q, self.R, _ = fit_noise(self.problem, [z], *self.spec.start(self.Q, self.R),
                                          maxiter=self.spec.maxiter)  # fmt: skip
        trace = super().run(z)
        trace.seconds = time.perf_counter() - started
        return trace
