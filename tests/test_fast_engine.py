"""The fast engine against the filterpy engine (SPEC 11, issue 14).

Every kernel is checked against the reference code it replaces, then whole runs: the small test
world and the four paper scenarios, through `filterpy_engine.run_filter(spec.build(ctx), ...)`
and `fast.run_filter_fast(spec, ctx, ...)` on the same data.

Equivalence means: the same update, gate-rejection and divergence counts, NaN in the same
records, and x, P, R_diag, Q_diag, P_infl and the NIS sum equal to TOL = 1e-9, relative to each
quantity's scale over the run (`assert_same_run`). The engines differ only by rounding (BLAS's
order and fused multiply-adds inside numpy's small products, numpy's vectorised exp): about
1e-13 on every scenario here, none of which is ill-conditioned at that level.

The compiled kernels are used when numba is installed; `pure` tests run the plain-Python copy
of the same kernels (`kernels.pure_module()`), which is what runs without numba.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from anfekf_bench import compiled
from anfekf_bench.compiled import reached_modules
from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines import families, fast, kernels, loop
from anfekf_bench.engines.filterpy_engine import _healthy, run_filter
from anfekf_bench.filters import (
    ANFEKFSpec,
    EKFSpec,
    FilterContext,
    OracleSpec,
    RobotEKF,
    anfis,
    build_filter,
    q_step,
    r_step,
)
from anfekf_bench.filters.spec import FilterSpec
from anfekf_bench.models import Bicycle, Unicycle
from anfekf_bench.runner import simulate
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.sources.simulator import RunData, Scan
from anfekf_bench.storage import write_new

from .conftest import corrupted_half_way, small_scenario

TOL = 1e-9
CONFIGS = Path(__file__).resolve().parent.parent / "configs"
PAPER = ("correct", "wrong_r", "wrong_q", "consistency")
KEYS = ("x", "P", "R_diag", "Q_diag", "P_infl")

# The compiled kernels (numba when installed) and the plain-Python copy.
KERNELS = {"jit": kernels, "pure": kernels.pure_module()}


def _anfekf(name: str, **kw) -> ANFEKFSpec:
    return ANFEKFSpec(name=name, kind="anfekf", **kw)


# Every configuration of the ANFEKF the engine must reproduce.
VARIANTS: dict[str, FilterSpec] = {
    "ekf": EKFSpec(name="ekf"),
    "oracle": OracleSpec(name="oracle", kind="ekf-oracle"),
    "anfekf-R": _anfekf("R", adapt="R"),
    "anfekf-Q": _anfekf("Q", adapt="Q"),
    "anfekf-RQ": _anfekf("RQ", adapt="RQ"),
    "no-adaptation": _anfekf("noad", adapt="RQ", adaptation=False),
    "no-learning": _anfekf("nolearn", adapt="RQ", learning=False),
    "from-accepted": _anfekf("acc", adapt="RQ", adapt_from="accepted"),
    "tight-bounds": _anfekf("bounds", adapt="RQ", bounds=(0.5, 2.0)),
    "clipped-outputs": _anfekf("clip", adapt="RQ", output_clip=0.02, window=5),
    "rates-and-shapes": _anfekf(
        "shapes", adapt="RQ", learning_rate=(0.05, 0.0, 0.2), singleton_scale=0.3, width_d=0.2,
        width_dd=0.05, centres_dd=(-0.3, -0.1, 0.0, 0.1, 0.3), window=7,
    ),
}  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Helpers


def ctx_of(spec: FilterSpec, scenario, world) -> FilterContext:
    """The FilterContext `build_filter` gives this spec (read back from the filter it builds;
    the pose block of an augmented one)."""
    flt = build_filter(spec, scenario, world)
    return FilterContext(
        x0=flt.x[:3].copy(), P0=flt.P[:3, :3].copy(), Qu=flt.Qu.copy(), R=flt.R.copy(),
        model=flt.model, dt=flt.dt, gate=flt.gate,
    )  # fmt: skip


def both(spec, ctx, data, world, record_every, *, jit=True) -> tuple[dict, dict]:
    """(filterpy engine, fast engine) on the same filter, context and data."""
    ref = run_filter(spec.build(ctx), data, world, record_every)
    out = fast.run_filter_fast(spec, ctx, data, world, record_every, jit=jit)
    return ref, out


def assert_same_run(ref: dict, out: dict, tol: float = TOL, what: str = "") -> dict:
    """The equivalence of two engines' results (module doc); returns the largest errors."""
    assert set(out) == set(ref)
    for key in ("diverged", "n_updates", "n_rejected"):
        assert out[key] == ref[key], (what, key, ref[key], out[key])
        assert type(out[key]) is type(ref[key]), (what, key)
    errs = {}
    for key in KEYS:
        a, b = ref[key], out[key]
        assert b.shape == a.shape and b.dtype == a.dtype, (what, key)
        np.testing.assert_array_equal(np.isnan(b), np.isnan(a), err_msg=f"{what} {key}: NaNs")
        ok = np.isfinite(a)
        np.testing.assert_array_equal(np.isfinite(b), ok, err_msg=f"{what} {key}: infinities")
        if ok.any():
            scale = max(float(np.abs(a[ok]).max()), 1e-300)
            errs[key] = float(np.abs(a[ok] - b[ok]).max()) / scale
            assert errs[key] <= tol, (what, key, errs[key])
    assert isinstance(out["nis_sum"], float)
    # (NaN for a filter without a covariance: KalmanNet)
    assert out["nis_sum"] == pytest.approx(ref["nis_sum"], rel=tol, abs=1e-300, nan_ok=True)
    return errs


