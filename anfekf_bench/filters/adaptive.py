"""What every adaptive filter shares (SPEC 7): bounds, which innovations feed adaptation, the
process noise of the interval between Q events, and the map from a state-space Q to Qu.

Q events are scans that saw a landmark; the interval's process noise is accumulated from the end
of the previous Q event (research notes 0.3-0.4): because Qu = diag(qv, qg),

    Q_scan(q) = qv A_v + qg A_g,   A <- F A F^T + G e e^T G^T at every predict,

so a state-space estimate Q_hat maps to Qu by a two-parameter least squares through A_v, A_g
(`qu_least_squares`), weighted by P-^-1 so that metres and radians are commensurate.
"""

from __future__ import annotations

import numpy as np

from .ekf import Innovation, RobotEKF
from .spec import AdaptiveParams

_E_V = np.array([[1.0, 0.0], [0.0, 0.0]])
_E_G = np.array([[0.0, 0.0], [0.0, 1.0]])


def matmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B. The rules below multiply their 3 x 3 and 3 x 2 matrices with it so that the fast
    engine can compile it as a plain loop (engines/kernels.py), where BLAS's call costs more
    than the product; numpy's `@` here."""
    return A @ B


def outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.outer(a, b). Compiled (engines/kernels.py), a plain loop: numba's np.outer costs ten
    times that for three-vectors."""
    return np.outer(a, b)


def trace_of_product(A: np.ndarray, B: np.ndarray) -> float:
    """tr(A B) = np.trace(A @ B). Compiled (engines/kernels.py), the product's diagonal only, each
    entry summed as `matmul`'s loop sums it."""
    return np.trace(A @ B)


# numpy's lstsq cutoff for rcond=None on a 2 x 2 system (eps * max(M, N)), given explicitly so
# that the compiled `lstsq` cuts the same singular values.
LSTSQ_RCOND = 2.0 * float(np.finfo(float).eps)


def inv(A: np.ndarray) -> np.ndarray:
    """np.linalg.inv(A). Compiled (engines/kernels.py), a 3 x 3 inverse by Gaussian elimination
    with partial pivoting in plain loops, where LAPACK's call costs more than the inverse; it
    raises np.linalg.LinAlgError for an exactly singular matrix, as numpy does."""
    return np.linalg.inv(A)


def lstsq(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.linalg.lstsq(M, b, rcond=LSTSQ_RCOND)[0]: the least-squares solution of a 2 x 2 system,
    the least-norm one when M is singular. Compiled (engines/kernels.py), in closed form: LAPACK's
    SVD costs about a microsecond there."""
    return np.linalg.lstsq(M, b, rcond=LSTSQ_RCOND)[0]


def clip_to_bounds(value, start, bounds: tuple[float, float]):
    """Variances clipped to [floor * start, ceiling * start] elementwise (SPEC 7); NaN stays
    NaN. Floats or arrays: np.clip's result, written with np.maximum and np.minimum because
    numba's np.clip takes no scalars (the fast engine's kernels clip each channel as a float,
    without building an array)."""
    return np.minimum(np.maximum(value, bounds[0] * start), bounds[1] * start)


def qu_least_squares(Q_hat, A_v, A_g, W):
    """(qv, qg) minimising ||W^1/2 (Q_hat - qv A_v - qg A_g) W^1/2||_F (research notes 0.4 a).

    The normal equations M q = b with <X, Y>_W = tr(W X W Y); a singular M (an interval that
    excited one control only) falls back to the least-norm solution. Not yet clipped. 3 x 3
    float64 arrays in, a (2,) array out; numba compiles it as it is (the fast engine's kernels).
    """
    WAv, WAg, WQ = matmul(W, A_v), matmul(W, A_g), matmul(W, Q_hat)
    M = np.array(
        (
            (trace_of_product(WAv, WAv), trace_of_product(WAv, WAg)),
            (trace_of_product(WAg, WAv), trace_of_product(WAg, WAg)),
        )
    )
    b = np.array((trace_of_product(WAv, WQ), trace_of_product(WAg, WQ)))
    return lstsq(M, b)


def propagate_interval(A_v, A_g, F_scan, F, Q_v, Q_g):
    """One predict of the interval's accumulators: A <- F A F^T + Q_e with Q_e the step's noise
    of a unit variance on one control (G e e^T G^T), and F_scan <- F F_scan."""
    return (
        matmul(matmul(F, A_v), F.T) + Q_v,
        matmul(matmul(F, A_g), F.T) + Q_g,
        matmul(F, F_scan),
    )


class AdaptiveEKF(RobotEKF):
    """A `RobotEKF` that adapts R, Qu or P-: the common rules live here, the rule in subclasses.

    `params` is an `AdaptiveParams` (a built-in filter's spec, or a custom filter's Params).
    When "Q" is in `adapts`, the interval's process-noise accumulators `A_v`, `A_g` (and the
    interval's total `Q_scan`) are kept from one Q event to the next; subclasses call
    `reset_interval()` after using them.
    """

    params: AdaptiveParams

    def __init__(self, *args, params: AdaptiveParams, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        self.bounds = tuple(params.bounds)
        self.reset_interval()

    def reset_interval(self) -> None:
        """Start a new interval between Q events."""
        self.A_v = np.zeros((3, 3))
        self.A_g = np.zeros((3, 3))
        self.F_scan = np.eye(3)  # transition over the interval, for Q-from-correction rules
        self.P_scan_start = self.P.copy()  # P+ at the previous Q event

    def predict(self, u=0, dt: float | None = None):
        super().predict(u, dt)
        if "Q" in self.adapts:
            G = self.G
            self.A_v, self.A_g, self.F_scan = propagate_interval(
                self.A_v, self.A_g, self.F_scan, self.F,
                self.model.Q(G, _E_V, self.dt), self.model.Q(G, _E_G, self.dt),
            )  # fmt: skip

    @property
    def Q_scan(self) -> np.ndarray:
        """The process noise the interval added with the current Qu (propagated to now)."""
        return self.Qu[0, 0] * self.A_v + self.Qu[1, 1] * self.A_g

    def feeds_adaptation(self, inn: Innovation) -> bool:
        """Whether this innovation may feed adaptation (SPEC 7: all, or gate-accepted only)."""
        if self.params.adapt_from == "all" or self.gate is None:
            return True
        S = inn.HPHt + self.R
        return float(inn.nu @ np.linalg.solve(S, inn.nu)) <= self.gate

    def set_R_diag(self, R_diag: np.ndarray) -> None:
        """R <- diag(R_diag), within the bounds of its starting value."""
        self.R = np.diag(clip_to_bounds(np.asarray(R_diag, float), np.diag(self.R0), self.bounds))

    def set_Qu_diag(self, Qu_diag: np.ndarray) -> None:
        """Qu <- diag(Qu_diag), within the bounds of its starting value."""
        self.Qu = np.diag(
            clip_to_bounds(np.asarray(Qu_diag, float), np.diag(self.Qu0), self.bounds)
        )

    def qu_estimate(self, Q_hat: np.ndarray) -> np.ndarray:
        """diag(Qu) whose interval noise best matches a state-space estimate Q_hat
        (`qu_least_squares`, weighted by the inverse of the current P); not clipped, for rules
        that clamp or average the sample before setting Qu."""
        return qu_least_squares(Q_hat, self.A_v, self.A_g, np.linalg.inv(self.P))

    def set_Qu_from_state_noise(self, Q_hat: np.ndarray) -> None:
        """Qu from a state-space estimate of the interval's process noise (`qu_estimate`),
        within bounds."""
        self.set_Qu_diag(self.qu_estimate(Q_hat))
