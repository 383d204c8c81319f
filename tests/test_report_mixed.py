"""One report over a simulated and a recorded result: both go through the one Document pipeline
into one report.md and one report.html (sections, tables, figures, contents), and every link and
image of the page resolves."""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from anfekf_bench.analysis.metrics import format_number, format_sig
from anfekf_bench.cli import app

from .conftest import small_scenario, write_scenario
from .test_real_data import user_scenario
from .test_report import CHROMIUM, _chromium

runner = CliRunner()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _run(path: Path, out: Path) -> None:
    res = runner.invoke(app, ["run", str(path), "--out", str(out)])
    assert res.exit_code == 0, res.output


def _cells(page: str) -> list[str]:
    return [html.unescape(re.sub(r"<[^>]+>", "", c)) for c in re.findall(r"<td[^>]*>(.*?)</td>",
                                                                          page)]  # fmt: skip


@pytest.fixture(scope="module")
def mixed(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny simulated scenario (2 runs) and a recorded log (test_real_data's user log: two
    held-out segments) in one results folder, and their report: (results, report folder)."""
    root = tmp_path_factory.mktemp("mixed")
    results = root / "results"
    doc = small_scenario(name="tiny", runs=2, record_every=8)
    _run(write_scenario(root / "tiny.yaml", doc), results)
    _run(user_scenario(root), results)
    out = root / "report"
    res = runner.invoke(app, ["report", str(results), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return results, out


def test_one_report_holds_a_simulated_and_a_recorded_result(mixed):
    results, out = mixed
    assert sorted(p.name for p in out.glob("*.md")) == ["report.md"]  # one report, not two
    page = (out / "report.html").read_text(encoding="utf-8")
    text = (out / "report.md").read_text(encoding="utf-8")

    # both sections, in the contents and with their anchors
    ids = set(re.findall(r' id="([^"]+)"', page))
    assert {"summary", "scenario-tiny", "real-data", "real-my-robot"} <= ids
    for anchor in ("scenario-tiny", "real-my-robot"):
        assert f'href="#{anchor}"' in page and f"](#{anchor})" in text
    assert '<h2 id="scenario-tiny">tiny</h2>' in page
    assert '<h3 id="real-my-robot">my-robot (real data)</h3>' in page

    # their tables: every filter's RMSE as saved (summary.parquet of the simulated result; the
    # recorded result's summary.json and its ratio to ekf-tuned from comparisons.parquet)
    cells = _cells(page)
    sim = pd.read_parquet(results / "tiny" / "summary.parquet")
    for r in sim.itertuples():
        assert format_sig(r.rmse_pos) in cells
    rec = pd.read_json(results / "my-robot" / "summary.json")
    comparisons = pd.read_parquet(results / "my-robot" / "comparisons.parquet")
    assert len(rec) == 5
    for r in rec.itertuples():
        assert format_number(r.rmse_pos, 3) in cells and format_number(r.rmse_pos, 3) in text
        hit = comparisons[(comparisons["filter"] == r.filter)
                          & (comparisons["metric"] == "rmse_pos")]  # fmt: skip
        if len(hit):
            ratio = format_number(float(hit["estimate"].iloc[0]), 2)
            assert any(c.startswith(ratio) for c in cells), (r.filter, ratio)

    # their figures: each file written, linked from both pages and embedded once as a PNG
    figures = sorted(p.name for p in out.glob("*.png"))
    for name in ("tiny_rmse.png", "tiny_nees.png", "tiny_noise.png", "tiny_map.png",
                 "overview.png", *(f"my-robot_{k}.png" for k in
                                   ("ratios", "track", "errors", "noise"))):  # fmt: skip
        assert name in figures
    images = re.findall(r'<img src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == page.count("<img ") == len(figures)
    assert all(base64.b64decode(data).startswith(PNG_MAGIC) for data in images)
    embedded = {base64.b64decode(data) for data in images}
    assert embedded == {(out / name).read_bytes() for name in figures}

    # every link resolves: to an anchor of the page, or to a file or folder beside the report
    links = re.findall(r'href="([^"]+)"', page) + re.findall(r"\]\(([^)#\s][^)\s]*)\)", text)
    assert links
    for link in links:
        link = html.unescape(link)
        if link.startswith("#"):
            assert link[1:] in ids, link
        else:
            assert (out / link).exists(), link
    for name in figures:
        assert f"]({name})" in text and f'href="{name}"' in page


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_the_mixed_report_opens_in_a_browser_with_every_image(mixed, tmp_path):
    _, out = mixed
    dom = _chromium(out / "report.html", tmp_path / "profile", "--dump-dom")
    assert dom.returncode == 0, dom.stderr[-2000:]
    found = re.search(rb'data-images-ok="(\d+)/(\d+)"', dom.stdout)
    assert found, "the page's load handler did not run"
    ok, total = int(found.group(1)), int(found.group(2))
    assert total == len(list(out.glob("*.png"))) == 10 and ok == total
