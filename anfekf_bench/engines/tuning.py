"""Fitting a fixed EKF's four noise sigmas on training runs (`ekf-ml`, `ekf-tuned`), on the fast
engine's kernels.

One objective evaluation runs the plain EKF (bicycle model) over every training run with one
setting of (sigma_v, sigma_gamma, sigma_range, sigma_bearing) and returns what both criteria need
(`ekf_scores`, compiled by numba with the other kernels):

- the innovation log-likelihood (`ekf-ml`, no truth): -1/2 sum_k [log|S_k| + nu_k^T S_k^-1 nu_k]
  (the constant 2 pi dropped) over EVERY associated landmark measurement, whether the gate
  accepted it or not: the gate decides whether the filter updates, not whether the measurement
  is evidence. Leaving rejected innovations out would reward settings so tight that the gate
  discards whatever they predict badly (the likelihood of the measurements kept grows as S
  shrinks); capping their NIS at the gate would make S -> 0 optimal.
- the squared position error and the NEES at every control step (`ekf-tuned`, with truth); the
  criterion is the scorer's scalar RMSE: sqrt(mean over runs of e^2) at each recorded step,
  averaged over the steps (analysis.metrics, SPEC 5).

`fit_noise` minimises either criterion over the LOG sigmas with scipy's Nelder-Mead from several
starts (the likelihood has a ridge between Q and R and local optima), each start's simplex
spanning a factor of 2 along each axis; a setting whose filter diverges in any training run
scores +inf. The starts run one per worker process (`jobs`).
"""

from __future__ import annotations

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
from .fast import flat_scans
from .kernels import correct, healthy, innovation, maybe_njit, nis, predict, wrap

SIGMA_NAMES = ("sigma_v", "sigma_gamma", "sigma_range", "sigma_bearing")


@maybe_njit
def ekf_scores(
    u_odo, every, scan_start, scan_lm, scan_z, T, B, x0, P0, Qu, R, gate, has_gate, x_true,
    out_sq, out_nees,
):  # fmt: skip
    """The plain EKF over one run (the same arithmetic as `kernels.run_kernel` with adaptation
    off) and what the tuning criteria need.

    x_true (K + 1, 3): the truth at every control step (row 0: the start). Writes the squared
    position error and the NEES after control step k to out_sq[k - 1] and out_nees[k - 1].
    Returns (diverged, nll, n_innovations, n_rejected) with nll = sum over every associated
    innovation of log|S| + nu^T S^-1 nu (accepted or not).
    """
    K = u_odo.shape[0]
    x = (x0[0], x0[1], x0[2])
    P = (P0[0], P0[1], P0[2], P0[3], P0[4], P0[5], P0[6], P0[7], P0[8])
    Qt = (Qu[0], Qu[1], Qu[2], Qu[3])
    Rt = (R[0], R[1], R[2], R[3])
    nll = 0.0
    n_inn = 0
    n_rejected = 0
    for k in range(1, K + 1):
        x, P, Q = predict(x, P, u_odo[k - 1, 0], u_odo[k - 1, 1], T, B, Qt)
        if k % every == 0:
            s = k // every - 1
            first = scan_start[s]
            last = scan_start[s + 1]
            if last > first:
                for m in range(first, last):
                    z0 = scan_z[m, 0]
                    z1 = scan_z[m, 1]
                    H, zh, nu, HPHt = innovation(x, P, scan_lm[m, 0], scan_lm[m, 1], z0, z1)
                    ok, v = nis(HPHt, Rt, nu[0], nu[1])
                    if not ok or not math.isfinite(v):
                        return True, nll, n_inn, n_rejected
                    s00 = HPHt[0] + Rt[0]
                    s01 = HPHt[1] + Rt[1]
                    s10 = HPHt[2] + Rt[2]
                    s11 = HPHt[3] + Rt[3]
                    det = s00 * s11 - s01 * s10
                    if not det > 0.0:
                        return True, nll, n_inn, n_rejected
                    nll += math.log(det) + v
                    n_inn += 1
                    if has_gate and not v <= gate:
                        n_rejected += 1
                        continue
                    ok, x, P = correct(x, P, H, zh, z0, z1, Rt)
                    if not ok:
                        return True, nll, n_inn, n_rejected
                if not healthy(x, P, Rt, Qt):
                    return True, nll, n_inn, n_rejected
        e0 = x_true[k, 0] - x[0]
        e1 = x_true[k, 1] - x[1]
        e2 = wrap(x_true[k, 2] - x[2])
        out_sq[k - 1] = e0 * e0 + e1 * e1
        # e^T P^-1 e by Cramer's rule on the 3 x 3 P (NaN when P is singular)
        a, b, c, d, e, f, g, h, i = P
        c0 = e * i - f * h
        c1 = f * g - d * i
        c2 = d * h - e * g
        det3 = a * c0 + b * c1 + c * c2
        y0 = (e0 * c0 + e1 * (c * h - b * i) + e2 * (b * f - c * e)) / det3
        y1 = (e0 * c1 + e1 * (a * i - c * g) + e2 * (c * d - a * f)) / det3
        y2 = (e0 * c2 + e1 * (b * g - a * h) + e2 * (a * e - b * d)) / det3
        out_nees[k - 1] = e0 * y0 + e1 * y1 + e2 * y2
    return False, nll, n_inn, n_rejected


