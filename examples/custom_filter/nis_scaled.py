"""A worked example of your own filter in anfekf-bench: an EKF that scales R by its NIS.

Run it from the repository root (the folder holding this file must be importable):

    PYTHONPATH=examples/custom_filter anfekf run examples/custom_filter/scenario.yaml

The rule: a consistent filter has E[NIS] = 2 for a 2-dim measurement, so an exponentially
smoothed NIS above 2 means S (and so R) is too small, below 2 too large. At every landmark, before
the gain, R is rescaled by (smoothed NIS / 2)^gain. It uses the common adaptive rules of the
benchmark (bounds on R, adaptation from all innovations or only gate-accepted ones) through
`AdaptiveEKF`, so it is compared on the same terms as the built-in filters.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from anfekf_bench.filters import AdaptiveEKF, AdaptiveParams, Innovation


class NisScaledR(AdaptiveEKF):
    """R <- R * (nis_bar / 2)^gain, nis_bar an exponential average of the NIS (m = 2)."""

    adapts = frozenset({"R"})

    class Params(AdaptiveParams):
        """Validated from the scenario's `params:`; the filter gets them as `self.params`."""

        forgetting: float = Field(0.9, gt=0, lt=1, description="weight of the past NIS")
        gain: float = Field(0.2, gt=0, le=1, description="exponent of the R correction")

    def __init__(self, *args, params: Params, **kwargs):
        super().__init__(*args, params=params, **kwargs)
        self.nis_bar = 2.0

    def before_gain(self, inn: Innovation) -> None:
        if not (self.params.adaptation and self.feeds_adaptation(inn)):
            return
        S = inn.HPHt + self.R
        nis = float(inn.nu @ np.linalg.solve(S, inn.nu))
        a = self.params.forgetting
        self.nis_bar = a * self.nis_bar + (1.0 - a) * min(nis, 100.0)
        self.set_R_diag(np.diag(self.R) * (self.nis_bar / 2.0) ** self.params.gain)
