"""Two-input, 25-rule zero-order Sugeno ANFIS (Havangi et al., Sec. 5.1.1).

The network has five layers (equation numbers refer to the paper):

1. Input layer: ``u = (u0, u1)``.
2. Membership layer, eq. (35): five Gaussian membership functions (MFs) per input,
   labelled L, LM, Z, HM, H (index 0..4),
   ``mu_ij(u_i) = exp(-(u_i - m_ij)^2 / delta_ij^2)``.
3. Rule layer, eq. (36): 25 rules ``(r, c)`` (``r`` = MF index of input 0, ``c`` = MF
   index of input 1), firing strength ``f_rc = mu_0r(u0) * mu_1c(u1)`` (product t-norm).
4. Normalisation layer, eq. (37): ``fbar_rc = f_rc / sum_{r'c'} f_r'c'``.
5. Output layer, eq. (38): ``o = sum_rc fbar_rc * w[RULE_TABLE[r, c]]`` with seven
   singleton consequents S1..S7 stored as ``w[0..6]`` and shared between rules.

Parameters are trained by steepest descent, eqs. (41)-(42), ``W <- W - eta * dE/dW`` with
``dE/dW = (dE/do) * (do/dW)`` (the paper's eq. (42) has a loose sign; this is the
descent direction).

Numerical safety: because the rule firing strengths factorise, ``sum_rc f_rc =
(sum_r mu_0r)(sum_c mu_1c)``, so the normalised firing strengths are the outer product of
two softmaxes of the log-memberships ``l_ij = -(u_i - m_ij)^2 / delta_ij^2``:
``fbar_rc = p_r * q_c`` with ``p = softmax(l_0)``, ``q = softmax(l_1)``. Subtracting the
maximum log-membership before exponentiating means the largest term is exactly 1, so the
normalisation never divides by zero even when every raw membership underflows (input far
outside all MFs), and all outputs and gradients stay finite.

Everything is pure: functions take an :class:`ANFISParams` and return new values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "MF_LABELS",
    "N_INPUTS",
    "N_MF",
    "N_SINGLETONS",
    "RULE_TABLE",
    "ANFISParams",
    "firing",
    "forward",
    "init_params",
    "memberships",
    "output_and_gradient",
    "sgd_step",
]

N_INPUTS = 2
N_MF = 5
N_SINGLETONS = 7
MF_LABELS: tuple[str, ...] = ("L", "LM", "Z", "HM", "H")

# Inputs are clipped to this magnitude (far beyond any sensible MF range) so that the
# squared distances (u - m)^2 / delta^2 and their derivatives cannot overflow to inf.
_U_CLIP = 1e100


def _build_rule_table() -> np.ndarray:
    """w-index of rule (r, c): S-index ``clip(8 - (r + c), 1, 7)`` minus one."""
    r = np.arange(N_MF)[:, None]
    c = np.arange(N_MF)[None, :]
    table = np.clip(8 - (r + c), 1, N_SINGLETONS) - 1
    table.setflags(write=False)
    return table


RULE_TABLE: np.ndarray = _build_rule_table()
"""(5, 5) int array: index into ``w`` (0..6, i.e. S1..S7 minus one) of rule (r, c).

Rows are the MF of input 0, columns the MF of input 1 (L, LM, Z, HM, H)::

    L : S7 S7 S6 S5 S4
    LM: S7 S6 S5 S4 S3
    Z : S6 S5 S4 S3 S2
    HM: S5 S4 S3 S2 S1
    H : S4 S3 S2 S1 S1