@dataclass(frozen=True)
class TrainingProblem:
    """What every objective evaluation needs: the training runs as the kernel reads them, the
    filter's start, the gate and which steps the scorer records."""

    runs: tuple  # per run: (u_odo, scan_start, scan_lm, scan_z, x_true)
    every: int
    T: float
    B: float
    x0: np.ndarray
    P0: np.ndarray  # (9,) row-major
    gate: float
    has_gate: bool
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
        flat = []
        for data in runs:
            scans = flat_scans(data, world)
            flat.append(
                (
                    np.ascontiguousarray(data.u_odo, dtype=float),
                    scans.start,
                    scans.landmarks,
                    scans.z,
                    np.ascontiguousarray(data.truth.x, dtype=float),
                )
            )
        K = min(len(data.u_odo) for data in runs)
        return cls(
            runs=tuple(flat),
            every=int(world.sensor_every),
            T=float(world.T),
            B=float(world.B),
            x0=np.ascontiguousarray(world.x0, dtype=float).reshape(3),
            P0=np.ascontiguousarray(P0, dtype=float).ravel(),
            gate=math.inf if gate is None else float(gate),
            has_gate=gate is not None,
            steps=recorded_steps(K, record_every),
        )

    def evaluate(self, sigmas: np.ndarray) -> dict:
        """Run the EKF with `sigmas` (sv, sg, sr, sb; radians) over every training run."""
        sv, sg, sr, sb = (float(s) for s in sigmas)
        Qu = np.array([sv * sv, 0.0, 0.0, sg * sg])
        R = np.array([sr * sr, 0.0, 0.0, sb * sb])
        nll, n_inn, n_rej, diverged = 0.0, 0, 0, False
        sq, nees = [], []
        for u, start, lm, z, xt in self.runs:
            out_sq = np.full(len(u), np.nan)
            out_nees = np.full(len(u), np.nan)
            d, ll, n, r = ekf_scores(
                u, self.every, start, lm, z, self.T, self.B, self.x0, self.P0, Qu, R,
                self.gate, self.has_gate, xt, out_sq, out_nees,
            )  # fmt: skip
            diverged |= bool(d)
            nll += ll
            n_inn += n
            n_rej += r
            sq.append(out_sq[self.steps - 1])
            nees.append(out_nees[self.steps - 1])
        sq, nees = np.array(sq), np.array(nees)
        with np.errstate(all="ignore"):
            rmse = float(np.mean(np.sqrt(np.mean(sq, axis=0))))
            anees = np.mean(nees, axis=0)
        n = len(self.runs)
        lo, hi = chi2.ppf(0.025, 3 * n) / n, chi2.ppf(0.975, 3 * n) / n
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


CRITERIA = {
    "likelihood": "nll_per_innovation",  # -2/N log-likelihood per innovation (no truth)
    "rmse": "rmse_pos",  # the scorer's position RMSE (truth)
}


def _one_start(
    problem: TrainingProblem, criterion: str, theta0: np.ndarray, max_evaluations: int
) -> dict:
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


def fit_noise(
    problem: TrainingProblem,
    criterion: str,
    start_sigmas: np.ndarray,
    starts: list[float],
    max_evaluations: int,
    jobs: int = 1,
) -> dict:
    """The sigmas (radians) minimising `criterion` ("likelihood" or "rmse") over the training
    runs, from each start multiplier of `start_sigmas`; what it found and what it cost."""
    started = time.perf_counter()
    thetas = [np.log(np.asarray(start_sigmas, float) * m) for m in starts]
    if jobs > 1 and len(thetas) > 1:
        from ..workers import local_workers

        with local_workers():
            found = Parallel(n_jobs=min(jobs, len(thetas)))(
                delayed(_one_start)(problem, criterion, t, max_evaluations) for t in thetas
            )
    else:
        found = [_one_start(problem, criterion, t, max_evaluations) for t in thetas]
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
        "seconds": round(time.perf_counter() - started, 3),
    }
