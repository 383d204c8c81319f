"""The generic (E)KF every problem filter is built on: one step (update with z(k), then predict
to k + 1) and the Gaussian log-likelihood of the innovations.

Convention: at step k the prior (x, P) is that of x(k) given z(0..k-1); the update with z(k)
gives the estimate scored at k; the prediction with f, F, G and Q gives the prior of k + 1.
`linear_nll` is the same likelihood for a linear time-invariant problem as one loop that numba
compiles when installed (the maximum-likelihood fits evaluate it hundreds of times).
"""

from __future__ import annotations

import math

import numpy as np

from ..compiled import use_reached_sources_stamp
from .base import Problem, wrap

LOG_2PI = math.log(2.0 * math.pi)

try:  # numba is optional (the `fast` extra): the same code runs as Python without it
    from numba import njit as _njit

    use_reached_sources_stamp()  # the package's one cache stamp, whichever module comes first

    def compiled(fn):
        return _njit(cache=True)(fn)

except ImportError:  # pragma: no cover - numba is installed wherever CI runs the fast engine

    def compiled(fn):
        return fn


@compiled
def linear_recursion(A, B, u, x0):  # pragma: no cover - compiled; tests call it
    """x(0) = x0, x(k+1) = A x(k) + B u(k): the states (len(u), n) of a linear recursion."""
    n, steps = x0.shape[0], u.shape[0]
    x = np.empty((steps, n))
    x[0] = x0
    for k in range(steps - 1):
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += A[i, j] * x[k, j]
            for j in range(u.shape[1]):
                acc += B[i, j] * u[k, j]
            x[k + 1, i] = acc
    return x


def symmetric(M: np.ndarray) -> np.ndarray:
    return 0.5 * (M + M.T)


def nearest_psd(M: np.ndarray, floor: float) -> np.ndarray:
    """The symmetric matrix nearest to M (Frobenius) with every eigenvalue >= floor."""
    w, V = np.linalg.eigh(symmetric(M))
    return symmetric((V * np.maximum(w, floor)) @ V.T)


def joseph_update(x, P, nu, H, R):
    """(x+, P+, S, K) of the Kalman update with innovation nu (Joseph form: P+ stays symmetric
    positive for any gain)."""
    S = H @ P @ H.T + R
    K = np.linalg.solve(S.T, (P @ H.T).T).T
    x = x + K @ nu
    IKH = np.eye(len(x)) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T
    return x, symmetric(P), S, K


def innovation(problem: Problem, x: np.ndarray, z: np.ndarray, k: int):
    """(nu, H) at step k: z - h(x) with angle components wrapped, and the Jacobian."""
    return wrap(z - problem.h(x, k), problem.angles), problem.H(x, k)


def outside_gate(problem: Problem, nu: np.ndarray, H: np.ndarray, P: np.ndarray,
                 R: np.ndarray) -> bool:  # fmt: skip
    """Whether the problem's gate drops the measurement: nu^T (H P H^T + R)^-1 nu > gate."""
    if problem.gate is None:
        return False
    return float(nu @ np.linalg.solve(H @ P @ H.T + R, nu)) > problem.gate


def gaussian_nll(nu: np.ndarray, S: np.ndarray) -> float:
    """-log N(nu; 0, S)."""
    sign, logdet = np.linalg.slogdet(S)
    if sign <= 0:
        return math.inf
    return 0.5 * (logdet + float(nu @ np.linalg.solve(S, nu)) + len(nu) * LOG_2PI)


def ekf_nll(problem: Problem, z: np.ndarray, Q: np.ndarray, R: np.ndarray) -> float:
    """-log p(z | Q, R) of one run by the (E)KF from the problem's start (the EKF's likelihood
    is approximate for a nonlinear problem)."""
    x, P, total = problem.x0.copy(), problem.P0.copy(), 0.0
    for k in range(len(z)):
        nu, H = innovation(problem, x, z[k], k)
        x, P, S, _ = joseph_update(x, P, nu, H, R)
        total += gaussian_nll(nu, S)
        F, G = problem.F(x, k), problem.G(x, k)
        x = problem.f(x, k)
        P = symmetric(F @ P @ F.T + G @ Q @ G.T)
    return total


