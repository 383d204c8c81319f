"""The fast engine's kernel of `kalmannet` (filters/kalmannet.py): the trained network's filter.

The maths is filters/kalmannet.py's plain functions (`gain_update`: the features, `gain_network`:
FC + ReLU, the GRU cell, FC + ReLU, FC; the gain applied), called here as the filterpy engine's
`KalmanNetFilter` calls them (numba compiles them with `register_jitable`; the three primitives
that map over a layer, numpy's there, are plain loops here, each writing into its buffer: no
array is allocated inside the loop). The weights are arguments (`KalmanNetWeights.net`, a tuple
of arrays), so one compiled signature serves every trained network. The predict is kernels.py's
`predict` (its P stays NaN: the filter has no covariance), on either motion model.

The loop runs over one run's stamps like every kernel: stamp i predicts with the controls u[i]
over dt[i], then fuses the landmarks lm[i] .. lm[i + 1] - 1 (their map positions xy and
measurements z) one after another, then records when record_at[i]. F1 needs each landmark's
measurement at the last scan that saw landmarks: it is kept in two small buffers (this scan's
and the last one's) sized by the run's largest scan, found by the landmark's map position.

`pure_module()` gives a never-compiled copy (plain Python, kernels.py's pure copy underneath).
numba's disk cache of the kernel is stamped with every source it reaches
(filters/kalmannet_net.py included: compiled.use_reached_sources_stamp), so an edit there
compiles it anew.
"""

from __future__ import annotations

import math

import numpy as np

from ..filters import kalmannet_net as _kn
from ..models import angles as _angles
from . import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
JIT: bool = _k.JIT  # True: the kernel below is numba-compiled
maybe_njit = _k.maybe_njit
predict = _k.predict

MOTION_BICYCLE, MOTION_UNICYCLE = _k.MOTION_BICYCLE, _k.MOTION_UNICYCLE


def pure_module():
    """A fresh copy of this module whose kernel is plain Python, whatever is installed."""
    return _kernels.pure_copy(__name__, __file__)


if JIT and not _PURE_COPY:
    from numba.extending import overload, register_jitable

    @overload(_kn.affine)
    def _affine_loop(Wt, v, b, out):
        """Compiled, out = W v + b as a sum of W's columns (rows of Wt) v[c] W[:, c]: the inner
        loop runs over contiguous outputs, which LLVM vectorises, and each output is still
        summed in input order, as a dot product (three times faster than row by row)."""

        def impl(Wt, v, b, out):
            m, n = Wt.shape
            for i in range(n):
                out[i] = 0.0
            for c in range(m):
                vc = v[c]
                for i in range(n):
                    out[i] += Wt[c, i] * vc
            for i in range(n):
                out[i] += b[i]
            return out

        return impl

    @overload(_kn.relu_in_place)
    def _relu_loop(v):
        """Compiled, `relu` on each entry in place."""

        def impl(v):
            for i in range(v.shape[0]):
                v[i] = _kn.relu(v[i])
            return v

        return impl

    @overload(_kn.gru_update)
    def _gru_loop(gi, gh, h):
        """Compiled, `gru_unit` on each unit in place."""

        def impl(gi, gh, h):
            H = h.shape[0]
            for i in range(H):
                h[i] = _kn.gru_unit(
                    gi[i], gi[H + i], gi[2 * H + i], gh[i], gh[H + i], gh[2 * H + i], h[i]
                )

        return impl

    for _rule in (
        _angles.wrap_scalar, _kn.sigmoid, _kn.relu, _kn.gru_unit, _kn.work_arrays,
        _kn.gain_network, _kn.normalized2, _kn.normalized3, _kn.state_change, _kn.gain_update,
    ):  # fmt: skip
        register_jitable(_rule)

gain_update = _kn.gain_update
work_arrays = _kn.work_arrays


