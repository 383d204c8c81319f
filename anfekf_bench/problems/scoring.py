"""Scoring a problem's batch (SPEC 17): the state (RMSE of the position components and of the
rest, NEES of the whole state in chi-square bounds of its dimension) and the noise estimate itself
(each filter's Q and R at the last step against the true ones: every entry's mean, standard
deviation and bias over runs, and the relative Frobenius error ||Q^ - Q||_F / ||Q||_F per run).

Where the problem gates its measurements (tracking), the runs and the summary also count the
measurements each filter's gate dropped (`gated`: per run; the summary's: mean per run).

The RMSE ratio against the oracle carries the package's paired bootstrap interval over runs
(`analysis.statistics.paired_bootstrap`, seeded from the scenario's seed). Timings sit in a table
of their own, so every other table is the same bytes for the same seed.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..analysis.metrics import nees_bounds
from ..analysis.statistics import paired_bootstrap, rmse_statistic
from .base import Problem


def relative_frobenius(estimate: np.ndarray, true: np.ndarray) -> np.ndarray:
    """||estimate - true||_F / ||true||_F for a stack of estimates (..., m, m)."""
    return np.linalg.norm(estimate - true, axis=(-2, -1)) / np.linalg.norm(true)


def _errors(problem: Problem, truth: np.ndarray, x: np.ndarray, idx: tuple[int, ...]):
    """Per-step error norms (runs, steps) of the components `idx` (NaN when none)."""
    if not idx:
        return np.full(truth.shape[:2], np.nan)
    e = truth[..., list(idx)] - x[..., list(idx)]
    return np.sqrt(np.sum(e * e, axis=-1))


def nees_steps(truth: np.ndarray, x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """e^T P^-1 e (runs, steps) over the whole state."""
    e = truth - x
    return np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])


def entry_columns(prefix: str, M: np.ndarray) -> dict[str, np.ndarray]:
    """{'q_0_0': M[:, 0, 0], ...} for a stack (runs, m, m)."""
    m = M.shape[-1]
    return {f"{prefix}_{i}_{j}": M[:, i, j] for i in range(m) for j in range(m)}


def score(problem: Problem, truth: np.ndarray, traces: dict[str, list], specs: dict,
          reference: str | None, seed: int) -> dict[str, pd.DataFrame]:  # fmt: skip
    """{'runs', 'summary', 'noise', 'timing'} of a batch. truth (runs, steps, n); traces: filter
    name -> its Trace per run; specs: name -> spec; reference: the oracle's name (or None)."""
    runs_n = truth.shape[0]
    lo_b, hi_b = nees_bounds(runs_n, dim=problem.n)
    err_pos = {}
    run_rows, summary_rows, noise_rows, timing_rows = [], [], [], []
    for name, traces_f in traces.items():
        x = np.stack([t.x for t in traces_f])
        P = np.stack([t.P for t in traces_f])
        Q_end = np.stack([t.Q[-1] for t in traces_f])
        R_end = np.stack([t.R[-1] for t in traces_f])
        err_pos[name] = _errors(problem, truth, x, problem.position)
        err_rest = _errors(problem, truth, x, problem.rest)
        nees = nees_steps(truth, x, P)
        q_err, r_err = relative_frobenius(Q_end, problem.Q), relative_frobenius(R_end, problem.R)
        spec = specs[name]
        frame = {
            "filter": name,
            "kind": spec.kind,
            "run": np.arange(runs_n),
            "rmse_pos": np.sqrt(np.mean(err_pos[name] ** 2, axis=1)),
            "rmse_rest": np.sqrt(np.mean(err_rest**2, axis=1)),
            "anees": nees.mean(axis=1),
            "q_rel_err": q_err,
            "r_rel_err": r_err,
            **entry_columns("q", Q_end),
            **entry_columns("r", R_end),
        }
        if problem.gate is not None:
            frame["gated"] = [t.gated for t in traces_f]
        run_rows.append(pd.DataFrame(frame))
        timing_rows.append(pd.DataFrame({"filter": name, "run": np.arange(runs_n),
                                         "seconds": [t.seconds for t in traces_f]}))  # fmt: skip
        avg = nees.mean(axis=0)
        estimated = spec.estimated()
        summary_rows.append({
            "filter": name,
            "kind": spec.kind,
            "estimates": "".join(sorted(estimated)),
            "runs": runs_n,
            "rmse_pos": rmse_statistic(err_pos[name]),
            "rmse_rest": (rmse_statistic(err_rest) if problem.rest else np.nan),
            "anees": float(nees.mean()),
            "nees_in_bounds": float(np.mean((avg > lo_b) & (avg < hi_b))),
            "q_rel_err": float(q_err.mean()),
            "q_rel_err_sd": float(q_err.std(ddof=1)) if runs_n > 1 else np.nan,
            "r_rel_err": float(r_err.mean()),
            "r_rel_err_sd": float(r_err.std(ddof=1)) if runs_n > 1 else np.nan,
        })  # fmt: skip
        if problem.gate is not None:
            summary_rows[-1]["gated"] = float(np.mean([t.gated for t in traces_f]))
        for label, est, true in (("Q", Q_end, problem.Q), ("R", R_end, problem.R)):
            m = true.shape[0]
            for i in range(m):
                for j in range(m):
                    values = est[:, i, j]
                    noise_rows.append({
                        "filter": name, "matrix": label, "i": i, "j": j,
                        "estimated": label in estimated, "true": float(true[i, j]),
                        "mean": float(values.mean()),
                        "sd": float(values.std(ddof=1)) if runs_n > 1 else np.nan,
                        "bias": float(values.mean() - true[i, j]),
                    })  # fmt: skip
    summary = pd.DataFrame(summary_rows)
    ratios = []
    for name in summary["filter"]:
        if reference is None:
            ratios.append((np.nan, np.nan, np.nan))
            continue
        iv = paired_bootstrap(err_pos[name], err_pos[reference], rmse_statistic,
                              seed=np.random.SeedSequence([seed, 3]))  # fmt: skip
        ratios.append((iv.estimate, iv.lo, iv.hi))
    summary.insert(5, "rmse_ratio", [r[0] for r in ratios])
    summary.insert(6, "rmse_ratio_lo", [r[1] for r in ratios])
    summary.insert(7, "rmse_ratio_hi", [r[2] for r in ratios])
    timing = pd.concat(timing_rows, ignore_index=True)
    return {
        "runs": pd.concat(run_rows, ignore_index=True),
        "summary": summary,
        "noise": pd.DataFrame(noise_rows),
        "timing": timing,
    }
