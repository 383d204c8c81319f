"""The adaptive fading-factor EKF (filters/fading.py): a step by hand from Yang & Gao's
equations, once per scan, the window's warm-up, both motion models."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.filters import FilterContext, RobotEKF
from anfekf_bench.filters.fading import FadingEKF, FadingSpec, fading_factor
from anfekf_bench.models import Bicycle, Unicycle, h, residual_z
from anfekf_bench.models.range_bearing import H_jacobian

from .test_filter_bank import _drive, _unicycle_events

LM = np.array([[6.0, 2.0], [1.0, 7.0]])


def _ctx(model, gate=None):
    return FilterContext(
        x0=np.array([0.2, -0.1, 0.3]), P0=np.diag([0.04, 0.03, 0.01]), Qu=np.diag([0.02, 0.05]),
        R=np.diag([0.01, 0.001]), model=model, dt=0.1, gate=gate,
    )  # fmt: skip


def test_fading_factor():
    assert fading_factor(5.0, 1.0, 2.0, 100.0) == 2.0
    assert fading_factor(1.5, 1.0, 2.0, 100.0) == 1.0  # never deflates
    assert fading_factor(500.0, 0.0, 1.0, 100.0) == 100.0  # the ceiling
    assert math.isnan(fading_factor(math.nan, 1.0, 2.0, 100.0))


@pytest.mark.parametrize("model", [Bicycle(0.1, 2.0), Unicycle(0.1)], ids=["bicycle", "unicycle"])
def test_one_step_by_hand(model):
    """Window 1: C = nu nu^T of the scan's first landmark; lambda from eq. F.2; its gain uses
    lambda P-; the scan's second landmark is not inflated again."""
    ctx = _ctx(model)
    flt = FadingSpec(name="f", kind="fading", window=1).build(ctx)
    ref = RobotEKF(**ctx.kwargs())
    u = np.array([1.0, 0.2])
    zs = np.array([[6.5, 0.05], [7.2, 1.1]])  # far from what the state predicts
    flt.predict(u)
    ref.predict(u)
    # by hand, at x-: nu, H, H P- H^T
    H = H_jacobian(ref.x, LM[0])
    nu = residual_z(zs[0], h(ref.x, LM[0]))
    lam = max(1.0, (nu @ nu - np.trace(ctx.R)) / np.trace(H @ ref.P @ H.T))
    assert lam > 1.5
    ref.P = lam * ref.P
    ref.update_landmark(zs[0], LM[0])
    ref.update_landmark(zs[1], LM[1])
    flt.update_scan(zs, LM)
    assert flt.P_inflation == pytest.approx(lam, rel=1e-12)
    np.testing.assert_allclose(flt.x, ref.x, atol=1e-12)
    np.testing.assert_allclose(flt.P, ref.P, atol=1e-12)


def test_no_inflation_until_the_window_is_full():
    ctx = _ctx(Bicycle(0.1, 2.0))
    flt = FadingSpec(name="f", kind="fading", window=3).build(ctx)
    ref = RobotEKF(**ctx.kwargs())
    zs = np.array([[6.5, 0.05]])
    for _ in range(2):  # two innovations: the window of 3 is not full
        for f in (flt, ref):
            f.predict(np.array([1.0, 0.2]))
            f.update_scan(zs, LM[:1])
    assert flt.P_inflation == 1.0
    np.testing.assert_allclose(flt.P, ref.P, atol=1e-12)
    flt.predict(np.array([1.0, 0.2]))
    flt.update_scan(zs, LM[:1])
    assert flt.P_inflation > 1.0 and flt.n_window == 3


def test_spec_validation():
    with pytest.raises(ValueError):
        FadingSpec(name="f", kind="fading", window=0)


def test_unicycle_adaptation_off_is_the_ekf_and_on_stays_positive():
    events = _unicycle_events()
    ctx = _ctx(Unicycle(0.12), gate=13.8)
    x_ref, P_ref = _drive(RobotEKF(**ctx.kwargs()), events)
    x_off, P_off = _drive(FadingSpec(name="f", kind="fading", adaptation=False).build(ctx), events)
    np.testing.assert_allclose(x_off, x_ref, atol=1e-12)
    np.testing.assert_allclose(P_off, P_ref, atol=1e-12)
    flt = FadingSpec(name="f", kind="fading", window=5).build(ctx)
    assert isinstance(flt, FadingEKF)
    x, P = _drive(flt, events)
    assert np.isfinite(x).all() and all(np.linalg.eigvalsh(p).min() > 0 for p in P)