@maybe_njit
def largest_scan(lm):
    """The most landmarks at one stamp (at least 1)."""
    most = 1
    for i in range(lm.shape[0] - 1):
        most = max(most, lm[i + 1] - lm[i])
    return most


@maybe_njit
def run_kalmannet_kernel(
    u, dt, lm, xy, z, motion, B, T0, x0, P0, Qu0, R0, gate, has_gate,
    net, scales, record_at, out_x, out_P, out_R, out_Q,
):  # fmt: skip
    """filterpy_engine.run_filter with filters.kalmannet.KalmanNetFilter: the arguments every
    kernel starts with (P0 and the gate unused: no covariance, no gate), the network's arrays
    `net` (KalmanNetWeights.net) and its input `scales` (KalmanNetWeights.scales). Every
    measurement is fused; a posterior that is not finite is the divergence. Records x, P (NaN),
    R and Qu (the context's). Returns (diverged, records written, nis_sum (NaN), n_updates,
    n_rejected (0)) as the other kernels."""
    n_stamps = u.shape[0]
    nan = math.nan
    x = (x0[0], x0[1], x0[2])
    P = (nan, nan, nan, nan, nan, nan, nan, nan, nan)
    Qu = (Qu0[0], Qu0[1], Qu0[2], Qu0[3])
    R = (R0[0], R0[1], R0[2], R0[3])
    post_prev = x
    post_prev2 = x
    prior_prev = x
    hidden = np.zeros(net[4].shape[0])
    work = work_arrays(net)
    most = largest_scan(lm)
    # (landmark x, y, z0, z1) of the last scan's measurements (F1) and of this scan's: buffers
    # `last` and 1 - `last` (swapping two arrays in the loop costs every stamp their
    # reference counts)
    seen_at = np.empty((2, most, 4))
    last = 0
    n_last = 0
    n_updates = 0
    n_records = out_x.shape[0]
    j = 0
    bad_record = False
    for i in range(n_stamps):
        x, _, _ = predict(x, P, u[i, 0], u[i, 1], dt[i], motion, B, T0, Qu)
        first = lm[i]
        end = lm[i + 1]
        if end > first:
            n_scan = 0
            for m in range(first, end):
                lx = xy[m, 0]
                ly = xy[m, 1]
                z0 = z[m, 0]
                z1 = z[m, 1]
                seen = False
                p0 = 0.0
                p1 = 0.0
                for q in range(n_last):  # the last match: a dict keeps a key's last value
                    if seen_at[last, q, 0] == lx and seen_at[last, q, 1] == ly:
                        seen = True
                        p0 = seen_at[last, q, 2]
                        p1 = seen_at[last, q, 3]
                x_post = gain_update(
                    x, lx, ly, z0, z1, seen, p0, p1, post_prev, post_prev2, prior_prev, scales,
                    net, hidden, work,
                )  # fmt: skip
                if not (
                    math.isfinite(x_post[0]) and math.isfinite(x_post[1])
                    and math.isfinite(x_post[2])
                ):  # fmt: skip
                    return True, j, nan, n_updates, 0
                post_prev2 = post_prev
                post_prev = x_post
                prior_prev = x
                x = x_post
                n_updates += 1
                seen_at[1 - last, n_scan, 0] = lx
                seen_at[1 - last, n_scan, 1] = ly
                seen_at[1 - last, n_scan, 2] = z0
                seen_at[1 - last, n_scan, 3] = z1
                n_scan += 1
            last = 1 - last
            n_last = n_scan
        if record_at[i] and j < n_records:
            for c in range(3):
                out_x[j, c] = x[c]
                if not math.isfinite(x[c]):
                    bad_record = True  # (a predict's blow-up after the last scan)
            for c in range(9):
                out_P[j, c // 3, c % 3] = P[c]
            out_R[j, 0] = R[0]
            out_R[j, 1] = R[3]
            out_Q[j, 0] = Qu[0]
            out_Q[j, 1] = Qu[3]
            j += 1
    return bad_record, j, nan, n_updates, 0
