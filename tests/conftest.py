"""Shared fixtures: a short route on a small map, so end-to-end tests take seconds."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

os.environ.setdefault("MPLBACKEND", "Agg")

SMALL_WORLD = {
    "landmarks": [[10, 8], [25, -6], [40, 10], [55, -5], [30, 15], [15, -10], [48, 4]],
    "waypoints": [[20, 0], [40, 8], [55, 0]],
}


def small_scenario(**overrides) -> dict:
    """A scenario dict on SMALL_WORLD (a ~60 m route: ~800 control steps)."""
    doc = {
        "name": "small",
        "seed": 7,
        "runs": 4,
        "jobs": 1,
        "record_every": 1,
        "world": dict(SMALL_WORLD),
        "filter_noise": {"sigma_range": 2.0, "sigma_bearing_deg": 0.1},
        "filters": [
            {"name": "ekf", "kind": "ekf"},
            {"name": "anfekf", "kind": "anfekf", "adapt": "R"},
            {"name": "ekf-oracle", "kind": "ekf-oracle"},
        ],
    }
    doc.update(overrides)
    return doc


def write_scenario(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


@pytest.fixture
def small_yaml(tmp_path: Path) -> Path:
    return write_scenario(tmp_path / "small.yaml", small_scenario())


def live_group_members(pgid: int) -> list[int]:
    """Processes of a process group that are still running (zombies are not): what a killed
    command leaves behind."""
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            alive.append(int(stat.parent.name))
    return alive
