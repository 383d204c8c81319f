"""KalmanNet (Revach et al., IEEE TSP 70:1532-1547, 2022), architecture 1, on the robot's models:
the network, its weights and the filter (the spec, `kind: kalmannet`, is in `kalmannet`).

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
import functools
import hashlib
import importlib.util
import io
import json
import math
import re
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..models import wrap_scalar
from .ekf import FilterDiverged, RobotEKF

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

    @functools.cached_property
    def net(self) -> tuple[np.ndarray, ...]:
        """The arrays in the order of `NET_ARRAYS`, as both engines take them: each layer's
        weight matrix transposed (inputs x outputs: the compiled product then runs along
        contiguous rows of outputs), C-contiguous, writable float64 copies (a read-only array
        would be another compiled signature)."""
        return tuple(
            np.array(self.arrays[n].T, dtype=np.float64, order="C")  # (a bias: itself)
            for n in NET_ARRAYS
        )  # fmt: skip

    @property
    def scales(self) -> tuple[float, ...]:
        """(obs_scale, state_scale, range_scale) as the 6 floats `gain_update` takes."""
        return (*map(float, self.obs_scale), *map(float, self.state_scale), float(self.range_scale))

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
    def random(
        cls, hidden_size: int = 32, seed: int = 0, obs_scale=(0.1, 0.02),
        state_scale=(0.3, 0.3, 0.03), range_scale: float = 10.0,
    ) -> KalmanNetWeights:  # fmt: skip
        """An untrained network of seeded random weights (torch's default initialisation,
        uniform within 1/sqrt(fan_in)) whose output layer starts near a damped inverse of the
        sensor Jacobian (range corrects the position along the line of sight, bearing the
        lateral position and the heading), so that a filter with it tracks: for tests and the
        bench, which need a network without PyTorch, not a trained filter."""
        rng = np.random.default_rng(seed)
        H, n_out = hidden_size, N_STATE * N_OBS

        def uniform(shape, fan_in):
            return rng.uniform(-1.0, 1.0, shape) / math.sqrt(fan_in)

        arrays = {
            "fc_in.weight": uniform((H, N_FEATURES), N_FEATURES),
            "fc_in.bias": uniform(H, N_FEATURES),
            "gru.weight_ih": uniform((3 * H, H), H),
            "gru.bias_ih": uniform(3 * H, H),
            "gru.weight_hh": uniform((3 * H, H), H),
            "gru.bias_hh": uniform(3 * H, H),
            "fc_out1.weight": uniform((H, H), H),
            "fc_out1.bias": uniform(H, H),
            "fc_out2.weight": 0.05 * uniform((n_out, H), H),
            "fc_out2.bias": np.array([-0.3, 0.0, 0.0, -0.1, 0.0, -0.2]),
        }
        return cls(
            arrays=arrays, obs_scale=np.array(obs_scale, dtype=float),
            state_scale=np.array(state_scale, dtype=float), range_scale=float(range_scale),
            hidden_size=H,
        )  # fmt: skip

    @classmethod
    def from_bytes(cls, data: bytes) -> KalmanNetWeights:
        """The weights `to_bytes` wrote; ValueError (one phrase) for anything else: a header
        that is not this format's, negative or inconsistent shapes, scales that are not
        finite and positive, a body of another size, values that are not finite."""
        head, _, body = data.partition(b"\n")
        try:
            header = json.loads(head.decode("utf-8"))
        except ValueError:  # not UTF-8 (UnicodeDecodeError is one) or not JSON
            raise ValueError("KalmanNet weights: the header is not JSON") from None
        if not isinstance(header, dict) or header.get("format") != "anfekf-kalmannet-1":
            raise ValueError("not a KalmanNet weights file (format anfekf-kalmannet-1)")
        hidden = header.get("hidden_size")
        if not _whole(hidden) or not 1 <= hidden <= 1024:
            raise ValueError("KalmanNet weights: hidden_size must be an integer in [1, 1024]")
        obs_scale = _positive_floats(header.get("obs_scale"), "obs_scale")
        state_scale = _positive_floats(header.get("state_scale"), "state_scale")
        (range_scale,) = _positive_floats([header.get("range_scale")], "range_scale")
        listed = header.get("arrays")
        if not isinstance(listed, list) or not all(
            isinstance(item, list) and len(item) == 2 and isinstance(item[0], str)
            and isinstance(item[1], list) and all(_whole(n) and n >= 0 for n in item[1])
            for item in listed
        ):  # fmt: skip
            raise ValueError("KalmanNet weights: arrays must be [name, [sizes >= 0]] pairs")
        shapes = {name: tuple(shape) for name, shape in listed}
        if len(shapes) != len(listed) or set(shapes) != set(NET_ARRAYS):
            raise ValueError(f"KalmanNet weights: the arrays must be {', '.join(NET_ARRAYS)}")
        if len(body) != 8 * sum(math.prod(shape) for shape in shapes.values()):
            raise ValueError("KalmanNet weights file: size does not match its header")
        arrays, offset = {}, 0
        for name, shape in listed:
            size = math.prod(shape)
            arrays[name] = np.frombuffer(body, dtype="<f8", count=size, offset=8 * offset).reshape(
                shape
            )
            offset += size
        if not all(np.isfinite(a).all() for a in arrays.values()):
            raise ValueError("KalmanNet weights: a weight is not finite")
        return cls(
            arrays=arrays,
            obs_scale=obs_scale,
            state_scale=state_scale,
            range_scale=float(range_scale),
            hidden_size=int(hidden),
        )


def _whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _positive_floats(values, name: str) -> np.ndarray:
    """`values` as finite, positive floats (the scales the features are divided by)."""
    ok = isinstance(values, list) and len(values) >= 1 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
        for v in values
    )  # fmt: skip
    if not ok:
        raise ValueError(f"KalmanNet weights: {name} must be finite numbers > 0")
    return np.array(values, dtype=float)


def weight_shapes(hidden_size: int) -> dict[str, tuple[int, ...]]:
    """Each array of the robot's network of `hidden_size` and its shape (torch's layout, as
    `random`; `kalmannet_train` trains other systems' networks too, of other shapes)."""
    H = hidden_size
    return {
        "fc_in.weight": (H, N_FEATURES), "fc_in.bias": (H,),
        "gru.weight_ih": (3 * H, H), "gru.bias_ih": (3 * H,),
        "gru.weight_hh": (3 * H, H), "gru.bias_hh": (3 * H,),
        "fc_out1.weight": (H, H), "fc_out1.bias": (H,),
        "fc_out2.weight": (N_STATE * N_OBS, H), "fc_out2.bias": (N_STATE * N_OBS,),
    }  # fmt: skip


