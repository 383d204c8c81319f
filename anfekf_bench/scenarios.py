"""Loading a scenario whatever its source: the one place that tells a simulated scenario from a
recorded log's (a document with a `data:` key, SPEC 9). It sits above both `config` (the
simulated schema) and `sources.recorded` (the recorded one), so neither imports the other.
"""

from __future__ import annotations

from pathlib import Path

from .config import Scenario, World, parse_scenario, read_scenario_document, resolve_world


def scenario_from_data(data: object, path: str | Path) -> tuple[Scenario, World]:
    """A scenario document already read (a file's YAML, or a dict from Python) validated and
    resolved; relative paths in it are taken relative to `path`'s folder."""
    path = Path(path)
    if isinstance(data, dict) and "data" in data:  # a recorded log, not the simulator (SPEC 9)
        from .sources.recorded import load_recorded  # the recorded schema loads only when used

        return load_recorded(data, path)
    scenario = parse_scenario(data, path)
    return scenario, resolve_world(scenario.world, path)


def load_scenario(path: str | Path) -> tuple[Scenario, World]:
    """Read, validate and resolve a scenario file; raises ScenarioError with a one-line message."""
    return scenario_from_data(read_scenario_document(path), Path(path))
