"""The scenario's spec of KalmanNet (`kind: kalmannet`): its training settings, its fit (trained by
`kalmannet_train`, PyTorch, the optional extra `.[learned]`) and its filter (`kalmannet_net`: the
network, its weights and the filter, numpy only). Layers: this module > kalmannet_train >
kalmannet_net, so training is imported only when a fit runs and nothing imports upwards.
"""

from __future__ import annotations

import base64
import hashlib
from typing import ClassVar, Literal

from pydantic import Field, PrivateAttr, model_validator

from .context import filter_context
from .fitted import FittedSpec
from .kalmannet_net import (
    INSTALL_HINT,
    KalmanNetFilter,
    KalmanNetWeights,
    TrainingResult,
    fitted_weights_problem,
    torch_available,
)
from .spec import FilterContext, Role

# ---------------------------------------------------------------------------------------------
# The scenario's spec


class KalmanNetSpec(FittedSpec):
    """KalmanNet (Revach et al. 2022, architecture 1): the EKF's structure with each landmark's
    gain from a GRU, trained on the scenario's training runs (`training.runs`, see
    anfekf_bench.fitting.simulated) or, on recorded data, on the training drives of each
    cross-drive fold (or the training segments; anfekf_bench.fitting.recorded); the extra
    `.[learned]`; no covariance, no NEES.

    A fitted filter like `ekf-ml`: `fit` trains on the training set and returns the weights
    (base64 of `KalmanNetWeights.to_bytes`, their SHA-256) with the training cost, which the
    experiment caches by fingerprint and records in the manifest's `training` key."""

    kind: Literal["kalmannet"]
    fast_kernel: ClassVar[str | None] = "kernels_kalmannet"
    robot_only_because: ClassVar[str] = "its features, network sizes and training are the robot's"
    role: ClassVar[Role] = "trained"
    fit_sources: ClassVar[frozenset[str]] = frozenset({"simulated", "recorded"})
    epochs: int = Field(30, ge=1, le=10_000, description="passes over the training runs")
    learning_rate: float = Field(
        2e-3, gt=0, le=1, allow_inf_nan=False, description="Adam's step size"
    )
    hidden_size: int = Field(32, ge=2, le=1024, description="GRU and layer width")
    bptt: int = Field(
        25, ge=1, le=100_000, description="truncated BPTT: landmark updates per gradient step"
    )
    batch_size: int = Field(25, ge=1, le=10_000, description="training runs per batch")
    validation_runs: int = Field(
        10, ge=0, le=10_000,
        description="of the scenario's training runs (training.runs), held out to keep the"
        " epoch that does best on them (0: keep the last epoch)",
    )  # fmt: skip
    seed: int = Field(0, ge=0, le=2**63 - 1, description="initial weights and batch order")
    window_s: float = Field(
        60.0, ge=1.0, le=1e5, allow_inf_nan=False,
        description="recorded drives: the training drives are cut into windows of this many"
        " seconds, each cold-started from ground truth (validation_runs of them held out)",
    )  # fmt: skip
    _weights: KalmanNetWeights | None = PrivateAttr(None)

    @model_validator(mode="after")
    def _torch_installed(self) -> KalmanNetSpec:
        if not torch_available():
            raise ValueError(INSTALL_HINT)
        return self

    def training_problem(self, training_runs: int) -> str | None:
        """Why the scenario's `training.runs` cannot train this filter, or None."""
        if self.validation_runs >= training_runs:
            return (
                f"validation_runs: {self.validation_runs} must be fewer than training.runs"
                f" ({training_runs}): the rest are fitted"
            )
        return None

    @property
    def trained(self) -> bool:
        """Whether this spec carries trained weights (`with_fit` or `with_weights`)."""
        return self._weights is not None

    @property
    def trained_weights(self) -> KalmanNetWeights:
        """The weights this spec carries (what both engines run); RuntimeError without them."""
        if self._weights is None:
            raise RuntimeError(f"kalmannet filter {self.name!r} has no trained weights")
        return self._weights

    def with_weights(self, weights: KalmanNetWeights) -> KalmanNetSpec:
        """This spec carrying trained weights (what `build` needs)."""
        spec = self.model_copy()
        spec._weights = weights
        return spec

    def train(self, runs, world, ctx: FilterContext, progress=False) -> TrainingResult:
        """Train on `runs` (simulated RunData with truth) of `world`; deterministic for `seed`.
        `progress`: False (quiet), True (its own bar) or a rich Progress to add a task to."""
        from . import kalmannet_train

        return kalmannet_train.train(self, runs, world, ctx, progress=progress)

    def fit(self, training) -> dict:
        """Train on the training runs (fitting.fit): the simulated training set's runs (all
        `training.runs` of them, the last `validation_runs` held out), or a recorded log's
        training segments or a fold's training drives (their timelines and truth, NaN where not
        scored, on the unicycle: kalmannet_train.train_recorded). The weights and the cost,
        JSON-able."""
        if training.source == "recorded":
            from . import kalmannet_train

            return self.fitted_doc(
                kalmannet_train.train_recorded(
                    self,
                    training.pairs(),
                    training.model,
                    training.progress,
                    training.progress_label(self),
                )
            )
        ctx = filter_context(self, training.scenario, training.world)
        return self.fitted_doc(
            self.train(training.runs, training.world, ctx, progress=training.progress)
        )

    @staticmethod
    def fitted_doc(result: TrainingResult) -> dict:
        """What `fit` returns of a training: the weights (base64) and their hash, the cost."""
        data = result.weights.to_bytes()
        return {
            "weights_sha256": hashlib.sha256(data).hexdigest(),
            "training_time_s": round(result.training_time_s, 3),
            "training_cpu_s": round(result.training_cpu_s, 3),
            "epochs": len(result.epoch_loss),
            "best_epoch": result.best_epoch,
            "epoch_loss": [float(v) for v in result.epoch_loss],
            "validation_loss": [float(v) for v in result.validation_loss],
            "weights_base64": base64.b64encode(data).decode("ascii"),
        }

    def fit_record(self, fitted: dict) -> dict:
        """The manifest records the weights' hash and the cost, not the weights themselves."""
        return {k: v for k, v in fitted.items() if k != "weights_base64"}

    def fit_problem(self, fitted) -> str | None:
        return fitted_weights_problem(fitted, self.hidden_size)

    def with_fit(self, fitted: dict) -> KalmanNetSpec:
        data = base64.b64decode(fitted["weights_base64"])
        if hashlib.sha256(data).hexdigest() != fitted["weights_sha256"]:
            raise ValueError(f"kalmannet {self.name!r}: the fitted weights do not match their hash")
        spec = super().with_fit(fitted)
        spec._weights = KalmanNetWeights.from_bytes(data)
        return spec

    def build(self, ctx: FilterContext) -> KalmanNetFilter:
        return KalmanNetFilter(**ctx.kwargs(), weights=self.trained_weights)
