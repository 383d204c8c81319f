"""The residual- and VB-based adaptive filters on the fast engine against the filterpy engine
(SPEC 11, issue 22): akhlaghi, vb-r, vbakf and swvb in every mode, the same update, rejection and
divergence counts, the same NaN records, x, P, R_diag, Q_diag and P_infl to 1e-9
(`test_fast_engine.assert_same_run`), compiled and as plain Python."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines import fast
from anfekf_bench.filters.akhlaghi import AkhlaghiSpec
from anfekf_bench.filters.swvb import SWVBSpec
from anfekf_bench.filters.vb import VBAKFSpec, VBRSpec
from anfekf_bench.runner import simulate
from anfekf_bench.scenarios import load_scenario

from .conftest import small_scenario
from .test_fast_engine import assert_same_run, both, ctx_of

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _akhlaghi(**kw):
    return AkhlaghiSpec(name="a", kind="akhlaghi", **kw)


def _vbr(**kw):
    return VBRSpec(name="v", kind="vb-r", **kw)


def _vbakf(**kw):
    return VBAKFSpec(name="h", kind="vbakf", **kw)


def _swvb(**kw):
    return SWVBSpec(name="s", kind="swvb", **kw)


VARIANTS = {
    "akhlaghi": _akhlaghi(),
    "akhlaghi-R": _akhlaghi(adapt="R"),
    "akhlaghi-Q": _akhlaghi(adapt="Q"),
    "akhlaghi-slow": _akhlaghi(alpha=0.97),
    "akhlaghi-accepted": _akhlaghi(adapt_from="accepted"),
    "akhlaghi-bounds": _akhlaghi(bounds=(0.5, 2.0)),
    "akhlaghi-off": _akhlaghi(adaptation=False),
    "vb-r": _vbr(),
    "vb-r-one-iteration": _vbr(iterations=1),
    "vb-r-stationary": _vbr(rho=1.0, alpha0=5.0),
    "vb-r-accepted": _vbr(adapt_from="accepted"),
    "vb-r-bounds": _vbr(bounds=(0.5, 2.0)),
    "vb-r-off": _vbr(adaptation=False),
    "vbakf": _vbakf(),
    "vbakf-full-R": _vbakf(R_structure="full"),
    "vbakf-few-iterations": _vbakf(iterations=2, tau=6.0, tau_R=1.0),
    "vbakf-stationary": _vbakf(rho=1.0),
    "vbakf-accepted": _vbakf(adapt_from="accepted"),
    "vbakf-bounds": _vbakf(bounds=(0.5, 2.0)),
    "vbakf-off": _vbakf(adaptation=False),
    "swvb": _swvb(),
    "swvb-one-iteration": _swvb(iterations=1, a0=3.0),
    "swvb-stationary": _swvb(rho=1.0),
    "swvb-accepted": _swvb(adapt_from="accepted"),
    "swvb-bounds": _swvb(bounds=(0.5, 2.0)),
    "swvb-off": _swvb(adaptation=False),
}


@pytest.fixture(scope="module")
def worlds():
    """The small world twice: R wrong (the default: range 10x too small, so the gate rejects and
    rejected landmarks feed adaptation) and Qu 30x too large (something for Qu to find)."""
    out = {}
    for name, noise in (("wrong-R", {}), ("wrong-Q", {"sigma_v": 9.0, "sigma_gamma_deg": 9.0})):
        doc = small_scenario(record_every=1, **({"filter_noise": noise} if noise else {}))
        scenario = parse_scenario(doc)
        world = resolve_world(scenario.world, Path("small.yaml"))
        data = simulate(scenario, world, np.random.SeedSequence(23).spawn(1)[0])
        out[name] = (scenario, world, data)
    return out


def test_the_engine_supports_them():
    for spec in VARIANTS.values():
        assert fast.supports(spec)


@pytest.mark.parametrize("mode", ["jit", "pure"])
@pytest.mark.parametrize("name", VARIANTS)
@pytest.mark.parametrize("noise", ["wrong-R", "wrong-Q"])
def test_small_world_every_variant(worlds, noise, name, mode):
    scenario, world, data = worlds[noise]
    spec = VARIANTS[name]
    ctx = ctx_of(spec, scenario, world)
    ref, out = both(spec, ctx, data, world, 1, jit=mode == "jit")
    assert not ref["diverged"] and ref["n_updates"] > 50
    adapts = spec.adaptation and name != "akhlaghi-Q"
    if adapts:  # it did adapt R (the test compares something that moves)
        assert np.ptp(ref["R_diag"][:, 0]) > 0
    if spec.adaptation and name.startswith(("akhlaghi", "swvb")) and name != "akhlaghi-R":
        assert np.ptp(ref["Q_diag"][:, 0]) > 0
    if spec.adaptation and name.startswith("vbakf"):  # it did rescale P-
        assert np.nanmax(np.abs(ref["P_infl"] - 1.0)) > 0.01
    assert_same_run(ref, out, what=f"{noise} {name}")


def test_rejected_landmarks_feed_adaptation(worlds):
    """The wrong-R world has rejections (R held within tight bounds for the VB filters, which
    otherwise learn it within a few scans), so `adapt_from: all` feeds them on both engines."""
    scenario, world, data = worlds["wrong-R"]
    for name in ("akhlaghi", "vb-r-bounds", "vbakf-bounds", "swvb-bounds"):
        spec = VARIANTS[name]
        ref, out = both(spec, ctx_of(spec, scenario, world), data, world, 1)
        assert ref["n_rejected"] > 0
        assert_same_run(ref, out, what=name)


@pytest.mark.parametrize("name", ["akhlaghi", "vb-r", "vbakf", "swvb"])
def test_gate_off_and_record_every(worlds, name):
    scenario, world, data = worlds["wrong-R"]
    spec = VARIANTS[name]
    ctx = dataclasses.replace(ctx_of(spec, scenario, world), gate=None)
    for record_every in (1, 8):
        ref, out = both(spec, ctx, data, world, record_every)
        assert ref["n_rejected"] == 0
        assert_same_run(ref, out, what=f"{name} record_every {record_every}")


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("name", ["akhlaghi", "vb-r", "vbakf", "swvb"])
@pytest.mark.parametrize(
    "changes",
    [
        pytest.param({"x0": np.array([np.nan, 0.0, 0.0])}, id="NIS-not-finite"),
        pytest.param({"P0": -np.eye(3)}, id="P-not-positive-definite"),
    ],
)
def test_forced_divergence(worlds, name, changes):
    scenario, world, data = worlds["wrong-R"]
    spec = VARIANTS[name]
    ctx = dataclasses.replace(ctx_of(spec, scenario, world), **changes)
    ref, out = both(spec, ctx, data, world, 1)
    assert ref["diverged"] and out["diverged"]
    assert_same_run(ref, out, what=str(changes))


@pytest.mark.parametrize("name", ["akhlaghi", "vb-r", "vbakf", "swvb"])
@pytest.mark.parametrize(
    "path", ["wrong_r.yaml", pytest.param("wrong_q.yaml", marks=pytest.mark.slow)]
)
def test_paper_scenarios(path, name):
    """The paper's scenarios, one run each, on both engines."""
    scenario, world = load_scenario(CONFIGS / path)
    data = simulate(scenario, world, np.random.SeedSequence(scenario.seed).spawn(1)[0])
    spec = VARIANTS[name]
    ctx = ctx_of(spec, scenario, world)
    assert_same_run(*both(spec, ctx, data, world, scenario.record_every), what=f"{path} {name}")


