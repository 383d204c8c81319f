"""The report's files are the same bytes however often they are drawn: two `anfekf report` runs
in fresh processes (other hash seeds, so other set orders) over the same saved results write
identical report.md, report.html and figures, drawn in the report's process or in worker
processes. `make reproduce` left results/report/ dirty (one
PNG a pixel off): the committed report came from older code; the runs themselves are bit for bit
the same with one or two workers (tests/test_pipeline.py), so the report must be too."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from anfekf_bench.experiment import execute, make_plan
from anfekf_bench.scenarios import load_scenario

from .conftest import small_scenario, write_scenario

pytestmark = pytest.mark.slow  # a tiny run, then two reports in fresh processes


def test_two_reports_of_the_same_results_are_the_same_bytes(tmp_path):
    doc = small_scenario(name="same", runs=3, record_every=8)
    doc["filters"].insert(2, {"name": "sage-husa", "kind": "sage-husa", "adapt": "R"})
    scenario, world = load_scenario(write_scenario(tmp_path / "same.yaml", doc))
    execute(make_plan(scenario, world, None, None, 1), tmp_path / "results")
    root = Path(__file__).resolve().parents[1]
    outs = []
    # the second draws its figures in two worker processes (report.render)
    for seed, jobs in (("1", "1"), ("2", "2")):
        out = tmp_path / f"report-{seed}"
        env = {**os.environ, "PYTHONHASHSEED": seed, "PYTHONPATH": str(root)}
        done = subprocess.run(
            [sys.executable, "-m", "anfekf_bench.entry", "report", str(tmp_path / "results"),
             "--out", str(out), "--jobs", jobs],
            env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        outs.append(out)
    names = sorted(p.name for p in outs[0].iterdir())
    assert names == sorted(p.name for p in outs[1].iterdir())
    assert "report.html" in names and any(n.endswith(".png") for n in names)
    for name in names:
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
