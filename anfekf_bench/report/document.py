"""The report as a list of blocks, written twice: as GitHub markdown (report.md) and as one
self-contained HTML file (report.html: figures embedded as data URIs, tables sortable by a click
on their header, a few lines of inline JavaScript, nothing fetched from anywhere).

Text in blocks uses a small markdown subset that both writers understand: `code`, **bold** and
[links](relative/path). Both files are reproducible: no dates, no random ids.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Cell:
    """A table cell: the text shown and, for numbers, the value a column sorts by."""

    text: str
    sort: float | None = None


@dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2
    anchor: str = ""


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Warning:  # noqa: A001 - a block of the report, not the builtin exception
    text: str


@dataclass(frozen=True)
class ListBlock:
    """A bulleted list, one item a line of text (nothing when empty)."""

    items: Sequence[str]


@dataclass(frozen=True)
class TableBlock:
    header: Sequence[str]
    rows: Sequence[Sequence[Cell | str]]
    numeric: Sequence[bool] = ()  # right-aligned columns
    caption: str = ""


@dataclass(frozen=True)
class FigureBlock:
    """A figure: its file beside the report, a caption, and the image the HTML embeds."""

    file: str  # relative to the report folder
    caption: str
    image: bytes = b""  # PNG or SVG bytes for the HTML
    mime: str = "image/png"
    link_only: bool = False  # markdown links the file instead of embedding it (PDF)


@dataclass(frozen=True)
class Contents:
    """The table of contents: a link to every heading of `level` (and one level below) that
    follows; both writers fill it in from the document's headings."""

    level: int = 2


Block = Heading | Paragraph | Warning | ListBlock | TableBlock | FigureBlock | Contents


def anchor_of(h: Heading) -> str:
    """The id a heading gets in report.html and (as an <a id>) in report.md."""
    return h.anchor or _slug(h.text)


def _contents(doc: Document, c: Contents) -> list[tuple[int, str, str]]:
    """(depth, text, anchor) of the headings the contents list."""
    return [
        (b.level - c.level, b.text, anchor_of(b))
        for b in doc.blocks
        if isinstance(b, Heading) and c.level <= b.level <= c.level + 1
    ]


@dataclass
class Document:
    title: str
    blocks: list[Block] = field(default_factory=list)

    def add(self, *blocks: Block) -> None:
        self.blocks.extend(blocks)


# --------------------------------------------------------------------------- markdown


def _md_cell(cell: Cell | str) -> str:
    text = cell.text if isinstance(cell, Cell) else cell
    return text.replace("|", "\\|").replace("\n", " ")


def _md_table(t: TableBlock) -> list[str]:
    numeric = list(t.numeric) + [False] * (len(t.header) - len(t.numeric))
    out = []
    if t.caption:
        out += [t.caption, ""]
    out.append("| " + " | ".join(_md_cell(h) for h in t.header) + " |")
    out.append("|" + "|".join("---:" if n else "---" for n in numeric) + "|")
    out += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in t.rows]
    return out


def to_markdown(doc: Document) -> str:
    out = [f"# {doc.title}", ""]
    for b in doc.blocks:
        if isinstance(b, Heading):
            # an explicit anchor: the contents' links work in report.md as in report.html
            out += [f'<a id="{anchor_of(b)}"></a>', ""] if b.level in (2, 3) else []
            out += ["#" * b.level + " " + b.text, ""]
        elif isinstance(b, Contents):
            entries = _contents(doc, b)
            if not entries:
                continue
            out += ["**Contents**", ""]
            for depth, text, anchor in entries:
                out.append("  " * depth + f"- [{_md_cell(text)}](#{anchor})")
            out.append("")
        elif isinstance(b, Paragraph):
            out += [b.text, ""]
        elif isinstance(b, Warning):
            out += [f"> **Warning:** {b.text}", ""]
        elif isinstance(b, ListBlock):
            out += [*(f"- {item}" for item in b.items), ""] if b.items else []
        elif isinstance(b, TableBlock):
            out += [*_md_table(b), ""]
        elif isinstance(b, FigureBlock):
            if b.link_only:
                out += [f"[{b.caption} ({b.file})]({b.file})", ""]
            else:
                out += [f"![{b.caption}]({b.file})", ""]
    return "\n".join(out).rstrip() + "\n"


