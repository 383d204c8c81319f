"""The tuning kernel: the plain EKF for one noise setting over one run, compiled, and what every
tuning criterion needs; and the fits built on it (`ekf-ml`, `ekf-tuned`).

One kernel (`ekf_fit_kernel`, compiled by numba with the fast engine's kernels) serves every
search of a fixed EKF's four sigmas, on both motion models, through the per-stamp contract of a
recorded `engines.events.Timeline` (the simulator's fixed-rate runs are written in it too):
stamp k predicts over dt[k] with the command u[k], fuses the landmarks lm[k]:lm[k+1] of z / xy
one at a time, and, if record[k], scores the estimate against the next row of `truth`. `motion`
is the fast engine's motion argument of `kernels.predict`: MOTION_BICYCLE (the simulated worlds)
or MOTION_UNICYCLE (recorded logs: midpoint Euler with the rate-consistent process noise of
`models.Unicycle`). The landmark update is the fast engine's (`kernels.innovation`, `kernels.nis`,
`kernels.correct`: RobotEKF's, to round-off), the health check the reference engine's
(`kernels.healthy` after every stamp that fused a landmark). The constants and the contract are
those of the fast engine's kernels (u (n, 2), dt (n,), lm (n + 1,) offsets into z / xy (m, 2),
record (n,) bool); what it adds to the fast engine's EKF is the scoring.

What it returns serves three searches:

- the innovation likelihood (`ekf-ml`, no truth): sum_k [log|S_k| + nu_k^T S_k^-1 nu_k] (-2 x
  the log-likelihood, the constant 2 pi dropped) over EVERY associated landmark measurement,
  whether the gate accepted it or not. The filter is fitted exactly as it runs (same gate: the
  gate decides whether it updates), but every measurement is evidence, so every setting is scored
  on the same set of measurements and the objective is well defined: a change of units adds the
  same constant to every setting, and the minimiser does not move. A sum over the accepted
  updates only runs over a set that depends on the setting: its minimiser depends on the units
  (in millimetres it prefers settings that reject many measurements, since each accepted term is
  then positive; tests/test_ekf_ml_real.py). The price: an outlier the gate rejects still costs
  its full term, so gross outliers pull the fitted R up;
- the squared position error and the NEES at the scored record stamps (`ekf-tuned` on simulated
  runs: the scorer's RMSE, then a consistency rescale);
- the summed squared position error with an early stop (`bound`: the loop stops once the sum
  passes it): the grid searches of `ekf-tuned` on recorded data, whose criterion is a pooled
  RMSE over the same scored times for every setting, so a setting whose partial sum passes the
  best complete one can never win (branch and bound, real_experiment).

`fit_noise` minimises the likelihood or the RMSE over the LOG sigmas with scipy's Nelder-Mead
from several starts (the likelihood has a ridge between Q and R and local optima), each start's
simplex spanning a factor of 2 along each axis; a setting whose filter diverges scores +inf. The
starts run one per thread (`jobs`). A problem is anything with `evaluate(sigmas)`:
`TrainingProblem` (simulated training runs, bicycle) or `TimelineLikelihood` (one recorded run's
own innovations, unicycle).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass

import numpy as np
from joblib import Parallel, delayed
from scipy.optimize import minimize
from scipy.stats import chi2

from ..analysis.metrics import recorded_steps
from ..config import World
from ..sources.simulator import RunData
from ..timeline import from_run
from .kernels import (
    MOTION_BICYCLE,
    MOTION_UNICYCLE,
    correct,
    healthy,
    innovation,
    jacobians_at,
    maybe_njit,
    nis,
    noise_scale,
    predict_from,
    step_terms,
    wrap,
)

SIGMA_NAMES = ("sigma_v", "sigma_gamma", "sigma_range", "sigma_bearing")

# What ended a run of the kernel
FINISHED = 0
STOPPED = 1  # the summed squared error passed `bound`
DIVERGED = 2  # the estimate or its covariance stopped being finite and positive definite
# A run stopped by `bound`, to go on from: next stamp, next record index, x (3), P (9), the
# squared-error sum, the largest squared error, nll, updates, rejections
RESUME_SIZE = 19
NO_STATE = np.zeros(0)  # `resume` / `stopped` of a call that neither resumes nor keeps its stop


@maybe_njit
def step_terms_table(u, dt, motion, B):
    """`kernels.step_terms` of every stamp, (n, 9): what a stamp's predict computes whatever the
    heading (the steering's sine and cosine among them). A fit runs the same stamps hundreds of
    times, so they are computed once per run; `ekf_fit_kernel` gives the same bits as with
    `kernels.predict`, which computes them at every step."""
    n = len(dt)
    out = np.empty((n, 9))
    for k in range(n):
        terms = step_terms(u[k, 0], u[k, 1], dt[k], motion, B)
        for c in range(9):
            out[k, c] = terms[c]
    return out


@maybe_njit
def ekf_fit_kernel(
    motion, dt, u, lm, z, xy, record, x0, P0, Qu, R, gate, has_gate, T0, B, truth, scored,
    bound, out_sq, out_nees, terms, resume, stopped,
):  # fmt: skip
    """The plain EKF with one noise setting over one run (see the module doc).

    resume: empty, or a `stopped` state (RESUME_SIZE,) of an earlier call on this run with this
    setting: the run goes on from there (its stamp, record index, x, P and sums), so that it
    gives the bits of running it from the start. stopped: empty, or (RESUME_SIZE,) filled with
    that state when the sum passes `bound`.

    terms: the run's `step_terms_table`. x0 (3,), P0 (9,) row-major, Qu and R (4,) row-major
    (the unicycle reads Qu's diagonal); T0:
    the unicycle's reference step of Qu; B: the bicycle's wheelbase (its step is dt[k]). truth
    (n_rec, 3) and scored (n_rec,) are indexed by record stamp: at the j-th record stamp with
    scored[j], the squared position error goes to out_sq[j] and into the sum, the NEES to
    out_nees[j] (the other entries are left as they are; truth is never read where scored[j] is
    False). Returns (status, sq_sum, max_err, nll, n_updates, n_rejected): status FINISHED,
    STOPPED (the sum passed `bound`) or DIVERGED; nll = sum over every associated innovation of
    log|S| + nu^T S^-1 nu.
    """
    x = (x0[0], x0[1], x0[2])
    P = (P0[0], P0[1], P0[2], P0[3], P0[4], P0[5], P0[6], P0[7], P0[8])
    Qt = (Qu[0], Qu[1], Qu[2], Qu[3])
    Rt = (R[0], R[1], R[2], R[3])
    sq_sum = 0.0
    max_sq = 0.0
    nll = 0.0
    n_upd = 0
    n_rej = 0
    j = 0
    first_k = 0
    if len(resume) > 0:
        first_k, j = int(resume[0]), int(resume[1])
        x = (resume[2], resume[3], resume[4])
        P = (
            resume[5], resume[6], resume[7], resume[8], resume[9], resume[10], resume[11],
            resume[12], resume[13],
        )  # fmt: skip
        sq_sum, max_sq, nll = resume[14], resume[15], resume[16]
        n_upd, n_rej = int(resume[17]), int(resume[18])
    for k in range(first_k, len(dt)):
        # kernels.predict, its heading-free terms read from the table
        tk = (
            terms[k, 0], terms[k, 1], terms[k, 2], terms[k, 3], terms[k, 4], terms[k, 5],
            terms[k, 6], terms[k, 7], terms[k, 8],
        )  # fmt: skip
        f02, f12, G = jacobians_at(x[2], tk)
        x, P, _ = predict_from(x, P, f02, f12, G, tk[8], noise_scale(dt[k], motion, T0), Qt)
        first = lm[k]
        last = lm[k + 1]
        if last > first:
            for i in range(first, last):
                z0 = z[i, 0]
                z1 = z[i, 1]
                H, zh, nu, HPHt = innovation(x, P, xy[i, 0], xy[i, 1], z0, z1)
                ok, v = nis(HPHt, Rt, nu[0], nu[1])
                if not ok or not math.isfinite(v):
                    return DIVERGED, math.inf, math.inf, nll, n_upd, n_rej
                s00 = HPHt[0] + Rt[0]
                s01 = HPHt[1] + Rt[1]
                s10 = HPHt[2] + Rt[2]
                s11 = HPHt[3] + Rt[3]
                det = s00 * s11 - s01 * s10
                if not det > 0.0:
                    return DIVERGED, math.inf, math.inf, nll, n_upd, n_rej
                nll += math.log(det) + v
                if has_gate and not v <= gate:
                    n_rej += 1
                    continue
                ok, x, P = correct(x, P, H, zh, z0, z1, Rt)
                if not ok:
                    return DIVERGED, math.inf, math.inf, nll, n_upd, n_rej
                n_upd += 1
            if not healthy(x, P, Rt, Qt):
                return DIVERGED, math.inf, math.inf, nll, n_upd, n_rej
        if record[k]:
            if scored[j]:
                e0 = truth[j, 0] - x[0]
                e1 = truth[j, 1] - x[1]
                e2 = wrap(truth[j, 2] - x[2])
                sq = e0 * e0 + e1 * e1
                if not math.isfinite(sq):
                    return DIVERGED, math.inf, math.inf, nll, n_upd, n_rej
                out_sq[j] = sq
                # e^T P^-1 e by Cramer's rule on the 3 x 3 P (NaN when P is singular)
                a, b, c, d, e, f, g, h, i = P
                c0 = e * i - f * h
                c1 = f * g - d * i
                c2 = d * h - e * g
                det3 = a * c0 + b * c1 + c * c2
                y0 = (e0 * c0 + e1 * (c * h - b * i) + e2 * (b * f - c * e)) / det3
                y1 = (e0 * c1 + e1 * (a * i - c * g) + e2 * (c * d - a * f)) / det3
                y2 = (e0 * c2 + e1 * (b * g - a * h) + e2 * (a * e - b * d)) / det3
                out_nees[j] = e0 * y0 + e1 * y1 + e2 * y2
                sq_sum += sq
                if sq > max_sq:
                    max_sq = sq
                if sq_sum > bound:
                    if len(stopped) > 0:
                        stopped[0] = k + 1
                        stopped[1] = j + 1
                        for c in range(3):
                            stopped[2 + c] = x[c]
                        for c in range(9):
                            stopped[5 + c] = P[c]
                        stopped[14] = sq_sum
                        stopped[15] = max_sq
                        stopped[16] = nll
                        stopped[17] = n_upd
                        stopped[18] = n_rej
                    return STOPPED, sq_sum, math.sqrt(max_sq), nll, n_upd, n_rej
            j += 1
    return FINISHED, sq_sum, math.sqrt(max_sq), nll, n_upd, n_rej


def _variances(sigmas) -> tuple[np.ndarray, np.ndarray]:
    """(Qu, R) as the kernel reads them, row-major (4,), from (s_v, s_turn, s_range, s_bearing)."""
    sv, sg, sr, sb = (float(s) for s in sigmas)
    return np.array([sv * sv, 0.0, 0.0, sg * sg]), np.array([sr * sr, 0.0, 0.0, sb * sb])


def _gate(gate: float | None) -> tuple[float, bool]:
    return (math.inf, False) if gate is None else (float(gate), True)


# --------------------------------------------------------------------------------------------
# Recorded runs (the unicycle): one setting scored against ground truth, and the likelihood


def unicycle_terms(tl) -> np.ndarray:
    """A recorded `Timeline`'s `step_terms_table` (the unicycle), for `score_setting`'s `terms`."""
    return step_terms_table(tl.u, tl.dt, MOTION_UNICYCLE, 0.0)


def score_setting(tl, x0, P0, sig, gate, T0, truth, scored, bound=math.inf, terms=None) -> tuple:
    """One setting sig = (sv, sw, sr, sb) over a recorded `Timeline`, scored at its record stamps
    (truth (n_rec, 2 or 3): the heading is not needed for the position error): (sq_sum, max_err,
    n_updates, n_rejected, finished). `finished` is False when the sum passed `bound`; a filter
    that diverges scores infinity (finished True). `terms`: the timeline's `step_terms_table`
    (unicycle), if the caller scores many settings on it (computed here otherwise)."""
    Qu, R = _variances(sig)
    g, has_gate = _gate(gate)
    truth = np.asarray(truth, dtype=float)
    if truth.shape[1] == 2:  # NEES is not asked for: any finite heading
        truth = np.column_stack([truth, np.zeros(len(truth))])
    n_rec = len(truth)
    status, sq, mx, _, nu, nr = ekf_fit_kernel(
        MOTION_UNICYCLE, tl.dt, tl.u, tl.lm, tl.z, tl.xy, tl.record,
        np.ascontiguousarray(x0, dtype=float).reshape(3),
        np.ascontiguousarray(P0, dtype=float).ravel(), Qu, R, g, has_gate, float(T0), 0.0,
        np.ascontiguousarray(truth), np.ascontiguousarray(scored, dtype=np.bool_),
        float(bound), np.empty(n_rec), np.empty(n_rec),
        unicycle_terms(tl) if terms is None else terms, NO_STATE, NO_STATE,
    )  # fmt: skip
    return sq, mx, nu, nr, status != STOPPED


@maybe_njit
def grid_kernel(
    dt, u, lm, z, xy, record, terms, x0, truth, scored, stamps, marks, obs, recs, P0, sigmas,
    gate, has_gate, T0, bound, branch_and_bound, known, out, done, partial,
):  # fmt: skip
    """`ekf_fit_kernel` (the unicycle) for every setting sigmas[g] = (sv, sw, sr, sb) over every
    run of a `GridRuns` pack, in one compiled call: out[g] = (sq_sum, max_err, n_updates,
    n_rejected, finished) summed over the runs in their order.

    Without `branch_and_bound` each run is scored whole (no bound) and the sums may be infinite
    (a run that diverged). With it, a setting stops at its first run that passes the bound (the
    best complete sum seen so far in this call, at first `bound`) or diverges, and finished is
    0; a complete sum below the best becomes the bound of the next settings.

    known[g, r] = (sq_sum, max_err, n_updates, n_rejected) of setting g over run r where an
    earlier call scored that run whole (NaN where not): read instead of run again. A run's
    partial sums only grow, so the bound stops it exactly when its whole sum passes the bound:
    the same finished settings and sums as running it. done[g, r] receives the whole runs this
    call scored (NaN where it stopped one or read it from `known`).

    partial[g, r] (RESUME_SIZE,): where an earlier call's bound stopped setting g on run r (NaN
    where none), kept up to date: a run is resumed from there (its partial sum alone may stop
    it at once: sums only grow), and a run the bound stops leaves its state there."""
    n_runs = len(stamps) - 1
    longest = 0
    for r in range(n_runs):
        longest = max(longest, recs[r + 1] - recs[r])
    out_sq = np.empty(longest)
    out_nees = np.empty(longest)
    Qu = np.zeros(4)
    R = np.zeros(4)
    best = bound
    motion = np.int64(MOTION_UNICYCLE)  # not the literal: numba would compile the kernel twice
    for g in range(len(sigmas)):
        Qu[0] = sigmas[g, 0] * sigmas[g, 0]
        Qu[3] = sigmas[g, 1] * sigmas[g, 1]
        R[0] = sigmas[g, 2] * sigmas[g, 2]
        R[3] = sigmas[g, 3] * sigmas[g, 3]
        total = 0.0
        worst = 0.0
        upd = 0
        rej = 0
        finished = True
        for r in range(n_runs):
            a, b = stamps[r], stamps[r + 1]
            c, d = recs[r], recs[r + 1]
            lo, hi = obs[r], obs[r + 1]
            limit = best - total if branch_and_bound else math.inf
            resume = partial[g, r, :0]
            if partial[g, r, 0] == partial[g, r, 0]:
                resume = partial[g, r]
            if known[g, r, 0] == known[g, r, 0]:
                sq, mx = known[g, r, 0], known[g, r, 1]
                nu, nr = int(known[g, r, 2]), int(known[g, r, 3])
                status = STOPPED if sq > limit else FINISHED
            elif len(resume) > 0 and resume[14] > limit:
                status, sq, mx = STOPPED, resume[14], math.sqrt(resume[15])
                nu, nr = int(resume[17]), int(resume[18])
            else:
                status, sq, mx, _, nu, nr = ekf_fit_kernel(
                    motion, dt[a:b], u[a:b], lm[marks[r] : marks[r + 1]], z[lo:hi],
                    xy[lo:hi], record[a:b], x0[r], P0, Qu, R, gate, has_gate, T0, 0.0,
                    truth[c:d], scored[c:d], limit, out_sq, out_nees, terms[a:b], resume.copy(),
                    partial[g, r],
                )  # fmt: skip
                if status != STOPPED:
                    partial[g, r, 0] = math.nan
                    done[g, r, 0] = sq
                    done[g, r, 1] = mx
                    done[g, r, 2] = nu
                    done[g, r, 3] = nr
            total += sq
            if mx > worst:
                worst = mx
            upd += nu
            rej += nr
            if branch_and_bound and (status == STOPPED or not math.isfinite(total)):
                finished = math.isfinite(total) and status != STOPPED
                break
        out[g, 0] = total
        out[g, 1] = worst
        out[g, 2] = upd
        out[g, 3] = rej
        out[g, 4] = 1.0 if finished else 0.0
        if finished and total < best:
            best = total


@dataclass(frozen=True, eq=False)
class GridRuns:
    """Recorded runs packed for `grid_kernel`: each run's stamps, landmarks and record stamps
    concatenated, with offsets (`stamps`, `marks` into `lm`, `obs` into z / xy, `recs` into
    truth / scored), its start pose and its `step_terms_table` (the unicycle)."""

    dt: np.ndarray
    u: np.ndarray
    lm: np.ndarray
    z: np.ndarray
    xy: np.ndarray
    record: np.ndarray
    terms: np.ndarray
    x0: np.ndarray  # (runs, 3)
    truth: np.ndarray  # (records, 3)
    scored: np.ndarray  # (records,) bool
    stamps: np.ndarray
    marks: np.ndarray
    obs: np.ndarray
    recs: np.ndarray

    @classmethod
    def of(cls, runs) -> GridRuns:
        """`runs`: (Timeline, start pose, truth (n_rec, 2 or 3), scored (n_rec,)) of each run."""
        tls = [tl for tl, *_ in runs]
        truths = []
        for _, _, truth, _ in runs:
            truth = np.asarray(truth, dtype=float)
            if truth.shape[1] == 2:  # NEES is not asked for: any finite heading
                truth = np.column_stack([truth, np.zeros(len(truth))])
            truths.append(truth)

        def offsets(sizes) -> np.ndarray:
            return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

        return cls(
            dt=np.concatenate([tl.dt for tl in tls]).astype(float),
            u=np.ascontiguousarray(np.concatenate([tl.u for tl in tls]), dtype=float),
            lm=np.concatenate([tl.lm for tl in tls]).astype(np.int64),
            z=np.ascontiguousarray(np.concatenate([tl.z for tl in tls]), dtype=float),
            xy=np.ascontiguousarray(np.concatenate([tl.xy for tl in tls]), dtype=float),
            record=np.concatenate([tl.record for tl in tls]).astype(np.bool_),
            terms=np.concatenate([unicycle_terms(tl) for tl in tls]),
            x0=np.array([np.asarray(x0, dtype=float).reshape(3) for _, x0, _, _ in runs]),
            truth=np.ascontiguousarray(np.concatenate(truths)),
            scored=np.concatenate([np.asarray(s, dtype=np.bool_) for *_, s in runs]),
            stamps=offsets([len(tl.dt) for tl in tls]),
            marks=offsets([len(tl.lm) for tl in tls]),
            obs=offsets([len(tl.z) for tl in tls]),
            recs=offsets([len(t) for t in truths]),
        )

    def score(
        self, sigmas, P0, gate, T0, bound=math.inf, branch_and_bound=False, known=None,
        partial=None,
    ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """`grid_kernel`'s sums (G, 5) of the settings `sigmas` (G, 4) over these runs, and the
        runs it scored whole (G, runs, 4; NaN elsewhere). `known`: whole runs scored before
        (G, runs, 4, NaN where not), read instead of run again. `partial`: (G, runs,
        RESUME_SIZE), where earlier calls stopped runs (NaN where none), resumed from there and
        updated in place (C-ordered float64)."""
        sigmas = np.ascontiguousarray(sigmas, dtype=float).reshape(-1, 4)
        g, has_gate = _gate(gate)
        shape = (len(sigmas), len(self.stamps) - 1, 4)
        out = np.zeros((len(sigmas), 5))
        done = np.full(shape, np.nan)
        known = np.full(shape, np.nan) if known is None else np.ascontiguousarray(known, float)
        if partial is None:
            partial = np.full((*shape[:2], RESUME_SIZE), np.nan)
        grid_kernel(
            self.dt, self.u, self.lm, self.z, self.xy, self.record, self.terms, self.x0,
            self.truth, self.scored, self.stamps, self.marks, self.obs, self.recs,
            np.ascontiguousarray(P0, dtype=float).ravel(), sigmas, g, has_gate, float(T0),
            float(bound), bool(branch_and_bound), known, out, done, partial,
        )  # fmt: skip
        return out, done


@dataclass(frozen=True, eq=False)
class TimelineLikelihood:
    """One recorded run's own innovations as an objective (`ekf-ml` on recorded data): the
    unicycle EKF from the run's start over its timeline. It holds no ground truth: no stamp is a
    record stamp for the kernel, so no truth is ever read."""

    dt: np.ndarray
    u: np.ndarray
    lm: np.ndarray
    z: np.ndarray
    xy: np.ndarray
    x0: np.ndarray
    P0: np.ndarray  # (9,) row-major
    gate: float | None
    T0: float
    terms: np.ndarray  # step_terms_table of the timeline (unicycle)

    @classmethod
    def of(cls, tl, x0, P0, gate: float | None, T0: float) -> TimelineLikelihood:
        return cls(
            dt=tl.dt, u=tl.u, lm=tl.lm, z=tl.z, xy=tl.xy,
            x0=np.ascontiguousarray(x0, dtype=float).reshape(3),
            P0=np.ascontiguousarray(P0, dtype=float).ravel(), gate=gate, T0=float(T0),
            terms=unicycle_terms(tl),
        )  # fmt: skip

    def nll(self, sigmas) -> tuple[int, float, int, int]:
        """(status, sum of log|S| + nu^T S^-1 nu, n_updates, n_rejected) at `sigmas`."""
        Qu, R = _variances(sigmas)
        g, has_gate = _gate(self.gate)
        none = np.zeros(len(self.dt), np.bool_)
        status, _, _, nll, nu, nr = ekf_fit_kernel(
            MOTION_UNICYCLE, self.dt, self.u, self.lm, self.z, self.xy, none, self.x0, self.P0,
            Qu, R, g, has_gate, self.T0, 0.0, np.zeros((0, 3)), np.zeros(0, np.bool_),
            math.inf, np.zeros(0), np.zeros(0), self.terms, NO_STATE, NO_STATE,
        )  # fmt: skip
        return status, nll, nu, nr

    def evaluate(self, sigmas: np.ndarray) -> dict:
        """The per-innovation objective `fit_noise` minimises, and the gate's share."""
        status, nll, nu, nr = self.nll(sigmas)
        n = len(self.z)
        diverged = status == DIVERGED
        return {
            "nll_per_innovation": math.inf if diverged else nll / max(n, 1),
            "innovations": n,
            "gate_rejected": nr / n if n and not diverged else math.nan,
            "diverged": diverged,
        }


# --------------------------------------------------------------------------------------------
# Simulated training runs (the bicycle)


def _fixed_rate_timeline(data: RunData, world: World, steps: np.ndarray) -> tuple:
    """A simulated run in the per-stamp contract (`timeline.from_run`: one stamp per control
    step, the scan of step k at stamp k), its record stamps at the scorer's steps, and the truth
    there."""
    tl = from_run(data, world, 0)
    record = np.zeros(len(tl.t), np.bool_)
    record[steps - 1] = True
    truth = np.ascontiguousarray(data.truth.x[steps], dtype=float)
    terms = step_terms_table(tl.u, tl.dt, MOTION_BICYCLE, float(world.B))
    return tl.dt, tl.u, tl.lm, tl.z, tl.xy, record, truth, terms


@dataclass(frozen=True)
class TrainingProblem:
    """What every objective evaluation needs: the training runs as the kernel reads them, the
    filter's start, the gate and which steps the scorer records."""

    runs: tuple  # per run: (dt, u, lm, z, xy, record, truth at the record stamps, step terms)
    B: float
    x0: np.ndarray
    P0: np.ndarray  # (9,) row-major
    gate: float | None
    steps: np.ndarray  # recorded control steps (1-based), the scorer's

    @classmethod
    def of(
        cls,
        runs: list[RunData],
        world: World,
        P0: np.ndarray,
        gate: float | None,
        record_every: int,
    ) -> TrainingProblem:
        K = min(len(data.u_odo) for data in runs)
        steps = recorded_steps(K, record_every)
        return cls(
            runs=tuple(_fixed_rate_timeline(data, world, steps) for data in runs),
            B=float(world.B),
            x0=np.ascontiguousarray(world.x0, dtype=float).reshape(3),
            P0=np.ascontiguousarray(P0, dtype=float).ravel(),
            gate=gate,
            steps=steps,
        )

    def evaluate(self, sigmas: np.ndarray) -> dict:
        """Run the EKF with `sigmas` (sv, sg, sr, sb; radians) over every training run."""
        Qu, R = _variances(sigmas)
        g, has_gate = _gate(self.gate)
        nll, n_inn, n_rej, diverged = 0.0, 0, 0, False
        sq, nees = [], []
        scored = np.ones(len(self.steps), np.bool_)
        for dt, u, lm, z, xy, record, truth, terms in self.runs:
            out_sq = np.full(len(self.steps), np.nan)
            out_nees = np.full(len(self.steps), np.nan)
            status, _, _, ll, nu, nr = ekf_fit_kernel(
                MOTION_BICYCLE, dt, u, lm, z, xy, record, self.x0, self.P0, Qu, R, g, has_gate,
                0.0, self.B, truth, scored, math.inf, out_sq, out_nees, terms, NO_STATE,
                NO_STATE,
            )  # fmt: skip
            diverged |= status == DIVERGED
            nll += ll
            n_inn += nu + nr
            n_rej += nr
            sq.append(out_sq)
            nees.append(out_nees)
        sq, nees = np.array(sq), np.array(nees)
        with np.errstate(all="ignore"):
            rmse = float(np.mean(np.sqrt(np.mean(sq, axis=0))))
            anees = np.mean(nees, axis=0)
        n = len(self.runs)
        lo, hi = _anees_bounds(n)
        if diverged or not math.isfinite(rmse):
            rmse, nll, anees = math.inf, math.inf, np.full_like(anees, math.inf)
        return {
            "rmse_pos": rmse,
            "nll_per_innovation": nll / max(n_inn, 1),
            "anees": float(np.mean(anees)),
            "nees_in_bounds": float(np.mean((anees >= lo) & (anees <= hi))),
            "gate_rejected": n_rej / n_inn if n_inn else math.nan,
            "diverged": diverged,
        }


@functools.lru_cache(maxsize=16)
def _anees_bounds(n: int) -> tuple[float, float]:
    """The 95 % bounds of an n-run average NEES (3 states), as `evaluate` compares them; cached:
    scipy's chi2.ppf costs about as much as a tenth of an evaluation's kernels."""
    return chi2.ppf(0.025, 3 * n) / n, chi2.ppf(0.975, 3 * n) / n


CRITERIA = {
    "likelihood": "nll_per_innovation",  # -2/N log-likelihood per innovation (no truth)
    "rmse": "rmse_pos",  # the scorer's position RMSE (truth)
}


def _one_start(problem, criterion: str, theta0: np.ndarray, max_evaluations: int) -> dict:
    key = CRITERIA[criterion]
    evaluations = 0

    def objective(theta: np.ndarray) -> float:
        nonlocal evaluations
        evaluations += 1
        if not np.all(np.abs(theta) < 50):  # sigmas beyond e^+-50: not a filter
            return math.inf
        value = problem.evaluate(np.exp(theta))[key]
        return value if math.isfinite(value) else math.inf

    simplex = np.vstack([theta0, theta0 + math.log(2.0) * np.eye(4)])
    res = minimize(
        objective, theta0, method="Nelder-Mead",
        options={"initial_simplex": simplex, "maxfev": max_evaluations, "xatol": 0.01,
                 "fatol": 1e-6},
    )  # fmt: skip
    return {"theta": res.x.tolist(), "value": float(res.fun), "evaluations": evaluations}


SCALE_RMSE_TOLERANCE = 1.005  # a consistency rescale may cost at most 0.5 % of training RMSE


def _consistent_scale(problem: TrainingProblem, sigmas: np.ndarray, at_fit: dict):
    """The RMSE fixes the sigmas only up to a common factor: scaling every variance by c scales
    P by c and leaves the gains, hence the estimates, unchanged (but for the gate and P0). Pick
    the point of that ray whose training ANEES is the state dimension, 3 (ANEES ~ 1/c: two fixed
    point steps); keep it if the training RMSE stays within SCALE_RMSE_TOLERANCE.
    Returns (sigmas, their evaluation, the variance factor applied)."""
    total, best = 1.0, (sigmas, at_fit, 1.0)
    current, at = sigmas, at_fit
    for _ in range(3):
        if not (math.isfinite(at["anees"]) and at["anees"] > 0):
            break
        c = at["anees"] / 3.0
        current = current * math.sqrt(c)
        total *= c
        at = problem.evaluate(current)
        if at["rmse_pos"] <= SCALE_RMSE_TOLERANCE * at_fit["rmse_pos"]:
            best = (current, at, total)
    return best


def start_results(problem, fits: list[tuple], jobs: int = 1) -> list[list[dict]]:
    """The Nelder-Mead result of every start of every fit (criterion, start_sigmas, starts,
    max_evaluations) over `problem`, per fit: all the fits' starts in one batch on `jobs`
    threads (each evaluation's time is in the compiled kernel, which releases the GIL), so that
    two fits of one scenario keep both cores busy where each alone would leave one idle (3
    starts on 2 threads). Each start is computed as alone: the same numbers."""
    tasks = [
        (i, criterion, np.log(np.asarray(start_sigmas, float) * m), max_evaluations)
        for i, (criterion, start_sigmas, starts, max_evaluations) in enumerate(fits)
        for m in starts
    ]
    if jobs > 1 and len(tasks) > 1:
        done = Parallel(n_jobs=min(jobs, len(tasks)), backend="threading")(
            delayed(_one_start)(problem, c, t, n) for _, c, t, n in tasks
        )
    else:
        done = [_one_start(problem, c, t, n) for _, c, t, n in tasks]
    out: list[list[dict]] = [[] for _ in fits]
    for (i, *_), result in zip(tasks, done, strict=True):
        out[i].append(result)
    return out


def fit_noise(
    problem,
    criterion: str,
    start_sigmas: np.ndarray,
    starts: list[float],
    max_evaluations: int,
    jobs: int = 1,
    found: list[dict] | None = None,
    found_seconds: float = 0.0,
) -> dict:
    """The sigmas (radians) minimising `criterion` ("likelihood" or "rmse", the latter for a
    `TrainingProblem` only) over `problem`, from each start multiplier of `start_sigmas`; what
    it found and what it cost. `found`: the starts' Nelder-Mead results if already computed
    (`start_results`; the same numbers), `found_seconds` what they cost (counted in
    "seconds")."""
    started = time.perf_counter()
    if found is None:
        found = start_results(problem, [(criterion, start_sigmas, starts, max_evaluations)], jobs)[
            0
        ]
    best = min(range(len(found)), key=lambda i: found[i]["value"])
    sigmas = np.exp(found[best]["theta"])
    at_fit = problem.evaluate(sigmas)
    scale = 1.0
    if criterion == "rmse":
        sigmas, at_fit, scale = _consistent_scale(problem, sigmas, at_fit)
    at_start = problem.evaluate(np.asarray(start_sigmas, float))
    return {
        "criterion": criterion,
        "sigmas": sigmas.tolist(),
        "training": at_fit,
        "start": at_start,
        "starts": [
            {
                "multiplier": m,
                "value": f["value"],
                "evaluations": f["evaluations"],
                "sigmas": np.exp(f["theta"]).tolist(),
            }
            for m, f in zip(starts, found, strict=True)
        ],  # fmt: skip
        "consistency_scale": scale,
        "evaluations": int(sum(f["evaluations"] for f in found)) + 2,
        "seconds": round(time.perf_counter() - started + found_seconds, 3),
    }
