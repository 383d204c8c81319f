"""Metrics, tables, statistics and the regression gate: everything computed from results."""
