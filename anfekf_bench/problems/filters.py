"""Dimension-generic filters on the problem interface, with full Q and R (SPEC 17).

Each is a kind of the filter registry (`filters.registry`, which says on every spec which
problems the kind supports and why not where it does not); here is its implementation for any
`Problem`. One loop (`GenericKF.run`) steps them all; a family overrides its hooks:

- `ekf`: the (E)KF with the assumed noise (the scenario's `filter_noise`, or its own Q, R);
- `ekf-oracle`: the same with the true Q and R;
- `sage-husa`: covariance matching, recursive (Sage & Husa 1969): R from the innovation before
  the gain, Q from the correction, each a fading mean (the zoo's `fading_weight` and `q_sample`
  rules), projected onto the positive semidefinite matrices;
- `vb-r`: variational Bayes with an inverse-Wishart posterior on the full R (Sarkka & Hartikainen
  2013's adaptive filter in its full-matrix form); Q stays the assumed one (the VB of Q needs a
  smoother over a window: not defined here);
- `als` (`problems.als`), `ekf-ml` (`problems.ml`) and `ekf-tuned` (`problems.tuned`) build on
  the same loop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field

from ..filters.registry import SPEC_BY_KIND, role_of
from ..filters.sage_husa import fading_weight, q_sample
from ..schema import StrictModel
from .base import Problem
from .kalman import innovation, joseph_update, nearest_psd, outside_gate, symmetric

Matrix = list[list[Annotated[float, Field(allow_inf_nan=False)]]]

# A filter's name: plain text (it is printed in tables and the gate's lines).
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9 _.+-]*$"
# Floor of a projected covariance's eigenvalues, as a share of the mean variance it started at
# (sage-husa: of each component's starting variance).
PSD_FLOOR = 1e-6


@dataclass
class Trace:
    """A filter's run: x (steps, n), P (steps, n, n) after each update, the Q and R in force
    at each step (steps, nw, nw), (steps, nz, nz), its seconds (fits on the run included) and
    the measurements the problem's gate dropped."""

    x: np.ndarray
    P: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    seconds: float = 0.0
    gated: int = 0


class ProblemFilterSpec(StrictModel):
    """A filter of a problem scenario: a unique `name` and a `kind` of the registry, whose spec
    there names this class as its form on the problems (`problem_form`; problems.forms). What
    the kind is (its role, whether it is given the true noise) is the registry's."""

    name: str = Field(min_length=1, max_length=64, pattern=NAME_PATTERN)
    kind: str
    estimates: ClassVar[frozenset[str]] = frozenset()  # "Q", "R": what it identifies

    @property
    def role(self) -> str | None:
        """What it is in a comparison (filters.spec.ROLES), as the registry says of its kind."""
        return role_of(self.kind)

    @property
    def uses_true_noise(self) -> bool:
        """Whether it is given the true Q and R (the oracle), as its kind's spec declares."""
        return SPEC_BY_KIND[self.kind].uses_true_noise

    def check(self, problem: Problem) -> None:
        """ValueError saying why it cannot run on `problem` (checked with the scenario)."""

    def fits_on_training(self) -> bool:
        """Whether it is fitted once on the scenario's training runs before the batch."""
        return False

    def estimated(self) -> frozenset[str]:
        return self.estimates

    def fit_training(self, problem: Problem, runs: list, Q0: np.ndarray, R0: np.ndarray):
        """(Q, R, record) fitted on the training runs (`base.Trajectory`s: truth and
        measurements) from the assumed (Q0, R0); the record goes to the manifest. Only for
        the specs that `fits_on_training`."""
        raise NotImplementedError

    def build(self, problem: Problem, Q: np.ndarray, R: np.ndarray) -> GenericKF:
        """A fresh filter for one run, starting from (Q, R): the assumed noise, or the true one
        for the oracle (the caller decides by `uses_true_noise`)."""
        raise NotImplementedError


