"""`als` on the fast engine (engines/kernels_als.py) against the filterpy engine: the same update,
rejection and divergence counts, the same NaN records, x, P, R_diag, Q_diag and the NIS sum to
1e-9 (`test_fast_engine.assert_same_run`), on the small world whose filters assume the wrong Qu
and R, in every mode; and its non-negative least squares (filters.als.nnls, the one solver of
both engines) against scipy.optimize.nnls."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import nnls as scipy_nnls

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines import fast, kernels_als
from anfekf_bench.filters.als import ALSSpec, nnls
from anfekf_bench.runner import simulate

from .conftest import corrupted_half_way, small_scenario, small_world_noise_off
from .test_fast_engine import assert_same_run, both, ctx_of

VARIANTS = {
    "default": {},
    "adapt-Q": {"adapt": "Q"},
    "adapt-R": {"adapt": "R"},
    "accepted": {"adapt_from": "accepted"},
    "lags-0-every-scan": {"lags": 0, "window": 50, "every": 1, "warmup": 5},
    "lags-5-short-window": {"lags": 5, "window": 40, "every": 3, "warmup": 10},
    "tight-bounds": {"bounds": (0.5, 2.0), "window": 20, "every": 1, "warmup": 3},
    "off": {"adaptation": False},
}


@pytest.fixture(scope="module")
def noise_off():
    """The small world with Qu about 10x too large and R off (sigma_range 0.5 m)."""
    return small_world_noise_off(17, 2)


@pytest.fixture(scope="module")
def q_small():
    """The small world with Qu 100x too small: the identified Qu must rise."""
    doc = small_scenario(record_every=1, filter_noise={"sigma_v": 0.03, "sigma_gamma_deg": 0.5})
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, Path("small.yaml"))
    runs = [simulate(scenario, world, s) for s in np.random.SeedSequence(5).spawn(2)]
    return scenario, world, runs


def test_the_engine_supports_als():
    for params in VARIANTS.values():
        assert fast.supports(ALSSpec(name="a", kind="als", **params))


@pytest.mark.parametrize("world", ["noise_off", "q_small"])
@pytest.mark.parametrize("name", VARIANTS)
def test_small_world_every_variant(request, world, name):
    scenario, w, runs = request.getfixturevalue(world)
    spec = ALSSpec(name="a", kind="als", **VARIANTS[name])
    ctx = ctx_of(spec, scenario, w)
    adapted = False
    for data in runs:
        ref, out = both(spec, ctx, data, w, 1)
        assert ref["n_updates"] > 100
        assert_same_run(ref, out, what=f"{world} {name}")
        adapted = adapted or not np.allclose(ref["R_diag"][-1], np.diag(ctx.R))
    assert adapted == (name not in ("off", "adapt-Q"))


def test_gate_off_record_every_and_plain_python(noise_off):
    scenario, world, runs = noise_off
    spec = ALSSpec(name="a", kind="als", window=60, every=2, warmup=10)
    ctx = ctx_of(spec, scenario, world)
    for record_every in (1, 8):
        ref, out = both(spec, ctx, runs[0], world, record_every)
        assert_same_run(ref, out, what=f"record_every {record_every}")
    ref, out = both(spec, dataclasses.replace(ctx, gate=None), runs[1], world, 8)
    assert ref["n_rejected"] == 0
    assert_same_run(ref, out, what="no gate")
    ref, out = both(spec, ctx, runs[1], world, 8, jit=False)
    assert_same_run(ref, out, what="plain Python")


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("what", ["odometry", "measurement"])
def test_divergence_in_mid_run(noise_off, what):
    """A corrupted sample half-way (after identifications began): diverged at the same landmark
    of the same scan, the same counts, the records NaN from there on."""
    scenario, world, runs = noise_off
    data = runs[0]
    spec = ALSSpec(name="a", kind="als", every=1, warmup=5)
    ctx = ctx_of(spec, scenario, world)
    data, bad = corrupted_half_way(data, what)
    ref, out = both(spec, ctx, data, world, 1)
    assert ref["diverged"] and ref["n_updates"] > 10
    assert np.isnan(ref["x"][bad.step - 1 :]).all() and np.isfinite(ref["x"][: bad.step - 5]).all()
    assert not np.allclose(ref["R_diag"][bad.step - 6], np.diag(ctx.R))  # it had adapted
    assert_same_run(ref, out, what=what)


# ---------------------------------------------------------------------------------------------
# The solver


def _problems():
    """(name, A, b): random least-squares problems, well posed and degenerate."""
    rng = np.random.default_rng(7)
    for i in range(40):
        m, n = int(rng.integers(5, 60)), int(rng.integers(1, 7))
        yield f"random-{i}", rng.normal(size=(m, n)), rng.normal(size=m)
    for i in range(20):  # an exact non-negative solution with zeros on the boundary
        A = rng.normal(size=(30, 4))
        x = np.maximum(rng.normal(size=4), 0.0)
        yield f"exact-{i}", A, A @ x
    A = rng.normal(size=(20, 4))
    yield "negative-cone", A, -A @ np.ones(4)  # the optimum is x = 0 or close to it
    yield "zero-b", A, np.zeros(20)
    yield "zero-column", np.column_stack([A[:, :3], np.zeros(20)]), rng.normal(size=20)
    yield "duplicate-column", np.column_stack([A[:, :3], A[:, 2]]), rng.normal(size=20)
    yield "fewer-rows", rng.normal(size=(3, 4)), rng.normal(size=3)
    yield "one-row", rng.normal(size=(1, 4)), np.array([1.0])
    scales = np.array([1e-4, 1.0, 1e2, 1e-2])  # the ALS columns' spread of scales
    for i in range(10):
        A = rng.normal(size=(300, 4)) * scales
        yield f"scaled-{i}", A, A @ (np.abs(rng.normal(size=4)) / scales) + rng.normal(size=300)


@pytest.mark.parametrize("solver", ["numpy", "kernel"])
def test_nnls_equals_scipy(solver):
    solve = nnls if solver == "numpy" else kernels_als.nnls
    for name, A, b in _problems():
        x_ref, r_ref = scipy_nnls(A, b)
        x = solve(np.ascontiguousarray(A), np.ascontiguousarray(b))
        assert x.shape == x_ref.shape and np.all(x >= 0), name
        r = np.linalg.norm(A @ x - b)
        # the same optimum: no worse a residual, and the same solution where it is unique
        assert r <= r_ref * (1 + 1e-12) + 1e-14, (name, r, r_ref)
        if np.linalg.matrix_rank(A) == A.shape[1]:
            scale = max(np.abs(x_ref).max(), 1e-300)
            assert np.abs(x - x_ref).max() <= 1e-9 * scale, (name, x, x_ref)


def test_nnls_kkt_and_non_finite_input():
    rng = np.random.default_rng(3)
    A, b = rng.normal(size=(50, 4)), rng.normal(size=50)
    x = nnls(A, b)
    w = A.T @ (b - A @ x)  # Karush-Kuhn-Tucker: w <= 0 where x = 0, w = 0 where x > 0
    assert np.all(w[x == 0] <= 1e-12) and np.allclose(w[x > 0], 0.0, atol=1e-12)
    A[3, 2] = np.nan
    assert np.all(np.isnan(nnls(A, b)))
    assert np.all(np.isnan(kernels_als.nnls(A, b)))


@pytest.mark.skipif(not kernels_als.JIT, reason="numba is not installed: nothing is compiled")
def test_compiled_products_equal_numpy():
    """The fused batched products (filters.als) as the fast engine compiles them, plain loops,
    equal numpy's on every shape their loops special-case (2, 3) and on the general one (4)."""
    from numba import njit

    from anfekf_bench.filters import als

    @njit
    def compiled(L, X, Rm, Y, Xr, Rr, Yb, Ly, K, H, R, c, x):
        Z = X.copy()
        als.left_in_place(Yb[0], Z)
        return (
            als.batch_left(L, X), Z, als.sandwich_plus(L, X, Rm, Y),
            als.right_plus_sandwich(Xr, Rr, L, Yb), als.right_minus_left(Xr, Rr, L, Ly),
            als.closed_loop(K, H), als.dual(R, c, x),
        )  # fmt: skip

    rng = np.random.default_rng(3)
    for b in (2, 3, 4):
        for c in (2, 3, 4):
            a, d, q = 3, 2, 5
            L, X = rng.standard_normal((a, b)), rng.standard_normal((q, b, c))
            Rm, Y = rng.standard_normal((d, c)), rng.standard_normal((q, a, d))
            Xr, Rr = rng.standard_normal((q, a, c)), rng.standard_normal((a, c))
            Yb, Ly = rng.standard_normal((q, b, b)), rng.standard_normal((q, b, a))
            K, H = rng.standard_normal((b, c)), rng.standard_normal((c, b))
            R, v, x = rng.standard_normal((b, c)), rng.standard_normal(b), rng.standard_normal(c)
            expected = (
                L @ X, Yb[0] @ X, als.sandwich_plus(L, X, Rm, Y),
                als.right_plus_sandwich(Xr, Rr, L, Yb), als.right_minus_left(Xr, Rr, L, Ly),
                als.closed_loop(K, H), als.dual(R, v, x),
            )  # fmt: skip
            got = compiled(L, X, Rm, Y, Xr, Rr, Yb, Ly, K, H, R, v, x)
            for g, e in zip(got, expected, strict=True):
                np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-12)