@compiled
def linear_nll(F, G, H, Q, R, x0, P0, z):  # pragma: no cover - compiled; tests call it
    """-log p(z | Q, R) of a linear time-invariant system by the Kalman filter (+inf when an
    innovation covariance is not positive definite). The same filter as `ekf_nll` (standard
    covariance update instead of Joseph's: equal to rounding), written as scalar loops over
    preallocated arrays: small matrices through numpy's operators cost microseconds each in
    numba, this costs nanoseconds (the likelihood fits call it hundreds of times per run)."""
    n, m = x0.shape[0], H.shape[0]
    GQG = G @ Q @ G.T
    x, P = x0.copy(), P0.copy()
    x2, P2 = np.empty(n), np.empty((n, n))
    PHt, S, L = np.empty((n, m)), np.empty((m, m)), np.empty((m, m))
    K, nu, a = np.empty((n, m)), np.empty(m), np.empty(m)
    total = 0.0
    for k in range(z.shape[0]):
        for i in range(m):
            acc = z[k, i]
            for j in range(n):
                acc -= H[i, j] * x[j]
            nu[i] = acc
        for i in range(n):
            for j in range(m):
                acc = 0.0
                for l in range(n):
                    acc += P[i, l] * H[j, l]
                PHt[i, j] = acc
        for i in range(m):
            for j in range(m):
                acc = R[i, j]
                for l in range(n):
                    acc += H[i, l] * PHt[l, j]
                S[i, j] = acc
        # Cholesky S = L L^T
        logdet = 0.0
        for j in range(m):
            d = S[j, j]
            for l in range(j):
                d -= L[j, l] * L[j, l]
            if not d > 0.0:
                return np.inf
            L[j, j] = np.sqrt(d)
            logdet += 2.0 * np.log(L[j, j])
            for i in range(j + 1, m):
                acc = S[i, j]
                for l in range(j):
                    acc -= L[i, l] * L[j, l]
                L[i, j] = acc / L[j, j]
            for i in range(j):
                L[i, j] = 0.0
        # a = L^-1 nu: the quadratic form is a . a
        quad = 0.0
        for i in range(m):
            acc = nu[i]
            for l in range(i):
                acc -= L[i, l] * a[l]
            a[i] = acc / L[i, i]
            quad += a[i] * a[i]
        total += 0.5 * (logdet + quad + m * 1.8378770664093453)
        # K = PHt S^-1, row by row: L L^T k = PHt[i]
        for i in range(n):
            for j in range(m):
                acc = PHt[i, j]
                for l in range(j):
                    acc -= L[j, l] * K[i, l]
                K[i, j] = acc / L[j, j]
            for j in range(m - 1, -1, -1):
                acc = K[i, j]
                for l in range(j + 1, m):
                    acc -= L[l, j] * K[i, l]
                K[i, j] = acc / L[j, j]
        # x+ = x + K nu, P+ = P - K PHt^T (symmetrised), then the prediction
        for i in range(n):
            acc = x[i]
            for j in range(m):
                acc += K[i, j] * nu[j]
            x2[i] = acc
        for i in range(n):
            for j in range(n):
                acc = P[i, j]
                for l in range(m):
                    acc -= K[i, l] * PHt[j, l]
                P2[i, j] = acc
        for i in range(n):
            for j in range(i + 1, n):
                sym = 0.5 * (P2[i, j] + P2[j, i])
                P2[i, j] = sym
                P2[j, i] = sym
        for i in range(n):
            acc = 0.0
            for j in range(n):
                acc += F[i, j] * x2[j]
            x[i] = acc
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for l in range(n):
                    acc += F[i, l] * P2[l, j]
                P[i, j] = acc
        # P = (F P+) F^T + GQG: P holds F P+ now
        for i in range(n):
            for j in range(n):
                acc = GQG[i, j]
                for l in range(n):
                    acc += P[i, l] * F[j, l]
                P2[i, j] = acc
        for i in range(n):
            for j in range(n):
                P[i, j] = 0.5 * (P2[i, j] + P2[j, i])
    return total
