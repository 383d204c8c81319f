"""KalmanNet on a paper scenario: train on training runs, score on the scenario's own runs.

    python -m anfekf_bench.kalmannet_study configs/wrong_r.yaml [--eval-runs 20] [--out DIR]

(`make learned`.) For each scenario: `train_runs` training runs drawn from the training branch of
the scenario's seed (`kalmannet.training_seeds`, disjoint from every evaluation run's seed), one
KalmanNet trained on them (progress bar, training time), then the first `--eval-runs` evaluation
runs, the very runs `anfekf run` would make (run i from SeedSequence(seed).spawn(runs)[i]), through
the scenario's filters and KalmanNet. Printed and written to OUT/kalmannet-<scenario>.json:
position RMSE of each filter, KalmanNet's paired ratios to the others with 95 % BCa intervals,
the training time and the weights' SHA-256. Until the experiment trains filters itself (the
training-runs mechanism), this is how KalmanNet is measured.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from .analysis.metrics import add_trace_metrics, recorded_steps
from .analysis.statistics import paired_bootstrap, rmse_statistic
from .config import load_scenario
from .filters.kalmannet import KalmanNetSpec, training_seeds
from .filters.registry import filter_context
from .runner import run_filter_on, run_tasks, simulate
from .sources.simulator import world_path
from .storage import write_atomic


def study(path: Path, eval_runs: int, spec: KalmanNetSpec, progress: bool = True) -> dict:
    scenario, world = load_scenario(path)
    wpath = world_path(world)
    training = [
        simulate(scenario, world, s, wpath) for s in training_seeds(scenario.seed, spec.train_runs)
    ]
    trained = spec.train(training, world, filter_context(spec, scenario, world), progress=progress)
    kn = spec.with_weights(trained.weights)
    specs = [*scenario.filters, kn]
    errors: dict[str, list[np.ndarray]] = {s.name: [] for s in specs}
    diverged: dict[str, int] = {s.name: 0 for s in specs}
    started = time.perf_counter()
    tasks = list(run_tasks(scenario, world, scenario.runs, scenario.seed))[:eval_runs]
    for task in tasks:
        data = simulate(scenario, world, task["seed"], wpath)
        steps = recorded_steps(len(data.u_odo), scenario.record_every)
        for s in specs:
            trace = run_filter_on(scenario.engine, s, scenario, world, data)
            trace = add_trace_metrics(trace, data.truth.x[steps])
            diverged[s.name] += bool(trace["diverged"])
            errors[s.name].append(trace["pos_err"])
    pos = {name: np.array(rows) for name, rows in errors.items()}
    out = {
        "scenario": scenario.name,
        "file": str(path),
        "kalmannet": spec.model_dump(),
        "training_runs": spec.train_runs,
        "training_seed_branch": "SeedSequence(seed, spawn_key=(2**32 - 1,)).spawn(train_runs)",
        "training_time_s": round(trained.training_time_s, 2),
        "training_cpu_s": round(trained.training_cpu_s, 2),
        "epoch_loss": trained.epoch_loss,
        "validation_loss": trained.validation_loss,
        "best_epoch": trained.best_epoch,
        "weights_sha256": hashlib.sha256(trained.weights.to_bytes()).hexdigest(),
        "evaluation_runs": len(tasks),
        "evaluation_time_s": round(time.perf_counter() - started, 2),
        "rmse_pos": {name: float(rmse_statistic(e)) for name, e in pos.items()},
        "diverged": diverged,
        "kalmannet_over": {},
    }
    for other in scenario.filters:
        iv = paired_bootstrap(pos[spec.name], pos[other.name], rmse_statistic, seed=0)
        out["kalmannet_over"][other.name] = {"ratio": iv.estimate, "lo": iv.lo, "hi": iv.hi}
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="+", type=Path)
    parser.add_argument("--eval-runs", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("results/learned"))
    parser.add_argument("--train-runs", type=int, default=None)
    parser.add_argument("--epochs", type=int, default=None)
    parser.add_argument("--seed", type=int, default=None, help="KalmanNet's own seed")
    parser.add_argument("--validation-runs", type=int, default=None)
    args = parser.parse_args(argv)
    chosen = (
        ("train_runs", args.train_runs), ("epochs", args.epochs), ("seed", args.seed),
        ("validation_runs", args.validation_runs),
    )  # fmt: skip
    overrides = {k: v for k, v in chosen if v is not None}
    spec = KalmanNetSpec(name="kalmannet", kind="kalmannet", **overrides)
    args.out.mkdir(parents=True, exist_ok=True)
    for path in args.scenarios:
        res = study(path, args.eval_runs, spec)
        target = args.out / f"kalmannet-{res['scenario']}.json"
        text = json.dumps(res, indent=2) + "\n"
        write_atomic(target, lambda tmp, text=text: tmp.write_text(text))
        print(
            f"{res['scenario']}: training {res['training_time_s']} s (CPU"
            f" {res['training_cpu_s']} s) on {spec.train_runs} runs"
        )
        for name, value in res["rmse_pos"].items():
            print(f"  {name:12s} rmse_pos {value:.4f} m  diverged {res['diverged'][name]}")
        for name, r in res["kalmannet_over"].items():
            print(f"  kalmannet / {name:12s} {r['ratio']:.3f} [{r['lo']:.3f}, {r['hi']:.3f}]")
        print(f"  written {target}")


if __name__ == "__main__":
    main()
