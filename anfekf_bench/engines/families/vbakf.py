"""Huang et al.'s VBAKF on the fast engine's loop (`engines/loop.py`): the hooks of
filterpy_engine.run_filter with filters.vb.VBAKF (Algorithm 1). Per scan with a landmark the
forgetting of (u, U) (`vbakf_predict`); per landmark that feeds adaptation `iterations` updates
from the same x- (filters.vb.vbakf_update), P- re-estimated at the first landmark of the scan
only (`vbakf_prior`, `inflation_cap`) and put back if the gate rejects that landmark;
`inflation` is the filter's P_inflation.
"""

from __future__ import annotations

import collections

from ...filters.vb import VBAKFSpec, clip_covariance_2, inflation_cap, vbakf_predict, vbakf_prior
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
feeds_adaptation, correct, innovation, hph, wrap = (
    _k.feeds_adaptation, _k.correct, _k.innovation, _k.hph, _k.wrap,
)  # fmt: skip

M2 = 2.0  # the measurement's dimension m

Params = collections.namedtuple(
    "Params", "adaptation from_all floor ceiling rho iterations tau tau_R diagonal_R"
)


def params(spec: VBAKFSpec, ctx) -> Params:
    return Params(
        bool(spec.adaptation), spec.adapt_from == "all", float(spec.bounds[0]),
        float(spec.bounds[1]), float(spec.rho), int(spec.iterations), float(spec.tau),
        float(spec.tau_R), spec.R_structure == "diagonal",
    )  # fmt: skip


def start(fam, x, P, Qu, R, scan_start):
    # (u, U) of R's inverse-Wishart; P_inflation; whether this landmark re-estimated P- and the
    # P- it had; whether it is the scan's first; R0's diagonal
    tR = fam.tau_R
    U = (tR * R[0], tR * R[1], tR * R[2], tR * R[3])
    return M2 + 1.0 + tR, U, 1.0, False, P, True, (R[0], R[3])


def begin_scan(fam, st, x, P, R, Qu):
    u, U, infl, adapted_P, P_predicted, _, R0 = st
    if fam.adaptation:
        u_, U00 = vbakf_predict(u, U[0], fam.rho, M2)
        _, U01 = vbakf_predict(u, U[1], fam.rho, M2)
        _, U10 = vbakf_predict(u, U[2], fam.rho, M2)
        _, U11 = vbakf_predict(u, U[3], fam.rho, M2)
        u = u_
        U = (U00, U01, U10, U11)
    return (u, U, infl, adapted_P, P_predicted, True, R0), R


def before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    u, U, infl, _, _, first, R0 = st
    adapted_P = False
    P_predicted = P
    if fam.adaptation:
        infl = 1.0
        d = u - M2 - 1.0
        R = (U[0] / d, U[1] / d, U[2] / d, U[3] / d)
        ok, feeds = feeds_adaptation(HPHt, R, nu, fam.from_all, gate, has_gate)
        if not ok:
            return False, st, P, R, Qu, HPHt
        if feeds:  # filters.vb.vbakf_update
            tau = fam.tau
            u_post = u + 1.0
            d = u_post - M2 - 1.0
            xi = x
            Pi = P
            P_hat = P
            tr_P = P[0] + P[4] + P[8]
            U_post = U
            clipped = False
            for _ in range(fam.iterations):
                if first:
                    dx = (xi[0] - x[0], xi[1] - x[1], wrap(xi[2] - x[2]))
                    P_hat = (
                        vbakf_prior(Pi[0], dx[0] * dx[0], P[0], tau),
                        vbakf_prior(Pi[1], dx[0] * dx[1], P[1], tau),
                        vbakf_prior(Pi[2], dx[0] * dx[2], P[2], tau),
                        vbakf_prior(Pi[3], dx[1] * dx[0], P[3], tau),
                        vbakf_prior(Pi[4], dx[1] * dx[1], P[4], tau),
                        vbakf_prior(Pi[5], dx[1] * dx[2], P[5], tau),
                        vbakf_prior(Pi[6], dx[2] * dx[0], P[6], tau),
                        vbakf_prior(Pi[7], dx[2] * dx[1], P[7], tau),
                        vbakf_prior(Pi[8], dx[2] * dx[2], P[8], tau),
                    )  # fmt: skip
                    cap = inflation_cap(P_hat[0] + P_hat[4] + P_hat[8], tr_P, fam.ceiling)
                    if cap != 1.0:
                        P_hat = (
                            P_hat[0] * cap, P_hat[1] * cap, P_hat[2] * cap,
                            P_hat[3] * cap, P_hat[4] * cap, P_hat[5] * cap,
                            P_hat[6] * cap, P_hat[7] * cap, P_hat[8] * cap,
                        )  # fmt: skip
                _, _, e, _ = innovation(xi, Pi, lm[0], lm[1], z[0], z[1])
                HPiHt = hph(H, Pi)
                b00 = e[0] * e[0] + HPiHt[0]
                b11 = e[1] * e[1] + HPiHt[3]
                if fam.diagonal_R:
                    U_post = (U[0] + b00, U[1], U[2], U[3] + b11)
                else:
                    b01 = e[0] * e[1] + HPiHt[1]
                    b10 = e[1] * e[0] + HPiHt[2]
                    U_post = (
                        U[0] + 0.5 * (b00 + b00), U[1] + 0.5 * (b01 + b10),
                        U[2] + 0.5 * (b10 + b01), U[3] + 0.5 * (b11 + b11),
                    )  # fmt: skip
                R_raw = (U_post[0] / d, U_post[1] / d, U_post[2] / d, U_post[3] / d)
                clipped, R = clip_covariance_2(R_raw, R0[0], R0[1], fam.floor, fam.ceiling)
                ok, xi, Pi = correct(x, P_hat, H, zh, z[0], z[1], R)
                if not ok:
                    return False, st, P, R, Qu, HPHt
            if clipped:  # keep the posterior consistent with the R in force
                U_post = (d * R[0], d * R[1], d * R[2], d * R[3])
            u = u_post
            U = U_post
            if first:
                adapted_P = True
                infl = (P_hat[0] + P_hat[4] + P_hat[8]) / (P[0] + P[4] + P[8])
                P = P_hat
    if infl != 1.0:  # RobotEKF.update_landmark: H P- H^T follows the new P-
        HPHt = hph(H, P)
    return True, (u, U, infl, adapted_P, P_predicted, False, R0), P, R, Qu, HPHt


def rejected(fam, st, x, P, R, H, zh, lm, z):
    u, U, infl, adapted_P, P_predicted, first, R0 = st
    if adapted_P:  # VBAKF.update_landmark: back to the prediction
        return True, (u, U, 1.0, False, P_predicted, first, R0), P_predicted, R
    return True, st, P, R


def inflation(fam, st):
    return st[2]
