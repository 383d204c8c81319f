"""Autocovariance least squares (ALS) for a linear time-invariant problem, full Q and R
(Odelson, Rajamani, Rawlings 2006; the survey's "direct correlation" class, SPEC 17).

A stable fixed-gain predictor x^(k+1) = F x^(k) + K (z(k) - H x^(k)) runs beside the filter. Its
error e = x - x^ obeys e(k+1) = A e(k) + G w(k) - K v(k), A = F - K H, and its innovations
y(k) = H e(k) + v(k) have, in steady state, the autocovariances

    C_0 = H P H^T + R,     C_j = H A^j P H^T - H A^(j-1) K R  (j >= 1),
    P = A P A^T + G Q G^T + K R K^T,

linear in the unknown Q and R. Stacking C_0 .. C_(L-1) for each symmetric basis matrix of Q and
R (P by scipy's discrete Lyapunov solver) gives the design matrix; the sample autocovariances
are the right-hand side; least squares (numpy's lstsq) gives vech(Q), vech(R), each projected
onto the positive semidefinite matrices. Lags >= 1 are what tell Q from R (covariance matching
has lag 0 only). The kind's filter re-identifies every `every` steps from the innovations so
far and uses the latest estimate (causal); its estimate at the end uses the whole run.
"""

from __future__ import annotations

import time
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy.linalg import solve_discrete_lyapunov

from .base import Problem
from .filters import PSD_FLOOR, GenericKF, Matrix, ProblemFilterSpec, Trace
from .kalman import linear_recursion, nearest_psd


def symmetric_basis(m: int) -> list[np.ndarray]:
    """E_ij (i <= j, row by row) with ones at (i, j) and (j, i): vech's basis."""
    out = []
    for i in range(m):
        for j in range(i, m):
            E = np.zeros((m, m))
            E[i, j] = E[j, i] = 1.0
            out.append(E)
    return out


def autocovariances(F, G, H, K, Q, R, lags: int) -> np.ndarray:
    """C_0 .. C_(lags-1) (lags, nz, nz) of the fixed-gain innovations (linear in Q and R)."""
    A = F - K @ H
    P = solve_discrete_lyapunov(A, G @ Q @ G.T + K @ R @ K.T)
    out = [H @ P @ H.T + R]
    Aj_prev = np.eye(len(F))  # A^(j-1)
    for _ in range(1, lags):
        out.append(H @ (A @ Aj_prev) @ P @ H.T - H @ Aj_prev @ K @ R)
        Aj_prev = A @ Aj_prev
    return np.array(out)


def design_matrix(F, G, H, K, lags: int) -> np.ndarray:
    """Columns: the stacked autocovariances of each basis matrix of Q, then of R."""
    nw, nz = G.shape[1], H.shape[0]
    cols = [autocovariances(F, G, H, K, E, np.zeros((nz, nz)), lags).ravel()
            for E in symmetric_basis(nw)]  # fmt: skip
    cols += [autocovariances(F, G, H, K, np.zeros((nw, nw)), E, lags).ravel()
             for E in symmetric_basis(nz)]  # fmt: skip
    return np.stack(cols, axis=1)


def from_vech(theta: np.ndarray, m: int) -> np.ndarray:
    return sum((t * E for t, E in zip(theta, symmetric_basis(m), strict=True)), np.zeros((m, m)))


def sample_autocovariances(y: np.ndarray, lags: int) -> np.ndarray:
    """Chat_j = mean over k of y(k + j) y(k)^T, j = 0 .. lags - 1."""
    n = len(y)
    return np.array([y[j:].T @ y[: n - j] / (n - j) for j in range(lags)])


