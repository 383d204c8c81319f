"""Tests for the two-input, 25-rule ANFIS (anfekf_bench.anfis)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from anfekf_bench.filters.anfis import (
    MF_LABELS,
    RULE_TABLE,
    ANFISParams,
    firing,
    forward,
    init_params,
    memberships,
    output_and_gradient,
    sgd_step,
)

PARAM_KINDS = ("m", "delta", "w")


def _same_scale_params() -> ANFISParams:
    """Init used for the (d11, d22) pairing: same centres/widths for both inputs."""
    return init_params(centres1=(-1.0, -0.5, 0.0, 0.5, 1.0), width1=0.35)


def _random_params(seed: int) -> ANFISParams:
    rng = np.random.default_rng(seed)
    base = init_params()
    return ANFISParams(
        m=base.m + rng.normal(scale=0.05, size=base.m.shape) * base.delta,
        delta=base.delta * rng.uniform(0.7, 1.4, size=base.delta.shape),
        w=base.w + rng.normal(scale=0.05, size=base.w.shape),
    )


PARAM_SETS = {
    "default": init_params,
    "same_scale": _same_scale_params,
    "random_seed0": lambda: _random_params(0),
    "random_seed1": lambda: _random_params(1),
}

# Inputs in units of the default MF scales (input 0 ~ [-1, 1], input 1 ~ [-0.2, 0.2]).
INPUT_POINTS = {
    "inside": (0.3, -0.05),
    "inside_2": (-0.62, 0.13),
    "at_centre_HM_HM": (0.5, 0.1),
    "at_centre_Z_Z": (0.0, 0.0),
    "edge_H_H": (1.0, 0.2),
    "edge_L_L": (-1.0, -0.2),
    "edge_H_L": (1.0, -0.2),
    "mildly_outside_pos": (1.3, 0.27),
    "mildly_outside_neg": (-1.25, -0.3),
}


def _perturbed(params: ANFISParams, kind: str, index: tuple[int, ...], h: float) -> ANFISParams:
    arr = np.array(getattr(params, kind), dtype=float)
    arr[index] += h
    return dataclasses.replace(params, **{kind: arr})


def _fd_gradient(params: ANFISParams, u: tuple[float, float], kind: str) -> np.ndarray:
    """Central finite differences of forward() w.r.t. one parameter kind."""
    base = getattr(params, kind)
    grad = np.zeros(base.shape)
    for index in np.ndindex(base.shape):
        h = 1e-6 * max(1.0, abs(float(base[index])))
        fp = forward(_perturbed(params, kind, index, h), u)
        fm = forward(_perturbed(params, kind, index, -h), u)
        grad[index] = (fp - fm) / (2.0 * h)
    return grad


@pytest.mark.parametrize("kind", PARAM_KINDS)
@pytest.mark.parametrize("u", list(INPUT_POINTS.values()), ids=list(INPUT_POINTS))
@pytest.mark.parametrize("make_params", list(PARAM_SETS.values()), ids=list(PARAM_SETS))
def test_gradient_matches_finite_differences(make_params, u, kind):
    params = make_params()
    _, grad = output_and_gradient(params, u)
    analytic = getattr(grad, kind)
    numeric = _fd_gradient(params, u, kind)
    assert analytic.shape == getattr(params, kind).shape
    scale = max(np.linalg.norm(numeric), np.linalg.norm(analytic))
    assert scale > 1e-8, "degenerate test point: gradient is ~0"
    rel_err = np.linalg.norm(analytic - numeric) / scale
    assert rel_err < 1e-6, f"{kind}: rel err {rel_err:.2e}\n{analytic}\n{numeric}"


def test_rule_table_matches_paper():
    paper_table = {
        "L": "S7 S7 S6 S5 S4",
        "LM": "S7 S6 S5 S4 S3",
        "Z": "S6 S5 S4 S3 S2",
        "HM": "S5 S4 S3 S2 S1",
        "H": "S4 S3 S2 S1 S1",
    }
    expected = np.array(
        [[int(s[1:]) - 1 for s in paper_table[label].split()] for label in MF_LABELS]
    )
    assert RULE_TABLE.shape == (5, 5)
    assert np.issubdtype(RULE_TABLE.dtype, np.integer)
    np.testing.assert_array_equal(RULE_TABLE, expected)


def test_default_init_values():
    params = init_params()
    np.testing.assert_allclose(params.m[0], [-1, -0.5, 0, 0.5, 1])
    np.testing.assert_allclose(params.m[1], [-0.2, -0.1, 0, 0.1, 0.2])
    np.testing.assert_allclose(params.delta[0], 0.35)
    np.testing.assert_allclose(params.delta[1], 0.1)
    np.testing.assert_allclose(params.w, [-0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3])
    same = _same_scale_params()
    np.testing.assert_allclose(same.m[1], same.m[0])
    np.testing.assert_allclose(same.delta[1], 0.35)
    np.testing.assert_allclose(init_params(singleton_scale=0.5).w[-1], 1.5)


def test_init_rejects_nonpositive_width():
    with pytest.raises(ValueError, match="widths must be > 0"):
        init_params(width0=0.0)


def test_output_sign_and_symmetry_default():
    params = init_params()
    assert forward(params, (1.0, 0.2)) < -0.25  # H,H -> S1 = -0.3
    assert forward(params, (-1.0, -0.2)) > 0.25  # L,L -> S7 = +0.3
    assert abs(forward(params, (0.0, 0.0))) < 1e-12
    for u in [(0.3, -0.05), (0.8, 0.11), (-0.4, 0.17)]:
        mirrored = (-u[0], -u[1])
        assert forward(params, u) == pytest.approx(-forward(params, mirrored), abs=1e-12)


def test_output_monotone_decreasing_in_u0():
    params = init_params()
    grid = np.linspace(-1.2, 1.2, 49)
    outputs = np.array([forward(params, (x, 0.0)) for x in grid])
    assert np.all(np.diff(outputs) < 0)


@pytest.mark.parametrize("make_params", list(PARAM_SETS.values()), ids=list(PARAM_SETS))
@pytest.mark.parametrize("u", list(INPUT_POINTS.values()), ids=list(INPUT_POINTS))
def test_normalised_firing_sums_to_one(make_params, u):
    params = make_params()
    fbar = firing(params, u)
    assert fbar.shape == (5, 5)
    assert np.all(fbar >= 0)
    assert fbar.sum() == pytest.approx(1.0, abs=1e-12)
    # Consistent with raw memberships (eqs. 35-37) where nothing underflows.
    mu = memberships(params, u)
    f = np.outer(mu[0], mu[1])
    np.testing.assert_allclose(fbar, f / f.sum(), rtol=1e-10, atol=1e-15)
    expected_o = float(np.sum(fbar * params.w[RULE_TABLE]))
    assert forward(params, u) == pytest.approx(expected_o, abs=1e-14)


EXTREME_INPUTS = {
    "zero": (0.0, 0.0),
    "huge_pos": (1e6, 1e6),
    "huge_neg": (-1e6, -1e6),
    "huge_mixed": (1e6, -1e6),
    "enormous": (1e300, -1e308),
}


@pytest.mark.parametrize("u", list(EXTREME_INPUTS.values()), ids=list(EXTREME_INPUTS))
@pytest.mark.parametrize("make_params", list(PARAM_SETS.values()), ids=list(PARAM_SETS))
def test_output_and_gradient_finite_for_extreme_inputs(make_params, u):
    params = make_params()
    o, grad = output_and_gradient(params, u)
    assert np.isfinite(o)
    assert abs(o) <= np.max(np.abs(params.w)) + 1e-12  # convex combination of singletons
    for kind in PARAM_KINDS:
        assert np.all(np.isfinite(getattr(grad, kind)))
    fbar = firing(params, u)
    assert np.all(np.isfinite(fbar))
    assert fbar.sum() == pytest.approx(1.0, abs=1e-12)


def test_saturation_far_outside():
    params = init_params()
    # Far beyond H for both inputs: only rule (H, H) -> S1 fires.
    assert forward(params, (1e6, 1e6)) == pytest.approx(params.w[0])
    assert forward(params, (-1e6, -1e6)) == pytest.approx(params.w[6])


@pytest.mark.parametrize("make_params", list(PARAM_SETS.values()), ids=list(PARAM_SETS))
@pytest.mark.parametrize("u", list(INPUT_POINTS.values()), ids=list(INPUT_POINTS))
def test_forward_equals_output_of_output_and_gradient(make_params, u):
    params = make_params()
    o, _ = output_and_gradient(params, u)
    assert isinstance(o, float)
    assert forward(params, u) == o
    assert forward(params, np.asarray(u)) == o


def _loss_and_grad(params: ANFISParams, u, target: float) -> tuple[float, ANFISParams]:
    o, do = output_and_gradient(params, u)
    err = o - target
    grad = ANFISParams(m=err * do.m, delta=err * do.delta, w=err * do.w)
    return 0.5 * err**2, grad


@pytest.mark.parametrize("eta", [0.5, (0.2, 0.2, 1.0), (0.0, 0.0, 1.0), (0.5, 0.0, 0.0)], ids=str)
def test_sgd_reduces_loss(eta):
    params = init_params()
    u = (0.3, -0.05)
    target = 0.2
    losses = []
    for _ in range(20):
        loss, grad = _loss_and_grad(params, u, target)
        losses.append(loss)
        params = sgd_step(params, grad, eta)
    losses.append(_loss_and_grad(params, u, target)[0])
    assert np.all(np.diff(losses) < 0), losses
    assert losses[-1] < 0.5 * losses[0]


def test_sgd_fits_a_target_mapping():
    """A few epochs over several inputs reduce the summed loss to a fraction of its start."""
    rng = np.random.default_rng(42)
    inputs = np.column_stack([rng.uniform(-1, 1, 30), rng.uniform(-0.2, 0.2, 30)])
    targets = 0.2 * np.tanh(2 * inputs[:, 0])  # a different (positive-slope) mapping

    def total_loss(p):
        return sum(_loss_and_grad(p, u, t)[0] for u, t in zip(inputs, targets, strict=True))

    params = init_params()
    start = total_loss(params)
    for _ in range(30):
        for u, t in zip(inputs, targets, strict=True):
            params = sgd_step(params, _loss_and_grad(params, u, t)[1], 0.2)
    assert total_loss(params) < 0.2 * start


def test_sgd_widths_stay_above_min_width():
    params = init_params()
    grad = ANFISParams(m=np.zeros((2, 5)), delta=np.full((2, 5), 1e6), w=np.zeros(7))
    new = sgd_step(params, grad, 10.0, min_width=1e-3)
    np.testing.assert_array_equal(new.delta, 1e-3)
    new = sgd_step(params, grad, 10.0, min_width=0.05)
    np.testing.assert_array_equal(new.delta, 0.05)
    o, g = output_and_gradient(new, (0.3, -0.05))
    assert np.isfinite(o)
    assert all(np.all(np.isfinite(getattr(g, k))) for k in PARAM_KINDS)


def test_sgd_does_not_mutate_inputs():
    params = _random_params(3)
    copies = {k: np.array(getattr(params, k)) for k in PARAM_KINDS}
    _, grad = output_and_gradient(params, (0.3, -0.05))
    grad_copies = {k: np.array(getattr(grad, k)) for k in PARAM_KINDS}
    new = sgd_step(params, grad, 0.7)
    assert new is not params
    for k in PARAM_KINDS:
        np.testing.assert_array_equal(getattr(params, k), copies[k])
        np.testing.assert_array_equal(getattr(grad, k), grad_copies[k])
        assert not np.shares_memory(getattr(new, k), getattr(params, k))
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.w = np.zeros(7)  # type: ignore[misc]


def test_init_params_arrays_read_only():
    params = init_params()
    with pytest.raises(ValueError, match="read-only"):
        params.w[0] = 1.0
    new = sgd_step(params, output_and_gradient(params, (0.1, 0.0))[1], 0.1)
    with pytest.raises(ValueError, match="read-only"):
        new.m[0, 0] = 1.0


@pytest.mark.parametrize(
    ("eta", "changed"),
    [
        ((0.0, 0.0, 1.0), {"w"}),
        ((1.0, 0.0, 0.0), {"m"}),
        ((0.0, 1.0, 0.0), {"delta"}),
        ((1.0, 1.0, 1.0), {"m", "delta", "w"}),
    ],
    ids=["w_only", "m_only", "delta_only", "all"],
)
def test_sgd_eta_triple_applies_per_kind(eta, changed):
    params = init_params()
    _, grad = output_and_gradient(params, (0.3, -0.05))
    new = sgd_step(params, grad, eta)
    for kind in PARAM_KINDS:
        expected = getattr(params, kind) - eta[PARAM_KINDS.index(kind)] * getattr(grad, kind)
        if kind == "delta":
            expected = np.maximum(expected, 1e-3)
        np.testing.assert_allclose(getattr(new, kind), expected, rtol=0, atol=1e-15)
        differs = not np.array_equal(getattr(new, kind), getattr(params, kind))
        assert differs == (kind in changed), kind


def test_sgd_rejects_bad_eta():
    params = init_params()
    _, grad = output_and_gradient(params, (0.3, -0.05))
    with pytest.raises(ValueError, match="eta must be"):
        sgd_step(params, grad, (0.1, 0.1))  # type: ignore[arg-type]
