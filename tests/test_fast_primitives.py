"""The numeric primitives the adaptive rules call (filters.adaptive: matmul, outer,
trace_of_product, inv, lstsq) as the fast engine compiles them (engines/kernels.py: plain loops
and a closed form) against numpy's, which the filterpy engine runs (issue 22)."""

from __future__ import annotations

import numpy as np
import pytest

from anfekf_bench.engines import kernels
from anfekf_bench.filters import adaptive

pytestmark = pytest.mark.skipif(not kernels.JIT, reason="numba is not installed")

rng = np.random.default_rng(7)


@pytest.fixture(scope="module")
def compiled():
    """numba-compiled callers of the primitives (the overloads exist only in compiled code)."""
    import numba

    def wrap(fn):
        return numba.njit(lambda *args: fn(*args))

    return {
        name: wrap(getattr(adaptive, name))
        for name in ("matmul", "outer", "trace_of_product", "inv", "lstsq")
    }


def test_products_are_numpys(compiled):
    for _ in range(20):
        A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        v = rng.normal(size=3)
        np.testing.assert_allclose(compiled["matmul"](A, B), A @ B, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(compiled["matmul"](A, B.T), A @ B.T, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(compiled["matmul"](A, v), A @ v, rtol=1e-14, atol=1e-15)
        np.testing.assert_array_equal(compiled["outer"](v, v), np.outer(v, v))
        assert compiled["trace_of_product"](A, B) == pytest.approx(np.trace(A @ B), rel=1e-13)
        # the compiled trace sums as the compiled product does: the same bits
        assert compiled["trace_of_product"](A, B) == np.trace(compiled["matmul"](A, B))


def test_products_sum_in_k_order(compiled):
    """The unrolled 3 x 3 product and the general loop (3 x 2, 2 x 3) both sum each entry from
    0.0 with k ascending: the same bits as that sum written out in Python floats."""

    def k_order(A, B):
        out = np.empty((A.shape[0], B.shape[1]))
        for i in range(A.shape[0]):
            for j in range(B.shape[1]):
                t = 0.0
                for k in range(A.shape[1]):
                    t += float(A[i, k]) * float(B[k, j])
                out[i, j] = t
        return out

    for shape_a, shape_b in (((3, 3), (3, 3)), ((3, 3), (3, 2)), ((2, 3), (3, 3))):
        A, B = rng.normal(size=shape_a), rng.normal(size=shape_b)
        np.testing.assert_array_equal(compiled["matmul"](A, B), k_order(A, B))
        np.testing.assert_array_equal(compiled["matmul"](A, B.T.T), k_order(A, B))
    A = rng.normal(size=(3, 3))
    np.testing.assert_array_equal(compiled["matmul"](A, A.T), k_order(A, A.T))


def test_inv_is_numpys_with_pivoting(compiled):
    for _ in range(20):
        A = rng.normal(size=(3, 3))
        np.testing.assert_allclose(compiled["inv"](A), np.linalg.inv(A), rtol=1e-10, atol=1e-12)
    # a zero leading entry needs a row swap; an ill-scaled SPD matrix (metres and radians)
    swap = np.array([[0.0, 2.0, 1.0], [1.0, 0.0, 3.0], [4.0, 1.0, 0.0]])
    np.testing.assert_allclose(compiled["inv"](swap), np.linalg.inv(swap), rtol=1e-13)
    L = np.array([[1.0, 0.0, 0.0], [0.3, 2e-2, 0.0], [1e-3, 2e-4, 1e-4]])
    P = L @ L.T
    np.testing.assert_allclose(compiled["inv"](P), np.linalg.inv(P), rtol=1e-9)


@pytest.mark.parametrize(
    "A",
    [
        pytest.param(np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]), id="singular"),
        pytest.param(np.array([[np.nan, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), id="not-finite"),
    ],
)
def test_inv_raises_as_numba_does(compiled, A):
    with pytest.raises(np.linalg.LinAlgError):
        compiled["inv"](A)


def _numpy_lstsq(M, b):
    return np.linalg.lstsq(M, b, rcond=adaptive.LSTSQ_RCOND)[0]


def test_lstsq_full_rank_is_numpys(compiled):
    for _ in range(50):
        X = rng.normal(size=(2, 2))
        M = X @ X.T + 1e-3 * np.eye(2)  # a Gram matrix, as qu_least_squares builds
        b = rng.normal(size=2)
        np.testing.assert_allclose(compiled["lstsq"](M, b), _numpy_lstsq(M, b), rtol=1e-10)
    M = np.array([[3.0, 1.0], [0.5, -2.0]])  # not symmetric: LU with pivoting
    b = np.array([1.0, 2.0])
    np.testing.assert_allclose(compiled["lstsq"](M, b), _numpy_lstsq(M, b), rtol=1e-13)


@pytest.mark.parametrize(
    "M",
    [
        pytest.param(np.array([[2.0, 0.0], [0.0, 0.0]]), id="one-control-only"),
        pytest.param(np.outer([1.0, 3.0], [1.0, 3.0]), id="rank-one"),
        pytest.param(np.outer([1.0, 3.0], [1.0, 3.0]) + 1e-17 * np.eye(2), id="below-rcond"),
        pytest.param(np.zeros((2, 2)), id="zero"),
    ],
)
def test_lstsq_singular_is_the_least_norm_solution(compiled, M):
    b = np.array([0.7, -0.2])
    np.testing.assert_allclose(compiled["lstsq"](M, b), _numpy_lstsq(M, b), rtol=1e-12, atol=1e-15)


def test_lstsq_not_finite_raises_as_numpy(compiled):
    with pytest.raises(np.linalg.LinAlgError):
        compiled["lstsq"](np.array([[np.inf, 0.0], [0.0, 1.0]]), np.ones(2))


def test_wrap_skips_the_modulo_with_the_same_bits():
    """kernels.wrap and filters.bank._wrap (compiled and plain) skip the modulo where it is the
    identity: bit for bit models.angles.wrap_scalar, at the edges and far from them."""
    import math

    from anfekf_bench.filters import bank
    from anfekf_bench.models.angles import wrap_scalar

    edges = [0.0, -0.0, math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 1e-300, -1e-20,
             math.nextafter(math.pi, 0), math.nextafter(math.pi, 4), math.nextafter(-math.pi, 0),
             math.nextafter(-math.pi, -4), 3 * math.pi, -5 * math.pi, 1e17, -1e17, math.inf,
             -math.inf, math.nan]  # fmt: skip
    values = edges + list(rng.uniform(-20, 20, 2000)) + list(rng.uniform(-3.2, 3.2, 2000))
    pure = kernels.pure_module()
    with np.errstate(invalid="ignore"):
        for a in values:
            want = wrap_scalar(a)
            for fn in (kernels.wrap, pure.wrap, bank._wrap):
                got = fn(a)
                assert (got == want and math.copysign(1, got) == math.copysign(1, want)) or (
                    math.isnan(got) and math.isnan(want)
                ), (fn, a, got, want)


def test_jacobians_from_the_shared_step_terms_are_the_models():
    """jacobians (via step_terms / jacobians_at, a bank's per-step sharing) equals the
    models' own Jacobians bit for bit, on both motion models."""
    from anfekf_bench.models import Bicycle, Unicycle

    for _ in range(50):
        x = np.array([*rng.normal(size=2), rng.uniform(-3.1, 3.1)])
        u = np.array([rng.uniform(0.1, 3), rng.uniform(-0.5, 0.5)])
        dt = float(rng.uniform(0.01, 0.2))
        bic = Bicycle(T=dt, B=4.0)
        F, G = bic.jacobians(x, u, dt)
        f02, f12, Gk = kernels.jacobians(x[2], u[0], u[1], dt, kernels.MOTION_BICYCLE, 4.0)
        assert (f02, f12) == (F[0, 2], F[1, 2])
        np.testing.assert_array_equal(np.array(Gk).reshape(3, 2), G)
        uni = Unicycle()
        F, G = uni.jacobians(x, u, dt)
        f02, f12, Gk = kernels.jacobians(x[2], u[0], u[1], dt, kernels.MOTION_UNICYCLE, 0.0)
        assert (f02, f12) == (F[0, 2], F[1, 2])
        np.testing.assert_array_equal(np.array(Gk).reshape(3, 2), G)
