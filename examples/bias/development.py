"""What the development scripts of examples/bias/ share (settings.py, calibrated.py): the
pooled position-RMSE ratio of a variant to the oracle over development runs, with its 95 %
bootstrap interval over runs."""

from __future__ import annotations

import numpy as np

RESAMPLES = 2000


def pooled_ratio(e: np.ndarray, ref: np.ndarray, rng: np.random.Generator):
    """sqrt(mean squared error / the oracle's), pooled over runs and steps (`e`, `ref`: runs x
    steps), and its 2.5 and 97.5 percentiles over RESAMPLES bootstrap resamples of the runs."""
    pooled = np.sqrt(e.mean() / ref.mean())
    boot = []
    for _ in range(RESAMPLES):
        i = rng.integers(0, len(e), len(e))
        boot.append(np.sqrt(e[i].mean() / ref[i].mean()))
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return pooled, lo, hi
