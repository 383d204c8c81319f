"""Sliding-window VB on Qu and R (filters/swvb.py): the lag-one smoother's moment against a
brute-force Gaussian computation, one scan by hand from eqs. S.1-S.4, both motion models."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.filters import FilterContext, RobotEKF, qu_least_squares
from anfekf_bench.filters.swvb import SWVBEKF, SWVBSpec, process_noise_moment
from anfekf_bench.models import Bicycle, Unicycle, h, residual_z, wrap_scalar
from anfekf_bench.models.range_bearing import H_jacobian

from .test_filter_bank import _drive, _unicycle_events

LM = np.array([[6.0, 2.0], [1.0, 7.0]])
rng = np.random.default_rng(5)


def test_process_noise_moment_is_the_smoothed_second_moment():
    """Linear-Gaussian check: x_s ~ N(a, P_s), x_k = F x_s + w, w ~ N(0, Q), y = C x_k + v;
    the formula's E[(x_k - F x_s)(...)^T | y] against the joint Gaussian conditioned on y."""
    A = rng.normal(size=(3, 3))
    P_s = A @ A.T + np.eye(3)
    F = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    B = rng.normal(size=(3, 3))
    Q = 0.3 * (B @ B.T) + 0.1 * np.eye(3)
    C = rng.normal(size=(2, 3))
    Rv = np.diag([0.2, 0.05])
    y = rng.normal(size=2)
    # Kalman filter step from x_s+ = 0: x- = 0, P- = F P_s F^T + Q
    P_m = F @ P_s @ F.T + Q
    K = P_m @ C.T @ np.linalg.inv(C @ P_m @ C.T + Rv)
    x_p = K @ y
    P_p = (np.eye(3) - K @ C) @ P_m
    W = process_noise_moment(x_p, F @ P_s @ F.T, np.linalg.inv(P_m), P_p)
    # brute force: the joint of (x_s, x_k, y), conditioned on y
    T = np.vstack([np.hstack([np.eye(3), np.zeros((3, 3))]), np.hstack([F, np.eye(3)])])
    S_sw = np.block([[P_s, np.zeros((3, 3))], [np.zeros((3, 3)), Q]])
    S_z = T @ S_sw @ T.T  # cov of (x_s, x_k)
    Cz = np.hstack([np.zeros((2, 3)), C])
    G = S_z @ Cz.T @ np.linalg.inv(Cz @ S_z @ Cz.T + Rv)
    mean = G @ y
    cov = S_z - G @ Cz @ S_z
    D = np.hstack([-F, np.eye(3)])  # w = x_k - F x_s
    ref = D @ cov @ D.T + np.outer(D @ mean, D @ mean)
    np.testing.assert_allclose(W, ref, atol=1e-10)


def _ctx(model, gate=None):
    return FilterContext(
        x0=np.array([0.2, -0.1, 0.3]), P0=np.diag([0.04, 0.03, 0.01]), Qu=np.diag([0.02, 0.05]),
        R=np.diag([0.01, 0.001]), model=model, dt=0.1, gate=gate,
    )  # fmt: skip


@pytest.mark.parametrize("model", [Bicycle(0.1, 2.0), Unicycle(0.1)], ids=["bicycle", "unicycle"])
def test_one_scan_by_hand(model):
    """Two iterations of S.1-S.4 for one scan, written out with a plain EKF."""
    ctx = _ctx(model)
    spec = SWVBSpec(name="s", kind="swvb", iterations=2, rho=0.9, a0=2.0)
    flt = spec.build(ctx)
    assert isinstance(flt, SWVBEKF)
    us = [np.array([1.0, 0.2])] * 3
    zs = np.array([[6.5, 0.05], [7.2, 1.1]])
    ekf = RobotEKF(**ctx.kwargs())
    A_v, A_g, F_s = np.zeros((3, 3)), np.zeros((3, 3)), np.eye(3)
    for u in us:
        flt.predict(u)
        ekf.predict(u)
        F, G = ekf.F, ekf.G
        A_v = F @ A_v @ F.T + model.Q(G, np.diag([1.0, 0.0]), ekf.dt)
        A_g = F @ A_g @ F.T + model.Q(G, np.diag([0.0, 1.0]), ekf.dt)
        F_s = F @ F_s
    x_m, P_m1 = ekf.x.copy(), ekf.P.copy()
    P_s = ctx.P0
    a_q, b_q = 0.9 * 2.0 * np.ones(2), 0.9 * 2.0 * np.diag(ctx.Qu)
    a_r, b_r = 0.9 * 2.0 * np.ones(2), 0.9 * 2.0 * np.diag(ctx.R)
    qu, r = np.diag(ctx.Qu), np.diag(ctx.R)
    for n in range(2):
        P_m = P_m1 if n == 0 else F_s @ P_s @ F_s.T + qu[0] * A_v + qu[1] * A_g
        e = RobotEKF(x_m, P_m, np.diag(qu), np.diag(r), model, ctx.dt, None)
        for z, lm in zip(zs, LM, strict=True):
            e.update_landmark(z, lm)
        dx = e.x - x_m
        dx[2] = wrap_scalar(dx[2])
        J = P_s @ F_s.T @ np.linalg.inv(P_m)
        m = dx - F_s @ J @ dx
        P_ss = P_s + J @ (e.P - P_m) @ J.T
        W = np.outer(m, m) + e.P - e.P @ J.T @ F_s.T - F_s @ J @ e.P + F_s @ P_ss @ F_s.T
        q = qu_least_squares(W, A_v, A_g, np.linalg.inv(P_m))
        q = np.clip(q, 1e-4 * np.diag(ctx.Qu), 1e4 * np.diag(ctx.Qu))
        qu = (b_q + q / 2) / (a_q + 0.5)
        s = np.zeros(2)
        for z, lm in zip(zs, LM, strict=True):
            res = residual_z(z, h(e.x, lm))
            H = H_jacobian(e.x, lm)
            s += res**2 + np.diag(H @ e.P @ H.T)
        r = (b_r + s / 2) / (a_r + 1.0)
    flt.update_scan(zs, LM)
    np.testing.assert_allclose(flt.x, e.x, atol=1e-12)
    np.testing.assert_allclose(flt.P, e.P, atol=1e-12)
    np.testing.assert_allclose(np.diag(flt.Qu), qu, rtol=1e-10)
    np.testing.assert_allclose(np.diag(flt.R), r, rtol=1e-10)
    assert (flt.n_updates, flt.n_rejected) == (2, 0)  # the last iteration's counts only


def test_unicycle_adaptation_off_is_the_ekf_and_on_stays_positive():
    events = _unicycle_events()
    ctx = _ctx(Unicycle(0.12), gate=13.8)
    x_ref, P_ref = _drive(RobotEKF(**ctx.kwargs()), events)
    off = SWVBSpec(name="s", kind="swvb", adaptation=False).build(ctx)
    x_off, P_off = _drive(off, events)
    np.testing.assert_allclose(x_off, x_ref, atol=1e-12)
    np.testing.assert_allclose(P_off, P_ref, atol=1e-12)
    flt = SWVBSpec(name="s", kind="swvb").build(ctx)
    x, P = _drive(flt, events)
    assert np.isfinite(x).all() and all(np.linalg.eigvalsh(p).min() > 0 for p in P)
    assert (np.diag(flt.Qu) > 0).all() and (np.diag(flt.R) > 0).all()
    assert math.isfinite(flt.nis_sum)