@pytest.fixture(scope="module")
def small():
    """The small test world (tests/conftest.py), its scenario (wrong R) and two runs."""
    scenario = parse_scenario(small_scenario(record_every=1))
    world = resolve_world(scenario.world, Path("small.yaml"))
    runs = [simulate(scenario, world, s) for s in np.random.SeedSequence(11).spawn(2)]
    return scenario, world, runs


# ---------------------------------------------------------------------------------------------
# The engine's interface


def test_supports_the_built_in_filters_only():
    for spec in VARIANTS.values():
        assert fast.supports(spec), spec

    class MySpec(EKFSpec):  # a subclass may build another filter: filterpy runs it
        pass

    assert not fast.supports(MySpec(name="mine"))
    assert fast.supports(VARIANTS["ekf"], Bicycle(0.025, 4.0))
    assert fast.supports(VARIANTS["ekf"], Unicycle())
    assert not fast.supports(VARIANTS["ekf"], MyModel())


class MyModel(Unicycle):  # a user's model: the kernels do not know its maths
    pass


def test_refuses_what_it_does_not_implement(small):
    scenario, world, runs = small
    ctx = ctx_of(VARIANTS["ekf"], scenario, world)

    class MySpec(EKFSpec):
        pass

    with pytest.raises(ValueError, match="does not implement"):
        fast.run_filter_fast(MySpec(name="mine"), ctx, runs[0], world, 1)
    mine = dataclasses.replace(ctx, model=MyModel())
    with pytest.raises(ValueError, match="motion models"):
        fast.run_filter_fast(VARIANTS["ekf"], mine, runs[0], world, 1)


def test_kernels_are_compiled_when_numba_is_installed():
    numba = pytest.importorskip("numba")
    assert fast.JIT and kernels.JIT
    assert isinstance(kernels.correct, numba.core.registry.CPUDispatcher)
    anfekf = families.module("anfekf")
    assert isinstance(loop.compiled_loop(anfekf), numba.core.registry.CPUDispatcher)
    assert loop.compiled_loop(anfekf) is loop.compiled_loop(anfekf)  # one per family
    assert not isinstance(loop.run_loop, numba.core.registry.CPUDispatcher)  # the template
    pure = KERNELS["pure"]
    assert not pure.JIT
    assert not isinstance(pure.correct, numba.core.registry.CPUDispatcher)
    pure_loop = loop.pure_module()
    assert pure_loop.compiled_loop(families.module("anfekf", pure=True)) is pure_loop.run_loop