class GenericKF:
    """The (E)KF with fixed Q and R; the adaptive families override the hooks."""

    def __init__(self, problem: Problem, Q: np.ndarray, R: np.ndarray):
        self.problem = problem
        self.Q = np.array(Q, dtype=float)
        self.R = np.array(R, dtype=float)
        # The problem's compiled model (`problems.fast.CompiledModel`): set, `run` runs the
        # family's compiled loop (the fast engine) instead of this Python loop.
        self.model = None

    def before_gain(self, k: int, nu: np.ndarray, H: np.ndarray, P: np.ndarray) -> None:
        """Adapt R (or anything the gain uses) from the innovation of step k."""

    def after_update(self, k: int, dx: np.ndarray, P_post: np.ndarray, prev) -> None:
        """Adapt Q from the update's correction dx = x+ - x- (prev: (F, G, P+) of the
        transition into step k and the posterior it started from; None at k = 0)."""

    def finish(self, z: np.ndarray) -> None:
        """After the last step (a batch identifier's final estimate)."""

    def run(self, z: np.ndarray) -> Trace:
        if self.model is not None:
            return self.run_compiled(z)
        p = self.problem
        steps = len(z)
        xs, Ps = np.empty((steps, p.n)), np.empty((steps, p.n, p.n))
        Qs, Rs = np.empty((steps, p.nw, p.nw)), np.empty((steps, p.nz, p.nz))
        x, P = p.x0.copy(), p.P0.copy()
        prev = None
        gated = 0
        started = time.perf_counter()
        for k in range(steps):
            nu, H = innovation(p, x, z[k], k)
            if outside_gate(p, nu, H, P, self.R):  # dropped: no update, nothing adapted
                gated += 1
            else:
                self.before_gain(k, nu, H, P)
                x_prior = x
                x, P, _, _ = joseph_update(x, P, nu, H, self.R)
                self.after_update(k, x - x_prior, P, prev)
            xs[k], Ps[k], Qs[k], Rs[k] = x, P, self.Q, self.R
            F, G = p.F(x, k), p.G(x, k)
            prev = (F, G, P)
            x = p.f(x, k)
            P = symmetric(F @ P @ F.T + G @ self.Q @ G.T)
        self.finish(z)
        Qs[-1], Rs[-1] = self.Q, self.R
        return Trace(xs, Ps, Qs, Rs, time.perf_counter() - started, gated)

    def run_compiled(self, z: np.ndarray) -> Trace:
        """`run` on the fast engine: the family's loop in `problems.fast` (here: fixed Q, R)."""
        from .fast import as_arrays, ekf_run, gate_of

        p = self.problem
        started = time.perf_counter()
        xs, Ps, gated = ekf_run(*self.model.args(), *as_arrays(p.x0, p.P0, self.Q, self.R, z),
                                gate_of(p))  # fmt: skip
        return Trace(xs, Ps, repeat(self.Q, len(z)), repeat(self.R, len(z)),
                     time.perf_counter() - started, gated)  # fmt: skip


def repeat(M: np.ndarray, steps: int) -> np.ndarray:
    """M at every step (steps, *M.shape)."""
    return np.repeat(M[None], steps, axis=0)


class EKFSpec(ProblemFilterSpec):
    """The (E)KF with the assumed noise (the scenario's filter_noise, or its own Q and R)."""

    kind: Literal["ekf"]
    Q: Matrix | None = Field(None, description="its own assumed Q (nw x nw); default filter_noise")
    R: Matrix | None = Field(None, description="its own assumed R (nz x nz); default filter_noise")

    def build(self, problem, Q, R):
        return GenericKF(problem, Q if self.Q is None else self.Q, R if self.R is None else self.R)


class OracleSpec(ProblemFilterSpec):
    """The (E)KF given the true Q and R: the reference every ratio is taken against."""

    kind: Literal["ekf-oracle"]

    def build(self, problem, Q, R):
        return GenericKF(problem, Q, R)


class SageHusaSpec(ProblemFilterSpec):
    """Recursive covariance matching (Sage-Husa) of the full R and Q, fading or cumulative."""

    kind: Literal["sage-husa"]
    estimates: ClassVar[frozenset[str]] = frozenset({"Q", "R"})
    b: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        1.0,
        description="fading factor: d_k = (1 - b) / (1 - b^(k+1)); 1: the plain mean of every"
        " sample so far (d_k = 1 / (k + 1))",
    )
    adapt: Literal["R", "Q", "RQ"] = Field("RQ", description="what it estimates")
    warmup: int = Field(
        0, ge=0, le=10**7, description="steps whose samples are averaged before the estimate"
        " is used (the assumed noise is in force until then)",
    )  # fmt: skip

    def estimated(self):
        return frozenset(self.adapt)

    def build(self, problem, Q, R):
        return SageHusaKF(problem, Q, R, self)


class SageHusaKF(GenericKF):
    def __init__(self, problem, Q, R, spec: SageHusaSpec):
        super().__init__(problem, Q, R)
        self.spec = spec
        self.R_hat, self.Q_hat = self.R.copy(), self.Q.copy()
        # The projection works in units of the starting standard deviations, so that a floor
        # of PSD_FLOOR means the same for every component (range in m, bearing in rad: the
        # tracking radar's R spans seven decades).
        sd_R, sd_Q = np.sqrt(np.diag(self.R)), np.sqrt(np.diag(self.Q))
        self.R_units, self.Q_units = np.outer(sd_R, sd_R), np.outer(sd_Q, sd_Q)

    def weight(self, k: int) -> float:
        b = self.spec.b
        return 1.0 / (k + 1) if b == 1.0 else fading_weight(k, b)

    def before_gain(self, k, nu, H, P):
        if "R" not in self.spec.adapt:
            return
        sample = np.outer(nu, nu) - H @ P @ H.T
        d = self.weight(k)
        self.R_hat = (1.0 - d) * self.R_hat + d * sample
        if k + 1 >= self.spec.warmup:
            self.R = nearest_psd(self.R_hat / self.R_units, PSD_FLOOR) * self.R_units

    def after_update(self, k, dx, P_post, prev):
        if "Q" not in self.spec.adapt or prev is None:
            return
        F_prev, G_prev, P_prev = prev
        # The state-space sample's expectation is G Q G^T: Q by least squares through G.
        G_pinv = np.linalg.pinv(G_prev)
        sample = G_pinv @ q_sample(dx, P_post, P_prev, F_prev, True) @ G_pinv.T
        d = self.weight(k - 1)  # Q's first sample comes at step 1
        self.Q_hat = (1.0 - d) * self.Q_hat + d * symmetric(sample)
        if k + 1 >= self.spec.warmup:
            self.Q = nearest_psd(self.Q_hat / self.Q_units, PSD_FLOOR) * self.Q_units

    def run_compiled(self, z):
        from .fast import as_arrays, gate_of, sage_husa_run

        p, spec = self.problem, self.spec
        started = time.perf_counter()
        arrays = as_arrays(p.x0, p.P0, self.Q, self.R, z)
        *out, gated = sage_husa_run(*self.model.args(), *arrays, gate_of(p), float(spec.b),
                                    int("R" in spec.adapt), int("Q" in spec.adapt),
                                    int(spec.warmup), *as_arrays(self.R_units, self.Q_units),
                                    PSD_FLOOR)  # fmt: skip
        return Trace(*out, time.perf_counter() - started, gated)