# --------------------------------------------------------------------------- HTML

_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*([^*]+)\*\*")
_EM = re.compile(r"(?<![*\w])\*([^*\s][^*]*)\*(?![*\w])")
_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")


_SCHEME = re.compile(r"([A-Za-z][A-Za-z0-9+.-]*):")
LINK_SCHEMES = ("http", "https")  # besides relative links: nothing that runs (javascript:, data:)


def safe_href(url: str) -> bool:
    """Whether a link target may become a live link: http(s) or relative. Checked on the text a
    browser would see (entities decoded, the control characters and spaces it skips removed)."""
    seen = re.sub(r"[\x00-\x20\x7f]", "", html.unescape(url))
    scheme = _SCHEME.match(seen)
    if scheme is not None:
        return scheme.group(1).lower() in LINK_SCHEMES
    return not seen.startswith("\\")


def _link(match: re.Match) -> str:
    text, url = match.group(1), match.group(2)
    if safe_href(url):
        return f'<a href="{url}">{text}</a>'
    return match.group(0)  # shown as the (escaped) text it was written as


def inline_html(text: str) -> str:
    """The markdown subset of a block's text as HTML (everything else escaped); a link only to
    an http(s) or relative address (`safe_href`), any other shown as plain text."""
    out = html.escape(text, quote=True)
    out = _CODE.sub(r"<code>\1</code>", out)
    out = _BOLD.sub(r"<strong>\1</strong>", out)
    out = _EM.sub(r"<em>\1</em>", out)
    return _LINK.sub(_link, out)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


_INTERVAL = re.compile(r"^(\S+) (\[[^\]]+\])$")


