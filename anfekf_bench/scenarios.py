"""Loading a scenario whatever its source: the one place that picks the member of the source
union (`config.source_of`: a document with a `data:` key is a recorded log's, SPEC 9) and
resolves it (a simulated world's map; a recorded log read and cut). It sits above both `config`
(the shared `Scenario` and `SimulatedScenario`) and `sources.recorded` (`RecordedScenario`), so
neither imports the other.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Union

from .config import (
    ScenarioError,
    SimulatedScenario,
    World,
    check_document,
    is_problem_document,
    read_scenario_document,
    resolve_world,
    source_of,
    validate_as,
)

if TYPE_CHECKING:
    from .problems.schema import ProblemScenario
    from .sources.recorded import DriveSet, RecordedScenario, Recording

# The source union: every scenario is exactly one of these (`Scenario.source` says which).
AnyScenario = Union[SimulatedScenario, "RecordedScenario"]  # noqa: UP007


def member(source: str) -> type[SimulatedScenario] | type[RecordedScenario]:
    """The member of the source union named `source` (a recorded log's schema, and the log
    readers with it, load only when used)."""
    if source == SimulatedScenario.source:
        return SimulatedScenario
    from .sources.recorded import RecordedScenario

    return RecordedScenario


def parse_any_scenario(data: object, path: str | Path = "<scenario>") -> AnyScenario:
    """A scenario document validated as its source's member; ScenarioError (one line) if not."""
    data = check_document(data, path)
    if data.get("problem") == "robot":  # the default, said aloud
        data = {k: v for k, v in data.items() if k != "problem"}
    if is_problem_document(data):  # a problem beyond the robot (SPEC 17): its own pipeline
        raise ScenarioError(
            path,
            "problem",
            f"{data['problem']!r}: a problem scenario runs with `anfekf run`"
            " only (its tables: `anfekf report`)",
        )
    return validate_as(member(source_of(data)), data, path)


def scenario_from_data(
    data: object, path: str | Path
) -> tuple[AnyScenario, World | Recording | DriveSet]:
    """A scenario document already read (a file's YAML, or a dict from Python) validated and
    resolved; relative paths in it are taken relative to `path`'s folder."""
    path = Path(path)
    scenario = parse_any_scenario(data, path)
    if scenario.source == "recorded":
        from .sources.recorded import resolve_scenario_log

        return scenario, resolve_scenario_log(scenario, path)
    return scenario, resolve_world(scenario.world, path)


def load_scenario(path: str | Path) -> tuple[AnyScenario, World | Recording | DriveSet]:
    """Read, validate and resolve a scenario file; raises ScenarioError with a one-line message."""
    return scenario_from_data(read_scenario_document(path), Path(path))


def split_problem_files(files: list[Path]) -> tuple[list[Path], list[tuple[Path, ProblemScenario]]]:
    """(the robot's scenario files, [(file, problem scenario)]) of `files`: the problem
    scenarios (SPEC 17) validated here, the others left to `load_scenario`."""
    robot, problems = [], []
    for path in files:
        data = read_scenario_document(path)
        if is_problem_document(data):
            # imported here: a robot's scenarios never pay for the problems' schema (~0.1 s)
            from .problems.schema import parse_problem_scenario

            problems.append((path, parse_problem_scenario(data, path)))
        else:
            robot.append(path)
    return robot, problems