def fixed_gain_innovations(problem: Problem, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """y(k) = z(k) - H x^(k) of the predictor x^(k+1) = F x^(k) + K y(k) from the start."""
    # x^(k+1) = (F - K H) x^(k) + K z(k): a linear recursion driven by z
    F, H = problem.Fm, problem.Hm
    x = linear_recursion(F - K @ H, K, np.ascontiguousarray(z, dtype=float), problem.x0)
    return z - x @ H.T


class ALSIdentifier:
    """The least-squares map from sample autocovariances to (Q, R) of one problem and gain."""

    def __init__(self, problem: Problem, K: np.ndarray, lags: int):
        if not problem.linear:
            raise ValueError("ALS needs a linear time-invariant problem")
        A = problem.Fm - K @ problem.Hm
        if max(abs(np.linalg.eigvals(A))) >= 1.0:
            raise ValueError("the gain K does not make F - K H stable")
        self.problem, self.K, self.lags = problem, K, lags
        self.D = design_matrix(problem.Fm, problem.Gm, problem.Hm, K, lags)
        if np.linalg.matrix_rank(self.D) < self.D.shape[1]:
            raise ValueError(f"Q and R are not identifiable from {lags} lags with this gain")
        self.pinv = np.linalg.pinv(self.D)
        self.nq = problem.nw * (problem.nw + 1) // 2

    def solve(self, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Q, R), unconstrained least squares (may be indefinite)."""
        theta = self.pinv @ C.ravel()
        return (from_vech(theta[: self.nq], self.problem.nw),
                from_vech(theta[self.nq :], self.problem.nz))  # fmt: skip


def als_identify(problem: Problem, z: np.ndarray, K: np.ndarray, lags: int, burn: int = 0):
    """(Q, R) of one run by ALS: the fixed-gain innovations after `burn` steps, least squares,
    no projection (the raw estimate: unbiased, may be indefinite)."""
    y = fixed_gain_innovations(problem, z, K)[burn:]
    return ALSIdentifier(problem, K, lags).solve(sample_autocovariances(y, lags))


class ALSSpec(ProblemFilterSpec):
    """Autocovariance least squares of the full Q and R (linear time-invariant problems)."""

    kind: Literal["als"]
    estimates: ClassVar[frozenset[str]] = frozenset({"Q", "R"})
    gain: Annotated[float, Field(gt=-1e6, lt=1e6, allow_inf_nan=False)] | Matrix = Field(
        0.8,
        description="the fixed gain K of the predictor whose innovations are used: a number g"
        " (K = g I) or an n x nz matrix; F - K H must be stable (the survey: K = 0.8 I)",
    )
    lags: int = Field(3, ge=2, le=100, description="autocovariance lags 0 .. lags - 1")
    every: int = Field(10, ge=1, le=10**7, description="re-identify every this many steps")
    burn: int = Field(20, ge=0, le=10**6, description="first innovations left out (transient)")
    min_steps: int = Field(
        50, ge=2, le=10**7, description="innovations (after burn) before the first estimate"
    )

    def gain_matrix(self, problem: Problem) -> np.ndarray:
        if isinstance(self.gain, list):
            return np.array(self.gain, dtype=float)
        return self.gain * np.eye(problem.n, problem.nz)

    def check(self, problem):
        # the predictor's gain and the identifier's design (a linear problem, F - K H stable)
        self.build(problem, np.eye(problem.nw), np.eye(problem.nz))

    def build(self, problem, Q, R):
        return ALSKF(problem, Q, R, self)


class ALSKF(GenericKF):
    """The KF with the latest ALS estimate of Q and R (the assumed ones until the first)."""

    def __init__(self, problem, Q, R, spec: ALSSpec):
        super().__init__(problem, Q, R)
        self.spec = spec
        self.K = spec.gain_matrix(problem)
        self.identifier = ALSIdentifier(problem, self.K, spec.lags)
        self.Q_floor = PSD_FLOOR * float(np.trace(self.Q)) / problem.nw
        self.R_floor = PSD_FLOOR * float(np.trace(self.R)) / problem.nz
        self.xp = problem.x0.copy()
        self.y: list[np.ndarray] = []
        L, nz = spec.lags, problem.nz
        self.sums = np.zeros((L, nz, nz))
        self.counts = np.zeros(L)

    def before_gain(self, k, nu, H, P):
        p, spec = self.problem, self.spec
        y = self.problem_innovation(k)
        if k >= spec.burn:
            self.y.append(y)
            used = self.y[-spec.lags :]
            for j in range(len(used)):
                self.sums[j] += np.outer(y, used[-1 - j])
                self.counts[j] += 1
            if len(self.y) >= spec.min_steps and (len(self.y) - spec.min_steps) % spec.every == 0:
                self.identify()
        self.xp = p.Fm @ self.xp + self.K @ y

    def problem_innovation(self, k):
        return self.z[k] - self.problem.Hm @ self.xp

    def identify(self):
        Q, R = self.identifier.solve(self.sums / self.counts[:, None, None])
        self.Q = nearest_psd(Q, self.Q_floor)
        self.R = nearest_psd(R, self.R_floor)

    def run(self, z):
        self.z = z
        return super().run(z)

    def finish(self, z):
        if len(self.y) >= self.spec.lags:
            self.identify()

    def run_compiled(self, z):
        from .fast import als_run, as_arrays, gate_of

        p, spec = self.problem, self.spec
        started = time.perf_counter()
        x0, P0, Q, R, z = as_arrays(p.x0, p.P0, self.Q, self.R, z)
        identifier = as_arrays(p.Fm, p.Hm, self.K, self.identifier.pinv)
        *out, gated = als_run(*self.model.args(), x0, P0, Q, R, z, gate_of(p), *identifier,
                              int(spec.lags), int(spec.every), int(spec.burn),
                              int(spec.min_steps), self.Q_floor, self.R_floor)  # fmt: skip
        return Trace(*out, time.perf_counter() - started, gated)
