"""Innovation-based adaptive estimation on the fast engine's loop (`engines/loop.py`): the hooks
of filterpy_engine.run_filter with filters.iae.IAEEKF. A window of the last `window`
innovations (and their H P- H^T) that feed adaptation; R (not adapt_Q) at every landmark once it
is full (`r_estimate`), or Qu (adapt_Q) at the end of a scan with fused landmarks from their
gains (`q_estimate`), Qu the mean of the last q_window samples.
"""

from __future__ import annotations

import collections

import numpy as np

from ...filters.adaptive import clip_to_bounds
from ...filters.iae import (
    IAESpec,
    hold_nonpositive,
    q_estimate,
    r_estimate,
    window_covariance,
    window_mean,
)  # fmt: skip
from .. import kernels as _kernels

_PURE_COPY: bool = globals().get("_PURE", False)
_k = _kernels.pure_module() if _PURE_COPY else _kernels
feeds_adaptation, interval_step, qu_estimate, as_matrix, matmul, gain = (
    _k.feeds_adaptation, _k.interval_step, _k.qu_estimate, _k.as_matrix, _k.matmul, _k.gain,
)  # fmt: skip
ZERO9, EYE9 = _k.ZERO9, _k.EYE9

Params = collections.namedtuple(
    "Params",
    "adaptation from_all lo hi adapt_Q window hph_window hold q_full q_window nus hph_diags"
    " q_samples Ks",
)


def params(spec: IAESpec, ctx) -> Params:
    return Params(
        bool(spec.adaptation), spec.adapt_from == "all", *(float(b) for b in spec.bounds),
        spec.adapt == "Q", int(spec.window), spec.hph == "window", spec.nonpositive == "hold",
        spec.q_form == "full", int(spec.q_window),
        # the windows, oldest first (`push_row`), updated in place: innovations, diag(H P- H^T),
        # diag(Qu) samples (parameters rather than state: arrays in the state, which passes
        # through the hooks, cost reference counts)
        np.zeros((int(spec.window), 2)), np.zeros((int(spec.window), 2)),
        np.zeros((int(spec.q_window), 2)), np.zeros((1, 3, 2)),
    )  # fmt: skip


def for_run(fam: Params, scan_start) -> Params:
    """`fam` for one run (loop.py's optional `for_run`): room in Ks for the gains of the run's
    largest scan (adapt Q)."""
    most = int(np.max(np.diff(scan_start), initial=0)) if fam.adapt_Q else 0
    return fam._replace(Ks=np.zeros((max(most, 1), 3, 2)))


def push_row(win, n, a, b):
    """Append the row (a, b) to a window of rows kept oldest first (a deque's order) that holds
    n rows: at row n while it is not full, else after moving the others up one (no copy of the
    window when a rule reads it)."""
    N = win.shape[0]
    if n < N:
        win[n, 0] = a
        win[n, 1] = b
        return
    for i in range(N - 1):
        win[i, 0] = win[i + 1, 0]
        win[i, 1] = win[i + 1, 1]
    win[N - 1, 0] = a
    win[N - 1, 1] = b


def row_mean(win):
    """`window_mean` of a full window of rows (a, b), as two floats."""
    m = window_mean(win)
    return m[0], m[1]


def r_sample(nus, hph_diags, hph_window, hph0, hph1, hold, R):
    """IAEEKF.adapt_R before the bounds, from the full windows (oldest first): (r0, r1), the
    diagonal of C - H P- H^T with the window's mean diag(H P- H^T) (hph_window) or the current
    one (hph0, hph1); hold: a channel <= 0 keeps its value in R."""
    C = window_covariance(nus)
    if hph_window:
        h0, h1 = row_mean(hph_diags)
    else:
        h0 = hph0
        h1 = hph1
    r0 = r_estimate(C[0, 0], h0)
    r1 = r_estimate(C[1, 1], h1)
    if hold:
        held = hold_nonpositive(np.array([r0, r1]), np.array([R[0], R[3]]))
        r0 = held[0]
        r1 = held[1]
    return r0, r1


