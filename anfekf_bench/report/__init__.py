"""The report: figures and tables drawn from saved results only."""

from .report import ImageFormat, rich_table, write_report

__all__ = ["ImageFormat", "rich_table", "write_report"]
