"""The augmented EKF (`ekf-aug`, SPEC 18) and the simulator's error sources.

- Jacobians: the augmented F, G (noise on the odometry) and H against central finite
  differences of the augmented step and measurement, on both motion models, every parameter
  estimated.
- Nothing estimated and nothing injected: the plain EKF to 1e-12.
- Both engines on runs with errors injected, every parameter estimated: pose, P and the four
  parameter estimates to 1e-9 (the registry-wide equivalence test runs the defaults).
- The error sources draw nothing: a run with them is the plain run's draws, scaled and biased;
  without them, the same bytes.
- Convergence: on a run with every source injected the estimates end near the truth.
- `augment:` on sage-husa and vb-r: fast = filterpy to 1e-9 on both motion models (R adapted,
  parameters estimated, both `adapt_from` rules); nothing estimated is the family itself to
  1e-12; the estimates converge as ekf-aug's; bad blocks are refused (one line, exit 2).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines import fast
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.error_sources import ErrorSources
from anfekf_bench.filters import FilterContext
from anfekf_bench.filters.augmented import (
    PARAMETERS,
    AugmentedEKF,
    AugmentedSpec,
    AugmentedState,
    AugmentParams,
    augmented_f,
    augmented_h,
)
from anfekf_bench.filters.context import filter_context
from anfekf_bench.filters.ekf import EKFSpec, gate_threshold
from anfekf_bench.filters.sage_husa import SageHusaSpec
from anfekf_bench.filters.vb import VBRSpec
from anfekf_bench.models import Bicycle, Unicycle
from anfekf_bench.runner import simulate
from anfekf_bench.timeline import Timeline, from_run

from .conftest import small_scenario
from .test_engines_equivalence import synthetic_timeline
from .test_fast_engine import assert_same_run

ALL = AugmentedSpec(name="a", kind="ekf-aug", estimate=list(PARAMETERS))
MODELS = {"bicycle": Bicycle(0.025, 4.0), "unicycle": Unicycle(0.12)}
INJECTED = dict(speed_scale=1.1, steering_scale=1.3, steering_bias_deg=1.0, range_bias=0.3)


def _ctx(model, x0=(1.0, 2.0, 0.4)) -> FilterContext:
    return FilterContext(
        x0=np.array(x0), P0=np.diag([0.01, 0.02, 0.003]), Qu=np.diag([0.09, 0.004]),
        R=np.diag([0.01, 3e-4]), model=model, dt=0.1, gate=None,
    )  # fmt: skip


def _numeric_jacobian(fun, x, eps=1e-6):
    cols = []
    for i in range(len(x)):
        d = np.zeros(len(x))
        d[i] = eps
        cols.append((fun(x + d) - fun(x - d)) / (2 * eps))
    return np.column_stack(cols)


@pytest.mark.parametrize("motion", sorted(MODELS))
def test_augmented_jacobians_match_finite_differences(motion):
    model = MODELS[motion]
    flt = ALL.build(_ctx(model))
    x = np.array([1.0, 2.0, 0.4, 1.08, 1.25, 0.02, 0.3])
    flt.x = x.copy()
    u = np.array([2.5, 0.3])
    dt = 0.1
    flt.predict(u, dt=dt)
    F_num = _numeric_jacobian(lambda s: augmented_f(model, s, u, dt, ALL), x)
    np.testing.assert_allclose(flt.F, F_num, rtol=1e-6, atol=1e-8)
    # G: the step's derivative in the odometry (the noise enters there), pose rows
    G_num = _numeric_jacobian(lambda v: augmented_f(model, x, v, dt, ALL)[:3], u)
    np.testing.assert_allclose(flt.G, G_num, rtol=1e-6, atol=1e-8)
    assert (np.abs(flt.F[:3, 3:6]).max(axis=0) > 0).all()  # each odometry parameter moves it
    landmark = np.array([7.0, -3.0])
    flt.x = x.copy()
    inn = flt.innovation(augmented_h(x, landmark, ALL), landmark)
    H_num = _numeric_jacobian(lambda s: augmented_h(s, landmark, ALL), x)
    np.testing.assert_allclose(inn.H, H_num, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(inn.nu, 0.0, atol=1e-12)


def _small(errors: dict | None = None, seed: int = 3):
    doc = small_scenario(record_every=1)
    if errors:
        doc["error_sources"] = errors
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, ".")
    return scenario, world, simulate(scenario, world, np.random.SeedSequence(seed))


def test_nothing_estimated_nothing_injected_is_the_ekf():
    scenario, world, data = _small()
    known = AugmentedSpec(name="k", kind="ekf-aug", estimate=[])
    ekf = EKFSpec(name="e")
    tl = from_run(data, world, 1)
    ref = run_filter(ekf.build(filter_context(ekf, scenario, world)), tl)
    ctx = filter_context(known, scenario, world)
    for out in (run_filter(known.build(ctx), tl), fast.run_filter_fast(known, ctx, tl)):
        for key in ("x", "P"):
            np.testing.assert_allclose(out[key], ref[key], rtol=0, atol=1e-12, err_msg=key)
        assert (out["n_updates"], out["n_rejected"]) == (ref["n_updates"], ref["n_rejected"])


def _theta_of_filterpy(flt: AugmentedEKF, tl: Timeline) -> np.ndarray:
    """The filterpy filter's parameters at every recorded stamp (its own loop, as run_filter)."""
    rows = []
    for k in range(len(tl.dt)):
        flt.predict(tl.u[k], dt=tl.dt[k])
        a, b = tl.lm[k], tl.lm[k + 1]
        if b > a:
            flt.update_scan(tl.z[a:b], tl.xy[a:b])
        if tl.record[k]:
            rows.append(flt.parameters)
    return np.array(rows)


