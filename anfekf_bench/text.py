"""Text shown to the user: one line, control characters escaped.

Imports nothing (the command line's fast paths, `--version`, `--help`, use it before any of the
heavy modules load)."""

from __future__ import annotations


def one_line(text: str) -> str:
    """`text` with line breaks and other control characters escaped (a key may hold them)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def plural(n: int, noun: str) -> str:
    """'1 scenario', '2 scenarios'."""
    return f"{n} {noun}" + ("" if n == 1 else "s")
