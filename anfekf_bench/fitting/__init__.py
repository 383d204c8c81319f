"""Fits of filter parameters on training runs (the one place where a filter is fitted before the
batch): `simulated` (the simulated training runs, seeds disjoint from every evaluation run),
`recorded` (the training segments of a log, or the other datasets' drives of a cross-drive fold)
and `own` (a recorded run's own innovations, never its ground truth)."""
