"""The regression gate (`anfekf check`) on problem results (SPEC 17; problems.gate): they join
the robot's scenarios with the metrics they share (rmse_pos, anees against the state
dimension, nees_in_bounds), alone or beside robot results, through --update and comparisons."""

from __future__ import annotations

import json

from anfekf_bench import api
from anfekf_bench.analysis.gate import Tolerance, judge

from .test_api_problems import LINEAR
from .test_check import check, paper_like, write_results


def test_a_problem_result_alone_makes_a_baseline_that_then_passes_and_guards(tmp_path):
    api.run(LINEAR, out=tmp_path / "res")
    baseline = tmp_path / "ci.json"
    made = check(tmp_path / "res", "--baseline", baseline, "--update")
    assert made.exit_code == 0, made.output
    doc = json.loads(baseline.read_text())
    lin = doc["scenarios"]["lin"]
    assert lin["problem"] == "linear" and lin["anees_ideal"] == 2.0  # the state dimension
    assert lin["seed"] == 3 and lin["runs"] == 2
    assert set(lin["filters"]["sh"]) == {"rmse_pos", "anees", "nees_in_bounds"}
    passed = check(tmp_path / "res", "--baseline", baseline)
    assert passed.exit_code == 0, passed.output
    assert "9 metrics within tolerance" in passed.output  # 3 filters x 3 metrics
    lin["filters"]["sh"]["rmse_pos"] *= 0.9  # the results are now 11 % worse than this
    baseline.write_text(json.dumps(doc), encoding="utf-8")
    worse = check(tmp_path / "res", "--baseline", baseline)
    assert worse.exit_code == 1
    # the linear system has no unit: its RMSE is shown without one (the robot's is in m)
    assert "FAIL lin / sh / rmse_pos: " in worse.output and ": worse" in worse.output
    assert "rmse_pos [m]" not in worse.output


def test_the_gate_shows_rmse_pos_in_the_problems_unit():
    from anfekf_bench.analysis.gate import Baseline, ScenarioSummary, compare, shown_metric
    from anfekf_bench.problems.linear import survey_problem
    from anfekf_bench.problems.tracking import TrackingProblem

    assert TrackingProblem.position_unit == "m" and survey_problem().position_unit == ""
    assert shown_metric("rmse_pos") == "rmse_pos [m]"  # the robot's
    assert shown_metric("rmse_pos", {"rmse_pos": ""}) == "rmse_pos"
    assert shown_metric("rmse_heading", {"rmse_pos": "m"}) == "rmse_heading [deg]"
    metrics = {"f": {"rmse_pos": 1.0}}
    tolerances = {"rmse_pos": Tolerance("relative", 0.05)}
    for unit, shown in (("", "rmse_pos"), ("m", "rmse_pos [m]"), ("rad", "rmse_pos [rad]")):
        base = ScenarioSummary("p", 1, 2, metrics, problem="module")
        now = ScenarioSummary("p", 1, 2, {"f": {"rmse_pos": 2.0}}, problem="module",
                              units={"rmse_pos": unit})  # fmt: skip
        (row,) = [r for r in compare(Baseline(tolerances, {"p": base}), {"p": now})
                  if r.metric == "rmse_pos"]  # fmt: skip
        assert row.shown == shown and row.detail.startswith(f"p / f / {shown}: 1 -> 2")


def test_a_problems_anees_is_judged_against_its_state_dimension():
    tolerance = Tolerance("relative", 0.05)
    assert judge("anees", tolerance, 2.5, 2.1, sense=2.0) == "better (refresh the baseline)"
    assert judge("anees", tolerance, 2.5, 2.1) == "worse"  # the robot's: closer to 3


def test_problem_results_beside_robot_results(tmp_path):
    results = write_results(tmp_path / "res", paper_like())
    api.run(LINEAR, out=results)
    baseline = tmp_path / "ci.json"
    assert check(results, "--baseline", baseline, "--update").exit_code == 0
    doc = json.loads(baseline.read_text())
    assert "problem" not in doc["scenarios"]["wrong_r"]  # the robot's entries as before
    assert doc["scenarios"]["lin"]["problem"] == "linear"
    passed = check(results, "--baseline", baseline)
    assert passed.exit_code == 0, passed.output
    assert "69 metrics within tolerance, 4 claims hold" in passed.output  # 60 robot + 9
    (results / "lin" / "manifest.json").unlink()  # no longer a complete problem result
    missing = check(results, "--baseline", baseline)
    assert missing.exit_code == 1 and "scenario lin: in the baseline but not" in missing.output


def test_a_damaged_problem_result_is_one_line_with_exit_2(tmp_path):
    api.run(LINEAR, out=tmp_path)
    manifest = tmp_path / "lin" / "manifest.json"
    doc = json.loads(manifest.read_text())
    doc["scenario"]["name"] = "lin\x1b[31m"  # escape sequences: never printed in the tables
    manifest.write_text(json.dumps(doc), encoding="utf-8")
    done = check(tmp_path)
    assert done.exit_code == 2 and "Traceback" not in done.output
    assert "not a problem result as `anfekf run` writes it" in done.output
    assert "\x1b" not in done.output
    doc["scenario"]["name"] = "lin"
    doc["position_unit"] = "m\x1b[31m"  # printed in the gate's metric column
    manifest.write_text(json.dumps(doc), encoding="utf-8")
    done = check(tmp_path)
    assert done.exit_code == 2 and "position_unit" in done.output and "\x1b" not in done.output
