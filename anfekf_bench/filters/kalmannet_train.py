"""Training KalmanNet (architecture 1) with PyTorch on CPU: the optional extra `.[learned]`.

Imported only to train (`KalmanNetSpec.train`); the trained filter runs in numpy
(filters/kalmannet.py). The core is generic over a `System` (the known f and h, the frame the
gain is computed in, and the entry-wise scale of the gain), so that the same code trains the
robot's filter on the simulator's bicycle (`RobotSystem`), on recorded drives' unicycle with a
step length per step (`UnicycleSystem`) and the linear-Gaussian check of the tests (`LinearSystem`).

Training (the paper's recipe): Adam on the mean squared state error at every target step (the
scan steps, where the benchmark scores), truncated back-propagation through time every `bptt`
measurement updates, gradient norm clipped at 1 (KalmanNet's known NaN losses), float64.
A batch holds runs with the same schedule of controls and scans (every simulated run of a world
has the same one: the truth path is shared, only the noise differs), so their steps run as one
tensor operation. Recorded drives have no common schedule: their training windows
(`windows_of_drive`) are aligned stamp by stamp (`recorded_batch`), and an event carries a mask of
the windows it applies to (the others keep their state exactly). Deterministic on CPU for a seed:
torch.manual_seed, deterministic algorithms, one thread, a fixed batch order drawn from the seed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..models import Bicycle, Unicycle, residual_z
from .kalmannet_net import KalmanNetWeights, TrainingResult

DTYPE = torch.float64
HEADING_WEIGHT_M = 1.0  # loss = ex^2 + ey^2 + (HEADING_WEIGHT_M * ephi)^2 [m^2]
GRAD_CLIP = 1.0


def wrap(a: torch.Tensor) -> torch.Tensor:
    """models.angles.wrap_angle in torch: (-pi, pi]."""
    return -(torch.remainder(-a + math.pi, 2 * math.pi) - math.pi)


# ---------------------------------------------------------------------------------------------
# Systems: the known models, batched over runs


class RobotSystem:
    """The bicycle (eq. 17) and the range-bearing sensor, in the landmark's line-of-sight frame
    (filters/kalmannet.py says why); `aux` of a measurement is its landmark (B, 2)."""

    n, m, g = 3, 2, 1

    def __init__(self, T: float, B: float, range_scale: float):
        self.T, self.B, self.range_scale = T, B, range_scale

    def f(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        V, gamma = u[:, 0], u[:, 1]
        a = x[:, 2] + gamma
        return torch.stack(
            [
                x[:, 0] + self.T * V * torch.cos(a),
                x[:, 1] + self.T * V * torch.sin(a),
                wrap(x[:, 2] + self.T * V * torch.sin(gamma) / self.B),
            ],
            dim=1,
        )

    def prepare_span(self, u: torch.Tensor):
        """What `f_span` needs of the controls u (S, B, 2) of S steps, computed from the data
        once: the heading's increments do not depend on the state, so after S steps of f

            phi+ = phi + D,   x+ = x + cos(phi) A - sin(phi) C,   y+ = y + sin(phi) A + cos(phi) C

        with c_j = gamma_j + (the increments before step j), A = sum T V_j cos(c_j) and
        C = sum T V_j sin(c_j): the same values as S calls of f up to round-off, and a dozen
        graph nodes per span instead of a dozen per step."""
        V, gamma = u[..., 0], u[..., 1]
        dphi = self.T * V * torch.sin(gamma) / self.B  # (S, B)
        c = gamma + torch.cumsum(dphi, dim=0) - dphi
        step = self.T * V
        return torch.sum(step * torch.cos(c), 0), torch.sum(step * torch.sin(c), 0), dphi.sum(0)

    def f_span(self, x: torch.Tensor, span) -> torch.Tensor:
        A, C, D = span
        cos, sin = torch.cos(x[:, 2]), torch.sin(x[:, 2])
        return torch.stack(
            [x[:, 0] + cos * A - sin * C, x[:, 1] + sin * A + cos * C, wrap(x[:, 2] + D)], dim=1
        )

    def measure(self, x: torch.Tensor, landmark: torch.Tensor):
        """z_hat, the world -> local rotation (B, n, n), geometry inputs (B, g) and the gain's
        entry-wise scale (B, n, m)."""
        dx, dy = landmark[:, 0] - x[:, 0], landmark[:, 1] - x[:, 1]
        r = torch.sqrt(dx * dx + dy * dy)
        c, s = dx / r, dy / r
        z_hat = torch.stack([r, wrap(torch.atan2(dy, dx) - x[:, 2])], dim=1)
        zero, one = torch.zeros_like(r), torch.ones_like(r)
        rot = torch.stack(
            [torch.stack([c, s, zero], 1), torch.stack([-s, c, zero], 1),
             torch.stack([zero, zero, one], 1)], dim=1,
        )  # fmt: skip
        scale = torch.stack(
            [torch.stack([one, r], 1), torch.stack([one, r], 1), torch.stack([1 / r, one], 1)],
            dim=1,
        )
        return z_hat, rot, (r / self.range_scale)[:, None], scale

    def residual_z(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        d = a - b
        return torch.cat([d[:, :1], wrap(d[:, 1:])], dim=1)

    def residual_x(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        d = a - b
        return torch.cat([d[:, :2], wrap(d[:, 2:])], dim=1)

    def wrap_x(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x[:, :2], wrap(x[:, 2:])], dim=1)

    def loss_weights(self) -> torch.Tensor:
        return torch.tensor([1.0, 1.0, HEADING_WEIGHT_M**2], dtype=DTYPE)


class UnicycleSystem(RobotSystem):
    """The unicycle of recorded logs (models.unicycle: midpoint Euler) with the range-bearing
    sensor; a control is (v, w, dt): each step has its own length."""

    def __init__(self, range_scale: float):
        self.range_scale = range_scale

    def f(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        v, w, dt = u[:, 0], u[:, 1], u[:, 2]
        a = x[:, 2] + 0.5 * w * dt
        return torch.stack(
            [x[:, 0] + v * dt * torch.cos(a), x[:, 1] + v * dt * torch.sin(a),
             wrap(x[:, 2] + w * dt)], dim=1,
        )  # fmt: skip

    def prepare_span(self, u: torch.Tensor):
        """`RobotSystem.prepare_span` for the unicycle, u (S, B, 3): the heading's increments
        w dt do not depend on the state, so S steps are phi+ = phi + D and the rotated sums A, C
        of v dt at the midpoint angles c_j = (the increments before step j) + w_j dt_j / 2. A
        step of zeros (v = w = dt = 0, the padding of `recorded_batch`) adds exactly nothing."""
        v, w, dt = u[..., 0], u[..., 1], u[..., 2]
        dphi = w * dt
        c = torch.cumsum(dphi, dim=0) - dphi + 0.5 * dphi
        step = v * dt
        return torch.sum(step * torch.cos(c), 0), torch.sum(step * torch.sin(c), 0), dphi.sum(0)


class LinearSystem:
    """x+ = F x (+ noise), z = H x (+ noise): the linear-Gaussian check (no frame, no scale)."""

    g = 0

    def __init__(self, F: np.ndarray, H: np.ndarray):
        self.F = torch.as_tensor(F, dtype=DTYPE)
        self.H = torch.as_tensor(H, dtype=DTYPE)
        self.m, self.n = self.H.shape
        self.range_scale = 1.0

    def f(self, x, u):
        return x @ self.F.T

    def prepare_span(self, u):
        return len(u)

    def f_span(self, x, steps: int):
        for _ in range(steps):
            x = self.f(x, None)
        return x

    def measure(self, x, aux):
        B = len(x)
        eye = torch.eye(self.n, dtype=DTYPE).expand(B, -1, -1)
        ones = torch.ones(B, self.n, self.m, dtype=DTYPE)
        return x @ self.H.T, eye, torch.zeros(B, 0, dtype=DTYPE), ones

    def residual_z(self, a, b):
        return a - b

    def residual_x(self, a, b):
        return a - b

    def wrap_x(self, x):
        return x

    def loss_weights(self):
        return torch.ones(self.n, dtype=DTYPE)


# ---------------------------------------------------------------------------------------------
# Batches of aligned runs as events


@dataclass
class Batch:
    """Runs with one schedule, as a list of events over tensors batched on the runs:
    ("f", span): steps of the motion model (`system.prepare_span` of their controls);
    ("z", z (B, m), aux (B, a), d1 (B, m)): a measurement, aux its landmark, d1 the feature F1;
    ("target", x_true (B, n)): where the loss compares the estimate with the truth."""

    x0: torch.Tensor
    events: list


def robot_batch(system: RobotSystem, runs, world) -> Batch:
    """The events of simulated runs of one world (one schedule: asserted). F1 is the same
    landmark's measurement at the previous scan that saw a landmark (the numpy filter's rule)."""
    first = runs[0]
    K = len(first.u_odo)
    for run in runs[1:]:
        same = len(run.u_odo) == K and len(run.scans) == len(first.scans)
        same = same and all(
            a.step == b.step and np.array_equal(a.ids, b.ids)
            for a, b in zip(run.scans, first.scans, strict=True)
        )
        if not same:
            raise ValueError("training runs of one batch must share the schedule of scans")
    u = torch.as_tensor(np.stack([r.u_odo for r in runs], axis=1), dtype=DTYPE)  # (K, B, 2)
    scans = {s.step: i for i, s in enumerate(first.scans)}
    events: list = []
    last: dict[int, torch.Tensor] = {}
    start = 0  # first control step not yet in an "f" event
    for k in range(1, K + 1):
        if k % world.sensor_every and k < K:
            continue
        events.append(("f", system.prepare_span(u[start:k])))
        start = k
        if k % world.sensor_every:
            break
        i = scans.get(k)
        if i is not None and len(first.scans[i].ids):
            seen: dict[int, torch.Tensor] = {}
            for j, lm in enumerate(first.scans[i].ids.tolist()):
                z = torch.as_tensor(np.stack([r.scans[i].z[j] for r in runs]), dtype=DTYPE)
                if lm in last:
                    d = z - last[lm]
                    d1 = torch.cat([d[:, :1], wrap(d[:, 1:])], dim=1)
                else:
                    d1 = torch.zeros_like(z)
                landmark = torch.as_tensor(world.landmarks[lm], dtype=DTYPE).expand(len(runs), 2)
                events.append(("z", z, landmark, d1))
                seen[lm] = z
            last = seen
        truth = torch.as_tensor(first.truth.x[k], dtype=DTYPE).expand(len(runs), 3)
        events.append(("target", truth))
    x0 = torch.as_tensor(first.truth.x[0], dtype=DTYPE).expand(len(runs), 3).clone()
    return Batch(x0=x0, events=events)


@dataclass(frozen=True, eq=False)
class TrainingWindow:
    """A stretch of a recorded drive to train on, cold-started from ground truth: x0 at the
    stamp before `timeline`'s first (`timeline` holds the stamps after it, as
    engines.events.Timeline), and the truth (n_records, 3) at its evaluation times, NaN where
    it is not scored (the loss leaves those out)."""

    x0: np.ndarray
    timeline: object  # engines.events.Timeline
    truth: np.ndarray


def windows_of_drive(tl, truth: np.ndarray, window_s: float) -> list[TrainingWindow]:
    """A drive's timeline `tl` (engines.events.Timeline) and its truth at the evaluation times
    (NaN where not scored) cut into windows of about `window_s` seconds. Each starts at a scored
    evaluation time, from the truth there, and runs to the next window's start (the last to the
    end); a window without a scored time after its start is left out."""
    from dataclasses import replace

    rec = np.flatnonzero(tl.record)  # stamp of each evaluation time
    ok = np.all(np.isfinite(truth), axis=1)
    starts, last = [], -math.inf
    for i in np.flatnonzero(ok).tolist():
        if tl.t[rec[i]] - last >= window_s:
            starts.append(i)
            last = tl.t[rec[i]]
    out = []
    for j, i in enumerate(starts):
        a = rec[i] + 1  # first stamp after the start
        b = rec[starts[j + 1]] + 1 if j + 1 < len(starts) else len(tl.t)
        lo, hi = int(tl.lm[a]), int(tl.lm[b])
        part = replace(
            tl, t_start=float(tl.t[a - 1]), t=tl.t[a:b], dt=tl.dt[a:b], u=tl.u[a:b],
            lm=tl.lm[a : b + 1] - lo, z=tl.z[lo:hi], xy=tl.xy[lo:hi], record=tl.record[a:b],
        )  # fmt: skip
        n_before = int(np.sum(tl.record[:a]))
        window_truth = truth[n_before : n_before + int(part.record.sum())]
        if len(part.t) and np.all(np.isfinite(window_truth), axis=1).any():
            out.append(TrainingWindow(np.array(truth[i], dtype=float), part, window_truth))
    return out


# A masked-out measurement still runs through the (batched) arithmetic: its landmark is put far
# away so that every value stays finite (a NaN there would poison the gradient through `where`).
_FAR_LANDMARK = (1e3, 1e3)


def recorded_batch(system, windows: list[TrainingWindow]) -> Batch:
    """The events of training windows of recorded drives, aligned stamp by stamp: slot j holds
    the j-th "unit" of every window (the steps up to a stamp with a landmark or an evaluation
    time, its landmarks, its target), each event masked to the windows that have it. The steps
    of a unit are (v, w, dt), padded with zero steps; F1 is as `robot_batch`'s (the same
    landmark, told apart by its map position, at the previous stamp with a landmark)."""
    B = len(windows)
    per_window = []
    for w in windows:
        tl, units, steps, last, j = w.timeline, [], [], {}, 0
        lm = tl.lm.tolist()
        for k in range(len(tl.t)):
            steps.append((float(tl.u[k, 0]), float(tl.u[k, 1]), float(tl.dt[k])))
            zs = []
            if lm[k + 1] > lm[k]:
                seen = {}
                for i in range(lm[k], lm[k + 1]):
                    key = (float(tl.xy[i, 0]), float(tl.xy[i, 1]))
                    z = tl.z[i].astype(float)
                    prev = last.get(key)
                    d1 = np.zeros(2) if prev is None else residual_z(z.copy(), prev)
                    zs.append((z, tl.xy[i].astype(float), d1))
                    seen[key] = z
                last = seen
            target = None
            if tl.record[k]:
                target = w.truth[j]
                j += 1
            if zs or target is not None:
                units.append((steps, zs, target))
                steps = []
        per_window.append(units)
    n_slots = max((len(u) for u in per_window), default=0)
    events: list = []
    for j in range(n_slots):
        here = [u[j] if j < len(u) else None for u in per_window]
        has = torch.tensor([h is not None for h in here])
        S = max(len(h[0]) for h in here if h is not None)
        u = np.zeros((S, B, 3))
        for b, h in enumerate(here):
            if h is not None:
                u[: len(h[0]), b] = h[0]
        events.append(("f", system.prepare_span(torch.as_tensor(u, dtype=DTYPE)), has))
        n_z = max(len(h[1]) if h is not None else 0 for h in here)
        for i in range(n_z):
            z, aux, d1 = np.zeros((B, 2)), np.tile(_FAR_LANDMARK, (B, 1)), np.zeros((B, 2))
            mask = np.zeros(B, bool)
            for b, h in enumerate(here):
                if h is not None and i < len(h[1]):
                    z[b], aux[b], d1[b] = h[1][i]
                    mask[b] = True
            z, aux, d1 = (torch.as_tensor(a, dtype=DTYPE) for a in (z, aux, d1))
            events.append(("z", z, aux, d1, torch.as_tensor(mask)))
        truth, mask = np.zeros((B, 3)), np.zeros(B, bool)
        for b, h in enumerate(here):
            if h is not None and h[2] is not None and np.all(np.isfinite(h[2])):
                truth[b], mask[b] = h[2], True
        if mask.any():
            events.append(("target", torch.as_tensor(truth, dtype=DTYPE), torch.as_tensor(mask)))
    x0 = torch.as_tensor(np.stack([w.x0 for w in windows]), dtype=DTYPE)
    return Batch(x0=x0, events=events)


def linear_batch(x_true: np.ndarray, z: np.ndarray) -> Batch:
    """The events of sequences of a `LinearSystem`: x_true (B, T + 1, n) from x_true[:, 0], z
    (B, T, m) the measurement of x_true[:, t + 1]; F1 = z_t - z_{t-1} (zero at the first)."""
    x_true, z = (torch.as_tensor(a, dtype=DTYPE) for a in (x_true, z))
    events: list = []
    for t in range(z.shape[1]):
        d1 = z[:, t] - z[:, t - 1] if t else torch.zeros_like(z[:, 0])
        events += [("f", 1), ("z", z[:, t], None, d1), ("target", x_true[:, t + 1])]
    return Batch(x0=x_true[:, 0].clone(), events=events)


def mask_of(ev) -> torch.Tensor | None:
    """The (B,) mask of the runs an event applies to (`recorded_batch`), or None: all of them
    (events without a mask: `robot_batch`, `linear_batch`)."""
    want = {"f": 3, "z": 5, "target": 3}[ev[0]]
    return ev[want - 1] if len(ev) == want else None


def feature_scales(system, batches: list[Batch]) -> tuple[np.ndarray, np.ndarray]:
    """(obs_scale, state_scale): the RMS of each component of F1 over the training data (the
    measurements' change between scans) and of the truth's change between targets (the state's
    change between updates). Only data, never an estimate: the scales are fixed before training.
    A masked event counts its masked runs only; a truth that is NaN (not scored) breaks the
    chain of changes."""
    d1s, dxs = [], []
    for b in batches:
        prev = None
        for ev in b.events:
            mask = mask_of(ev)
            if ev[0] == "z":
                seen = torch.any(ev[3] != 0, dim=1)
                d1s.append(ev[3][seen if mask is None else seen & mask])
            elif ev[0] == "target":
                if mask is None:
                    if prev is not None:
                        dxs.append(system.residual_x(ev[1], prev))
                    prev = ev[1]
                    continue
                if prev is None:
                    prev = torch.full_like(ev[1], math.nan)
                d = system.residual_x(ev[1], prev)[mask]
                dxs.append(d[torch.all(torch.isfinite(d), dim=1)])
                prev = torch.where(mask[:, None], ev[1], prev)

    def rms(parts, dim):
        if not parts:
            return np.ones(dim)
        v = torch.sqrt(torch.mean(torch.cat(parts) ** 2, dim=0)).numpy()
        return np.where(v > 0, v, 1.0)

    return rms(d1s, system.m), rms(dxs, system.n)


# ---------------------------------------------------------------------------------------------
# The network (architecture 1) and the filter's pass over a batch


class GainNet(nn.Module):
    """FC + ReLU -> GRU cell -> FC + ReLU -> FC (the n x m gain); names as the numpy weights."""

    def __init__(self, n_in: int, hidden: int, n: int, m: int):
        super().__init__()
        self.fc_in = nn.Linear(n_in, hidden, dtype=DTYPE)
        self.gru = nn.GRUCell(hidden, hidden, dtype=DTYPE)
        self.fc_out1 = nn.Linear(hidden, hidden, dtype=DTYPE)
        self.fc_out2 = nn.Linear(hidden, n * m, dtype=DTYPE)
        # Start from the zero gain (dead reckoning): a random gain can make the first passes
        # unstable (losses of 1e10 on an unstable model), and gradients reach the inner layers
        # after the first step.
        nn.init.zeros_(self.fc_out2.weight)
        nn.init.zeros_(self.fc_out2.bias)
        self.n, self.m = n, m

    def forward(self, features: torch.Tensor, h: torch.Tensor):
        h = self.gru(torch.relu(self.fc_in(features)), h)
        k = self.fc_out2(torch.relu(self.fc_out1(h)))
        return k.reshape(-1, self.n, self.m), h


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return nn.functional.normalize(v, p=2.0, dim=1, eps=1e-12)


class FilterState:
    """x, the GRU's hidden state and the posteriors/prior the features F3, F4 need."""

    def __init__(self, x0: torch.Tensor, hidden: int):
        self.x = x0
        self.h = torch.zeros(len(x0), hidden, dtype=DTYPE)
        self.post_prev = self.post_prev2 = self.prior_prev = x0

    def detach(self) -> None:
        for name in ("x", "h", "post_prev", "post_prev2", "prior_prev"):
            setattr(self, name, getattr(self, name).detach())


def update(net, system, st: FilterState, z, aux, d1, obs_scale, state_scale, mask=None) -> None:
    """One measurement: the four features, the gain, x+ = x- + K nu (filters/kalmannet.py).
    With a mask, the runs outside it keep x, the hidden state and the features' history."""
    x = st.x
    z_hat, rot, geo, scale = system.measure(x, aux)
    nu = system.residual_z(z, z_hat)
    f3 = system.residual_x(st.post_prev, st.post_prev2)
    f4 = system.residual_x(st.post_prev, st.prior_prev)
    features = torch.cat(
        [
            _normalize(d1 / obs_scale),
            _normalize(nu / obs_scale),
            _normalize(torch.einsum("bij,bj->bi", rot, f3) / state_scale),
            _normalize(torch.einsum("bij,bj->bi", rot, f4) / state_scale),
            geo,
        ],
        dim=1,
    )
    st.h_prev = st.h
    k_raw, st.h = net(features, st.h)
    K = torch.einsum("bji,bjk->bik", rot, k_raw * scale)  # rot^T (K_local): back to the world
    x_post = system.wrap_x(x + torch.einsum("bij,bj->bi", K, nu))
    if mask is not None:
        keep, h_prev = mask[:, None], st.h_prev

        def pick(new, old):
            return torch.where(keep, new, old)

        st.post_prev2, st.prior_prev = pick(st.post_prev, st.post_prev2), pick(x, st.prior_prev)
        st.post_prev, st.x, st.h = pick(x_post, st.post_prev), pick(x_post, x), pick(st.h, h_prev)
        return
    st.post_prev2, st.post_prev, st.prior_prev = st.post_prev, x_post, x
    st.x = x_post


def run_pass(net, system, batch: Batch, scales, bptt: int, optimizer=None, on_step=None):
    """The filter over a batch; with `optimizer`, a gradient step every `bptt` updates (truncated
    BPTT) and at the end. Returns (mean loss, estimates at the targets (T, B, n))."""
    obs_scale, state_scale = (torch.as_tensor(s, dtype=DTYPE) for s in scales)
    weights = system.loss_weights()
    st = FilterState(batch.x0, net.gru.hidden_size)
    window_x, window_true, updates = [], [], 0
    total, count, estimates = 0.0, 0, []

    def step():
        nonlocal window_x, window_true, updates, total, count
        window_n = len(window_x)
        if window_n:
            e = system.residual_x(torch.cat(window_x), torch.cat(window_true))
            loss = torch.mean(torch.sum(e * e * weights, dim=1))
            if optimizer is not None and loss.requires_grad:  # (no update yet: no gradient)
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(net.parameters(), GRAD_CLIP)
                optimizer.step()
            total += loss.item() * window_n
            count += window_n
            if on_step is not None:
                on_step()
        window_x, window_true, updates = [], [], 0
        st.detach()

    for ev in batch.events:
        mask = mask_of(ev)
        if ev[0] == "f":
            moved = system.f_span(st.x, ev[1])
            st.x = moved if mask is None else torch.where(mask[:, None], moved, st.x)
        elif ev[0] == "z":
            update(net, system, st, ev[1], ev[2], ev[3], obs_scale, state_scale, mask)
            updates += 1
        else:
            # A masked target scores its masked runs only (the truth is NaN elsewhere).
            estimates.append(st.x.detach())
            if mask is not None and not bool(mask.any()):
                continue
            window_x.append(st.x if mask is None else st.x[mask])
            window_true.append(ev[1] if mask is None else ev[1][mask])
            if optimizer is not None and updates >= bptt:
                step()
    step()
    return total / max(count, 1), torch.stack(estimates) if estimates else None


def windows_of(batch: Batch, bptt: int) -> int:
    """Gradient steps one pass over `batch` takes (for the progress bar's total)."""
    n, updates, targets = 0, 0, 0
    for ev in batch.events:
        if ev[0] == "z":
            updates += 1
        elif ev[0] == "target":
            targets += 1
            if updates >= bptt:
                n, updates, targets = n + 1, 0, 0
    return n + (1 if targets else 0)


# ---------------------------------------------------------------------------------------------
# Training


def to_weights(net: GainNet, scales, range_scale: float) -> KalmanNetWeights:
    arrays = {k: v.detach().numpy().copy() for k, v in net.state_dict().items()}
    return KalmanNetWeights(
        arrays=arrays,
        obs_scale=np.asarray(scales[0], dtype=float),
        state_scale=np.asarray(scales[1], dtype=float),
        range_scale=float(range_scale),
        hidden_size=net.gru.hidden_size,
    )


def from_weights(weights: KalmanNetWeights, system) -> GainNet:
    net = GainNet(2 * system.m + 2 * system.n + system.g, weights.hidden_size, system.n, system.m)
    net.load_state_dict({k: torch.as_tensor(v.copy()) for k, v in weights.arrays.items()})
    return net


def fit(
    system,
    batches: list[Batch],
    *,
    epochs: int,
    learning_rate: float,
    hidden_size: int,
    bptt: int,
    seed: int,
    validation: list[Batch] | None = None,
    progress: bool = False,
    description: str = "training KalmanNet",
) -> TrainingResult:
    """Train a GainNet on `batches` of `system`; deterministic for `seed` (module docstring).
    With `validation` batches (held-out training runs), the weights returned are those of the
    epoch with the lowest validation loss (early stopping by selection); else the last epoch's."""
    started, cpu_started = time.perf_counter(), time.process_time()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        torch.manual_seed(seed)
        rng = np.random.default_rng(seed)
        scales = feature_scales(system, batches)
        net = GainNet(2 * system.m + 2 * system.n + system.g, hidden_size, system.n, system.m)
        optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
        total = epochs * sum(windows_of(b, bptt) for b in batches)
        epoch_loss, validation_loss, best = [], [], None
        with _progress(progress, description, total) as advance:
            for _ in range(epochs):
                losses = [
                    run_pass(net, system, batches[i], scales, bptt, optimizer, advance)[0]
                    for i in rng.permutation(len(batches))
                ]
                epoch_loss.append(float(np.mean(losses)))
                if not math.isfinite(epoch_loss[-1]):
                    raise FloatingPointError("KalmanNet training loss is not finite")
                if validation:
                    with torch.no_grad():
                        passes = [run_pass(net, system, b, scales, bptt)[0] for b in validation]
                    validation_loss.append(float(np.mean(passes)))
                    if best is None or validation_loss[-1] < min(validation_loss[:-1]):
                        best = {k: v.clone() for k, v in net.state_dict().items()}
        if best is not None:
            net.load_state_dict(best)
        weights = to_weights(net, scales, system.range_scale)
    finally:
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(deterministic)
    cpu = time.process_time() - cpu_started
    return TrainingResult(weights, time.perf_counter() - started, epoch_loss, cpu, validation_loss)


class _progress:
    """A rich progress bar with an ETA: a task added to `show` when it is a rich Progress (the
    CLI's bar, already live), a bar of its own when `show` is True, nothing when it is falsy."""

    def __init__(self, show, description: str, total: int):
        self.show, self.description, self.total = show, description, total
        self.bar, self.own = None, False

    def __enter__(self):
        if not self.show:
            return None
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        if isinstance(self.show, Progress):
            self.bar = self.show
        else:
            self.own = True
            self.bar = Progress(
                "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                TimeElapsedColumn(), "ETA", TimeRemainingColumn(), transient=False,
            )  # fmt: skip
            self.bar.__enter__()
        task = self.bar.add_task(self.description, total=self.total, unit="steps")
        return lambda: self.bar.advance(task)

    def __exit__(self, *exc):
        if self.own:
            self.bar.__exit__(*exc)
        return False


def estimate(weights: KalmanNetWeights, system, batch: Batch) -> np.ndarray:
    """The trained filter's estimates at the targets of `batch`, (T, B, n), without gradients."""
    net = from_weights(weights, system)
    with torch.no_grad():
        _, est = run_pass(net, system, batch, (weights.obs_scale, weights.state_scale), 1)
    return est.numpy()


def train(spec, runs, world, ctx, progress: bool = False) -> TrainingResult:
    """KalmanNet for the robot from simulated training runs of `world` (`spec`'s parameters):
    the last `spec.validation_runs` runs held out to pick the best epoch, the others fitted in
    batches of `spec.batch_size`; the filter's model from `ctx`."""
    if not runs:
        raise ValueError("kalmannet: no training runs")
    if not isinstance(ctx.model, Bicycle):
        raise ValueError("kalmannet trains on the simulated bicycle model only")
    ranges = np.concatenate([s.z[:, 0] for r in runs for s in r.scans if len(s.ids)])
    range_scale = float(np.mean(ranges)) if len(ranges) else 1.0
    system = RobotSystem(ctx.dt, ctx.model.B, range_scale)
    size, held_out = spec.batch_size, min(spec.validation_runs, len(runs) - 1)
    fitted, checked = runs[: len(runs) - held_out], runs[len(runs) - held_out :]
    batches = [
        robot_batch(system, fitted[i : i + size], world) for i in range(0, len(fitted), size)
    ]
    validation = [robot_batch(system, checked, world)] if checked else None
    return _fit_spec(spec, system, batches, validation, progress, f"training {spec.name}")


def _fit_spec(spec, system, batches, validation, progress, description: str) -> TrainingResult:
    """`fit` with the training parameters of a kalmannet spec."""
    return fit(
        system,
        batches,
        validation=validation,
        epochs=spec.epochs,
        learning_rate=spec.learning_rate,
        hidden_size=spec.hidden_size,
        bptt=spec.bptt,
        seed=spec.seed,
        progress=progress,
        description=description,
    )


def train_recorded(
    spec, drives, model: Unicycle, progress=False, description: str | None = None
) -> TrainingResult:
    """KalmanNet for the unicycle from recorded training drives (`spec`'s parameters): `drives`
    are (Timeline, truth at its evaluation times with NaN where not scored) pairs, each cut into
    windows of `spec.window_s` seconds (`windows_of_drive`); `spec.validation_runs` of the
    windows, spread evenly over them, are held out to pick the best epoch, the others fitted in
    batches of `spec.batch_size`. Only what `drives` holds is read: never a test drive."""
    if not isinstance(model, Unicycle):
        raise ValueError("kalmannet on recorded drives trains on the unicycle model")
    windows = [w for tl, truth in drives for w in windows_of_drive(tl, truth, spec.window_s)]
    if len(windows) <= spec.validation_runs:
        raise ValueError(
            f"validation_runs: {spec.validation_runs} must be fewer than the training windows"
            f" ({len(windows)} of {spec.window_s:g} s)"
        )
    ranges = np.concatenate([w.timeline.z[:, 0] for w in windows])
    system = UnicycleSystem(float(np.mean(ranges)) if len(ranges) else 1.0)
    held: set[int] = set()
    if spec.validation_runs:
        held = set(np.round(np.linspace(0, len(windows) - 1, spec.validation_runs)).astype(int))
    fitted = [w for i, w in enumerate(windows) if i not in held]
    checked = [w for i, w in enumerate(windows) if i in held]
    size = spec.batch_size
    batches = [recorded_batch(system, fitted[i : i + size]) for i in range(0, len(fitted), size)]
    validation = [recorded_batch(system, checked)] if checked else None
    description = description or f"training {spec.name}"
    return _fit_spec(spec, system, batches, validation, progress, description)
