"""A user's own problem (SPEC 17, docs/CUSTOM_PROBLEMS.md): a Python file the scenario names.

Checked against independent references: the survey's linear system written as a module gives
the built-in linear problem's numbers (to rounding); the example pendulum's Jacobians match finite
differences. Every bad input is a one-line error naming the file and the field, exit code 2."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError
from anfekf_bench.problems.experiment import run_one
from anfekf_bench.problems.linear import survey_problem
from anfekf_bench.problems.module import ModuleProblem, ModuleProblemError
from anfekf_bench.problems.schema import parse_problem_scenario

from .conftest import write_scenario

runner = CliRunner()
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "custom_problem"

# The survey's system (problems.linear) as a user would write it: a reference for the loader.
SURVEY_MODULE = """
import numpy as np

Fm = np.array([[0.9, 0.0], [-0.3, 0.8]])
Q = np.array([[2.0, -0.5], [-0.5, 1.0]])
R = np.array([[3.0, 0.0], [0.0, 2.0]])
x0 = np.zeros(2)
P0 = np.eye(2)
steps = 1001
linear = True


def f(x, k, p):
    return Fm @ x


def F(x, k, p):
    return Fm.copy()


def G(x, k, p):
    return np.eye(2)


def h(x, k, p):
    return x.copy()


def H(x, k, p):
    return np.eye(2)