def qu_sample(nus, Ks, n_K, P, P_scan_start, F_scan, A_v, A_g, q_full):
    """IAEEKF.end_scan's sample of diag(Qu), not clipped: Q_hat (`q_estimate`) from the full
    window's C (oldest first), the gains of the scan's n_K fused landmarks and, q_full, P+ -
    F_scan P_scan_start F_scan^T; mapped to (qv, qg). (ok, (qv, qg)) as `qu_estimate`."""
    C = window_covariance(nus)
    if q_full:
        F = as_matrix(F_scan)
        dP = as_matrix(P) - matmul(matmul(F, as_matrix(P_scan_start)), F.T)
    else:
        dP = np.zeros((3, 3))
    Q_hat = q_estimate(Ks[:n_K], C, dP)
    return qu_estimate(Q_hat, A_v, A_g, P)


def start(fam, x, P, Qu, R, scan_start):
    # the counts (n_win, n_q, n_K); the start's noise; the interval (A_v, A_g, F_scan, P at
    # its start). The arrays (the windows, the scan's gains Ks) are in `fam`.
    return (0, 0, 0), (R[0], R[3], Qu[0], Qu[3]), (ZERO9, ZERO9, EYE9, P)


def predicted(fam, st, f02, f12, G, c, Q):
    if not fam.adapt_Q:  # AdaptiveEKF.predict's interval accumulators
        return st
    counts, start0, interval = st
    A_v, A_g, F_scan = interval_step(interval[0], interval[1], interval[2], f02, f12, G, c)
    return counts, start0, (A_v, A_g, F_scan, interval[3])


def begin_scan(fam, st, x, P, R, Qu):  # IAEEKF.begin_scan
    counts, start0, interval = st
    return ((counts[0], counts[1], 0), start0, interval), R


def before_gain(fam, st, x, P, R, Qu, H, zh, nu, HPHt, lm, z, gate, has_gate):
    ok, feeds = feeds_adaptation(HPHt, R, nu, fam.from_all, gate, has_gate)
    if not ok:
        return False, st, P, R, Qu, HPHt
    if not feeds:
        return True, st, P, R, Qu, HPHt
    # IAEEKF.before_gain
    counts, start0, interval = st
    nus, hph_diags = fam.nus, fam.hph_diags
    n_win, n_q, n_K = counts
    window = fam.window
    push_row(nus, n_win, nu[0], nu[1])
    push_row(hph_diags, n_win, HPHt[0], HPHt[3])
    if n_win < window:
        n_win += 1
    if not fam.adapt_Q and n_win == window and fam.adaptation:  # IAEEKF.adapt_R
        r0, r1 = r_sample(nus, hph_diags, fam.hph_window, HPHt[0], HPHt[3], fam.hold, R)
        bounds = (fam.lo, fam.hi)
        R = (clip_to_bounds(r0, start0[0], bounds), 0.0, 0.0, clip_to_bounds(r1, start0[1], bounds))
    return True, ((n_win, n_q, n_K), start0, interval), P, R, Qu, HPHt


def corrected(fam, st, x_prior, P_prior, x, P, R, H, lm, z):
    if not fam.adapt_Q:
        return st, R
    # IAEEKF.after_update: the gain of each fused landmark
    counts, start0, interval = st
    Ks = fam.Ks
    n_win, n_q, n_K = counts
    _, Kg = gain(P_prior, H, R)
    for i in range(6):
        Ks[n_K, i // 2, i % 2] = Kg[i]
    return ((n_win, n_q, n_K + 1), start0, interval), R


def end_scan(fam, st, x, P, R, Qu):  # IAEEKF.end_scan
    counts, start0, interval = st
    nus, q_samples, Ks = fam.nus, fam.q_samples, fam.Ks
    n_win, n_q, n_K = counts
    if fam.adapt_Q and fam.adaptation and n_win == fam.window and n_K > 0:
        A_v, A_g, F_scan, P_scan_start = interval
        ok, q = qu_sample(nus, Ks, n_K, P, P_scan_start, F_scan, A_v, A_g, fam.q_full)
        if not ok:
            return False, st, R, Qu
        push_row(q_samples, n_q, q[0], q[1])
        if n_q < fam.q_window:
            n_q += 1
        if n_q == fam.q_window:
            q0, q1 = row_mean(q_samples)
            bounds = (fam.lo, fam.hi)
            Qu = (
                clip_to_bounds(q0, start0[2], bounds), 0.0,
                0.0, clip_to_bounds(q1, start0[3], bounds),
            )  # fmt: skip
    return True, ((n_win, n_q, n_K), start0, (ZERO9, ZERO9, EYE9, P)), R, Qu
