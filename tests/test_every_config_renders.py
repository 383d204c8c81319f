"""Every config folder under configs/ runs and its report renders (`make sweeps`' report step
crashed on the `scale:` axes all three sweep files use). Each folder is shrunk to stay quick: 2
runs (2 training runs; KalmanNet one epoch), the first two cells of each sweep axis, one naive
start and three filters (and KalmanNet) on the recorded data, two drives; the scenarios' own
structure (axes, schedules, filters of the simulated ones, protocols) is kept."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from anfekf_bench.cli import app

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
FOLDERS = [CONFIGS, *sorted(p for p in CONFIGS.iterdir() if p.is_dir())]
runner = CliRunner()
pytestmark = [pytest.mark.slow, pytest.mark.heavy]  # every shipped scenario, end to end


def shrink(doc: dict) -> dict:
    """The scenario at tiny counts, the same kind of scenario."""
    doc = dict(doc)
    doc["jobs"] = 1
    if "runs" in doc:
        doc["runs"] = 2
    if isinstance(doc.get("training"), dict):
        doc["training"] = {**doc["training"], "runs": 2}
    sweep = doc.get("sweep")
    if sweep:
        for axis in sweep["axes"]:
            if axis.get("factors"):
                axis["factors"] = {**axis["factors"], "num": 2}
            if axis.get("values"):
                axis["values"] = axis["values"][:2]
    filters = doc.get("filters") or []
    doc["filters"] = [
        {**f, "validation_runs": 1, "epochs": 1} if f.get("kind") == "kalmannet" else f
        for f in filters
    ]  # a network trained on the 2 training runs, 1 held out, for one epoch
    if "starts" in doc:  # recorded data: one naive start (the x1 where there is one), three filters
        doc["starts"] = doc["starts"][1:2] or doc["starts"][:1]
        kept = doc["filters"][:3]
        doc["filters"] = kept + [f for f in doc["filters"][3:] if f.get("kind") == "kalmannet"]
        doc.pop("pairs", None)
        doc.pop("compare", None)  # it may name a filter left out
    drives = (doc.get("data") or {}).get("drives")
    if drives:  # two drives of two datasets, each tuned on the other's
        doc["data"] = {**doc["data"], "drives": ["d6-r1", "d7-r1"]}
        doc["tune_on"] = {6: [7], 7: [6]}
    return doc


def needs_torch(folder: Path) -> bool:
    return any("kalmannet" in p.read_text(encoding="utf-8") for p in folder.glob("*.yaml"))


@pytest.mark.parametrize("folder", FOLDERS, ids=lambda p: p.name)
def test_every_config_folder_runs_and_its_report_renders(folder, tmp_path):
    if needs_torch(folder) and importlib.util.find_spec("torch") is None:
        pytest.skip("KalmanNet needs torch (pip install -e '.[learned]')")
    shrunk = tmp_path / "configs"
    shrunk.mkdir()
    for path in sorted(folder.glob("*.yaml")):
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
        (shrunk / path.name).write_text(yaml.safe_dump(shrink(doc), sort_keys=False))
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(shrunk), "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = tmp_path / "report"
    result = runner.invoke(app, ["report", str(out), "--out", str(report)])
    assert result.exit_code == 0, result.output
    assert "Traceback" not in result.output
    md = (report / "report.md").read_text(encoding="utf-8")
    figures = sorted(p.name for p in report.iterdir() if p.suffix == ".png")
    assert figures and all(f"({name})" in md for name in figures)