"""

_RULE_FLAT = RULE_TABLE.ravel()
# (7, 25) indicator: _RULE_INDICATOR[k, 5 r + c] = 1 iff rule (r, c) uses singleton k, so
# do/dw = _RULE_INDICATOR @ fbar.ravel().
_RULE_INDICATOR = (np.arange(N_SINGLETONS)[:, None] == _RULE_FLAT[None, :]).astype(float)
_RULE_INDICATOR.setflags(write=False)


@dataclass(frozen=True, eq=False)
class ANFISParams:
    """ANFIS parameters (or a gradient record of the same shape).

    Attributes:
        m: (2, 5) MF centres ``m_ij`` of eq. (35); row i = input, column j = MF (L..H).
        delta: (2, 5) MF widths ``delta_ij`` of eq. (35), > 0.
        w: (7,) singleton consequents S1..S7 of eq. (38).
    """

    m: np.ndarray
    delta: np.ndarray
    w: np.ndarray


def _frozen(a: ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.array(a, dtype=float)  # always a fresh copy
    if arr.shape != shape:
        raise ValueError(f"expected shape {shape}, got {arr.shape}")
    arr.setflags(write=False)
    return arr


def init_params(
    centres0: ArrayLike = (-1.0, -0.5, 0.0, 0.5, 1.0),
    centres1: ArrayLike = (-0.2, -0.1, 0.0, 0.1, 0.2),
    width0: float | ArrayLike = 0.35,
    width1: float | ArrayLike = 0.1,
    singleton_scale: float = 0.1,
) -> ANFISParams:
    """Initial ANFIS parameters.

    Defaults follow the project spec: input 0 (an innovation-like quantity) has centres
    (-1, -0.5, 0, 0.5, 1) and width 0.35; input 1 (its rate of change) has centres
    (-0.2, -0.1, 0, 0.1, 0.2) and width 0.1; singletons ``w = a * (-3, ..., 3)`` with
    ``a = singleton_scale`` so S1 = -3a (rule H,H) and S7 = +3a (rule L,L).

    For a pairing of two same-scale inputs (e.g. d11, d22) pass
    ``centres1=(-1, -0.5, 0, 0.5, 1), width1=0.35``.

    Args:
        centres0: five MF centres of input 0 (L, LM, Z, HM, H).
        centres1: five MF centres of input 1.
        width0: MF width(s) ``delta`` of input 0, scalar or five values (> 0).
        width1: MF width(s) of input 1, scalar or five values (> 0).
        singleton_scale: ``a`` in ``w = a * (-3, -2, -1, 0, 1, 2, 3)``.

    Returns:
        A new :class:`ANFISParams` with read-only float arrays.
    """
    m = np.stack(
        [np.broadcast_to(np.asarray(c, dtype=float), (N_MF,)) for c in (centres0, centres1)]
    )
    delta = np.stack(
        [np.broadcast_to(np.asarray(s, dtype=float), (N_MF,)) for s in (width0, width1)]
    )
    if not np.all(delta > 0):
        raise ValueError("MF widths must be > 0")
    w = float(singleton_scale) * np.arange(-3.0, 4.0)
    return ANFISParams(
        m=_frozen(m, (N_INPUTS, N_MF)),
        delta=_frozen(delta, (N_INPUTS, N_MF)),
        w=_frozen(w, (N_SINGLETONS,)),
    )


def _scaled_distance(params: ANFISParams, u: ArrayLike) -> np.ndarray:
    """``z_ij = (u_i - m_ij) / delta_ij``, shape (2, 5); ``log mu_ij = -z_ij^2``."""
    uu = np.clip(np.asarray(u, dtype=float).reshape(N_INPUTS, 1), -_U_CLIP, _U_CLIP)
    return (uu - params.m) / params.delta


def _softmax_rows(z: np.ndarray) -> np.ndarray:
    """Per-input normalised memberships ``mu_ij / sum_j mu_ij`` computed in log space."""
    logmu = -z * z
    e = np.exp(logmu - logmu.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


def memberships(params: ANFISParams, u: ArrayLike) -> np.ndarray:
    """Layer 2, eq. (35): raw Gaussian memberships ``mu_ij(u_i)``, shape (2, 5).

    Raw values may underflow to 0 far outside the MFs; use :func:`firing` for the
    (safely) normalised rule strengths.
    """
    z = _scaled_distance(params, u)
    return np.exp(-z * z)


def firing(params: ANFISParams, u: ArrayLike) -> np.ndarray:
    """Layers 3-4, eqs. (36)-(37): normalised firing strengths ``fbar_rc``, shape (5, 5).

    Rows index the MF of input 0, columns the MF of input 1; the entries sum to 1.
    """
    pq = _softmax_rows(_scaled_distance(params, u))
    return np.outer(pq[0], pq[1])


def forward(params: ANFISParams, u: ArrayLike) -> float:
    """Network output ``o`` of eq. (38) for inputs ``u = (u0, u1)``."""
    pq = _softmax_rows(_scaled_distance(params, u))
    return float(pq[0] @ (params.w[RULE_TABLE] @ pq[1]))


def output_and_gradient(params: ANFISParams, u: ArrayLike) -> tuple[float, ANFISParams]:
    """Output ``o`` (eq. 38) and its analytic gradient ``do/dparams``.

    Chain rule through the five layers, with ``fbar_rc = p_r q_c`` (see module docstring)
    and ``W_rc = w[RULE_TABLE[r, c]]``:

    * layer 5 -> singletons: ``do/dw_k = sum_{rc: RULE_TABLE[r,c]=k} fbar_rc``;
    * layers 5-4-3 -> memberships: ``do/dfbar_rc = W_rc`` and, through the normalisation
      (37) and product (36), ``mu_0r * do/dmu_0r = p_r ((W q)_r - o)`` and
      ``mu_1c * do/dmu_1c = q_c ((W^T p)_c - o)``;
    * layer 2 (eq. 35): ``dmu_ij/dm_ij = mu_ij * 2 (u_i - m_ij) / delta_ij^2`` and
      ``dmu_ij/ddelta_ij = mu_ij * 2 (u_i - m_ij)^2 / delta_ij^3``.

    The ``mu`` factors cancel, so the gradient is evaluated without ever dividing by a
    (possibly underflowed) membership.

    Returns:
        ``(o, grad)`` where ``grad`` is an :class:`ANFISParams` holding ``do/dm`` (2, 5),
        ``do/ddelta`` (2, 5) and ``do/dw`` (7,).
    """
    z = _scaled_distance(params, u)
    pq = _softmax_rows(z)
    p = pq[0]
    q = pq[1]
    wmat = params.w[RULE_TABLE]
    wq = wmat @ q
    wtp = p @ wmat
    o = float(p @ wq)
    # d o / d log(mu_ij), shape (2, 5)
    dlog = np.empty((N_INPUTS, N_MF))
    dlog[0] = p * (wq - o)
    dlog[1] = q * (wtp - o)
    dm = dlog * (2.0 * z / params.delta)  # d log mu / dm = 2 z / delta
    ddelta = dm * z  # d log mu / ddelta = 2 z^2 / delta
    dw = _RULE_INDICATOR @ np.outer(p, q).ravel()
    return o, ANFISParams(m=dm, delta=ddelta, w=dw)


def sgd_step(
    params: ANFISParams,
    grad: ANFISParams,
    eta: float | tuple[float, float, float],
    min_width: float = 1e-3,
) -> ANFISParams:
    """One steepest-descent update, eqs. (41)-(42): ``W <- W - eta * dE/dW``.

    Args:
        params: current parameters (not modified).
        grad: gradient of the *loss* ``E`` w.r.t. the parameters, e.g.
            ``(o - target) * do/dparams`` for ``E = 0.5 (o - target)^2``.
        eta: one learning rate for every parameter, or ``(eta_m, eta_delta, eta_w)``.
        min_width: widths are clipped to ``>= min_width`` so they stay positive.

    Returns:
        New :class:`ANFISParams` (read-only arrays).
    """
    if np.ndim(eta) == 0:
        eta_m = eta_d = eta_w = float(eta)  # type: ignore[arg-type]
    else:
        etas = tuple(float(e) for e in eta)  # type: ignore[union-attr]
        if len(etas) != 3:
            raise ValueError("eta must be a scalar or a triple (eta_m, eta_delta, eta_w)")
        eta_m, eta_d, eta_w = etas
    m = params.m - eta_m * np.asarray(grad.m)
    delta = np.maximum(params.delta - eta_d * np.asarray(grad.delta), min_width)
    w = params.w - eta_w * np.asarray(grad.w)
    for a in (m, delta, w):
        a.setflags(write=False)
    return ANFISParams(m=m, delta=delta, w=w)
