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
    SimulatedScenario,
    World,
    check_document,
    read_scenario_document,
    resolve_world,
    source_of,
    validate_as,
)

if TYPE_CHECKING:
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