def test_a_family_loop_is_generated_once_from_the_template_and_named_by_its_sources(
    tmp_path, monkeypatch
):
    """`compiled_loop`'s module: run_loop's own source with the family's hooks, written where
    NUMBA_CACHE_DIR says, never rewritten (numba's cache is keyed on the file), named by a
    digest of every source the loop reaches (the family's hooks and the filters' rules); it
    runs the text made here, not what the file holds; a source edited after the process
    imported it is refused."""
    import inspect

    config = pytest.importorskip("numba.core.config")
    monkeypatch.setattr(config, "CACHE_DIR", str(tmp_path))
    sage_husa = families.module("sage_husa")
    generated = loop._generated_module(sage_husa)
    path = Path(generated.__file__)
    assert path.parent == tmp_path / "anfekf_loops"
    text = path.read_text()
    assert text == loop._loop_source(sage_husa) and inspect.getsource(loop.run_loop) in text
    assert generated.end_scan.py_func is sage_husa.end_scan  # the family's hook, inlined
    assert generated.rejected.py_func is loop.DEFAULTS["rejected"]  # a hook it leaves out
    reached = {m.__name__ for m in reached_modules(sage_husa, loop)}
    assert {"anfekf_bench.filters.sage_husa", "anfekf_bench.engines.kernels"} <= reached
    stamp = path.stat().st_mtime_ns
    again = loop._generated_module(sage_husa)
    assert again.__file__ == generated.__file__ and path.stat().st_mtime_ns == stamp
    with pytest.raises(FileExistsError):  # another process's write never replaces the file
        write_new(path, b"other text")
    assert path.read_text() == text and path.stat().st_mtime_ns == stamp
    umask = os.umask(0o022)
    os.umask(umask)
    assert [p.name for p in path.parent.iterdir() if p.name.startswith(".")] == []
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask, "the mode open() gives (the umask's)"
    other = loop._generated_module(families.module("iae"))
    assert other.__file__ != generated.__file__
    path.chmod(0o644)  # a file changed behind the process's back is not what it runs
    path.write_text(text.replace("def run_loop(", "def run_loop_planted("))
    assert callable(loop._generated_module(sage_husa).run_loop)
    rule = tmp_path / "rule.py"  # a source the loop reaches, edited: another file, compiled anew
    rule.write_text("a = 1\n")
    monkeypatch.setattr(loop, "reached_modules", lambda *roots: [SimpleNamespace(__file__=rule)])
    before = loop._generated_module(sage_husa).__file__
    rule.write_text("a = 2\n")
    monkeypatch.setitem(compiled._SOURCE_TIMES, str(rule.resolve()), rule.stat().st_mtime_ns)
    assert loop._generated_module(sage_husa).__file__ != before
    os.utime(rule, ns=(1, rule.stat().st_mtime_ns + 10**9))  # edited after the process saw it
    with pytest.raises(RuntimeError, match="changed after this process imported it"):
        loop._generated_module(sage_husa)


def test_threads_asking_for_one_familys_loop_get_one_loop(tmp_path, monkeypatch):
    """Runs on threads may ask for a family's loop at once: one module is made, not several."""
    import threading

    config = pytest.importorskip("numba.core.config")
    monkeypatch.setattr(config, "CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(loop, "_COMPILED", {})
    made = []
    generate = loop._generated_module
    monkeypatch.setattr(loop, "_generated_module", lambda m: made.append(m) or generate(m))
    fading = families.module("fading")
    got = []
    threads = [
        threading.Thread(target=lambda: got.append(loop.compiled_loop(fading))) for _ in range(8)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(made) == 1 and len(got) == 8 and all(g is got[0] for g in got)


def test_the_code_version_ignores_the_generated_loops(tmp_path):
    """A batch's fingerprint holds the package's code version: the loops a first fast run
    writes under __pycache__ must not change it between one process and the next."""
    from anfekf_bench import outputs

    def package(name: str, files: dict[str, str]) -> Path:  # code_version is cached per folder
        for rel, text in files.items():
            (tmp_path / name / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / name / rel).write_text(text)
        return tmp_path / name

    before = outputs.code_version(package("before", {"a.py": "x = 1\n"}))
    generated = {"a.py": "x = 1\n", "__pycache__/loops/loop_fading_0123.py": "y = 2\n"}
    assert outputs.code_version(package("generated", generated)) == before
    edited = {"a.py": "x = 1\n", "b.py": "y = 2\n"}
    assert outputs.code_version(package("edited", edited)) != before
    assert outputs.code_version() == outputs.code_version(Path(outputs.__file__).parent)


_WITHOUT_NUMBA = """
import json, sys
sys.modules["numba"] = None  # `import numba` now raises ImportError, as when it is not installed
from pathlib import Path
import numpy as np
from anfekf_bench.config import parse_scenario, resolve_world
from anfekf_bench.engines import families, fast, kernels, loop
from anfekf_bench.engines.filterpy_engine import run_filter
from anfekf_bench.filters.context import build_filter
from anfekf_bench.runner import simulate

assert not fast.JIT and not kernels.JIT
assert loop.compiled_loop(families.module("anfekf")) is loop.run_loop  # plain Python
scenario = parse_scenario(json.loads(sys.argv[1]))
world = resolve_world(scenario.world, Path("small.yaml"))
data = simulate(scenario, world, np.random.SeedSequence(3))
for spec in scenario.filters:
    flt = build_filter(spec, scenario, world)
    ctx = fast.FilterContext(x0=flt.x.copy(), P0=flt.P.copy(), Qu=flt.Qu.copy(), R=flt.R.copy(),
                             model=flt.model, dt=flt.dt, gate=flt.gate)
    ref = run_filter(flt, data, world, 1)
    out = fast.run_filter_fast(spec, ctx, data, world, 1)
    assert (out["n_updates"], out["n_rejected"]) == (ref["n_updates"], ref["n_rejected"])
    assert np.abs(out["x"] - ref["x"]).max() < 1e-9, spec.name
print("ok", "numba" in sys.modules and sys.modules["numba"] is None)
"""


def test_runs_without_numba():
    """With numba not importable the fast engine runs the same kernels as plain Python."""
    doc = small_scenario(filters=[{"name": "a", "kind": "anfekf", "adapt": "RQ"}])
    proc = subprocess.run(
        [sys.executable, "-c", _WITHOUT_NUMBA, json.dumps(doc)], capture_output=True, text=True,
        check=False, cwd=Path(__file__).resolve().parent.parent,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["ok", "True"]


# ---------------------------------------------------------------------------------------------
# Kernels one by one, against the code they replace


def _rng_filter(rng, cls=RobotEKF, model=None, **kw):
    A = rng.standard_normal((3, 3))
    P0 = A @ A.T * 0.1 + np.eye(3) * 1e-3
    return cls(
        x0=np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-3, 3)]), P0=P0,
        Qu=np.diag([0.3**2, math.radians(3) ** 2]), R=np.diag([0.1**2, math.radians(1) ** 2]),
        model=Bicycle(0.025, 4.0) if model is None else model, dt=0.025, gate=None, **kw,
    )  # fmt: skip


