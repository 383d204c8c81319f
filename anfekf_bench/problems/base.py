"""The problem interface (SPEC 17): what a filter needs to know about a system, and its simulator.

Motion x(k+1) = f(x(k), k) + G w(k), w ~ N(0, Q) (Q is nw x nw: G maps the noise input into the
state); measurement z(k) = h(x(k), k) + v(k), v ~ N(0, R). `F`, `G`, `H` are the Jacobians.
Measurement components listed in `angles` are angle-valued: their residuals are wrapped to
(-pi, pi]. `position` names the state components scored as position (the rest are scored
together as "rest"). `gate`, where set, is the threshold of the normalised innovation squared
above which the filters drop a measurement (counted per run); `default_assumed` is the noise the
filters assume when a scenario does not say.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np


def wrap(residual: np.ndarray, angles: tuple[int, ...]) -> np.ndarray:
    """The residual with its angle-valued components wrapped to (-pi, pi]."""
    if not angles:
        return residual
    out = np.array(residual, dtype=float)
    idx = list(angles)
    out[..., idx] = np.pi - np.mod(np.pi - out[..., idx], 2 * np.pi)
    return out


class NotCompilable(Exception):
    """A problem cannot run on the fast engine; `str()` says why in one line."""


@dataclass(frozen=True)
class Trajectory:
    """One simulated run: the true states x (steps, n) and the measurements z (steps, nz);
    z[k] measures x[k]."""

    x: np.ndarray
    z: np.ndarray


class Problem(ABC):
    """A state-space problem. Subclasses set the dimensions, the true noise and the start."""

    name: str = "problem"
    n: int  # state dimension
    nw: int  # process-noise input dimension
    nz: int  # measurement dimension
    angles: tuple[int, ...] = ()  # angle-valued measurement components
    position: tuple[int, ...] = ()  # state components scored as position
    position_unit: str = ""  # their unit, as the gate shows rmse_pos ("m"); "": none
    linear: bool = False  # f and h linear and time-invariant (F, G, H constant)
    gate: float | None = None  # nu^T S^-1 nu above which a measurement is dropped; None: none
    Q: np.ndarray  # true process-noise covariance (nw, nw)
    R: np.ndarray  # true measurement-noise covariance (nz, nz)
    x0: np.ndarray  # mean of the true initial state, and the filters' starting estimate
    P0: np.ndarray  # covariance of the true initial state, and the filters' starting P
    steps: int  # measurements per run

    @property
    def rest(self) -> tuple[int, ...]:
        """The state components scored as the rest (those not in `position`)."""
        return tuple(i for i in range(self.n) if i not in self.position)

    def default_assumed(self) -> tuple[np.ndarray, np.ndarray]:
        """The (Q, R) the filters assume when the scenario gives no `filter_noise`: I, I."""
        return np.eye(self.nw), np.eye(self.nz)

    def fast_filter(self, Q: np.ndarray, R: np.ndarray, z: np.ndarray, *, gated: bool = True):
        """(x, P, -log likelihood, dropped) of the (E)KF with Q, R on z, compiled; None where
        the problem has no compiled filter (the fits then run the Python loop)."""
        return None

    @abstractmethod
    def f(self, x: np.ndarray, k: int) -> np.ndarray:
        """The noise-free motion from step k to k + 1."""

    @abstractmethod
    def F(self, x: np.ndarray, k: int) -> np.ndarray:
        """df/dx at x (n, n)."""

    @abstractmethod
    def G(self, x: np.ndarray, k: int) -> np.ndarray:
        """How the process noise enters the state (n, nw)."""

    @abstractmethod
    def h(self, x: np.ndarray, k: int) -> np.ndarray:
        """The noise-free measurement of x at step k."""

    @abstractmethod
    def H(self, x: np.ndarray, k: int) -> np.ndarray:
        """dh/dx at x (nz, n)."""

    def compiled_model(self):
        """Its functions compiled for the fast engine (`problems.fast.CompiledModel`), or
        `NotCompilable` saying why not."""
        raise NotCompilable(f"problem {self.name!r} has no compiled model")

    def simulate(self, rng: np.random.Generator) -> Trajectory:
        """Truth and measurements of one run: x(0) ~ N(x0, P0), then the model with its true
        noise. Draws, in order: x(0), all process noise, all measurement noise."""
        x = np.empty((self.steps, self.n))
        z = np.empty((self.steps, self.nz))
        x[0] = rng.multivariate_normal(self.x0, self.P0)
        w = rng.multivariate_normal(np.zeros(self.nw), self.Q, size=self.steps)
        v = rng.multivariate_normal(np.zeros(self.nz), self.R, size=self.steps)
        for k in range(self.steps):
            z[k] = self.h(x[k], k) + v[k]
            if k + 1 < self.steps:
                x[k + 1] = self.f(x[k], k) + self.G(x[k], k) @ w[k]
        return Trajectory(x=x, z=wrap(z, self.angles))
