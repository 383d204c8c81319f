"""Hardening 4 (issue 32): the defects the probe (`tests/probe/probe.py`) found, each a test that
failed before its fix (docs/HARDENING.md, "The probe (issue 32)")."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from anfekf_bench import api

from .conftest import tiny_scenario

TINY = tiny_scenario(name="tiny")


def test_the_api_names_every_state_run_can_end_in(tmp_path: Path) -> None:
    """A complete result without `force` (or a folder another process holds) is an exception a
    caller catches by its name in `anfekf_bench.api`, with the command line's one line; it was
    `anfekf_bench.outputs.OutputExists`, not part of the API."""
    api.run(TINY, out=tmp_path)
    with pytest.raises(api.OutputExists) as raised:
        api.run(TINY, out=tmp_path)
    assert "\n" not in str(raised.value)
    assert str(tmp_path / "tiny") in str(raised.value)
    assert issubclass(api.FolderBusy, Exception)
    assert {"OutputExists", "FolderBusy"} <= set(api.__all__)


@pytest.fixture(scope="module")
def claimed_result(tmp_path_factory) -> Path:
    """A complete result whose scenario declares one claim (it holds)."""
    out = tmp_path_factory.mktemp("claimed")
    claim = {"filter": "ekf", "vs": "oracle", "metric": "rmse_pos", "at_most": 100.0}
    doc = dict(TINY, runs=2, claims=[claim],
               filters=[*TINY["filters"], {"name": "oracle", "kind": "ekf-oracle"}])  # fmt: skip
    return api.run(doc, out=out).folder


@pytest.mark.parametrize("scenario", ["missing", "x", -1, None, [1], True])
def test_check_refuses_a_manifest_whose_scenario_is_damaged(
    claimed_result: Path, tmp_path: Path, scenario
) -> None:
    """The scenario's settings in manifest.json declare the claims `check` decides. A manifest
    whose `scenario` was missing or not an object was read as declaring none: the claim in
    claims.json was dropped without a word and the gate said it 'checked NOTHING' (exit 1).
    Now one line naming the file and the field, exit 2."""
    from typer.testing import CliRunner

    from anfekf_bench.cli import app

    folder = tmp_path / "tiny"
    shutil.copytree(claimed_result, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    if scenario == "missing":
        del manifest["scenario"]
    else:
        manifest["scenario"] = scenario
    (folder / "manifest.json").write_text(json.dumps(manifest))
    found = CliRunner().invoke(app, ["check", str(tmp_path)])
    assert found.exit_code == 2, found.output
    assert found.output.startswith("error: ") and found.output.count("\n") == 1
    assert "manifest.json: scenario:" in found.output