def _injected_timeline(tl: Timeline, kv, kw, bw, br) -> Timeline:
    u = tl.u * [kv, kw] + [0.0, bw]
    z = tl.z + [br, 0.0]
    return Timeline(
        t_start=tl.t_start, t=tl.t, dt=tl.dt, u=u, lm=tl.lm, z=z, xy=tl.xy, record=tl.record
    )


@pytest.mark.parametrize("motion", ["bicycle", "unicycle"])
def test_fast_equals_filterpy_with_errors_injected(motion):
    if motion == "bicycle":
        scenario, world, data = _small(INJECTED)
        tl = from_run(data, world, 1)
        ctx = filter_context(ALL, scenario, world)
    else:
        tl, x0 = synthetic_timeline()
        tl = _injected_timeline(tl, 1.1, 1.3, 0.05, 0.2)
        ctx = FilterContext(
            x0=x0, P0=np.diag([0.01, 0.01, 0.001]), Qu=np.diag([0.05**2, 0.08**2]),
            R=np.diag([0.1**2, math.radians(3.0) ** 2]), model=Unicycle(0.12), dt=0.12,
            gate=gate_threshold(0.999),
        )  # fmt: skip
    ref = run_filter(ALL.build(ctx), tl)
    out, theta = fast.augmented_run(ALL, ctx, tl)
    assert not ref["diverged"] and ref["n_updates"] > 50
    assert_same_run(ref, out, what=f"ekf-aug {motion}")
    theta_ref = _theta_of_filterpy(ALL.build(ctx), tl)
    np.testing.assert_allclose(theta, theta_ref, rtol=0, atol=1e-9)
    assert np.ptp(theta, axis=0).min() > 0  # every parameter was estimated
    # the plain-Python kernel is the same code
    pure, theta_pure = fast.augmented_run(ALL, ctx, tl, jit=False)
    np.testing.assert_allclose(theta_pure, theta, rtol=0, atol=1e-9)


