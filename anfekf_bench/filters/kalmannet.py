"""KalmanNet (Revach et al., IEEE TSP 70:1532-1547, 2022), architecture 1, on the robot's models.

The EKF's structure with the Kalman gain computed by a small recurrent network: the prior comes
from the known motion model f, the innovation from the known range-bearing h, and the gain K of
each landmark measurement from the network, which is trained end to end on the state error of
training runs (`kalmannet_train.train`, PyTorch, the optional extra `.[learned]`). Architecture 1
of the paper: an input layer, one GRU, an output layer (FC -> GRU -> FC -> K).

One gain per landmark measurement: a scan holds 0-2 landmarks; they are fused one after another,
the GRU's hidden state carried across them (and across scans). The network's inputs are the
paper's four features at each update, before the gain:

    F1 observation difference   z - z_prev, the same landmark's measurement at the previous scan
                                (zero when it was not seen there)
    F2 innovation               nu = z - h(x-), bearing wrapped
    F3 forward evolution diff.  x+_{t-1} - x+_{t-2}, the last two posteriors
    F4 forward update diff.     x+_{t-1} - x-_{t-1}, the last update's correction

each divided component-wise by a fixed scale measured on the training runs (so that metres and
radians weigh alike) and then L2-normalised as in the paper, plus the landmark's range r over a
range scale (the gain's geometry depends on it). Features and the gain live in the landmark's
line-of-sight frame (position rotated by the bearing angle of the landmark from the robot): there
the sensor Jacobian H = [[-1, 0, 0], [0, -1/r, -1]] depends on r alone, so one network serves
landmarks in every direction. The network's 3x2 output is scaled entry-wise by the magnitude
pattern of H's inverse ([[1, r], [1, r], [1/r, 1]]) and rotated back to the world frame.

It has no covariance: P is NaN, so its NEES (and NIS) is "not available" in tables and figures.
This module needs only numpy (the trained filter runs without PyTorch); training imports torch.
"""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import io
import json
import math
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, PrivateAttr, model_validator

from ..models import residual_z, wrap_scalar
from .ekf import FilterDiverged, RobotEKF
from .fitted import FittedSpec
from .spec import FilterContext

INSTALL_HINT = "kind kalmannet needs PyTorch: install the extra with pip install -e '.[learned]'"

N_STATE, N_OBS = 3, 2


def torch_available() -> bool:
    """Whether PyTorch can be imported (without importing it)."""
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):  # a module hidden with sys.modules["torch"] = None
        return False


# ---------------------------------------------------------------------------------------------
# Trained weights: plain numpy arrays, serialised deterministically


@dataclass
class KalmanNetWeights:
    """A trained network: its arrays (float64, the names of torch's modules) and what scales its
    inputs. `to_bytes` is deterministic (same weights, same bytes)."""

    arrays: dict[str, np.ndarray]
    obs_scale: np.ndarray  # (2,) range [m], bearing [rad]: divides F1 and F2
    state_scale: np.ndarray  # (3,) x, y [m], phi [rad]: divides F3 and F4
    range_scale: float  # [m]: divides the landmark range
    hidden_size: int

    def to_bytes(self) -> bytes:
        names = sorted(self.arrays)
        header = {
            "format": "anfekf-kalmannet-1",
            "hidden_size": self.hidden_size,
            "range_scale": self.range_scale,
            "obs_scale": [float(v) for v in self.obs_scale],
            "state_scale": [float(v) for v in self.state_scale],
            "arrays": [[n, list(self.arrays[n].shape)] for n in names],
        }
        out = io.BytesIO()
        out.write(json.dumps(header, sort_keys=True).encode() + b"\n")
        for n in names:
            out.write(np.ascontiguousarray(self.arrays[n], dtype="<f8").tobytes())
        return out.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> KalmanNetWeights:
        head, _, body = data.partition(b"\n")
        header = json.loads(head)
        if header.get("format") != "anfekf-kalmannet-1":
            raise ValueError("not a KalmanNet weights file (format anfekf-kalmannet-1)")
        arrays, offset = {}, 0
        for name, shape in header["arrays"]:
            size = math.prod(shape)
            arrays[name] = np.frombuffer(body, dtype="<f8", count=size, offset=8 * offset).reshape(
                shape
            )
            offset += size
        if 8 * offset != len(body):
            raise ValueError("KalmanNet weights file: size does not match its header")
        return cls(
            arrays=arrays,
            obs_scale=np.array(header["obs_scale"]),
            state_scale=np.array(header["state_scale"]),
            range_scale=float(header["range_scale"]),
            hidden_size=int(header["hidden_size"]),
        )


