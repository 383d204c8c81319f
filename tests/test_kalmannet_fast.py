"""KalmanNet on the fast engine (engines/kernels_kalmannet.py) against the filterpy engine's
numpy filter (filters/kalmannet.py), without PyTorch: networks of seeded random weights
(`KalmanNetWeights.random`). The parametrised equivalence over every kind and both motion
models (tests/test_engines_equivalence.py) covers the default case; here what it does not:
the divergence, a landmark seen twice in one scan (F1's lookup), the weights reaching the
kernel through `with_fit` (what the simulated and the recorded trainings hand out), the network
maths against a hand-written reference, and the engine the runner picks."""

from __future__ import annotations

import base64
import hashlib
import math

import numpy as np
import pytest

from anfekf_bench.engines import fast
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import FilterContext
from anfekf_bench.filters import kalmannet_net as kn
from anfekf_bench.filters.ekf import gate_threshold
from anfekf_bench.filters.kalmannet import KalmanNetSpec, KalmanNetWeights
from anfekf_bench.models import Unicycle
from anfekf_bench.runner import engine_of, run_spec
from anfekf_bench.timeline import Timeline

from .test_engines_equivalence import synthetic_timeline
from .test_fast_engine import assert_same_run


def spec_with(weights: KalmanNetWeights) -> KalmanNetSpec:
    return KalmanNetSpec.model_construct(name="kn", kind="kalmannet").with_weights(weights)


@pytest.fixture(scope="module")
def drive():
    tl, x0 = synthetic_timeline(seed=9, n=400)
    ctx = FilterContext(
        x0=x0, P0=np.diag([0.01, 0.01, 0.001]), Qu=np.diag([0.05**2, 0.08**2]),
        R=np.diag([0.1**2, math.radians(3.0) ** 2]), model=Unicycle(0.12), dt=0.12,
        gate=gate_threshold(0.999),
    )  # fmt: skip
    return ctx, tl


def test_the_network_is_torchs_gru_cell_written_out():
    """`gain_network` (both engines' maths) against the layers written out by hand from
    torch.nn.GRUCell's documented equations."""
    w = KalmanNetWeights.random(hidden_size=5, seed=3)
    rng = np.random.default_rng(0)
    work = kn.work_arrays(w.net)
    work[0][:] = rng.standard_normal(kn.N_FEATURES)
    h0 = rng.standard_normal(5)
    hidden = h0.copy()
    k = kn.gain_network(w.net, hidden, work).copy()
    A = w.arrays
    a = np.maximum(A["fc_in.weight"] @ work[0] + A["fc_in.bias"], 0.0)
    Wir, Wiz, Win = np.split(A["gru.weight_ih"], 3)
    Whr, Whz, Whn = np.split(A["gru.weight_hh"], 3)
    bir, biz, bin_ = np.split(A["gru.bias_ih"], 3)
    bhr, bhz, bhn = np.split(A["gru.bias_hh"], 3)
    r = 1 / (1 + np.exp(-(Wir @ a + bir + Whr @ h0 + bhr)))
    z = 1 / (1 + np.exp(-(Wiz @ a + biz + Whz @ h0 + bhz)))
    n = np.tanh(Win @ a + bin_ + r * (Whn @ h0 + bhn))
    h1 = (1 - z) * n + z * h0
    want = A["fc_out2.weight"] @ np.maximum(A["fc_out1.weight"] @ h1 + A["fc_out1.bias"], 0)
    np.testing.assert_allclose(hidden, h1, rtol=0, atol=1e-14)
    np.testing.assert_allclose(k, want + A["fc_out2.bias"], rtol=0, atol=1e-14)


@pytest.mark.parametrize("jit", [True, False])
def test_the_kernel_equals_the_numpy_filter_and_the_network_matters(drive, jit):
    """Fast (compiled, and its plain-Python copy) = filterpy; a network of another seed gives
    other estimates (the weights reach the kernel), and the estimates track the drive."""
    ctx, tl = drive
    spec = spec_with(KalmanNetWeights.random(hidden_size=16, seed=1))
    ref = run_filter(spec.build(ctx), tl)
    out = fast.run_filter_fast(spec, ctx, tl, jit=jit)
    assert not ref["diverged"] and ref["n_updates"] == len(tl.z) and ref["n_rejected"] == 0
    assert np.isnan(out["P"]).all() and math.isnan(out["nis_sum"])
    assert_same_run(ref, out, what=f"kalmannet jit={jit}")
    other = fast.run_filter_fast(spec_with(KalmanNetWeights.random(16, seed=2)), ctx, tl)
    assert np.abs(other["x"] - out["x"]).max() > 1e-3


