"""The report: figures and tables drawn from saved results only.

The names below are imported on first use, so that `report.results` (the loader, no
matplotlib) can be imported without the figures.
"""

from __future__ import annotations

import importlib

__all__ = ["HTML_FILE", "REPORT_FILE", "ImageFormat", "rich_table", "write_report"]


def __getattr__(name: str):
    if name in __all__:
        return getattr(importlib.import_module(".report", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
