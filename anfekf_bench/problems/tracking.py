"""A tracking radar (SPEC 17): a 2-D nearly-constant-velocity target seen in range and bearing.

State x = (x, vx, y, vy) [m, m/s]; sampling period T. Motion: continuous white acceleration of
intensity q [m^2/s^3] on each axis, discretised exactly (Bar-Shalom, Li, Kirubarajan 2001,
section 6.2.2): x(k+1) = A x(k) + w(k), w ~ N(0, Q), Q = q blockdiag(B, B),
B = [[T^3/3, T^2/2], [T^2/2, T]]. The noise enters the state directly (G = I, nw = 4), so Q is the
full 4 x 4 state covariance, and every estimator's Q (covariance matching, the likelihood fit,
the truth-tuned scale) is that matrix: an estimate and the truth compare entry by entry.

The radar at a known position (px, py) measures z = (range, bearing) + v, v ~ N(0, R),
R = diag(sigma_range^2, sigma_bearing^2); the bearing atan2(y - py, x - px) is angle-valued
(wrapped). A gate drops measurements whose normalised innovation squared nu^T S^-1 nu exceeds the
chi-square quantile of the gate probability with 2 degrees of freedom: the filters do not use
them (nor adapt on them) and count them (`Trace.gated`).

A manoeuvre: over the steps [start, end) the truth turns at a constant rate omega [rad/s] (the
coordinated-turn transition with known rate, Bar-Shalom et al. 11.7.1), with the same process
noise. The filters' model is the nearly-constant-velocity one unless `known` says they are told
of the turn (then their f and F are the truth's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from .base import Problem, Trajectory, wrap
from .kalman import LOG_2PI, compiled


@dataclass(frozen=True)
class Turn:
    """The truth turns at omega [rad/s] over steps [start, end): the transition from k to k + 1
    for start <= k < end is the coordinated turn."""

    omega: float
    start: int
    end: int
    known: bool = False

    def rate(self, k: int) -> float:
        return self.omega if self.start <= k < self.end else 0.0


def transition(T: float, omega: float) -> np.ndarray:
    """The transition matrix over one period T: nearly constant velocity for omega = 0, the
    coordinated turn at rate omega otherwise (its limit as omega -> 0 is the former)."""
    if omega == 0.0:
        return np.array([[1, T, 0, 0], [0, 1, 0, 0], [0, 0, 1, T], [0, 0, 0, 1]], dtype=float)
    s, c = math.sin(omega * T), math.cos(omega * T)
    return np.array([
        [1, s / omega, 0, -(1 - c) / omega],
        [0, c, 0, -s],
        [0, (1 - c) / omega, 1, s / omega],
        [0, s, 0, c],
    ])  # fmt: skip


def white_acceleration_q(T: float, q: float) -> np.ndarray:
    """Q = q blockdiag(B, B), B = [[T^3/3, T^2/2], [T^2/2, T]] in the order (x, vx, y, vy)."""
    B = np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    Q = np.zeros((4, 4))
    Q[:2, :2] = Q[2:, 2:] = q * B
    return Q


def gate_threshold(probability: float | None, nz: int = 2) -> float | None:
    """The chi-square quantile of the gate probability (None: no gate)."""
    return None if probability is None else float(chi2.ppf(probability, nz))


@compiled
def range_bearing_filter(A, Q, R, x0, P0, radar, z, gate):  # pragma: no cover - compiled
    """The (E)KF of the tracking problem as scalar loops (numba compiles it): transitions A
    (steps, 4, 4), noise Q (4, 4) entering directly, range-bearing measurements z (steps, 2)
    from the radar at `radar`, measurements with nu^T S^-1 nu > gate dropped (inf: none).
    The same filter as `GenericKF.run` on `TrackingProblem` (2 x 2 inverse in closed form
    instead of a solve: equal to rounding); returns (x (steps, 4), P (steps, 4, 4), -log
    likelihood of the measurements used, measurements dropped). The likelihood fits and the
    truth-tuned fit evaluate it hundreds of times."""
    steps = z.shape[0]
    xs, Ps = np.empty((steps, 4)), np.empty((steps, 4, 4))
    x, P = x0.copy(), P0.copy()
    H, PHt, K = np.zeros((2, 4)), np.empty((4, 2)), np.empty((4, 2))
    IKH, T1, P2 = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    nu, x2 = np.empty(2), np.empty(4)
    nll, dropped = 0.0, 0
    for k in range(steps):
        dx, dy = x[0] - radar[0], x[2] - radar[1]
        r2 = max(dx * dx + dy * dy, 1e-12)
        r = np.sqrt(r2)
        nu[0] = z[k, 0] - np.hypot(dx, dy)
        nu[1] = np.pi - (np.pi - (z[k, 1] - np.arctan2(dy, dx))) % (2 * np.pi)
        H[0, 0], H[0, 2], H[1, 0], H[1, 2] = dx / r, dy / r, -dy / r2, dx / r2
        for i in range(4):
            for j in range(2):
                acc = 0.0
                for l in range(4):
                    acc += P[i, l] * H[j, l]
                PHt[i, j] = acc
        s00, s01, s10, s11 = R[0, 0], R[0, 1], R[1, 0], R[1, 1]
        for l in range(4):
            s00 += H[0, l] * PHt[l, 0]
            s01 += H[0, l] * PHt[l, 1]
            s10 += H[1, l] * PHt[l, 0]
            s11 += H[1, l] * PHt[l, 1]
        det = s00 * s11 - s01 * s10
        if not (det > 0.0 and s00 > 0.0):
            nll = np.inf
            det = 1.0
        i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
        a0 = i00 * nu[0] + i01 * nu[1]
        a1 = i10 * nu[0] + i11 * nu[1]
        d2 = nu[0] * a0 + nu[1] * a1
        if d2 > gate:
            dropped += 1
        else:
            nll += 0.5 * (np.log(det) + d2 + 2.0 * LOG_2PI)
            for i in range(4):
                K[i, 0] = PHt[i, 0] * i00 + PHt[i, 1] * i10
                K[i, 1] = PHt[i, 0] * i01 + PHt[i, 1] * i11
                x[i] += K[i, 0] * nu[0] + K[i, 1] * nu[1]
            for i in range(4):  # Joseph: (I - K H) P (I - K H)^T + K R K^T
                for j in range(4):
                    IKH[i, j] = (1.0 if i == j else 0.0) - K[i, 0] * H[0, j] - K[i, 1] * H[1, j]
            for i in range(4):
                for j in range(4):
                    acc = 0.0
                    for l in range(4):
                        acc += IKH[i, l] * P[l, j]
                    T1[i, j] = acc
            for i in range(4):
                for j in range(4):
                    acc = 0.0
                    for l in range(4):
                        acc += T1[i, l] * IKH[j, l]
                    for a in range(2):
                        for b in range(2):
                            acc += K[i, a] * R[a, b] * K[j, b]
                    P2[i, j] = acc
            for i in range(4):
                for j in range(4):
                    P[i, j] = 0.5 * (P2[i, j] + P2[j, i])
        xs[k] = x
        Ps[k] = P
        for i in range(4):
            acc = 0.0
            for j in range(4):
                acc += A[k, i, j] * x[j]
            x2[i] = acc
        x[:] = x2
        for i in range(4):
            for j in range(4):
                acc = 0.0
                for l in range(4):
                    acc += A[k, i, l] * P[l, j]
                T1[i, j] = acc
        for i in range(4):
            for j in range(4):
                acc = Q[i, j]
                for l in range(4):
                    acc += T1[i, l] * A[k, j, l]
                P2[i, j] = acc
        for i in range(4):
            for j in range(4):
                P[i, j] = 0.5 * (P2[i, j] + P2[j, i])
    return xs, Ps, nll, dropped


class TrackingProblem(Problem):
    """A nearly-constant-velocity target, a range-bearing radar, a gate, an optional turn."""

    name = "tracking"
    n, nw, nz = 4, 4, 2
    angles = (1,)
    position = (0, 2)
    position_unit = "m"

    def __init__(self, *, T: float, q: float, sigma_range: float, sigma_bearing: float,
                 radar, x0, P0, steps: int, gate: float | None = None,
                 turn: Turn | None = None):  # fmt: skip
        self.T, self.q = float(T), float(q)
        self.radar = np.array(radar, dtype=float)
        self.Q = white_acceleration_q(self.T, self.q)
        self.R = np.diag([float(sigma_range) ** 2, float(sigma_bearing) ** 2])
        self.x0 = np.array(x0, dtype=float)
        self.P0 = np.array(P0, dtype=float)
        self.steps = int(steps)
        self.gate_probability = gate
        self.gate = gate_threshold(gate, self.nz)
        self.turn = turn
        self._ncv = transition(self.T, 0.0)
        self._ct = None if turn is None else transition(self.T, turn.omega)
        self._transitions: dict[int, np.ndarray] = {}  # the filters' A per run length

    def default_assumed(self) -> tuple[np.ndarray, np.ndarray]:
        """The true noise: a scenario states what the filters get wrong (filter_noise)."""
        return self.Q.copy(), self.R.copy()

    def fast_filter(self, Q, R, z, *, gated: bool = True):
        """(x, P, -log likelihood, dropped) of the (E)KF with Q, R on measurements z, compiled
        (`range_bearing_filter`); `gated=False` uses every measurement."""
        if len(z) not in self._transitions:
            self._transitions[len(z)] = np.stack([self.model_transition(k) for k in range(len(z))])
        A = self._transitions[len(z)]
        gate = self.gate if gated and self.gate is not None else np.inf
        return range_bearing_filter(A, np.asarray(Q, float), np.asarray(R, float), self.x0,
                                    self.P0, self.radar, np.asarray(z, float), gate)  # fmt: skip

    def truth_transition(self, k: int) -> np.ndarray:
        """The true transition from step k to k + 1 (the turn where there is one)."""
        if self.turn is not None and self.turn.rate(k) != 0.0:
            return self._ct
        return self._ncv

    def model_transition(self, k: int) -> np.ndarray:
        """The filters' transition: the truth's if they are told of the turn, else NCV."""
        if self.turn is not None and self.turn.known:
            return self.truth_transition(k)
        return self._ncv

    def compiled_model(self):
        from .fast import tracking_model

        return tracking_model(self.radar, self._ncv, self._ct, self.turn, self.angles)

    def f(self, x, k):
        return self.model_transition(k) @ x

    def F(self, x, k):
        return self.model_transition(k)

    def G(self, x, k):
        return np.eye(4)

    def h(self, x, k):
        dx, dy = x[0] - self.radar[0], x[2] - self.radar[1]
        return np.array([math.hypot(dx, dy), math.atan2(dy, dx)])

    def H(self, x, k):
        dx, dy = x[0] - self.radar[0], x[2] - self.radar[1]
        r2 = max(dx * dx + dy * dy, 1e-12)  # at the radar itself the bearing is undefined
        r = math.sqrt(r2)
        return np.array([[dx / r, 0.0, dy / r, 0.0], [-dy / r2, 0.0, dx / r2, 0.0]])

    def simulate(self, rng: np.random.Generator) -> Trajectory:
        """As `Problem.simulate` (draws, in order: x(0), all process noise, all measurement
        noise), moved by the truth's transition: the turn whether or not the filters know it."""
        x = np.empty((self.steps, self.n))
        x[0] = rng.multivariate_normal(self.x0, self.P0)
        w = rng.multivariate_normal(np.zeros(self.nw), self.Q, size=self.steps)
        v = rng.multivariate_normal(np.zeros(self.nz), self.R, size=self.steps)
        for k in range(self.steps - 1):
            x[k + 1] = self.truth_transition(k) @ x[k] + w[k]
        dx, dy = x[:, 0] - self.radar[0], x[:, 2] - self.radar[1]
        z = np.column_stack([np.hypot(dx, dy), np.arctan2(dy, dx)]) + v
        return Trajectory(x=x, z=wrap(z, self.angles))
