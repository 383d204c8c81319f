"""The documentation site (mkdocs.yml, docs/): its build hook, and a strict build that fails on
a broken internal link or anchor. Skipped without the docs extra (`pip install -e '.[docs]'`);
CI installs it and also runs `make docs`."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _hooks():
    pytest.importorskip("mkdocs")
    spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_list_right_after_a_paragraph_line_becomes_a_list():
    hooks = _hooks()
    text = "Common choices:\n- one\n  more\n- two\n\n```\nx:\n- not a list\n```\nend\n5. no\n"
    assert hooks.lists_after_paragraphs(text) == (
        "Common choices:\n\n- one\n  more\n- two\n\n```\nx:\n- not a list\n```\nend\n5. no\n"
    )


def test_links_that_leave_docs_are_told_apart():
    hooks = _hooks()
    assert hooks._outside_docs("results/paper.md", "../../results/report/a.png") == (
        "results/report/a.png"
    )
    assert hooks._outside_docs("CUSTOM_FILTERS.md", "../examples/custom_filter/") == (
        "examples/custom_filter"
    )
    for target in ("zoo.md", "../DESIGN.md#x", "#anchor", "https://example.org/x"):
        assert hooks._outside_docs("results/paper.md", target) is None, target


def _site_copy(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    shutil.copytree(ROOT / "docs", root / "docs")
    shutil.copy(ROOT / "mkdocs.yml", root / "mkdocs.yml")
    shutil.copytree(ROOT / "anfekf_bench", root / "anfekf_bench")  # mkdocstrings reads the API
    for rel in ("results/report", "examples"):
        shutil.copytree(ROOT / rel, root / rel)
    return root


def _build(root: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(root), "NO_MKDOCS_2_WARNING": "1"}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", "site"]
    return subprocess.run(command, cwd=root, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
@pytest.mark.heavy  # CI builds the site itself (`make docs`)
def test_the_site_builds_strict_and_a_broken_link_or_anchor_fails_it(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    pytest.importorskip("mkdocstrings_handlers.python")
    root = _site_copy(tmp_path)
    done = _build(root)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (root / "site" / "reference" / "cli" / "index.html").is_file()
    assert (root / "site" / "repo" / "results" / "report" / "overview.png").is_file()
    page = root / "docs" / "results" / "zoo.md"
    text = page.read_text(encoding="utf-8")
    for broken in ("[x](../DESIGN.md#no-such-section)", "[x](no-such-page.md)"):
        page.write_text(text + f"\n{broken}\n", encoding="utf-8")
        done = _build(root)
        assert done.returncode != 0, broken
        assert "no-such" in done.stderr, done.stderr[-2000:]
