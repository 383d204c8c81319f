"""A user's own problem (SPEC 17): a Python file the scenario names, read as a `Problem`.

The file defines, at module level (docs/CUSTOM_PROBLEMS.md):

- `f(x, k, p)`, `F(x, k, p)`, `G(x, k, p)`, `h(x, k, p)`, `H(x, k, p)`: the motion, its Jacobians
  and the measurement with its Jacobian, as float arrays of shapes (n,), (n, n), (n, nw), (nz,),
  (nz, n); `p` is the problem's parameter vector (`params`, which a scenario may override);
- `Q` (nw x nw), `R` (nz x nz): the true noise; `x0` (n,), `P0` (n x n): the start; `steps`;
- optionally `params` (a float vector, default empty), `angles` (angle-valued measurement
  components), `position` (state components scored as position, default all),
  `position_unit` (their unit as the regression gate shows it, e.g. "m"; default none),
  `linear = True` (f = F x, h = H x with constant matrices: what ALS needs), and
  `simulate(rng, steps, p) -> (x, z)`, its own simulator (default `Problem.simulate`).

Every shape is checked once, when the scenario is read, by calling each function at (x0, 0, p):
a missing name, a wrong shape, a non-finite value or a function that raises is a one-line
`ModuleProblemError`. Written in the subset of numpy that numba compiles, the same functions run
on the fast engine (`problems.fast.compile_module_model`).
"""

from __future__ import annotations

import hashlib
import importlib.util
import re
import sys
from functools import lru_cache
from pathlib import Path

import numpy as np

from .base import Problem, Trajectory, wrap

FUNCTIONS = ("f", "F", "G", "h", "H")
REQUIRED = FUNCTIONS + ("Q", "R", "x0", "P0", "steps")
MAX_DIM = 50
UNIT = re.compile(r"[A-Za-z0-9/^]{0,16}")  # a position unit: printed in the gate's tables


class ModuleProblemError(ValueError):
    """A problem module cannot be used; `str()` is one line naming what is wrong."""


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@lru_cache(maxsize=16)
def _load(path: str, digest: str):
    """The module at `path` (executed once per content: `digest` keys the cache)."""
    name = f"anfekf_problem_{Path(path).stem}_{digest[:12]}"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ModuleProblemError("not a Python module")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # the user's code: any failure is reported in one line
        raise ModuleProblemError(f"importing it raised {first_line(exc)}") from None
    sys.modules[name] = module  # numba's cache and pickling look modules up by name
    return module


def load_module(path: Path):
    """(the user's module, its file's sha256); ModuleProblemError when it cannot be read or
    imported."""
    try:
        digest = file_digest(path)
    except OSError as exc:
        raise ModuleProblemError(f"cannot read it ({exc.strerror or exc})") from None
    return _load(str(path), digest), digest


def _matrix(value, what: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        M = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ModuleProblemError(f"{what}: not an array of numbers") from None
    if shape is not None and M.shape != shape:
        raise ModuleProblemError(f"{what}: expected shape {shape}, got {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ModuleProblemError(f"{what}: not finite")
    return M


def _covariance(value, m: int | None, what: str) -> np.ndarray:
    M = _matrix(value, what)
    if M.ndim != 2 or M.shape[0] != M.shape[1] or M.size == 0:
        raise ModuleProblemError(f"{what}: expected a square matrix, got shape {M.shape}")
    if m is not None and M.shape[0] != m:
        raise ModuleProblemError(f"{what}: expected {m} x {m}, got {M.shape[0]} x {M.shape[1]}")
    if M.shape[0] > MAX_DIM:
        raise ModuleProblemError(f"{what}: at most {MAX_DIM} x {MAX_DIM}")
    if not np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, np.abs(M).max())):
        raise ModuleProblemError(f"{what}: a covariance must be symmetric")
    if np.linalg.eigvalsh(M).min() <= 0:
        raise ModuleProblemError(f"{what}: a covariance must be positive definite")
    return M


def _indices(value, n: int, what: str) -> tuple[int, ...]:
    try:
        out = tuple(int(i) for i in value)
    except (TypeError, ValueError):
        raise ModuleProblemError(f"{what}: expected a list of indices") from None
    if len(set(out)) != len(out) or not all(0 <= i < n for i in out):
        raise ModuleProblemError(f"{what}: distinct indices 0 .. {n - 1}")
    return out