class VBRSpec(ProblemFilterSpec):
    """Variational Bayes with an inverse-Wishart posterior on the full R (Sarkka-Hartikainen)."""

    kind: Literal["vb-r"]
    estimates: ClassVar[frozenset[str]] = frozenset({"R"})
    rho: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        1.0, description="forgetting of the posterior's degrees of freedom (1: none)"
    )
    iterations: int = Field(5, ge=1, le=100, description="fixed-point iterations per update")
    prior_dof: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] | None = Field(
        None, description="prior degrees of freedom beyond nz + 1 (default 1: the vaguest proper)"
    )

    def build(self, problem, Q, R):
        return VBRKF(problem, Q, R, self)


class VBRKF(GenericKF):
    """R ~ IW(nu, V); the filter uses E[R^-1]^-1 = V / nu, the VB update's fixed point."""

    def __init__(self, problem, Q, R, spec: VBRSpec):
        super().__init__(problem, Q, R)
        self.spec = spec
        m = problem.nz
        self.nu = m + 1.0 + (1.0 if spec.prior_dof is None else spec.prior_dof)
        self.V = self.nu * self.R  # so that the filter starts from the assumed R

    def run_compiled(self, z):
        from .fast import as_arrays, gate_of, vbr_run

        p, spec = self.problem, self.spec
        started = time.perf_counter()
        arrays = as_arrays(p.x0, p.P0, self.Q, self.R, z)
        xs, Ps, Rs, gated = vbr_run(*self.model.args(), *arrays, gate_of(p), float(spec.rho),
                                    int(spec.iterations), float(self.nu))  # fmt: skip
        return Trace(xs, Ps, repeat(self.Q, len(z)), Rs, time.perf_counter() - started, gated)

    def run(self, z):
        if self.model is not None:
            return self.run_compiled(z)
        # The VB update iterates the Kalman update itself: its own loop.
        p, spec, m = self.problem, self.spec, self.problem.nz
        steps = len(z)
        xs, Ps = np.empty((steps, p.n)), np.empty((steps, p.n, p.n))
        Qs, Rs = np.empty((steps, p.nw, p.nw)), np.empty((steps, m, m))
        x, P = p.x0.copy(), p.P0.copy()
        gated = 0
        started = time.perf_counter()
        for k in range(steps):
            nu_z, H = innovation(p, x, z[k], k)
            if outside_gate(p, nu_z, H, P, self.R):  # dropped: the posterior stays as it was
                gated += 1
                xs[k], Ps[k], Qs[k], Rs[k] = x, P, self.Q, self.R
                F, G = p.F(x, k), p.G(x, k)
                x = p.f(x, k)
                P = symmetric(F @ P @ F.T + G @ self.Q @ G.T)
                continue
            nu_prior = spec.rho * (self.nu - m - 1.0) + m + 1.0
            V_prior = spec.rho * self.V
            self.nu = nu_prior + 1.0
            V = V_prior
            for _ in range(spec.iterations):
                R = V / self.nu
                nu_z, H = innovation(p, x, z[k], k)
                x_post, P_post, _, _ = joseph_update(x, P, nu_z, H, R)
                r, Hp = innovation(p, x_post, z[k], k)
                V = V_prior + np.outer(r, r) + Hp @ P_post @ Hp.T
            self.V = symmetric(V)
            self.R = self.V / self.nu
            x, P = x_post, P_post
            xs[k], Ps[k], Qs[k], Rs[k] = x, P, self.Q, self.R
            F, G = p.F(x, k), p.G(x, k)
            x = p.f(x, k)
            P = symmetric(F @ P @ F.T + G @ self.Q @ G.T)
        return Trace(xs, Ps, Qs, Rs, time.perf_counter() - started, gated)
