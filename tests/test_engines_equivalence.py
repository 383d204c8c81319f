"""The fast engine against the filterpy reference engine: every registered filter kind on both
motion models (SPEC 12, issue 22).

One test, parametrised over every kind of the registry (`filters.registry.SPEC_BY_KIND`, a
Q-adapting variant beside the default where the family has one) x both motion models:

- bicycle: one run of the small simulated world whose filters assume the wrong noise
  (`conftest.small_world_noise_off`), through `timeline.from_run`;
- unicycle: a synthetic recorded-like timeline (jittered dt, several landmarks at one stamp,
  stamps without a record, outliers the gate rejects), the shape `timeline.timeline` makes of
  a recorded log.

Both engines must give identical update, rejection and divergence counts and x, P, R_diag,
Q_diag and P_infl to 1e-9 (`test_fast_engine.assert_same_run`). `kalmannet` runs a network of
the default size with seeded random weights (`KalmanNetWeights.random`: no PyTorch needed; the
kernel's cost and maths do not depend on the weights having been trained). A kind the fast
engine does not implement (`fast.supports`) is skipped by name, and
`test_the_kinds_left_on_filterpy` lists them, so nothing is skipped silently.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from anfekf_bench.engines import fast
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters import FilterContext, RobotEKF
from anfekf_bench.filters.custom import CustomFilterFailed, CustomSpec
from anfekf_bench.filters.ekf import gate_threshold
from anfekf_bench.filters.fitted import EKFTunedSpec
from anfekf_bench.filters.kalmannet import KalmanNetWeights
from anfekf_bench.filters.registry import SPEC_BY_KIND
from anfekf_bench.models import Unicycle, h
from anfekf_bench.runner import engine_of, run_spec
from anfekf_bench.timeline import Timeline, from_run

from .conftest import small_world_noise_off
from .test_fast_engine import assert_same_run, ctx_of

# The kinds the fast engine leaves on filterpy today (a user's class): the list may only shrink.
NOT_FAST = {"custom"}
# Kinds built without validation: they need what a test cannot give them (torch for kalmannet's
# schema check; kalmannet gets its network below)
CONSTRUCTED = {"kalmannet", "custom"}

# Fitted kinds that build no filter without their fit: the fit given here (the kind's own tests
# fit it: tests/test_augmented_calibrated.py)
FITS = {
    "ekf-aug-calibrated": {
        "estimate": ["speed_scale", "turn_bias", "range_bias"],
        "start": [1.05, 1.0, 0.01, 0.1],
        "sigma0": [0.05, 0.0, 0.02, 0.1],
    },
}

# Per kind: the variants run (the default, and what else the family adapts)
EXTRA = {
    "anfekf": [{"adapt": "RQ"}],
    "cm-scale": [{"adapt": "RQ"}],
    "sage-husa": [{"adapt": "RQ"}],
    "iae": [{"adapt": "Q"}],
    "akhlaghi": [{"adapt_from": "accepted"}],
    "vb-imm": [
        {"r_rule": "sage-husa"},
        {"r_rule": "grid", "range_factors": (0.1, 1.0), "bearing_factors": (1.0, 3.0)},
        {"p_stay": 1.0, "adapt_from": "accepted"},
        {"likelihood_dof": math.inf, "p_stay": 0.98},
    ],
}


# A small grid for the banks (their default grid of 125 members costs seconds on filterpy)
BANK = {"qu_factors": (0.1, 1.0, 10.0), "range_factors": (0.1, 1.0), "bearing_factors": (1.0, 3.0)}
SLOW_VARIANTS = {"vb-imm"}
BASE = {"mmae": BANK, "imm": BANK, "vb-imm": {"qu_factors": (0.1, 1.0, 10.0)}}


def _cases():
    for kind in SPEC_BY_KIND:
        for extra in [{}, *EXTRA.get(kind, [])]:
            params = {**BASE.get(kind, {}), **extra}
            label = kind + "".join(f"-{k}={v}" for k, v in extra.items())
            # vb-imm's other designs: the full suite (each runs a bank on filterpy)
            marks = (pytest.mark.slow,) if extra and kind in SLOW_VARIANTS else ()
            yield pytest.param(kind, params, id=label, marks=marks)


def _spec(kind: str, params: dict):
    cls = SPEC_BY_KIND[kind]
    if kind == "kalmannet":  # the default size, seeded random weights
        spec = cls.model_construct(name=kind, kind=kind, **params)
        return spec.with_weights(KalmanNetWeights.random(hidden_size=spec.hidden_size, seed=7))
    if kind in CONSTRUCTED:
        return cls.model_construct(name=kind, kind=kind, **params)
    if kind in FITS:
        return cls(name=kind, kind=kind, **params).with_fit(FITS[kind])
    return cls(name=kind, kind=kind, **params)


# ---------------------------------------------------------------------------------------------
# The two runs


@pytest.fixture(scope="module")
def bicycle_run():
    scenario, world, runs = small_world_noise_off(31, 1)
    return scenario, world, from_run(runs[0], world, 1)


def synthetic_timeline(seed: int = 4, n: int = 700) -> tuple[Timeline, np.ndarray]:
    """A recorded-like drive on the unicycle: (timeline, true start pose). dt jittered in
    [0.02, 0.25] s, the command changing every few stamps, a scan at about every third stamp
    with every landmark within 7 m (several at one stamp), one measurement in 40 an outlier,
    a record at 80 % of the stamps."""
    rng = np.random.default_rng(seed)
    model = Unicycle(0.12)
    landmarks = np.array(
        [[2.0, 1.0], [4.0, -2.0], [-1.0, 3.0], [6.0, 2.5], [0.5, -3.0], [3.0, 4.0]]
    )
    dt = rng.uniform(0.02, 0.25, n)
    u_true = np.empty((n, 2))
    cmd = np.array([0.3, 0.2])
    for k in range(n):
        if k % 7 == 0:
            cmd = np.array([rng.uniform(0.1, 0.5), rng.uniform(-0.6, 0.6)])
        u_true[k] = cmd
    x = np.array([1.0, 0.0, 0.3])
    x0 = x.copy()
    sv, sw = 0.05, 0.08  # per T0
    u_odo = u_true + rng.standard_normal((n, 2)) * [sv, sw] * np.sqrt(0.12 / dt)[:, None]
    z_list, xy_list, counts = [], [], np.zeros(n, np.int64)
    for k in range(n):
        x = model.f(x, u_true[k], dt[k])
        if k % 3 != 2:
            continue
        for lm in landmarks:
            if np.hypot(*(lm - x[:2])) > 7.0:
                continue
            z = h(x, lm) + rng.standard_normal(2) * [0.1, math.radians(3.0)]
            if rng.uniform() < 1 / 40:
                z[0] += 3.0  # an outlier the gate rejects
            z_list.append(z)
            xy_list.append(lm)
            counts[k] += 1
    lm_off = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=lm_off[1:])
    tl = Timeline(
        t_start=0.0, t=np.cumsum(dt), dt=dt, u=np.ascontiguousarray(u_odo), lm=lm_off,
        z=np.array(z_list, float).reshape(-1, 2), xy=np.array(xy_list, float).reshape(-1, 2),
        record=rng.uniform(size=n) < 0.8,
    )  # fmt: skip
    assert counts.max() >= 3
    return tl, x0


@pytest.fixture(scope="module")
def unicycle_run():
    tl, x0 = synthetic_timeline()
    # The filters assume R too small (range 3x, bearing 2x) and Qu 4x too large.
    ctx = FilterContext(
        x0=x0, P0=np.diag([0.01, 0.01, 0.001]),
        Qu=np.diag([0.1**2, 0.16**2]), R=np.diag([0.033**2, math.radians(1.5) ** 2]),
        model=Unicycle(0.12), dt=0.12, gate=gate_threshold(0.999),
    )  # fmt: skip
    return ctx, tl


# ---------------------------------------------------------------------------------------------


def test_recorded_ekf_tuned(unicycle_run):
    """A recorded scenario's reference (`filters.fitted.EKFTunedSpec`, fitted by the grid
    search there) is the plain EKF on the fast engine too."""
    ctx, tl = unicycle_run
    spec = EKFTunedSpec(name="ekf-tuned", kind="ekf-tuned")
    assert fast.supports(spec, ctx.model)
    ref = run_filter(spec.build(ctx), tl)
    assert_same_run(ref, fast.run_filter_fast(spec, ctx, tl), what="recorded ekf-tuned")


def test_the_kinds_left_on_filterpy():
    """Every kind the fast engine does not run, named (it may only shrink)."""
    left = {kind for kind in SPEC_BY_KIND if not fast.supports(_spec(kind, {}))}
    assert left == NOT_FAST, left ^ NOT_FAST
    print("kinds on filterpy only:", sorted(left))


@pytest.mark.parametrize("motion", ["bicycle", "unicycle"])
@pytest.mark.parametrize(("kind", "params"), list(_cases()))
def test_fast_equals_filterpy(kind, params, motion, request):
    spec = _spec(kind, params)
    if not fast.supports(spec):
        pytest.skip(f"kind {kind!r} is not on the fast engine (it runs on filterpy)")
    if motion == "bicycle":
        scenario, world, tl = request.getfixturevalue("bicycle_run")
        # a fitted kind's noise is an input here: the assumed one
        ctx = ctx_of(
            SPEC_BY_KIND["ekf"](name="e") if spec.fitted_on_training else spec, scenario, world
        )
    else:
        ctx, tl = request.getfixturevalue("unicycle_run")
    assert fast.supports(spec, ctx.model)
    flt = spec.build(ctx)
    ref = run_filter(flt, tl)
    out = fast.run_filter_fast(spec, ctx, tl)
    assert not ref["diverged"] and ref["n_updates"] > 50, ref["n_updates"]
    assert len(ref["x"]) == int(tl.record.sum())
    if motion == "unicycle" and flt.has_covariance:  # (no covariance: no gate, KalmanNet)
        assert ref["n_rejected"] > 0  # the gate's decisions are compared too
    # what the filter adapts did move (P: only where R is assumed too small, the unicycle run)
    adapts = spec.adapted() - ({"P"} if motion == "bicycle" else set())
    moved = {
        "R": np.ptp(ref["R_diag"], axis=0).max() > 0,
        "Q": np.ptp(ref["Q_diag"], axis=0).max() > 0,
        "P": np.ptp(ref["P_infl"]) > 0,
    }
    assert any(moved[a] for a in adapts) or not adapts, (adapts, moved)
    assert_same_run(ref, out, what=f"{kind} {params} {motion}")


class RaisingEKF(RobotEKF):
    """A user's filter that fails in its predict: contained, named, on filterpy."""

    def predict(self, u=0, dt=None):
        raise RuntimeError("boom")


def test_run_spec_picks_the_engine_per_filter(unicycle_run):
    """`runner.run_spec`, the one place every pipeline (simulated, recorded) picks the engine:
    a built-in kind runs on the fast engine under `fast` on the unicycle too, a user's class
    on filterpy, contained (one line naming it), and `engine_of` says so for the manifest."""
    ctx, tl = unicycle_run
    spec = SPEC_BY_KIND["anfekf"](name="a", kind="anfekf", adapt="RQ")
    assert engine_of("fast", spec, model=ctx.model) == "fast"
    fast_out = run_spec("fast", spec, ctx, tl)
    ref = run_spec("filterpy", spec, ctx, tl)
    assert_same_run(ref, fast_out, what="run_spec")
    mine = CustomSpec.model_validate(
        {"name": "mine", "kind": "custom", "class": f"{__name__}:RaisingEKF"}
    )
    assert engine_of("fast", mine, model=ctx.model) == "filterpy"
    with pytest.raises(CustomFilterFailed, match="'mine'.*predict/update raised.*boom"):
        run_spec("fast", mine, ctx, tl, name="mine")