def fitted_weights_problem(fitted, hidden_size: int) -> str | None:
    """Why `fitted` (what `KalmanNetSpec.fitted_doc` returns, read back from the fit cache)
    cannot give a network of `hidden_size`, or None: the weights (base64, strict) must hash to
    `weights_sha256` and be a valid weights file of that size (`from_bytes`); the cost fields
    numbers. Needs no PyTorch."""
    if not isinstance(fitted, dict):
        return "fitted: must be a mapping"
    digest, encoded = fitted.get("weights_sha256"), fitted.get("weights_base64")
    if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
        return "weights_sha256: must be 64 hexadecimal digits"
    if not isinstance(encoded, str):
        return "weights_base64: must be text (base64)"
    try:
        data = base64.b64decode(encoded, validate=True)
    except ValueError:  # binascii.Error is one
        return "weights_base64: not valid base64"
    if hashlib.sha256(data).hexdigest() != digest:
        return "weights_base64: the weights do not match weights_sha256"
    try:
        weights = KalmanNetWeights.from_bytes(data)
    except ValueError as exc:
        return f"weights_base64: {exc}"
    if weights.hidden_size != hidden_size:
        return f"weights_base64: a network of hidden_size {weights.hidden_size}, not {hidden_size}"
    shapes = {name: array.shape for name, array in weights.arrays.items()}
    if shapes != weight_shapes(hidden_size) or (
        (len(weights.obs_scale), len(weights.state_scale)) != (N_OBS, N_STATE)
    ):
        return "weights_base64: not the robot's network (its arrays' shapes or its scales)"
    epochs = fitted.get("epochs")
    if not _whole(epochs) or epochs < 1 or not _whole(fitted.get("best_epoch")):
        return "epochs, best_epoch: must be integers >= 1"
    for key in ("epoch_loss", "validation_loss"):
        values = fitted.get(key)
        if not isinstance(values, list) or not all(
            v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in values
        ):
            return f"{key}: must be a list of numbers"
    return None


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
# The network and one landmark's update, written once as plain array functions: the filterpy
# engine's `KalmanNetFilter` calls them with numpy, the fast engine's kernel
# (engines/kernels_kalmannet.py) compiles the same functions with numba (`register_jitable`).
# Scalars are floats and tuples (elementwise functions work on floats and on arrays alike); the
# three primitives that map over a layer (`affine`, `relu_in_place`, `gru_update`) are numpy
# here and plain loops there (numba `overload`s), each writing into a buffer of `work_arrays`.

