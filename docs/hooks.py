"""mkdocs build hook (mkdocs.yml `hooks:`): links from the docs to files of the repository.

The pages link committed files outside docs/ with paths relative to the page, as GitHub renders
them (`../../results/report/overview.png`, `../examples/custom_filter/`). mkdocs sees only docs/,
so this hook
- publishes the committed report's figures (results/report/*.png, *.svg) under `repo/` in the
  site and points the pages' links there;
- turns a link to any other existing file or folder of the repository into its plain text (the
  site does not carry the code);
and leaves every other link alone, so a link to nothing still fails `mkdocs build --strict`.
It also starts a list that follows a paragraph line directly ("Common choices:" then "- ..."):
GitHub renders it as a list, Python-Markdown as running text unless a blank line comes first.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = ("results/report/*.png", "results/report/*.svg")
SITE_PREFIX = "repo/"
LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")
LIST_ITEM = re.compile(r"^ {0,3}(?:[-*+]|1[.)]) ")  # what may interrupt a paragraph (CommonMark)
FENCE = re.compile(r"^ {0,3}(```|~~~)")


def on_files(files, config):
    for pattern in PUBLISHED:
        for path in sorted(ROOT.glob(pattern)):
            rel = path.relative_to(ROOT).as_posix()
            files.append(File.generated(config, SITE_PREFIX + rel, abs_src_path=str(path)))
    return files


def _outside_docs(page_uri: str, target: str) -> str | None:
    """The repository path a relative link leaves docs/ for, or None."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
        return None
    path = target.split("#", 1)[0]
    resolved = posixpath.normpath(posixpath.join(posixpath.dirname(page_uri), path))
    if not resolved.startswith("../"):
        return None
    return resolved[len("../") :]


def lists_after_paragraphs(markdown: str) -> str:
    """A blank line before a list item that directly follows a paragraph's line (GitHub's
    reading), outside code fences; lines of a list already begun are left alone."""
    out: list[str] = []
    in_fence = in_list = False
    for line in markdown.split("\n"):
        if FENCE.match(line):
            in_fence = not in_fence
        elif not in_fence:
            if not line.strip():
                in_list = False
            elif LIST_ITEM.match(line):
                previous = out[-1] if out else ""
                if not in_list and previous.strip() and not previous.startswith((" ", "\t", "|")):
                    out.append("")
                in_list = True
        out.append(line)
    return "\n".join(out)


def on_page_markdown(markdown, page, config, files):
    markdown = lists_after_paragraphs(markdown)
    page_uri = page.file.src_uri

    def relink(match: re.Match) -> str:
        bang, text, target = match.groups()
        repo_path = _outside_docs(page_uri, target)
        if repo_path is None or not (ROOT / repo_path).exists():
            return match.group(0)
        published = SITE_PREFIX + repo_path
        if files.get_file_from_path(published) is not None:
            new = posixpath.relpath(published, posixpath.dirname(page_uri) or ".")
            return f"{bang}[{text}]({new})"
        return text

    return LINK.sub(relink, markdown)