def _motion_args(k, model):
    """The kernels' (motion, B, T0) for a model."""
    if isinstance(model, Bicycle):
        return k.MOTION_BICYCLE, model.B, 0.0
    return k.MOTION_UNICYCLE, 0.0, model.T0


def _close(a, b, tol=1e-12):
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(float(np.abs(a).max()), 1e-300)
    assert float(np.abs(a - b).max()) <= tol * scale, (a, b)


@pytest.mark.parametrize(
    "model", [Bicycle(0.025, 4.0), Unicycle(0.12)], ids=["bicycle", "unicycle"]
)
@pytest.mark.parametrize("mode", KERNELS)
def test_predict_innovation_gate_and_joseph_update_kernels(mode, model):
    k = KERNELS[mode]
    rng = np.random.default_rng(5)
    for _ in range(50):
        flt = _rng_filter(rng, model=model)
        u = np.array([rng.uniform(0, 5), rng.uniform(-0.5, 0.5)])
        # the bicycle's step is its period; the unicycle's varies
        dt = flt.dt if isinstance(model, Bicycle) else float(rng.uniform(0.01, 0.3))
        x, P = tuple(flt.x), tuple(flt.P.ravel())
        motion = _motion_args(k, model)
        xk, Pk, Qk = k.predict(x, P, u[0], u[1], dt, *motion, tuple(flt.Qu.ravel()))
        f02, f12, G = k.jacobians(x[2], u[0], u[1], dt, motion[0], motion[1])
        F = np.array([[1.0, 0.0, f02], [0.0, 1.0, f12], [0.0, 0.0, 1.0]])
        G = np.reshape(G, (3, 2))
        flt.predict(u, dt=dt)
        _close(F, flt.F)
        _close(G, flt.G)
        _close(xk, flt.x)
        _close(Pk, flt.P.ravel())
        _close(Qk, flt.Q.ravel())
        lm = flt.x[:2] + rng.uniform(-15, 15, 2)
        z = np.array([rng.uniform(1, 20), rng.uniform(-3.1, 3.1)])
        inn = flt.innovation(z, lm)
        H, zh, nu, HPHt = k.innovation(xk, Pk, lm[0], lm[1], z[0], z[1])
        _close(H, inn.H[:, :2].ravel())
        assert tuple(inn.H[:, 2]) == (0.0, -1.0)
        _close(zh, inn.z_hat)
        _close(nu, inn.nu)
        _close(HPHt, inn.HPHt.ravel())
        R = tuple(flt.R.ravel())
        ok, v = k.nis(HPHt, R, nu[0], nu[1])
        S = inn.HPHt + flt.R
        assert ok
        _close(v, inn.nu @ np.linalg.solve(S, inn.nu))
        ok, xc, Pc = k.correct(xk, Pk, H, zh, z[0], z[1], R)
        flt.correct(z, lm, inn)
        assert ok
        _close(xc, flt.x)
        _close(Pc, flt.P.ravel())
        assert Pc[1] == Pc[3] and Pc[2] == Pc[6] and Pc[5] == Pc[7]
        assert k.healthy(xc, Pc, R, tuple(flt.Qu.ravel())) == _healthy(flt)