# The network's arrays in the order the functions below take them (torch's module names)
NET_ARRAYS = (
    "fc_in.weight", "fc_in.bias", "gru.weight_ih", "gru.bias_ih", "gru.weight_hh",
    "gru.bias_hh", "fc_out1.weight", "fc_out1.bias", "fc_out2.weight", "fc_out2.bias",
)  # fmt: skip
N_FEATURES = 2 * N_OBS + 2 * N_STATE + 1  # F1, F2, F3, F4 and the range


def sigmoid(a):
    return 1.0 / (1.0 + np.exp(-a))


def relu(a):
    return np.maximum(a, 0.0)


def gru_unit(ir, iz, i_n, hr, hz, hn, h):
    """torch.nn.GRUCell's equations for one unit (or elementwise over arrays of units): the
    input's and the hidden state's parts of the reset, update and new gates, the old state h;
    returns the new state."""
    r = sigmoid(ir + hr)
    z = sigmoid(iz + hz)
    n = np.tanh(i_n + r * hn)
    return (1.0 - z) * n + z * h


def affine(Wt, v, b, out):
    """out = W v + b, given Wt = W^T (inputs x outputs); returns out."""
    np.matmul(v, Wt, out=out)
    out += b
    return out


def relu_in_place(v):
    """v = relu(v); returns v."""
    v[:] = relu(v)
    return v


def gru_update(gi, gh, h):
    """h = the GRU cell's new state (`gru_unit` over every unit), gi = W_ih a + b_ih and
    gh = W_hh h + b_hh stacked as (reset, update, new)."""
    H = h.shape[0]
    h[:] = gru_unit(gi[:H], gi[H : 2 * H], gi[2 * H :], gh[:H], gh[H : 2 * H], gh[2 * H :], h)


def work_arrays(net):
    """The buffers `gain_network` writes (features, a, gi, gh, o, k), sized by `net`."""
    Wt_in, Wt_ih, Wt_hh, Wt_o1, Wt_o2 = net[0], net[2], net[4], net[6], net[8]
    return (
        np.zeros(Wt_in.shape[0]), np.zeros(Wt_in.shape[1]), np.zeros(Wt_ih.shape[1]),
        np.zeros(Wt_hh.shape[1]), np.zeros(Wt_o1.shape[1]), np.zeros(Wt_o2.shape[1]),
    )  # fmt: skip


def gain_network(net, hidden, work):
    """Architecture 1: FC + ReLU, GRU cell (torch.nn.GRUCell's equations), FC + ReLU, FC, on
    the features in work[0]. `net`: the arrays of NET_ARRAYS (`KalmanNetWeights.net`: weights
    transposed); `hidden` is updated in place. Returns the raw gain (n * m,), row-major (a
    buffer of `work`)."""
    Wt_in, b_in, Wt_ih, b_ih, Wt_hh, b_hh, Wt_o1, b_o1, Wt_o2, b_o2 = net
    features, a, gi, gh, o, k = work
    relu_in_place(affine(Wt_in, features, b_in, a))
    affine(Wt_ih, a, b_ih, gi)
    affine(Wt_hh, hidden, b_hh, gh)
    gru_update(gi, gh, hidden)
    relu_in_place(affine(Wt_o1, hidden, b_o1, o))
    return affine(Wt_o2, o, b_o2, k)


def normalized2(a, b):
    """torch.nn.functional.normalize of (a, b): divided by max(|(a, b)|, 1e-12)."""
    n = max(math.sqrt(a * a + b * b), 1e-12)
    return a / n, b / n


def normalized3(a, b, c):
    """`normalized2` of a 3-vector."""
    n = max(math.sqrt(a * a + b * b + c * c), 1e-12)
    return a / n, b / n, c / n


def state_change(a, b):
    """a - b (3-tuples), heading wrapped."""
    return a[0] - b[0], a[1] - b[1], wrap_scalar(a[2] - b[2])