def test_a_landmark_twice_in_one_scan_keeps_its_last_measurement_for_f1(drive):
    """F1 looks the landmark up in the last scan by its map position; one seen twice there
    gives its last measurement (as the numpy filter's dict does), on both engines."""
    ctx, tl = drive
    first_scan = next(k for k in range(len(tl.dt)) if tl.lm[k + 1] > tl.lm[k])
    rows = []
    for k in range(len(tl.dt)):  # every scan's first landmark twice, the second time shifted
        a, b = tl.lm[k], tl.lm[k + 1]
        rows.extend(range(a, b))
        if b > a:
            rows.append(a)
    rows = np.array(rows)
    counts = np.diff(tl.lm) + (np.diff(tl.lm) > 0)
    lm = np.concatenate([[0], np.cumsum(counts)])
    z = tl.z[rows].copy()
    z[lm[1:][counts > 0] - 1, 0] += 0.05  # the duplicate measures 5 cm more
    twice = Timeline(
        t_start=tl.t_start, t=tl.t, dt=tl.dt, u=tl.u, lm=lm, z=z, xy=tl.xy[rows], record=tl.record
    )
    assert counts[first_scan] >= 2
    spec = spec_with(KalmanNetWeights.random(hidden_size=8, seed=4))
    ref = run_filter(spec.build(ctx), twice)
    assert_same_run(ref, fast.run_filter_fast(spec, ctx, twice), what="landmark twice")
    assert ref["n_updates"] == len(z)


def test_a_non_finite_posterior_diverges_at_the_same_stamp_on_both_engines(drive):
    ctx, tl = drive
    w = KalmanNetWeights.random(hidden_size=8, seed=5)
    arrays = {k: v.copy() for k, v in w.arrays.items()}
    arrays["fc_out2.bias"][0] = np.nan  # x + K nu is NaN from the first landmark measured
    broken = KalmanNetWeights(arrays, w.obs_scale, w.state_scale, w.range_scale, 8)
    spec = spec_with(broken)
    ref = run_filter(spec.build(ctx), tl)
    out = fast.run_filter_fast(spec, ctx, tl)
    assert ref["diverged"] and 0 < np.isnan(ref["x"][:, 0]).sum() < len(ref["x"])
    assert_same_run(ref, out, what="diverged")


def test_the_fitted_weights_reach_the_kernel_through_with_fit(drive):
    """The simulated (fitting/simulated.py) and recorded (fitting/recorded.py) trainings hand the
    workers `spec.with_fit(fitted)`: the kernel runs those weights, bytes for bytes."""
    ctx, tl = drive
    weights = KalmanNetWeights.random(hidden_size=8, seed=6)
    raw = weights.to_bytes()
    fitted = {"weights_sha256": hashlib.sha256(raw).hexdigest(),
              "weights_base64": base64.b64encode(raw).decode("ascii")}  # fmt: skip
    spec = KalmanNetSpec.model_construct(name="kn", kind="kalmannet").with_fit(fitted)
    assert spec.trained_weights.to_bytes() == raw
    out = fast.run_filter_fast(spec, ctx, tl)
    assert_same_run(fast.run_filter_fast(spec_with(weights), ctx, tl), out, tol=0.0)
    assert_same_run(run_filter(spec.build(ctx), tl), out, what="with_fit")


def test_the_runner_runs_it_fast_and_an_untrained_one_is_an_error(drive):
    ctx, tl = drive
    spec = spec_with(KalmanNetWeights.random(hidden_size=8, seed=6))
    untrained = KalmanNetSpec.model_construct(name="kn", kind="kalmannet")
    assert engine_of("fast", untrained, model=ctx.model) == "fast"  # the manifest's engines
    assert_same_run(run_spec("filterpy", spec, ctx, tl), run_spec("fast", spec, ctx, tl))
    with pytest.raises(RuntimeError, match="'kn' has no trained weights"):
        fast.run_filter_fast(untrained, ctx, tl)