@pytest.mark.parametrize("mode", KERNELS)
def test_singular_innovation_covariance_is_reported(mode):
    k = KERNELS[mode]
    x, P, R = (0.0, 0.0, 0.0), (0.0,) * 9, (0.0,) * 4
    H, zh, nu, HPHt = k.innovation(x, P, 10.0, 0.0, 10.0, 0.0)
    assert k.nis(HPHt, R, nu[0], nu[1]) == (False, pytest.approx(math.nan, nan_ok=True))
    assert k.correct(x, P, H, zh, 10.0, 0.0, R)[0] is False


@pytest.mark.parametrize("mode", KERNELS)
def test_health_kernel_equals_the_engines_check(mode):
    k = KERNELS[mode]
    rng = np.random.default_rng(9)
    cases = [np.diag([1.0, -1e-9, 1.0]), np.diag([1.0, 1.0, 0.0]), np.full((3, 3), 1.0)]
    cases += [np.array([[1, 0.9, 0.9], [0.9, 1, -0.9], [0.9, -0.9, 1.0]])]
    cases += [np.diag([1.0, np.nan, 1.0]), np.diag([np.inf, 1.0, 1.0])]
    cases += [(lambda A: A @ A.T)(rng.standard_normal((3, 3))) for _ in range(20)]
    flt = _rng_filter(rng)
    for P in cases:
        for R in (np.diag([0.01, 1e-4]), np.diag([0.0, 1e-4])):
            flt.P, flt.R = np.array(P, float), R
            got = k.healthy(tuple(flt.x), tuple(flt.P.ravel()), tuple(R.ravel()), (1, 0, 0, 1.0))
            assert got == _healthy(flt), P


ANFIS_PARAMS = [
    anfis.init_params(),
    anfis.init_params(centres1=(-1, -0.5, 0, 0.5, 1), width1=0.35, singleton_scale=0.3),
    anfis.ANFISParams(
        m=anfis.init_params().m + np.random.default_rng(1).normal(0, 0.2, (2, 5)),
        delta=anfis.init_params().delta * np.random.default_rng(2).uniform(0.5, 2, (2, 5)),
        w=np.random.default_rng(3).normal(0, 0.5, 7),
    ),
]


def _row(p: anfis.ANFISParams) -> np.ndarray:
    return np.concatenate([p.m.ravel(), p.delta.ravel(), p.w])


@pytest.mark.parametrize("mode", KERNELS)
@pytest.mark.parametrize("params", ANFIS_PARAMS, ids=["R", "Q", "perturbed"])
def test_anfis_forward_and_gradient_kernel(mode, params):
    k = KERNELS[mode]
    rng = np.random.default_rng(4)
    grad, ws = np.empty(k.N_ANFIS), np.empty(40)
    inputs = [tuple(rng.uniform(-1.5, 1.5, 2)) for _ in range(100)]
    inputs += [(5.0, -7.0), (1e150, -1e150), (0.0, 0.0)]  # far outside every MF, clipped inputs
    for u in inputs:
        o_ref, g_ref = anfis.output_and_gradient(params, u)
        o = k.anfis_output_grad(_row(params), u[0], u[1], grad, ws)
        assert math.isfinite(o)
        _close(o, o_ref, 1e-13) if abs(o_ref) > 1e-3 else _close([o, 1], [o_ref, 1], 1e-13)
        _close(grad, _row(g_ref), 1e-11)  # far inputs scale round-off by z^2 / delta


@pytest.mark.parametrize("mode", KERNELS)
@pytest.mark.parametrize("learning", [True, False])
def test_r_step_and_q_step_kernels_with_learning(mode, learning):
    """r_step/q_step plus ANFEKF._learn's steepest-descent step, clipped outputs included."""
    k = KERNELS[mode]
    rng = np.random.default_rng(8)
    eta = (0.01, 0.02, 0.05)
    grad, ws = np.empty(k.N_ANFIS), np.empty(40)
    for params in ANFIS_PARAMS:
        for clip in (1.0, 0.01):
            u = tuple(rng.uniform(-1, 1, 2))
            R_ii, HPH, C = rng.uniform(0.001, 1, 3)
            row = _row(params)
            R_new = k.r_step(row, u[0], u[1], R_ii, HPH, C, clip, learning, *eta, grad, ws)
            R_ref, _, g = r_step(params, u, R_ii, HPH, C, clip)
            new = anfis.sgd_step(params, g, eta) if learning and g is not None else params
            _close(R_new, R_ref, 1e-13)
            _close(row, _row(new), 1e-13)
            S, Cq, dS = rng.uniform(0.01, 1, 2), rng.uniform(0.01, 1, 2), rng.uniform(0, 0.01, 2)
            row = _row(params)
            scale = k.q_step(row, u[0], u[1], *S, *Cq, *dS, clip, learning, *eta, grad, ws)
            s_ref, _, g = q_step(params, u, S, Cq, dS, clip)
            new = anfis.sgd_step(params, g, eta) if learning and g is not None else params
            _close(scale, s_ref, 1e-13)
            _close(row, _row(new), 1e-13)