def gain_update(
    x, lx, ly, z0, z1, seen, p0, p1, post_prev, post_prev2, prior_prev, scales, net, hidden,
    work,
):  # fmt: skip
    """One landmark (module docstring): the features, the network's gain, x+ = x- + K nu.

    x, post_prev (x+_{t-1}), post_prev2 (x+_{t-2}), prior_prev (x-_{t-1}): 3-tuples; (lx, ly)
    the landmark, (z0, z1) its measurement, (p0, p1) its measurement at the last scan when
    `seen`; scales = (obs_scale[0], obs_scale[1], state_scale[0..2], range_scale). Returns x+
    (a 3-tuple, heading wrapped); `hidden` and `work` are updated in place."""
    x0, x1, x2 = x
    dx, dy = lx - x0, ly - x1
    r = math.hypot(dx, dy)
    c, s = dx / r, dy / r
    # F2: nu = residual_z(z, h(x-)), F1: residual_z(z, z at the last scan) or 0
    nu0 = z0 - r
    nu1 = wrap_scalar(z1 - wrap_scalar(math.atan2(dy, dx) - x2))
    d0, d1 = (z0 - p0, wrap_scalar(z1 - p1)) if seen else (0.0, 0.0)
    f3 = state_change(post_prev, post_prev2)
    f4 = state_change(post_prev, prior_prev)
    so0, so1, ss0, ss1, ss2, sr = scales
    features = work[0]
    features[0], features[1] = normalized2(d0 / so0, d1 / so1)
    features[2], features[3] = normalized2(nu0 / so0, nu1 / so1)
    # F3, F4 in the landmark's line-of-sight frame
    features[4], features[5], features[6] = normalized3(
        (c * f3[0] + s * f3[1]) / ss0, (-s * f3[0] + c * f3[1]) / ss1, f3[2] / ss2
    )
    features[7], features[8], features[9] = normalized3(
        (c * f4[0] + s * f4[1]) / ss0, (-s * f4[0] + c * f4[1]) / ss1, f4[2] / ss2
    )
    features[10] = r / sr
    k = gain_network(net, hidden, work)
    # K_local = k * H^-1's magnitude pattern [[1, r], [1, r], [1/r, 1]], rotated back
    l00, l01, l10, l11 = k[0] * 1.0, k[1] * r, k[2] * 1.0, k[3] * r
    l20, l21 = k[4] * (1.0 / r), k[5] * 1.0
    K00, K01 = c * l00 - s * l10, c * l01 - s * l11
    K10, K11 = s * l00 + c * l10, s * l01 + c * l11
    return (
        x0 + (K00 * nu0 + K01 * nu1),
        x1 + (K10 * nu0 + K11 * nu1),
        wrap_scalar(x2 + (l20 * nu0 + l21 * nu1)),
    )


class KalmanNetFilter(RobotEKF):
    """KalmanNet on the robot's motion model and range-bearing sensor (module docstring).

    The engine's interface of `RobotEKF` (predict, update_scan, x, R, Qu, the update counts);
    no covariance (P is NaN, `has_covariance` False), no gate (it has no S to gate with), so
    every measurement is fused and nis_sum stays NaN. Each landmark's update is `gain_update`.
    """

    has_covariance: ClassVar[bool] = False

    def __init__(self, *args, weights: KalmanNetWeights, **kwargs):
        super().__init__(*args, **kwargs)
        self.weights = weights
        self.net = weights.net
        self.scales = weights.scales
        self.work = work_arrays(self.net)
        self.P = np.full((3, 3), np.nan)
        self.nis_sum = math.nan
        self.hidden = np.zeros(weights.hidden_size)
        x = tuple(self.x.tolist())
        self.x_post_prev = x  # x+_{t-1}
        self.x_post_prev2 = x  # x+_{t-2}
        self.x_prior_prev = x  # x-_{t-1}
        self.z_last: dict[tuple[float, float], tuple[float, float]] = {}  # at the last scan

    def predict(self, u=0, dt: float | None = None):
        if dt is not None:
            self.dt = dt
        self.x = self.model.f(self.x, u, self.dt)

    def update_scan(self, zs: np.ndarray, landmarks: np.ndarray) -> None:
        # Landmarks are told apart by their map position (the engine passes positions); one
        # seen twice in a scan keeps its last measurement, as the kernel does.
        z_scan = {}
        for (z0, z1), (lx, ly) in zip(zs.tolist(), landmarks.tolist(), strict=True):
            prev = self.z_last.get((lx, ly))
            self.update_with_gain(z0, z1, lx, ly, prev)
            z_scan[(lx, ly)] = (z0, z1)
        self.z_last = z_scan

    def update_with_gain(self, z0: float, z1: float, lx: float, ly: float, prev) -> None:
        """One landmark (`gain_update`); `prev`: its measurement at the last scan, or None."""
        x = tuple(self.x.tolist())
        p0, p1 = (0.0, 0.0) if prev is None else prev
        x_post = gain_update(
            x, lx, ly, z0, z1, prev is not None, p0, p1, self.x_post_prev, self.x_post_prev2,
            self.x_prior_prev, self.scales, self.net, self.hidden, self.work,
        )  # fmt: skip
        if not all(map(math.isfinite, x_post)):
            raise FilterDiverged("KalmanNet estimate is not finite")
        self.x_post_prev2, self.x_post_prev, self.x_prior_prev = self.x_post_prev, x_post, x
        self.x = np.array(x_post)
        self.n_updates += 1