class ModuleProblem(Problem):
    """The problem a user's module defines (see the module docstring)."""

    name = "module"

    def __init__(self, path: Path, *, params=None, steps: int | None = None):
        self.path = Path(path)
        self.module, self.digest = load_module(self.path)
        mod = self.module
        missing = [key for key in REQUIRED if not hasattr(mod, key)]
        if missing:
            raise ModuleProblemError(
                f"does not define {', '.join(missing)} (a problem module defines the functions"
                f" {', '.join(FUNCTIONS)} and Q, R, x0, P0, steps)"
            )
        for key in FUNCTIONS:
            if not callable(getattr(mod, key)):
                raise ModuleProblemError(f"{key}: not a function")
        self.x0 = _matrix(mod.x0, "x0")
        if self.x0.ndim != 1 or not 1 <= self.x0.size <= MAX_DIM:
            raise ModuleProblemError(f"x0: expected a vector of 1 .. {MAX_DIM} values")
        self.n = self.x0.size
        self.P0 = _covariance(mod.P0, self.n, "P0")
        self.Q = _covariance(mod.Q, None, "Q")
        self.R = _covariance(mod.R, None, "R")
        self.nw, self.nz = self.Q.shape[0], self.R.shape[0]
        self.steps = int(mod.steps if steps is None else steps)
        if steps is None and (not isinstance(mod.steps, int) or mod.steps < 2):
            raise ModuleProblemError("steps: expected an integer >= 2")
        defaults = np.array(getattr(mod, "params", ()), dtype=float).ravel()
        self.params = defaults if params is None else np.array(params, dtype=float)
        if self.params.shape != defaults.shape:
            raise ModuleProblemError(
                f"params: expected {defaults.size} values (the module's params), got"
                f" {self.params.size}"
            )
        self.angles = _indices(getattr(mod, "angles", ()), self.nz, "angles")
        self.position = _indices(getattr(mod, "position", range(self.n)), self.n, "position")
        self.position_unit = getattr(mod, "position_unit", "")
        if not (isinstance(self.position_unit, str) and UNIT.fullmatch(self.position_unit)):
            raise ModuleProblemError("position_unit: expected a short unit name such as 'm'"
                                     " (letters, digits, '/', '^', at most 16)")  # fmt: skip
        self.user_simulate = getattr(mod, "simulate", None)
        self._check_functions()
        # `linear = True`: the module promises f = F x, h = H x with constant F, G, H (ALS and
        # the compiled likelihood need it); they are read once, at x0.
        self.linear = getattr(mod, "linear", False) is True
        if self.linear:
            self.Fm, self.Gm, self.Hm = (self.F(self.x0, 0), self.G(self.x0, 0),
                                         self.H(self.x0, 0))  # fmt: skip

    def _check_functions(self) -> None:
        n, nw, nz = self.n, self.nw, self.nz
        shapes = {"f": (n,), "F": (n, n), "G": (n, nw), "h": (nz,), "H": (nz, n)}
        for key, shape in shapes.items():
            try:
                value = getattr(self.module, key)(self.x0.copy(), 0, self.params.copy())
            except Exception as exc:  # the user's code: any failure is reported in one line
                raise ModuleProblemError(f"{key}(x0, 0, params) raised {first_line(exc)}") from None
            _matrix(value, f"{key}(x0, 0, params)", shape)

    def _call(self, key: str, x, k):
        try:
            return np.asarray(getattr(self.module, key)(x, k, self.params), dtype=float)
        except Exception as exc:  # the user's code: any failure is reported in one line
            raise ModuleProblemError(f"{key}(x, {k}, params) raised {first_line(exc)}") from None

    def f(self, x, k):
        return self._call("f", x, k)

    def F(self, x, k):
        return self._call("F", x, k)

    def G(self, x, k):
        return self._call("G", x, k)

    def h(self, x, k):
        return self._call("h", x, k)

    def H(self, x, k):
        return self._call("H", x, k)

    def simulate(self, rng: np.random.Generator) -> Trajectory:
        if self.user_simulate is None:
            return super().simulate(rng)
        try:
            x, z = self.user_simulate(rng, self.steps, self.params)
            x, z = np.asarray(x, dtype=float), np.asarray(z, dtype=float)
        except Exception as exc:  # the user's code: any failure is reported in one line
            raise ModuleProblemError(f"simulate raised {first_line(exc)}") from None
        if x.shape != (self.steps, self.n) or z.shape != (self.steps, self.nz):
            raise ModuleProblemError(
                f"simulate: expected x of shape {(self.steps, self.n)} and z of shape"
                f" {(self.steps, self.nz)}, got {x.shape} and {z.shape}"
            )
        return Trajectory(x=x, z=wrap(z, self.angles))

    def compiled_model(self):
        from .fast import compile_module_model

        return compile_module_model(self)