@dataclass
class TrainingResult:
    """What `train` returns: the weights, the training time [s] (for the manifest), the mean loss
    of each epoch and the CPU time [s]."""

    weights: KalmanNetWeights
    training_time_s: float  # wall
    epoch_loss: list[float] = field(default_factory=list)
    training_cpu_s: float = float("nan")  # this process's CPU time (a shared machine's wall lies)
    validation_loss: list[float] = field(default_factory=list)  # per epoch, on held-out runs

    @property
    def best_epoch(self) -> int:
        """The epoch (1-based) whose weights were kept: the lowest validation loss, or the last."""
        if not self.validation_loss:
            return len(self.epoch_loss)
        return int(np.argmin(self.validation_loss)) + 1


# ---------------------------------------------------------------------------------------------
# The network and one update, in numpy (the same maths as kalmannet_train's torch modules)


def _sigmoid(a: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-a))


def _normalize(v: np.ndarray) -> np.ndarray:
    """torch.nn.functional.normalize: v / max(|v|, 1e-12)."""
    return v / max(float(np.sqrt(v @ v)), 1e-12)


def gain_network(w: dict[str, np.ndarray], features: np.ndarray, hidden: np.ndarray):
    """Architecture 1: FC + ReLU, GRU cell (torch.nn.GRUCell's equations), FC + ReLU, FC.
    Returns the raw 3x2 gain and the new hidden state."""
    a = np.maximum(w["fc_in.weight"] @ features + w["fc_in.bias"], 0.0)
    H = len(hidden)
    gi = w["gru.weight_ih"] @ a + w["gru.bias_ih"]
    gh = w["gru.weight_hh"] @ hidden + w["gru.bias_hh"]
    r = _sigmoid(gi[:H] + gh[:H])
    z = _sigmoid(gi[H : 2 * H] + gh[H : 2 * H])
    n = np.tanh(gi[2 * H :] + r * gh[2 * H :])
    hidden = (1.0 - z) * n + z * hidden
    o = np.maximum(w["fc_out1.weight"] @ hidden + w["fc_out1.bias"], 0.0)
    k = w["fc_out2.weight"] @ o + w["fc_out2.bias"]
    return k.reshape(N_STATE, N_OBS), hidden


def state_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a - b
    d[2] = wrap_scalar(d[2])
    return d