def test_each_rule_is_written_once():
    """The kernels call the filter modules' own rule functions (no copies in kernels.py).

    The interval's accumulators A_v, A_g are the one exception: their step is the EKF's own
    covariance predict (`kernels.propagate`, the EKF core that both engines have on purpose),
    on tuples because it runs at every control step; the equivalence tests hold it to the rule.
    """
    from anfekf_bench.engines import kernels, kernels_swvb
    from anfekf_bench.filters import adaptive, akhlaghi, iae, sage_husa, swvb, vb

    rules = {
        "qu_least_squares": adaptive, "clip_to_bounds": adaptive, "matmul": adaptive,
        "inv": adaptive, "lstsq": adaptive,
        "forget": akhlaghi, "residual_variance": akhlaghi, "state_noise_estimate": akhlaghi,
        "vb_r_predict": vb, "vb_r_beta": vb,
        "vb_r_bounded_beta": vb, "vbakf_predict": vb, "vbakf_prior": vb, "inflation_cap": vb,
        "clip_covariance_2": vb,
        "next_beta": sage_husa, "fading_mean": sage_husa, "r_sample": sage_husa,
        "q_sample": sage_husa, "window_covariance": iae, "window_mean": iae, "r_estimate": iae,
        "hold_nonpositive": iae, "q_estimate": iae,
    }  # fmt: skip
    for mod in (kernels, kernels.pure_module()):
        for name, home in rules.items():
            assert getattr(mod, name) is getattr(home, name), name
    for mod in (kernels_swvb, kernels_swvb.pure_module()):  # swvb's kernel, beside kernels.py
        for name in ("interval_prior", "process_noise_moment"):
            assert getattr(mod, name) is getattr(swvb, name), name
