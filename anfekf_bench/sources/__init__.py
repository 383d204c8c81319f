"""Data sources: the simulator (and recorded datasets) that feed the filters."""