class KalmanNetFilter(RobotEKF):
    """KalmanNet on the robot's motion model and range-bearing sensor (module docstring).

    The engine's interface of `RobotEKF` (predict, update_scan, x, R, Qu, the update counts);
    no covariance (P is NaN, `has_covariance` False), no gate (it has no S to gate with), so
    every measurement is fused and nis_sum stays NaN.
    """

    has_covariance: ClassVar[bool] = False

    def __init__(self, *args, weights: KalmanNetWeights, **kwargs):
        super().__init__(*args, **kwargs)
        self.w = weights.arrays
        self.weights = weights
        self.P = np.full((3, 3), np.nan)
        self.nis_sum = math.nan
        self.hidden = np.zeros(weights.hidden_size)
        self.x_post_prev = self.x.copy()  # x+_{t-1}
        self.x_post_prev2 = self.x.copy()  # x+_{t-2}
        self.x_prior_prev = self.x.copy()  # x-_{t-1}
        self.z_last: dict[int, np.ndarray] = {}  # landmark -> its z at the last scan
        self.z_scan: dict[int, np.ndarray] = {}

    def predict(self, u=0, dt: float | None = None):
        if dt is not None:
            self.dt = dt
        self.x = self.model.f(self.x, u, self.dt)

    def update_scan(self, zs: np.ndarray, landmarks: np.ndarray) -> None:
        # Landmarks are told apart by their map position (the engine passes positions).
        keys = [(float(lm[0]), float(lm[1])) for lm in landmarks]
        self.z_scan = {}
        for z, landmark, key in zip(zs, landmarks, keys, strict=True):
            z = np.asarray(z, dtype=float)
            prev = self.z_last.get(key)
            d1 = residual_z(z.copy(), prev) if prev is not None else np.zeros(N_OBS)
            self.update_with_gain(z, landmark, d1)
            self.z_scan[key] = z
        self.z_last = self.z_scan

    def update_with_gain(self, z: np.ndarray, landmark: np.ndarray, d1: np.ndarray) -> None:
        """One landmark: the features, the network's gain, x+ = x- + K nu."""
        x = self.x
        dx, dy = landmark[0] - x[0], landmark[1] - x[1]
        r = math.hypot(dx, dy)
        c, s = dx / r, dy / r
        nu = residual_z(z.copy(), np.array([r, wrap_scalar(math.atan2(dy, dx) - x[2])]))
        f3 = state_residual(self.x_post_prev, self.x_post_prev2)
        f4 = state_residual(self.x_post_prev, self.x_prior_prev)

        def local(v):  # world -> line-of-sight frame
            return np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])

        wts = self.weights
        features = np.concatenate(
            [
                _normalize(d1 / wts.obs_scale),
                _normalize(nu / wts.obs_scale),
                _normalize(local(f3) / wts.state_scale),
                _normalize(local(f4) / wts.state_scale),
                [r / wts.range_scale],
            ]
        )
        k_raw, self.hidden = gain_network(self.w, features, self.hidden)
        K_local = k_raw * np.array([[1.0, r], [1.0, r], [1.0 / r, 1.0]])
        K = np.vstack(
            [c * K_local[0] - s * K_local[1], s * K_local[0] + c * K_local[1], K_local[2]]
        )
        x_post = x + K @ nu
        x_post[2] = wrap_scalar(x_post[2])
        if not np.isfinite(x_post).all():
            raise FilterDiverged("KalmanNet estimate is not finite")
        self.x_post_prev2, self.x_post_prev, self.x_prior_prev = self.x_post_prev, x_post, x
        self.x = x_post
        self.n_updates += 1


# ---------------------------------------------------------------------------------------------
# The scenario's spec


class KalmanNetSpec(FittedSpec):
    """KalmanNet (Revach et al. 2022, architecture 1): the EKF's structure with each landmark's
    gain from a GRU, trained on the scenario's training runs (`training.runs`, see
    anfekf_bench.training) or, on recorded data, on the training drives of each cross-drive fold
    (or the training segments; anfekf_bench.real_training); the extra `.[learned]`; no
    covariance, no NEES.

    A fitted filter like `ekf-ml`: `fit` trains on the training set and returns the weights
    (base64 of `KalmanNetWeights.to_bytes`, their SHA-256) with the training cost, which the
    experiment caches by fingerprint and records in the manifest's `training` key."""

    kind: Literal["kalmannet"]
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
        """Train on the training set's runs (all `training.runs` of them, the last
        `validation_runs` held out); the weights and the cost, JSON-able."""
        from .registry import filter_context

        ctx = filter_context(self, training.scenario, training.world)
        return self.fitted_doc(
            self.train(training.runs, training.world, ctx, progress=training.progress)
        )

    def fit_recorded(self, drives, model, progress=False, description: str | None = None) -> dict:
        """`fit` on recorded training drives: (Timeline, truth at its evaluation times, NaN
        where not scored) pairs on the unicycle `model` (kalmannet_train.train_recorded)."""
        from . import kalmannet_train

        return self.fitted_doc(
            kalmannet_train.train_recorded(self, drives, model, progress, description)
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

    def with_fit(self, fitted: dict) -> KalmanNetSpec:
        data = base64.b64decode(fitted["weights_base64"])
        if hashlib.sha256(data).hexdigest() != fitted["weights_sha256"]:
            raise ValueError(f"kalmannet {self.name!r}: the fitted weights do not match their hash")
        spec = super().with_fit(fitted)
        spec._weights = KalmanNetWeights.from_bytes(data)
        return spec

    def build(self, ctx: FilterContext) -> KalmanNetFilter:
        if self._weights is None:
            raise RuntimeError(f"kalmannet filter {self.name!r} has no trained weights")
        return KalmanNetFilter(**ctx.kwargs(), weights=self._weights)
