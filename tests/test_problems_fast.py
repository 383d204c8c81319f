"""The fast engine of problem scenarios (SPEC 17, SPEC 11): every supported (kind, problem)
pair's compiled loop against the Python filters (the reference) to 1e-9, on the same truth and
measurements; the gate (tracking) drops the same measurements on both engines; a problem whose
functions do not compile is a one-line error; the same seed gives the same tables on the fast
engine whatever the workers.

The pairs come from the registry (`supports_problem`) and `schema.PROBLEMS`: a problem added
there joins the test with its default system, or with the keys `PROBLEM_KEYS` gives it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError
from anfekf_bench.filters.registry import supports_problem
from anfekf_bench.problems.als import ALSSpec
from anfekf_bench.problems.experiment import TABLES, read_problem_result, run_one
from anfekf_bench.problems.filters import EKFSpec, SageHusaSpec, VBRSpec
from anfekf_bench.problems.forms import PROBLEM_KINDS
from anfekf_bench.problems.linear import survey_problem
from anfekf_bench.problems.schema import PROBLEMS, parse_problem_scenario

from .conftest import write_scenario

pytest.importorskip("numba")

runner = CliRunner()
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "custom_problem"
STEPS = 150

# What a problem's scenario needs beyond its defaults (the module problem: the example's file).
PROBLEM_KEYS = {
    "linear": {"system": {"steps": STEPS}},
    "tracking": {"system": {"steps": STEPS}},
    "module": {"module": {"file": "pendulum.py", "steps": STEPS}},
}
# Each kind once with its defaults, plus the variants that take other branches of its loop.
KIND_VARIANTS = {
    "sage-husa": [{"adapt": "RQ"}, {"adapt": "R", "b": 0.97, "warmup": 20}],
    "vb-r": [{}, {"rho": 0.98, "iterations": 2}],
    "als": [{"min_steps": 30, "burn": 5, "every": 7}],
    "ekf-ml": [{"fit_on": "run", "maxiter": 1}],
}


def pairs():
    for problem in PROBLEMS:
        for kind in PROBLEM_KINDS:
            if supports_problem(kind, problem):
                for i, extra in enumerate(KIND_VARIANTS.get(kind, [{}])):
                    yield pytest.param(problem, kind, extra, id=f"{problem}-{kind}-{i}")


def scenario_of(problem: str, filters: list[dict], engine: str = "filterpy"):
    doc = {"name": "eq", "problem": problem, "seed": 11, "runs": 1, "engine": engine,
           "filters": filters, **PROBLEM_KEYS.get(problem, {})}  # fmt: skip
    return parse_problem_scenario(doc, EXAMPLE / "scenario.yaml")


def with_assumed_noise(scenario, factor_q: float, factor_r: float):
    problem = scenario.build_problem()
    noise = {"Q": (factor_q * problem.Q).tolist(), "R": (factor_r * problem.R).tolist()}
    doc = scenario.model_dump(mode="json", exclude_unset=True)
    doc["filter_noise"] = noise
    return parse_problem_scenario(doc, EXAMPLE / "scenario.yaml")


@pytest.mark.parametrize("problem, kind, extra", list(pairs()))
def test_the_compiled_loop_equals_the_python_filter(problem, kind, extra):
    filters = [{"name": "a", "kind": kind, **extra}]
    try:
        base = scenario_of(problem, filters)
    except ScenarioError as exc:  # a kind the problem's instance cannot run (ALS: nonlinear)
        pytest.skip(str(exc))
    # Wrong assumed noise, so that every adaptive family moves its estimate.
    python = with_assumed_noise(base, 0.2, 3.0)
    py, fa = both_engines(python)
    spec = python.filters[0]
    if "R" in spec.estimated() and not spec.fits_on_training():  # moved: the test can fail
        assert not np.allclose(fa.R[-1], 3.0 * python.build_problem().R)


def both_engines(python, seed: int = 11, run: int = 0):
    """The first filter's traces of run `run` on filterpy and on fast, checked equal (1e-9;
    the same measurements dropped by the gate)."""
    fast = python.model_copy(update={"engine": "fast"})
    x_py, traces_py = run_one(python, seed, run, {})
    x_fast, traces_fast = run_one(fast, seed, run, {})
    assert np.array_equal(x_py, x_fast)  # the same truth and measurements on both engines
    name = python.filters[0].name
    py, fa = traces_py[name], traces_fast[name]
    assert np.all(np.isfinite(fa.x))
    for key in ("x", "P", "Q", "R"):
        want, got = getattr(py, key), getattr(fa, key)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9, err_msg=key)
    assert fa.gated == py.gated
    return py, fa


def gated_pairs():
    for kind in PROBLEM_KINDS:
        if supports_problem(kind, "tracking"):
            for i, extra in enumerate(KIND_VARIANTS.get(kind, [{}])):
                yield pytest.param(kind, extra, id=f"{kind}-{i}")


def tracking_scenario(kind: str, extra: dict, manoeuvre: dict, gate: float | None = 0.999):
    system = {"steps": STEPS, "manoeuvre": manoeuvre, "gate": gate}
    doc = {"name": "eq", "problem": "tracking", "seed": 11, "runs": 1, "system": system,
           "filters": [{"name": "a", "kind": kind, **extra}]}  # fmt: skip
    return with_assumed_noise(parse_problem_scenario(doc, EXAMPLE / "scenario.yaml"), 0.1, 1.0)


@pytest.mark.parametrize("kind, extra", list(gated_pairs()))
def test_the_gate_drops_the_same_measurements_on_both_engines(kind, extra):
    """A turn the filters are not told of, q assumed 10x too small: the radar's gate drops part
    of the measurements (counted), the same ones on both engines; without the gate the same
    filter gives another estimate (so a gate the loops ignored would fail here)."""
    turn = {"omega": 0.05, "start": 60, "end": 100}
    py, fa = both_engines(tracking_scenario(kind, extra, turn))
    assert 0 < fa.gated < STEPS
    _, fa_all = both_engines(tracking_scenario(kind, extra, turn, gate=None))
    assert fa_all.gated == 0
    assert not np.allclose(fa_all.x, fa.x)


@pytest.mark.parametrize("kind", ["ekf", "sage-husa"])
def test_a_known_turn_is_compiled_as_the_python_model(kind):
    """Filters told of the turn: their transition is the coordinated turn over its steps."""
    known = {"omega": 0.05, "start": 60, "end": 100, "known": True}
    _, fa = both_engines(tracking_scenario(kind, {}, known))
    _, fa_unknown = both_engines(tracking_scenario(kind, {}, {**known, "known": False}))
    assert fa.gated < fa_unknown.gated


@pytest.mark.parametrize(
    "spec",
    [
        pytest.param(SageHusaSpec(name="s", kind="sage-husa"), id="sage-husa"),
        pytest.param(VBRSpec(name="v", kind="vb-r", iterations=2), id="vb-r"),
        pytest.param(ALSSpec(name="a", kind="als", min_steps=30, burn=5, every=7), id="als"),
        pytest.param(EKFSpec(name="e", kind="ekf"), id="ekf"),
    ],
)
def test_every_compiled_loop_gates_as_the_python_filter(spec):
    """The gate in each loop, ALS's included (no registry problem gates a linear system: the
    gate is set on the survey's system here), against the Python filter: the same measurements
    dropped (not used, nor adapted on: the predictor of ALS skips them too)."""
    problem = survey_problem(STEPS)
    problem.gate = 2.0  # the chi-square(2) quantile of 0.63: about a third dropped
    z = problem.simulate(np.random.default_rng(5)).z
    Q, R = 0.3 * problem.Q, 2.0 * problem.R
    python = spec.build(problem, Q, R).run(z)
    flt = spec.build(problem, Q, R)
    flt.model = problem.compiled_model()
    fast = flt.run(z)
    assert 0 < python.gated < STEPS and fast.gated == python.gated
    for key in ("x", "P", "Q", "R"):
        np.testing.assert_allclose(getattr(fast, key), getattr(python, key), rtol=1e-9,
                                   atol=1e-9, err_msg=key)  # fmt: skip


@pytest.mark.slow
def test_a_problem_whose_functions_do_not_compile_is_one_line_with_exit_2(tmp_path):
    text = (EXAMPLE / "pendulum.py").read_text(encoding="utf-8")
    # A Python dictionary inside h: fine as Python, not in numba's nopython mode.
    good = "    return np.array([x[0], p[2] * np.sin(x[0])])"
    bad = "    table = {'a': object()}\n    return np.array([x[0], 0 * len(table)])"
    text = text.replace(good, bad)
    (tmp_path / "pendulum.py").write_text(text, encoding="utf-8")
    doc = {"name": "nc", "problem": "module", "module": {"file": "pendulum.py", "steps": 20},
           "runs": 1, "filters": [{"name": "kf", "kind": "ekf"}]}  # fmt: skip
    path = write_scenario(tmp_path / "scenario.yaml", doc)
    python = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "a")])
    assert python.exit_code == 0, python.output
    fast = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "b"), "--engine", "fast"])
    assert fast.exit_code == 2, fast.output
    assert "engine fast" in fast.output and "h does not compile with numba" in fast.output
    assert "pendulum.py" in fast.output and "Traceback" not in fast.output


@pytest.mark.slow  # a new module: its five functions compile (about 10 s)
def test_als_on_a_linear_module_compiled_equals_python(tmp_path):
    from .test_problems_custom import SURVEY_MODULE

    (tmp_path / "survey.py").write_text(SURVEY_MODULE, encoding="utf-8")
    als = {"name": "a", "kind": "als", "min_steps": 30, "burn": 5, "every": 7}
    doc = {"name": "als", "problem": "module", "module": {"file": "survey.py", "steps": STEPS},
           "filters": [als]}  # fmt: skip
    python = parse_problem_scenario(doc, tmp_path / "scenario.yaml")
    fast = python.model_copy(update={"engine": "fast"})
    py, fa = run_one(python, 2, 0, {})[1]["a"], run_one(fast, 2, 0, {})[1]["a"]
    for key in ("x", "P", "Q", "R"):
        np.testing.assert_allclose(getattr(fa, key), getattr(py, key), rtol=1e-9, atol=1e-9)
    assert not np.allclose(fa.Q[-1], np.eye(2))  # identified


@pytest.mark.slow
def test_the_example_on_the_fast_engine_same_bytes_whatever_the_workers(tmp_path):
    """Same seed, same tables (timing aside) on the fast engine with 1 or 2 workers; the same
    numbers as the Python engine to 1e-9 (bytes differ: the loops round differently)."""
    outs = {}
    for engine, jobs in (("fast", "1"), ("fast", "2"), ("filterpy", "1")):
        out = tmp_path / f"{engine}{jobs}"
        args = ["--runs", "3", "--jobs", jobs, "--engine", engine, "--out", str(out)]
        result = runner.invoke(app, ["run", str(EXAMPLE / "scenario.yaml"), *args])
        assert result.exit_code == 0, result.output
        outs[engine + jobs] = out / "custom_problem_example"
    for key, file in TABLES.items():
        if key != "timing":
            assert (outs["fast1"] / file).read_bytes() == (outs["fast2"] / file).read_bytes()
    fast, python = read_problem_result(outs["fast1"]), read_problem_result(outs["filterpy1"])
    assert fast["manifest"]["engine"] == "fast" and python["manifest"]["engine"] == "filterpy"
    cols = ["rmse_pos", "rmse_rest", "anees", "r_rel_err"]
    np.testing.assert_allclose(fast["runs"][cols].to_numpy(), python["runs"][cols].to_numpy(),
                               rtol=1e-9, atol=1e-12)  # fmt: skip
