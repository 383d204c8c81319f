"""A recorded-like drive from a known unicycle with known noise (tests of ekf-ml on recorded data):
variable odometry stamps, several landmarks at some stamps, the Unicycle's rate-consistent control
noise and Gaussian range-bearing noise."""

from __future__ import annotations

import math

import numpy as np

from anfekf_bench.engines.events import Timeline
from anfekf_bench.models import Unicycle


def synthetic_drive(
    seed: int, sigmas=(0.05, 0.15, 0.08, 0.03), seconds: float = 240.0, T0: float = 0.12
) -> tuple[Timeline, np.ndarray, np.ndarray]:
    """(timeline, start pose, truth at every stamp (n, 3)) of a drive around a ring of landmarks
    whose commands are noisy by sigmas = (sv, sw) per T0 (variance x T0 / dt over a step of dt)
    and whose landmarks are measured with (sr, sb)."""
    rng = np.random.default_rng(seed)
    sv, sw, sr, sb = sigmas
    dt = rng.uniform(0.01, 0.03, size=int(seconds / 0.02))
    t = np.cumsum(dt)
    n = len(t)
    # commands: a loop of radius about 3 m with a slow wobble, changed every ~0.5 s
    v = np.repeat(0.3 + 0.1 * rng.standard_normal(n // 25 + 1), 25)[:n]
    w = np.repeat(0.1 + 0.15 * rng.standard_normal(n // 25 + 1), 25)[:n]
    u = np.column_stack([v, w])
    angles = rng.uniform(-math.pi, math.pi, 14)
    radii = np.r_[np.full(7, 1.0), np.full(7, 5.5)] + rng.uniform(-0.5, 0.5, 14)
    landmarks = np.column_stack([radii * np.cos(angles), 3.0 + radii * np.sin(angles)])
    model = Unicycle(T0)
    x = np.array([0.0, 0.0, 0.0])
    truth = np.empty((n, 3))
    counts = np.zeros(n, dtype=np.int64)
    z, xy = [], []
    for k in range(n):
        noise = rng.standard_normal(2) * np.array([sv, sw]) * math.sqrt(T0 / dt[k])
        x = model.f(x, u[k] + noise, dt[k])
        truth[k] = x
        if rng.random() < 0.1:  # a scan at this stamp: the landmarks within 5 m, some of them
            for lx, ly in landmarks:
                dx, dy = lx - x[0], ly - x[1]
                if math.hypot(dx, dy) < 5.0 and rng.random() < 0.5:
                    r = math.hypot(dx, dy) + sr * rng.standard_normal()
                    b = math.atan2(dy, dx) - x[2] + sb * rng.standard_normal()
                    z.append((r, math.atan2(math.sin(b), math.cos(b))))
                    xy.append((lx, ly))
                    counts[k] += 1
    lm = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=lm[1:])
    tl = Timeline(
        t_start=0.0, t=t, dt=dt, u=np.ascontiguousarray(u), lm=lm,
        z=np.array(z, dtype=float).reshape(-1, 2), xy=np.array(xy, dtype=float).reshape(-1, 2),
        record=np.ones(n, bool),
    )  # fmt: skip
    return tl, np.zeros(3), truth
