"""Naive starts (`starts`) in simulated scenarios: each filter once per multiplier of its assumed
noise's standard deviations, the same instance naming and the same meaning as recorded logs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.cli import app
from anfekf_bench.config import ScenarioError, parse_scenario, resolve_world
from anfekf_bench.filters.context import recorded_context
from anfekf_bench.filters.registry import instance_names
from anfekf_bench.runner import simulated_run
from anfekf_bench.sources.recorded import parse_real_scenario

from .conftest import small_scenario, write_scenario

runner = CliRunner()
CLAIM = {"filter": "anfekf", "vs": "ekf x2", "metric": "rmse_pos", "at_most": 1}
ARRAYS = ("x", "P", "R_diag", "Q_diag", "pos_err", "nees")
ZOO = [
    {"name": "ekf", "kind": "ekf"},
    {"name": "sh", "kind": "sage-husa", "adapt": "R"},
    {"name": "imm", "kind": "imm"},
    {"name": "ekf-oracle", "kind": "ekf-oracle"},
]


def _run(doc: dict, engine: str = "filterpy", run: int = 0) -> dict:
    scenario = parse_scenario(doc)
    world = resolve_world(scenario.world, Path("small.yaml"))
    seed = np.random.SeedSequence(scenario.seed).spawn(run + 1)[run]
    return simulated_run(scenario, world, run, seed, engine=engine)["filters"]


def _same(a: dict, b: dict) -> None:
    for key in ARRAYS:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    for key in ("n_updates", "n_rejected", "diverged"):
        assert a[key] == b[key], key


def test_instances_are_named_as_on_recorded_logs_and_the_oracle_runs_once():
    sc = parse_scenario(small_scenario(filters=ZOO, starts=[0.25, 1, 4]))
    assert sc.instance_names() == [
        "ekf x0.25", "ekf x1", "ekf x4", "sh x0.25", "sh x1", "sh x4",
        "imm x0.25", "imm x1", "imm x4", "ekf-oracle",
    ]  # fmt: skip
    assert [m for _, _, m in sc.instances()] == [0.25, 1.0, 4.0] * 3 + [None]
    # No starts: every filter once under its own name (what every existing scenario does).
    assert parse_scenario(small_scenario(filters=ZOO)).instance_names() == [f["name"] for f in ZOO]
    # One expansion for both kinds of scenario.
    real = {"name": "r", "data": {"kind": "log", "path": "x"}, "filters": [{"name": "ekf",
            "kind": "ekf"}, {"name": "t", "kind": "ekf-tuned"}], "starts": [0.5, 2]}  # fmt: skip
    assert parse_real_scenario(real).instance_names() == instance_names(
        parse_real_scenario(real).filters, [0.5, 2]
    )


@pytest.mark.parametrize("engine", ["filterpy", "fast"])
def test_an_instance_is_its_filter_with_every_sigma_scaled_by_hand(engine):
    m = 4.0
    noise = {"sigma_v": 0.3, "sigma_gamma_deg": 3.0, "sigma_range": 2.0, "sigma_bearing_deg": 0.1}
    scaled = {k: v * m for k, v in noise.items()}
    filters = ZOO[:3] if engine == "fast" else ZOO[:2]  # a bank on filterpy takes seconds
    started = _run(small_scenario(filters=filters, filter_noise=noise, starts=[1, m]), engine)
    by_hand = _run(small_scenario(filters=filters, filter_noise=scaled), engine)
    plain = _run(small_scenario(filters=filters, filter_noise=noise), engine)
    for f in filters:
        _same(started[f"{f['name']} x4"], by_hand[f["name"]])
        _same(started[f"{f['name']} x1"], plain[f["name"]])  # x1 is the filter itself
    assert not np.array_equal(started["ekf x4"]["x"], started["ekf x1"]["x"])
    # The same meaning as a recorded log's starts: every standard deviation times m.
    real = parse_real_scenario({"name": "r", "data": {"kind": "log", "path": "x"}})
    pose = np.zeros(3)
    Qu, R = recorded_context(real, pose, m).Qu, recorded_context(real, pose, m).R
    Qu1, R1 = recorded_context(real, pose, 1.0).Qu, recorded_context(real, pose, 1.0).R
    np.testing.assert_allclose(np.diag(Qu) / np.diag(Qu1), m * m)
    np.testing.assert_allclose(np.diag(R) / np.diag(R1), m * m)


def test_the_oracle_is_told_the_truth_whatever_the_starts():
    doc = small_scenario(starts=[0.5, 2])
    assert "ekf-oracle" in parse_scenario(doc).instance_names()
    _same(_run(doc)["ekf-oracle"], _run(small_scenario())["ekf-oracle"])


@pytest.mark.parametrize(
    "change, field, words",
    [
        ({"starts": [1, 1.0001]}, "starts", "must differ"),
        ({"starts": []}, "starts", "at least 1"),
        ({"starts": [0]}, "starts", "greater than 0"),
        ({"starts": [2], "compare": [["ekf", "anfekf"]]}, "compare", "no filter named 'ekf'"),
        ({"starts": [2], "claims": [CLAIM]}, "claims", "no filter named 'anfekf'"),
    ],
)
def test_bad_starts_are_one_line_errors_naming_the_field(change, field, words):
    with pytest.raises(ScenarioError) as err:
        parse_scenario(small_scenario(**change), "s.yaml")
    message = str(err.value)
    assert "\n" not in message and field in message and words in message, message


def test_starts_with_a_sweep_are_refused_in_one_line(tmp_path):
    sweep = {"axes": [{"field": "seed", "values": [1, 2]}]}
    path = write_scenario(tmp_path / "s.yaml", small_scenario(starts=[1, 2], sweep=sweep))
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    assert "starts: not with sweep" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


def test_a_scenario_with_starts_runs_reports_and_compares_with_the_start_at_one(tmp_path):
    doc = small_scenario(filters=ZOO[:2] + ZOO[3:], starts=[0.5, 1, 2], runs=3, engine="fast")
    doc["compare"] = [["sh x2", "ekf x2"]]
    path = write_scenario(tmp_path / "s.yaml", doc)
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(path), "--out", str(out)])
    assert result.exit_code == 0, result.output
    folder = out / "small"
    manifest = json.loads((folder / "manifest.json").read_text())
    names = ["ekf x0.5", "ekf x1", "ekf x2", "sh x0.5", "sh x1", "sh x2", "ekf-oracle"]
    assert [f["name"] for f in manifest["filters"]] == names
    assert manifest["filters"][2] == {"name": "ekf x2", "base": "ekf", "kind": "ekf", "start": 2.0}
    assert manifest["filters"][-1]["start"] is None
    assert set(manifest["engines"]) == set(names) and set(manifest["engines"].values()) == {"fast"}
    summary = pd.read_parquet(folder / "summary.parquet")
    assert list(summary["filter"]) == names
    pairs = pd.read_parquet(folder / "comparisons.parquet")[["filter", "vs"]].drop_duplicates()
    vs = set(pairs["vs"])
    assert vs == {"ekf x1", "ekf-oracle", "ekf x2"}  # the ekf from the assumed noise itself
    assert ("sh x2", "ekf x2") in set(map(tuple, pairs.to_numpy()))
    report = runner.invoke(app, ["report", str(out), "--out", str(tmp_path / "report")])
    assert report.exit_code == 0, report.output
    text = (tmp_path / "report" / "report.md").read_text()
    assert all(name in text for name in names)


def test_the_example_with_starts_parses_into_its_instances():
    from anfekf_bench.scenarios import load_scenario

    example = Path(__file__).resolve().parent.parent / "examples/starts/wrong_r_starts.yaml"
    scenario, _ = load_scenario(example)
    assert len(scenario.instance_names()) == 10 and scenario.engine == "fast"
    assert scenario.instance_names()[-1] == "ekf-oracle"