def test_error_sources_scale_and_bias_the_same_draws():
    scenario, world, plain = _small(None, seed=9)
    again = _small(None, seed=9)[2]
    assert plain.u_odo.tobytes() == again.u_odo.tobytes()
    _, _, biased = _small(INJECTED, seed=9)
    u_true = plain.truth.u
    noise = plain.u_odo - u_true
    kv, kw, bw, br = ErrorSources(**INJECTED).parameters()
    expected = u_true * [kv, kw] + [0.0, bw] + noise
    np.testing.assert_allclose(biased.u_odo, expected, rtol=0, atol=1e-12)
    for a, b in zip(plain.scans, biased.scans, strict=True):
        np.testing.assert_allclose(b.z[:, 0], a.z[:, 0] + br, rtol=0, atol=1e-12)
        assert a.z[:, 1].tobytes() == b.z[:, 1].tobytes()


def test_an_empty_error_block_is_refused():
    with pytest.raises(ValueError, match="every source is off"):
        ErrorSources()
    with pytest.raises(ValueError, match="estimate"):
        AugmentedSpec(name="a", kind="ekf-aug", estimate=["turn_bias", "turn_bias"])


def test_the_estimates_converge_to_the_injected_errors():
    """One full run of the paper's world with every source injected: the estimates at the end
    within 0.03 of the scales, 0.25 deg of the steering bias, 0.05 m of the range bias."""
    doc = {"name": "c", "record_every": 8, "error_sources": INJECTED}
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, ".")
    data = simulate(scenario, world, np.random.SeedSequence(5))
    tl = from_run(data, world, 8)
    out, theta = fast.augmented_run(ALL, filter_context(ALL, scenario, world), tl)
    assert not out["diverged"]
    truth = np.array(ErrorSources(**INJECTED).parameters())
    tolerance = np.array([0.03, 0.03, math.radians(0.25), 0.05])
    assert (np.abs(theta[-1] - truth) < tolerance).all(), (theta[-1], truth)


# -- `augment:` on the adaptive families (SPEC 18): the family's R rule on the augmented state

AUGMENTED_FAMILIES = {
    "sage-husa": SageHusaSpec(name="sh", kind="sage-husa", augment={"estimate": list(PARAMETERS)}),
    "sage-husa accepted": SageHusaSpec(
        name="sh",
        kind="sage-husa",
        adapt_from="accepted",
        warmup=3,
        bounds=(0.1, 10.0),
        augment={"estimate": ["speed_scale", "turn_bias", "range_bias"]},
    ),  # fmt: skip
    "vb-r": VBRSpec(name="vb", kind="vb-r", augment={"estimate": list(PARAMETERS)}),
    "vb-r accepted": VBRSpec(
        name="vb",
        kind="vb-r",
        adapt_from="accepted",
        rho=0.9,
        iterations=2,
        augment={"estimate": ["turn_scale", "range_bias"], "start": (1.0, 1.2, 0.0, 0.1)},
    ),  # fmt: skip
}


def _run_inputs(motion):
    if motion == "bicycle":
        scenario, world, data = _small(INJECTED)
        tl = from_run(data, world, 1)
        return tl, lambda spec: filter_context(spec, scenario, world)
    tl, x0 = synthetic_timeline()
    tl = _injected_timeline(tl, 1.1, 1.3, 0.05, 0.2)
    ctx = FilterContext(
        x0=x0, P0=np.diag([0.01, 0.01, 0.001]), Qu=np.diag([0.05**2, 0.08**2]),
        R=np.diag([0.1**2, math.radians(3.0) ** 2]), model=Unicycle(0.12), dt=0.12,
        gate=gate_threshold(0.999),
    )  # fmt: skip
    return tl, lambda spec: ctx


