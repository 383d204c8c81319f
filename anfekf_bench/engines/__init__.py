"""Engines: what steps the filters over a run's data."""
