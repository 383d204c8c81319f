"""Loading a scenario whatever its source: the one place that tells a simulated scenario from a
recorded log's (a document with a `data:` key, SPEC 9). It sits above both `config` (the
simulated schema) and `sources.recorded` (the recorded one), so neither imports the other.
"""

from __future__ import annotations

from pathlib import Path

from .config import (
    Scenario,
    ScenarioError,
    World,
    parse_scenario,
    read_scenario_document,
    resolve_world,
)
from .problems.schema import ProblemScenario, is_problem_document, parse_problem_scenario


def scenario_from_data(data: object, path: str | Path) -> tuple[Scenario, World]:
    """A scenario document already read (a file's YAML, or a dict from Python) validated and
    resolved; relative paths in it are taken relative to `path`'s folder."""
    path = Path(path)
    if isinstance(data, dict) and data.get("problem") == "robot":  # the default, said aloud
        data = {k: v for k, v in data.items() if k != "problem"}
    if isinstance(data, dict) and "data" in data:  # a recorded log, not the simulator (SPEC 9)
        from .sources.recorded import load_recorded  # the recorded schema loads only when used

        return load_recorded(data, path)
    if is_problem_document(data):  # a problem beyond the robot (SPEC 17): its own pipeline
        raise ScenarioError(
            path,
            "problem",
            f"{data['problem']!r}: a problem scenario runs with `anfekf run`"
            " only (its tables: `anfekf report`)",
        )
    scenario = parse_scenario(data, path)
    return scenario, resolve_world(scenario.world, path)


def split_problem_files(files: list[Path]) -> tuple[list[Path], list[tuple[Path, ProblemScenario]]]:
    """(the robot's scenario files, [(file, problem scenario)]) of `files`: the problem
    scenarios (SPEC 17) validated here, the others left to `load_scenario`."""
    robot, problems = [], []
    for path in files:
        data = read_scenario_document(path)
        if is_problem_document(data):
            problems.append((path, parse_problem_scenario(data, path)))
        else:
            robot.append(path)
    return robot, problems


def load_scenario(path: str | Path) -> tuple[Scenario, World]:
    """Read, validate and resolve a scenario file; raises ScenarioError with a one-line message."""
    return scenario_from_data(read_scenario_document(path), Path(path))
