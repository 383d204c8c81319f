"""The report: figures and tables drawn from saved results only."""

from .report import HTML_FILE, REPORT_FILE, ImageFormat, rich_table, write_report

__all__ = ["HTML_FILE", "REPORT_FILE", "ImageFormat", "rich_table", "write_report"]
