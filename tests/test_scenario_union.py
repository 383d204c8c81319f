"""One scenario model with a source union (issue 33): the keys every scenario has are declared
once, on `config.Scenario`; each member adds only its source's keys; one validation gives the
same one-line errors for both."""

from pathlib import Path

import pytest

from anfekf_bench.config import Scenario, ScenarioError, SimulatedScenario, source_of
from anfekf_bench.problems.schema import is_problem_document, parse_problem_scenario
from anfekf_bench.scenarios import member, parse_any_scenario
from anfekf_bench.sources.recorded import RecordedScenario

ROOT = Path(__file__).resolve().parents[1]
RECORDED = {"name": "r", "data": {"kind": "log", "path": "x"}}


def _declared_by(model: type) -> set[str]:
    """The fields `model`'s own class body declares (not those it inherits unchanged)."""
    return set(model.__annotations__) & set(model.model_fields)


def test_the_shared_keys_are_declared_once():
    shared = set(SimulatedScenario.model_fields) & set(RecordedScenario.model_fields)
    assert shared == set(Scenario.model_fields)
    assert not _declared_by(SimulatedScenario) & set(Scenario.model_fields)
    # A recorded log narrows only the filter kinds and the starts' default.
    assert _declared_by(RecordedScenario) & set(Scenario.model_fields) == {"filters", "starts"}


def test_every_member_is_a_scenario_named_by_its_source():
    for source in ("simulated", "recorded"):
        assert issubclass(member(source), Scenario) and member(source).source == source


@pytest.mark.parametrize("path", sorted((ROOT / "configs").rglob("*.yaml")), ids=lambda p: p.name)
def test_every_config_is_the_member_its_document_says(path):
    import yaml

    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    if is_problem_document(doc):  # a problem beyond the robot (SPEC 17): its own schema
        assert parse_problem_scenario(doc, path).problem == doc["problem"]
        return
    try:
        scenario = parse_any_scenario(doc, path)
    except ScenarioError as exc:  # an optional extra (PyTorch) missing here
        assert "needs PyTorch" in str(exc)
        return
    assert scenario.source == source_of(doc)
    assert isinstance(scenario, member(source_of(doc)))


@pytest.mark.parametrize(
    "doc, message",
    [
        ({"name": "s", "runz": 3}, "s.yaml: runz: unknown key (allowed: backend,"),
        ({**RECORDED, "runs": 3}, "s.yaml: runs: unknown key (allowed: backend,"),
        ({**RECORDED, "data": {"kind": "log", "path": "x", "robt": 1}}, "(did you mean 'robot'?)"),
        ({**RECORDED, "name": "a b"}, "s.yaml: name: must start with a letter or digit"),
        (
            {**RECORDED, "filters": [{"name": "a", "kind": "ekf"}, {"name": "a", "kind": "ekf"}]},
            "s.yaml: filters: filter names must be unique; repeated: a",
        ),
        ({**RECORDED, "compare": [["ekf-tuned", "zz"]]}, "compare: entry 0: no filter named 'zz'"),
        ({**RECORDED, "filters": [{"name": "o", "kind": "ekf-oracle"}]}, "ekf-oracle needs the"),
    ],
)
def test_one_validation_one_line_errors_for_both_sources(doc, message):
    with pytest.raises(ScenarioError) as err:
        parse_any_scenario(doc, "s.yaml")
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_failed_filter_list_is_not_reported_again_by_the_claims():
    doc = {"name": "s", "filters": [{"name": "a", "kind": "nope"}], "compare": [["a", "b"]]}
    with pytest.raises(ScenarioError) as err:
        parse_any_scenario(doc, "s.yaml")
    assert "compare" not in str(err.value)