@pytest.mark.parametrize("mode", KERNELS)
def test_width_floor_of_the_descent_step(mode):
    """Widths pushed below anfis.sgd_step's floor stop there."""
    k = KERNELS[mode]
    params = anfis.init_params()
    g = anfis.ANFISParams(m=np.zeros((2, 5)), delta=np.full((2, 5), 1e3), w=np.zeros(7))
    row = _row(params)
    k.sgd_step(row, _row(g), 1.0, 0.0, 1.0, 0.0)
    np.testing.assert_array_equal(row, _row(anfis.sgd_step(params, g, (0.0, 1.0, 0.0))))
    assert np.all(row[k.D0 : k.W0] == k.MIN_WIDTH)


@pytest.mark.parametrize("mode", KERNELS)
def test_interval_noise_model_of_the_q_step(mode):
    """ANFEKF._adapt_Q's dS = min(diag(H Q_interval H^T), diag(H P H^T))."""
    k = KERNELS[mode]
    rng = np.random.default_rng(2)
    for _ in range(20):
        H = np.column_stack([rng.standard_normal((2, 2)), [0.0, -1.0]])
        A = rng.standard_normal((3, 3))
        Qi = A @ A.T
        HPH = rng.uniform(0, 5, 2)
        ref = np.minimum(np.einsum("ij,jk,ik->i", H, Qi, H), HPH)
        _close(k.hqh_diag(tuple(H[:, :2].ravel()), tuple(Qi.ravel()), *HPH), ref, 1e-13)


# ---------------------------------------------------------------------------------------------
# Whole runs on the small world


@pytest.mark.parametrize("name", VARIANTS)
def test_small_world_every_variant(small, name):
    scenario, world, runs = small
    spec = VARIANTS[name]
    ctx = ctx_of(spec, scenario, world)
    for data in runs:
        assert_same_run(*both(spec, ctx, data, world, 1), what=name)


@pytest.mark.parametrize("name", ["ekf", "anfekf-RQ", "from-accepted"])
def test_small_world_gate_off(small, name):
    scenario, world, runs = small
    scenario = scenario.model_copy(update={"gate_probability": None})
    spec = VARIANTS[name]
    ctx = ctx_of(spec, scenario, world)
    assert ctx.gate is None
    for data in runs:
        ref, out = both(spec, ctx, data, world, 1)
        assert ref["n_rejected"] == 0
        assert_same_run(ref, out, what=name)


@pytest.mark.parametrize("record_every", [1, 7, 8, 10_000])
def test_small_world_record_every(small, record_every):
    scenario, world, runs = small
    spec = VARIANTS["anfekf-RQ"]
    ctx = ctx_of(spec, scenario, world)
    ref, out = both(spec, ctx, runs[0], world, record_every)
    assert len(out["x"]) == len(runs[0].u_odo) // record_every
    assert_same_run(ref, out)


def test_record_none_keeps_the_counts(small):
    scenario, world, runs = small
    spec = VARIANTS["anfekf-RQ"]
    ctx = ctx_of(spec, scenario, world)
    ref, _ = both(spec, ctx, runs[0], world, 1)
    out = fast.run_filter_fast(spec, ctx, runs[0], world, 0)
    assert out["x"].shape == (0, 3) and out["P"].shape == (0, 3, 3)
    assert (out["n_updates"], out["n_rejected"], out["diverged"]) == (
        ref["n_updates"], ref["n_rejected"], ref["diverged"],
    )  # fmt: skip


@pytest.mark.parametrize("name", ["ekf", "anfekf-R", "anfekf-RQ"])
def test_small_world_pure_python_kernels(small, name):
    """What runs without numba: the same kernels as plain Python."""
    scenario, world, runs = small
    spec = VARIANTS[name]
    ctx = ctx_of(spec, scenario, world)
    ref, out = both(spec, ctx, runs[0], world, 1, jit=False)
    assert_same_run(ref, out, what=name)
    jit = fast.run_filter_fast(spec, ctx, runs[0], world, 1)
    assert_same_run(jit, out, tol=1e-12, what=name)


# ---------------------------------------------------------------------------------------------
# Divergence: the same health checks, the same records NaN


def _diverging(small, **ctx_changes):
    scenario, world, runs = small
    spec = VARIANTS["anfekf-RQ"]
    ctx = dataclasses.replace(ctx_of(spec, scenario, world), **ctx_changes)
    return spec, ctx, world, runs[0]