@pytest.mark.parametrize("motion", ["bicycle", "unicycle"])
@pytest.mark.parametrize("family", sorted(AUGMENTED_FAMILIES))
def test_augmented_families_fast_equal_filterpy(family, motion):
    spec = AUGMENTED_FAMILIES[family]
    tl, ctx_of = _run_inputs(motion)
    ctx = ctx_of(spec)
    flt = spec.build(ctx)
    assert isinstance(flt, AugmentedState) and len(flt.x) == 3 + len(spec.augment.estimate)
    ref = run_filter(flt, tl)
    out, theta = fast.augmented_run(spec, ctx, tl)
    assert not ref["diverged"] and ref["n_updates"] > 30
    assert np.ptp(ref["R_diag"], axis=0).min() > 0  # R was adapted
    assert_same_run(ref, out, what=f"{family} {motion}")
    np.testing.assert_allclose(theta, _theta_of_filterpy(spec.build(ctx), tl), rtol=0, atol=1e-9)
    via_engine = fast.run_filter_fast(spec, ctx, tl)
    np.testing.assert_allclose(via_engine["x"], out["x"], rtol=0, atol=0)
    if motion == "bicycle":  # the plain-Python kernel is the same code (the shorter run)
        pure, theta_pure = fast.augmented_run(spec, ctx, tl, jit=False)
        np.testing.assert_allclose(theta_pure, theta, rtol=0, atol=1e-9)


@pytest.mark.parametrize("family", ["sage-husa", "vb-r"])
def test_augmented_family_with_nothing_estimated_is_the_family(family):
    """`augment: {estimate: []}` with the default start: the family's own filter to 1e-12."""
    scenario, world, data = _small()
    tl = from_run(data, world, 1)
    plain = AUGMENTED_FAMILIES[family].model_copy(update={"augment": None})
    known = plain.model_copy(update={"augment": AugmentParams(estimate=[])})
    ctx = filter_context(plain, scenario, world)
    ref = run_filter(plain.build(ctx), tl)
    for out in (run_filter(known.build(ctx), tl), fast.run_filter_fast(known, ctx, tl)):
        for key in ("x", "P", "R_diag"):
            np.testing.assert_allclose(out[key], ref[key], rtol=0, atol=1e-12, err_msg=key)


def test_augment_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="R adaptation only"):
        SageHusaSpec(name="s", kind="sage-husa", adapt="RQ", augment={})
    with pytest.raises(ValueError, match="estimate"):
        VBRSpec(name="v", kind="vb-r", augment={"estimate": ["turn_bias", "turn_bias"]})
    with pytest.raises(ValueError, match="augment"):
        VBRSpec(name="v", kind="vb-r", augment={"estmate": ["turn_bias"]})
    with pytest.raises(ValueError, match="start"):
        SageHusaSpec(name="s", kind="sage-husa", augment={"start": (0.0, 1.0, 0.0, 0.0)})


def test_an_augmented_family_estimates_the_injected_errors():
    """The paper's world with every source injected: vb-r with `augment:` ends within the
    tolerances of `ekf-aug`'s convergence test."""
    doc = {"name": "c", "record_every": 8, "error_sources": INJECTED}
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, ".")
    data = simulate(scenario, world, np.random.SeedSequence(5))
    tl = from_run(data, world, 8)
    spec = AUGMENTED_FAMILIES["vb-r"]
    out, theta = fast.augmented_run(spec, filter_context(spec, scenario, world), tl)
    assert not out["diverged"]
    truth = np.array(ErrorSources(**INJECTED).parameters())
    tolerance = np.array([0.03, 0.03, math.radians(0.25), 0.05])
    assert (np.abs(theta[-1] - truth) < tolerance).all(), (theta[-1], truth)


@pytest.mark.parametrize(
    ("entry", "says"),
    [
        ({"kind": "vb-r", "augment": {"estimate": ["wheel_scale"]}}, "augment.estimate"),
        ({"kind": "sage-husa", "adapt": "RQ", "augment": {}}, "R adaptation only"),
        ({"kind": "vb-r", "augment": {"drift": [0, 0, 0, -1]}}, "augment.drift"),
    ],
)
def test_a_bad_augment_is_one_line_with_exit_2(tmp_path, entry, says):
    from typer.testing import CliRunner

    from anfekf_bench.cli import app

    path = tmp_path / "bad.yaml"
    doc = {"name": "bad", "runs": 1, "filters": [{"name": "f", **entry}]}
    path.write_text(yaml.safe_dump(doc))
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0].startswith(f"error: {path}") and says in lines[0], result.output
    assert not (tmp_path / "out").exists()
