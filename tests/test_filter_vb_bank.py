"""The default filter `vb-imm` (filters/vb_bank.py) against independent references: with one
member it is the single filter its R rule names (vb-r, sage-husa, the plain EKF), its grid rule
is the zoo's `imm` on the same grid, adaptation off is the EKF, and its weight goes to the true
Qu factor. The fast engine's kernel is checked in tests/test_engines_equivalence.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters.bank import IMMSpec
from anfekf_bench.filters.ekf import EKFSpec
from anfekf_bench.filters.sage_husa import SageHusaSpec
from anfekf_bench.filters.vb import VBRSpec
from anfekf_bench.filters.vb_bank import VBIMMSpec, member_factors

from .conftest import small_world_noise_off
from .test_fast_engine import ctx_of

TOL = 1e-12


@pytest.fixture(scope="module")
def small():
    scenario, world, data = small_world_noise_off(seed=41, runs=1)
    return scenario, world, data[0]


def _run(spec, small):
    scenario, world, data = small
    return run_filter(spec.build(ctx_of(spec, scenario, world)), data, world, 1)


def _same(a: dict, b: dict, keys=("x", "P", "R_diag")) -> None:
    for k in keys:
        np.testing.assert_allclose(a[k], b[k], rtol=TOL, atol=TOL, err_msg=k)
    assert a["diverged"] == b["diverged"]
    assert (a["n_updates"], a["n_rejected"]) == (b["n_updates"], b["n_rejected"])


def test_one_vb_member_is_vb_r(small):
    bank = VBIMMSpec(name="b", kind="vb-imm", qu_factors=(1.0,))
    single = VBRSpec(name="v", kind="vb-r", rho=bank.rho)
    _same(_run(bank, small), _run(single, small))


def test_one_sage_husa_member_is_sage_husa(small):
    bank = VBIMMSpec(name="b", kind="vb-imm", qu_factors=(1.0,), r_rule="sage-husa", b=0.95)
    single = SageHusaSpec(name="s", kind="sage-husa", b=0.95)
    _same(_run(bank, small), _run(single, small))


@pytest.mark.parametrize(
    "params", [{"adaptation": False}, {"qu_factors": (1.0,), "r_rule": "grid"}]
)
def test_without_adaptation_it_is_the_ekf(small, params):
    bank = VBIMMSpec(name="b", kind="vb-imm", **params)
    _same(_run(bank, small), _run(EKFSpec(name="e"), small))


def test_grid_rule_is_the_imm_on_the_same_grid(small):
    grid = {
        "qu_factors": (0.1, 1.0, 10.0),
        "range_factors": (0.3, 1.0),
        "bearing_factors": (1.0, 3.0),
    }
    bank = VBIMMSpec(
        name="b", kind="vb-imm", r_rule="grid", p_stay=0.95, likelihood_dof=math.inf, **grid
    )
    imm = IMMSpec(name="i", kind="imm", p_stay=0.95, **grid)
    _same(_run(bank, small), _run(imm, small), keys=("x", "P", "R_diag", "Q_diag"))


def test_members_cross_qu_with_r_only_on_the_grid_rule():
    spec = VBIMMSpec(name="b", kind="vb-imm", qu_factors=(0.1, 1.0), range_factors=(2.0, 3.0))
    assert member_factors(spec).tolist() == [[0.1, 1.0, 1.0], [1.0, 1.0, 1.0]]
    grid = spec.model_copy(update={"r_rule": "grid"})
    assert member_factors(grid)[:, :2].tolist() == [[0.1, 2.0], [0.1, 3.0], [1.0, 2.0], [1.0, 3.0]]


def test_factors_outside_the_bounds_are_refused():
    with pytest.raises(ValueError, match="qu_factors"):
        VBIMMSpec(name="b", kind="vb-imm", qu_factors=(1e-5, 1.0))


def test_weight_goes_to_the_true_qu(small):
    """The small world's filters assume sigma_v 3 m/s (true 0.3: 0.01x in variance) and sigma_gamma
    9 deg (true 3: 0.11x), sigma_range 0.5 m (true 0.1: R 25x too large). The most probable member
    at the end is the 0.01x one (the grid's nearest to both), and its adapted range variance is
    within a factor 2 of the true 0.01 m^2. (The recorded Qu is the weights' arithmetic mean: with
    p_stay 0.98 the largest factors' small predicted weights pull it far above the best
    member's.)"""
    scenario, world, data = small
    spec = VBIMMSpec(name="b", kind="vb-imm")
    flt = spec.build(ctx_of(spec, scenario, world))
    out = run_filter(flt, data, world, 1)
    assert not out["diverged"]
    best = int(np.argmax(flt.logw))
    assert spec.qu_factors[best] == pytest.approx(0.01)
    assert np.exp(flt.logw[best]) > 0.9
    assert 0.01 / 2 < flt.members[best].R[0, 0] < 0.01 * 2