@pytest.mark.parametrize(
    "changes",
    [
        pytest.param({"Qu": np.diag([-0.09, 0.003])}, id="Qu-not-positive"),
        pytest.param({"P0": -np.eye(3)}, id="P-not-positive-definite"),
        pytest.param({"x0": np.array([np.nan, 0.0, 0.0])}, id="NIS-not-finite"),
        pytest.param({"P0": np.zeros((3, 3)), "Qu": np.zeros((2, 2)), "R": np.zeros((2, 2))},
                     id="singular-S"),
    ],
)  # fmt: skip
@pytest.mark.parametrize("mode", ["jit", "pure"])
def test_forced_divergence(small, changes, mode):
    spec, ctx, world, data = _diverging(small, **changes)
    first = next(s.step for s in data.scans if len(s.ids))  # the first scan with a landmark
    for s in (spec, VARIANTS["ekf"]):
        ref, out = both(s, ctx, data, world, 1, jit=mode == "jit")
        assert ref["diverged"] and out["diverged"]
        assert np.isnan(ref["x"][first - 1 :]).all()  # from the failed scan on
        assert_same_run(ref, out, what=str(changes))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("what", ["odometry", "measurement"])
@pytest.mark.parametrize("name", ["ekf", "anfekf-R", "anfekf-RQ"])
def test_divergence_in_mid_run(small, what, name):
    """A healthy run that meets a corrupted sample half-way: diverged at the same landmark of
    the same scan, the same counts, its records NaN from there on."""
    scenario, world, runs = small
    data = runs[0]
    spec = VARIANTS[name]
    ctx = ctx_of(spec, scenario, world)
    data, bad = corrupted_half_way(data, what)
    ref, out = both(spec, ctx, data, world, 1)
    assert ref["diverged"] and ref["n_updates"] > 10
    assert np.isnan(ref["x"][bad.step - 1 :]).all() and np.isfinite(ref["x"][: bad.step - 5]).all()
    assert_same_run(ref, out, what=f"{name}, {what}")


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_blow_up_after_the_last_scan_is_caught_by_the_final_check(small):
    """No scan saw a landmark, so no health check ran: the records show the blow-up."""
    scenario, world, runs = small
    data = runs[0]
    empty = tuple(Scan(step=s.step, ids=s.ids[:0], z=s.z[:0]) for s in data.scans)
    data = RunData(truth=data.truth, u_odo=data.u_odo, scans=empty)
    spec = VARIANTS["ekf"]
    ctx = dataclasses.replace(ctx_of(spec, scenario, world), P0=np.eye(3) * 1e308)
    ref, out = both(spec, ctx, data, world, 1)
    assert ref["diverged"] and out["diverged"]
    assert (out["n_updates"], out["n_rejected"]) == (0, 0)
    # Both keep the records (the check runs after the loop); before overflow they agree.
    ok = np.isfinite(ref["P"]).all(axis=(1, 2))
    assert ok[0] and not ok[-1]
    np.testing.assert_array_equal(np.isfinite(out["P"]).all(axis=(1, 2)), ok)
    np.testing.assert_allclose(out["P"][ok], ref["P"][ok], rtol=TOL)


# ---------------------------------------------------------------------------------------------
# The four paper scenarios


def _paper_runs(name: str, runs: int, extra: tuple[FilterSpec, ...] = ()):
    scenario, world = load_scenario(CONFIGS / f"{name}.yaml")
    names = {f.name for f in scenario.filters}
    specs = list(scenario.filters) + [s for s in extra if s.name not in names]
    for i, seed in enumerate(np.random.SeedSequence(scenario.seed).spawn(scenario.runs)[:runs]):
        data = simulate(scenario, world, seed)
        for spec in specs:
            yield i, spec, scenario, world, data


def _check_paper(name: str, runs: int, extra: tuple[FilterSpec, ...] = ()) -> dict:
    worst: dict[str, float] = {}
    for i, spec, scenario, world, data in _paper_runs(name, runs, extra):
        ctx = ctx_of(spec, scenario, world)
        ref, out = both(spec, ctx, data, world, scenario.record_every)
        errs = assert_same_run(ref, out, what=f"{name} run {i} {spec.name}")
        for key, e in errs.items():
            worst[key] = max(worst.get(key, 0.0), e)
    return worst


PAPER_VARIANTS = ("anfekf-R", "anfekf-Q", "anfekf-RQ", "from-accepted")


@pytest.mark.parametrize("name", PAPER)
def test_paper_scenario(name):
    """Run 0 of each paper scenario, its own filters plus the ANFEKF's variants (adapting R, Q,
    both; learning from accepted measurements only)."""
    _check_paper(name, 1, extra=tuple(VARIANTS[k] for k in PAPER_VARIANTS))