"""

FILTERS = [
    {"name": "kf", "kind": "ekf"},
    {"name": "oracle", "kind": "ekf-oracle"},
    {"name": "cm", "kind": "sage-husa"},
    {"name": "vb", "kind": "vb-r"},
]


def scenario_doc(file: str = "model.py", **more) -> dict:
    return {"name": "mine", "problem": "module", "module": {"file": file, **more}, "runs": 2,
            "seed": 3, "filters": FILTERS}  # fmt: skip


def write_module(folder: Path, text: str, name: str = "model.py") -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def parse(folder: Path, doc: dict):
    return parse_problem_scenario(doc, folder / "scenario.yaml")


def test_the_survey_as_a_module_is_the_linear_problem_exactly(tmp_path):
    write_module(tmp_path, SURVEY_MODULE)
    doc = scenario_doc(steps=200)
    doc["filters"] = FILTERS + [{"name": "als", "kind": "als", "min_steps": 30, "burn": 5}]
    mine = parse(tmp_path, doc)
    reference = parse(tmp_path, {**doc, "problem": "linear", "module": None,
                                 "system": {"steps": 200}})  # fmt: skip
    x_a, traces_a = run_one(mine, 3, 0, {})
    x_b, traces_b = run_one(reference, 3, 0, {})
    # The linear problem simulates with a compiled recursion: equal to rounding, not bytes.
    np.testing.assert_allclose(x_a, x_b, rtol=0, atol=1e-11)
    for name, trace in traces_a.items():
        other = traces_b[name]
        for key in ("x", "P", "Q", "R"):
            np.testing.assert_allclose(getattr(trace, key), getattr(other, key), rtol=0,
                                       atol=1e-9, err_msg=f"{name} {key}")  # fmt: skip
    assert mine.build_problem().linear and np.array_equal(mine.build_problem().Fm,
                                                          survey_problem().Fm)  # fmt: skip


def test_the_example_pendulums_jacobians_are_its_functions_derivatives():
    problem = ModuleProblem(EXAMPLE / "pendulum.py")
    rng = np.random.default_rng(0)
    for _ in range(5):
        x, eps = rng.normal(size=2), 1e-6
        for fn, jac in ((problem.f, problem.F), (problem.h, problem.H)):
            numeric = np.stack([(fn(x + eps * e, 0) - fn(x - eps * e, 0)) / (2 * eps)
                                for e in np.eye(2)], axis=1)  # fmt: skip
            assert np.allclose(jac(x, 0), numeric, atol=1e-7)
    assert (problem.n, problem.nw, problem.nz, problem.angles) == (2, 1, 2, (0,))


def test_the_example_scenario_parses_and_its_params_and_steps_override(tmp_path):
    scenario = parse(EXAMPLE, {**scenario_doc("pendulum.py", params=[0.05, 9.81, 2.0, 0.1],
                                              steps=50)})  # fmt: skip
    problem = scenario.build_problem()
    assert problem.steps == 50 and problem.params[2] == 2.0
    assert problem.simulate(np.random.default_rng(1)).z.shape == (50, 2)


@pytest.mark.parametrize(
    "text, field, words",
    [
        (SURVEY_MODULE.replace("def H(", "def H_("), "module.file", "does not define H"),
        (SURVEY_MODULE.replace("return np.eye(2)\n\n\ndef h", "return np.eye(3)\n\n\ndef h"),
         "module.file", "G(x0, 0, params): expected shape (2, 2), got (3, 3)"),
        (SURVEY_MODULE.replace("return x.copy()", "return 1 / 0"), "module.file",
         "h(x0, 0, params) raised ZeroDivisionError"),
        (SURVEY_MODULE.replace("import numpy as np", "import numpy as np\nimport nothing_here"),
         "module.file", "importing it raised ModuleNotFoundError"),
        (SURVEY_MODULE.replace("[3.0, 0.0], [0.0, 2.0]", "[3.0, 1.0], [0.0, 2.0]"),
         "module.file", "R: a covariance must be symmetric"),
        (SURVEY_MODULE.replace("x0 = np.zeros(2)", "x0 = np.zeros(3)"), "module.file",
         "P0: expected 3 x 3"),
        (SURVEY_MODULE + "\nposition_unit = 'm\\x1b'\n", "module.file",
         "position_unit: expected a short unit name"),
    ],
)  # fmt: skip
def test_a_bad_module_is_a_one_line_error_naming_file_and_field(tmp_path, text, field, words):
    write_module(tmp_path, text)
    with pytest.raises(ScenarioError) as exc:
        parse(tmp_path, scenario_doc())
    message = str(exc.value)
    assert exc.value.field == field and words in message and "model.py" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    "file, words",
    [
        ("missing.py", "no such file"),
        ("../model.py", "outside the scenario file's folder"),
        ("/etc/model.py", "relative to the scenario file's folder"),
        ("model.txt", "expected a Python file"),
    ],
)
def test_a_module_path_must_be_a_python_file_inside_the_scenarios_folder(tmp_path, file, words):
    folder = tmp_path / "scenarios"
    folder.mkdir()
    write_module(tmp_path, SURVEY_MODULE)  # beside the folder, not in it
    with pytest.raises(ScenarioError) as exc:
        parse(folder, scenario_doc(file))
    assert exc.value.field == "module.file" and words in str(exc.value)


def test_a_modules_position_unit_is_its_own_or_none(tmp_path):
    write_module(tmp_path, SURVEY_MODULE)
    assert ModuleProblem(tmp_path / "model.py").position_unit == ""
    write_module(tmp_path, SURVEY_MODULE + "\nposition_unit = 'rad'\n")
    assert ModuleProblem(tmp_path / "model.py").position_unit == "rad"


def test_a_module_below_the_scenarios_folder_is_accepted(tmp_path):
    (tmp_path / "models").mkdir()
    write_module(tmp_path / "models", SURVEY_MODULE)
    assert parse(tmp_path, scenario_doc("models/model.py")).build_problem().n == 2


def test_params_of_the_wrong_length_and_misplaced_keys_are_refused(tmp_path):
    write_module(tmp_path, SURVEY_MODULE)
    with pytest.raises(ScenarioError, match="params: expected 0 values"):
        parse(tmp_path, scenario_doc(params=[1.0]))
    with pytest.raises(ScenarioError, match="problem: module names its file"):
        parse(tmp_path, {**scenario_doc(), "module": None})
    with pytest.raises(ScenarioError, match="a module defines its own system"):
        parse(tmp_path, {**scenario_doc(), "system": {"steps": 50}})
    with pytest.raises(ScenarioError, match="ALS needs a linear"):
        shutil.copy(EXAMPLE / "pendulum.py", tmp_path / "pendulum.py")
        parse(tmp_path, {**scenario_doc("pendulum.py"),
                         "filters": [{"name": "als", "kind": "als"}]})  # fmt: skip


def test_a_module_failing_during_a_run_is_one_line_with_exit_2(tmp_path):
    # f raises from step 5 on: the check at x0 passes, the run does not.
    text = SURVEY_MODULE.replace("    return Fm @ x", "    if k >= 5:\n        raise"
                                 " ValueError('diverged')\n    return Fm @ x")  # fmt: skip
    write_module(tmp_path, text)
    path = write_scenario(tmp_path / "scenario.yaml", scenario_doc(steps=20))
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    assert "f(x, 5, params) raised ValueError: diverged" in result.output
    assert "Traceback" not in result.output and "model.py" in result.output


def test_the_example_runs_through_the_command_line(tmp_path):
    result = runner.invoke(app, ["run", str(EXAMPLE / "scenario.yaml"), "--runs", "2",
                                 "--out", str(tmp_path)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "problem module, running on filterpy" in result.output
    assert "RMSE / oracle" in result.output


def test_a_function_raising_at_load_says_which_and_the_error_type():
    with pytest.raises(ModuleProblemError, match="cannot read it"):
        ModuleProblem(Path("/nonexistent/model.py"))