def _html_table(t: TableBlock) -> list[str]:
    numeric = list(t.numeric) + [False] * (len(t.header) - len(t.numeric))
    out = ['<table class="sortable">']
    if t.caption:
        out.append(f"<caption>{inline_html(t.caption)}</caption>")
    heads = "".join(
        f'<th class="{"num" if n else "text"}" title="click to sort">{inline_html(h)}</th>'
        for h, n in zip(t.header, numeric, strict=True)
    )
    out += ["<thead><tr>" + heads + "</tr></thead>", "<tbody>"]
    for row in t.rows:
        cells = []
        for cell, n in zip(row, numeric, strict=True):
            cell = cell if isinstance(cell, Cell) else Cell(cell)
            key = (
                f' data-sort="{cell.sort!r}"'
                if cell.sort is not None and cell.sort == cell.sort  # NaN sorts as text
                else ""
            )
            cls = ' class="num"' if n else ""
            text = inline_html(cell.text)
            if n:  # a ratio's interval on its own line, so wide tables fit the page
                text = _INTERVAL.sub(r'\1<span class="ci">\2</span>', text)
            cells.append(f"<td{cls}{key}>{text}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out += ["</tbody>", "</table>"]
    return out


_STYLE = """
body { font: 15px/1.45 system-ui, -apple-system, "Segoe UI", sans-serif; color: #222;
       max-width: 1400px; margin: 2em auto; padding: 0 1em; background: #fff; }
h1, h2, h3 { line-height: 1.2; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 13px; display: block;
        overflow-x: auto; max-width: 100%; }
caption { text-align: left; font-weight: 600; padding: .3em 0; }
th, td { border: 1px solid #ccc; padding: .25em .5em; }
td { white-space: nowrap; }
th { background: #f3f3f3; cursor: pointer; user-select: none; vertical-align: bottom; }
th[aria-sort="ascending"]::after { content: " \\25B2"; }
th[aria-sort="descending"]::after { content: " \\25BC"; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td .ci { display: block; color: #666; font-size: 11px; }
tbody tr:nth-child(even) { background: #fafafa; }
figure { margin: 1.5em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { color: #555; font-size: 13px; }
.warning { background: #fff4d6; border-left: 4px solid #e0a100; padding: .5em .8em; margin: 1em 0; }
.broken { outline: 3px solid #c00; }
code { background: #f3f3f3; padding: 0 .2em; }
nav.contents ul { margin: .3em 0; } nav.contents li.sub { margin-left: 1.5em; }
"""

# Click a header to sort by it (again: the other way). Numbers sort by data-sort; a cell without
# one sorts as text, after the numbers. On load, images that failed to decode are outlined and
# counted on <body data-images-ok="n/m">, so a broken report is visible (and testable).
_SCRIPT = """
document.querySelectorAll("table.sortable").forEach(function (table) {
  table.querySelectorAll("th").forEach(function (th, col) {
    th.addEventListener("click", function () {
      var up = th.getAttribute("aria-sort") !== "ascending";
      table.querySelectorAll("th").forEach(function (h) { h.removeAttribute("aria-sort"); });
      th.setAttribute("aria-sort", up ? "ascending" : "descending");
      var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows);
      function key(row) {
        var c = row.cells[col], s = c.getAttribute("data-sort");
        return s === null ? [1, c.textContent] : [0, parseFloat(s)];
      }
      rows.sort(function (a, b) {
        var x = key(a), y = key(b), d = x[0] - y[0];
        if (d === 0) { d = x[0] === 0 ? x[1] - y[1] : String(x[1]).localeCompare(String(y[1])); }
        return up ? d : -d;
      });
      rows.forEach(function (r) { body.appendChild(r); });
    });
  });
});
window.addEventListener("load", function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; }
    else { imgs[i].className += " broken"; }
  }
  document.body.setAttribute("data-images-ok", ok + "/" + imgs.length);
});
"""


def to_html(doc: Document) -> str:
    out = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(doc.title)}</title>",
        f"<style>{_STYLE}</style>",
        "</head>",
        "<body>",
        f"<h1>{html.escape(doc.title)}</h1>",
    ]
    for b in doc.blocks:
        if isinstance(b, Heading):
            anchor = b.anchor or _slug(b.text)
            out.append(f'<h{b.level} id="{html.escape(anchor)}">{inline_html(b.text)}</h{b.level}>')
        elif isinstance(b, Paragraph):
            out.append(f"<p>{inline_html(b.text)}</p>")
        elif isinstance(b, Contents):
            entries = _contents(doc, b)
            if entries:
                out.append('<nav class="contents"><strong>Contents</strong><ul>')
                for depth, text, anchor in entries:
                    cls = ' class="sub"' if depth else ""
                    href = html.escape("#" + anchor, quote=True)
                    out.append(f'<li{cls}><a href="{href}">{html.escape(text)}</a></li>')
                out.append("</ul></nav>")
        elif isinstance(b, Warning):
            text = inline_html(b.text)
            out.append(f'<div class="warning"><strong>Warning:</strong> {text}</div>')
        elif isinstance(b, ListBlock):
            if b.items:
                out += ["<ul>", *(f"<li>{inline_html(item)}</li>" for item in b.items), "</ul>"]
        elif isinstance(b, TableBlock):
            out += _html_table(b)
        elif isinstance(b, FigureBlock):
            alt = html.escape(b.caption, quote=True)
            link = f' <a href="{html.escape(b.file, quote=True)}">{html.escape(b.file)}</a>'
            if not b.image:  # a PDF drawn elsewhere (sweeps, real data): a browser shows a link
                out.append(f"<p>{inline_html(b.caption)}:{link}</p>")
                continue
            out += [
                "<figure>",
                f'<img src="{data_uri(b.image, b.mime)}" alt="{alt}">',
                f"<figcaption>{inline_html(b.caption)}.{link}</figcaption>",
                "</figure>",
            ]
    out += [f"<script>{_SCRIPT}</script>", "</body>", "</html>"]
    return "\n".join(out) + "\n"