# Runs differ only in their draws: `make test` checks run 0 of each paper scenario (above),
# `make test-all` (heavy) 10 runs.
@pytest.mark.slow
@pytest.mark.heavy
@pytest.mark.parametrize("name", PAPER)
def test_paper_scenario_many_runs(name):
    _check_paper(name, 10, extra=tuple(VARIANTS[k] for k in PAPER_VARIANTS))


@pytest.mark.slow
@pytest.mark.parametrize("name", PAPER)
def test_paper_scenario_pure_python(name):
    for i, spec, scenario, world, data in _paper_runs(name, 1):
        ctx = ctx_of(spec, scenario, world)
        ref, out = both(spec, ctx, data, world, scenario.record_every, jit=False)
        assert_same_run(ref, out, what=f"{name} run {i} {spec.name}")


def test_make_setup_compiles_a_kernel_of_every_fast_kind():
    """`make setup`'s warm-up runs one filter of every kernel (and of every family module on the
    one loop, each a loop of its own): a kind it leaves out runs its family's loop or shares
    the kernel of one it runs, so the first run after an install compiles nothing."""
    from anfekf_bench.engines.fast_support import SUPPORTED_SPECS
    from anfekf_bench.filters.spec import fast_family_of

    specs = fast.warm_up_specs()
    warmed = {type(spec) for spec in specs}
    families = {fast_family_of(spec) for spec in specs} - {None}
    for cls in SUPPORTED_SPECS:
        # a subclass of a warmed kind with a kernel of its own runs that kernel (the fitted
        # ekf-aug-calibrated: ekf-aug's)
        shares = any(issubclass(cls, w) for w in warmed if fast_family_of(w) is None)
        assert cls in warmed or shares or fast_family_of(cls) in families, cls.__name__
    assert len(warmed) == len(specs)  # one of each
    # one per family module: every module of engines/families is warmed
    modules = {p.stem for p in (Path(fast.__file__).parent / "families").glob("[!_]*.py")}
    assert families == modules


def test_every_kernel_a_spec_names_has_its_runner_and_no_kind_names_two_ways():
    """A kind on the fast engine names its family module on the one loop (`fast_family`) or its
    kernel of its own (`fast_kernel`), never both; every kernel named is in KERNEL_RUNNERS, and
    every runner there serves a registered kind."""
    from anfekf_bench.filters.registry import SPECS
    from anfekf_bench.filters.spec import fast_family_of, fast_kernel_of

    named = {fast_kernel_of(cls) for cls in SPECS} - {None}
    assert named == set(fast.KERNEL_RUNNERS)
    for cls in SPECS:
        assert fast_family_of(cls) is None or fast_kernel_of(cls) is None, cls.__name__
        assert fast.supports(cls.model_construct()) == (cls in fast.SUPPORTED_SPECS)


def test_the_warm_up_parts_are_the_whole_warm_up_split_by_the_loop():
    """`make setup` compiles the parts side by side: every family's loop in "loop", every
    other kernel in "kernels"."""
    from anfekf_bench.filters.spec import fast_family_of

    whole = [type(s) for s in fast.warm_up_specs()]
    loop, kernels = (tuple(type(s) for s in fast.warm_up_specs(p)) for p in fast.WARM_UP_PARTS)
    assert sorted(map(str, loop + kernels)) == sorted(map(str, whole))
    assert loop and all(fast_family_of(c) is not None for c in loop)
    assert kernels and all(fast_family_of(c) is None for c in kernels)


def test_serialised_cache_writes_keep_every_processs_entries(tmp_path, monkeypatch):
    """Two warm-up parts may compile one callee for different signatures at once: numba reads a
    function's cache index, adds its entry and writes it back, and numbers the data file by what
    it read. With the writes serialised, every entry survives with its own data (without, the
    threads below all read an empty index: one entry is left, its data another's)."""
    import threading
    import time

    caching = pytest.importorskip("numba.core.caching")
    monkeypatch.setattr(caching.IndexDataCacheFile, "save", caching.IndexDataCacheFile.save)
    assert fast.serialise_cache_writes() and fast.serialise_cache_writes()  # idempotent
    cache = caching.IndexDataCacheFile(str(tmp_path), "kernels.record-1.py311", ("stamp", 1))
    read_index = cache._load_index

    def slow_read():
        index = read_index()
        time.sleep(0.05)  # the window in which another process reads the same index
        return index

    monkeypatch.setattr(cache, "_load_index", slow_read)
    threads = [threading.Thread(target=cache.save, args=(f"sig{i}", i)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert {cache.load(f"sig{i}") for i in range(6)} == set(range(6))
