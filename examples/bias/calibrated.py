"""Which error states to estimate, chosen from training runs (issue 35's 1.10x of the oracle;
docs/results/bias.md). Development and training seeds only, never the scored runs:

- training: the runs of SeedSequence(seed + 8000) (8), disjoint from the scored runs
  (SeedSequence(seed)) and the development runs (seed + 7000);
- on each, ekf-aug as configured (all four parameters estimated); the training mean m and
  between-run standard deviation s of each parameter's estimate at the run's end;
- rule, fixed before looking at any development run: a parameter is present when its training
  mean differs from its nominal value (1, 1, 0, 0) by more than the tolerance the convergence
  acceptance states (0.03 on a scale, 0.25 deg on the turn bias, 0.05 m on the range bias);
- "selected": ekf-aug estimating the present parameters only (others held at nominal), its
  configured start and spreads; "calibrated": the same, started at the training mean with the
  training spread s as its start standard deviation (a vehicle's constants learnt on training
  runs, as ekf-tuned learns noise);
- scored on the development runs (seed + 7000, 16): pooled position RMSE ratio to
  ekf-aug-known with a 95 % bootstrap interval over runs, as examples/bias/settings.py.

    python examples/bias/calibrated.py [configs/bias/steering_bias.yaml ...]

The rule is now a filter kind, `ekf-aug-calibrated` (filters/augmented.py: `calibrate`, fitted
through anfekf_bench.fitting on the scenario's own training runs, the training branch of its
seed, `training.runs` of them: 8 in configs/bias), scored by `anfekf run configs/bias`
(docs/results/bias.md). This script stays as the record of how the rule was chosen: its
training (seed + 8000) and development (seed + 7000) runs and the figures it printed. The
kind adds one step this script does not take: its training runs run ekf-aug from each start of
a fixed grid of scale factors (`SCALE_STARTS`) and read the end estimates of the one of least
training RMSE, so that a large scale error (1.6x steering) does not teach the rule a wrong one.
"""

import math
import sys
from pathlib import Path

import numpy as np
from development import pooled_ratio  # this folder's shared part (run as a script)

from anfekf_bench.config import parse_scenario, read_scenario_document, resolve_world
from anfekf_bench.engines import fast
from anfekf_bench.filters.augmented import PARAMETERS
from anfekf_bench.filters.context import filter_context
from anfekf_bench.runner import simulate
from anfekf_bench.sources.simulator import world_path
from anfekf_bench.timeline import from_run

DEV_OFFSET, TRAIN_OFFSET, TRAIN_RUNS, DEV_RUNS = 7000, 8000, 8, 16
NOMINAL = np.array([1.0, 1.0, 0.0, 0.0])
TOLERANCE = np.array([0.03, 0.03, math.radians(0.25), 0.05])
configs = Path(__file__).resolve().parents[2] / "configs" / "bias"
paths = [Path(p) for p in sys.argv[1:]] or [
    configs / f"{n}.yaml" for n in ("steering_bias", "range_bias", "speed_scale", "combined")
]
rng = np.random.default_rng(0)


def runs(scenario, world, offset: int, n: int):
    shared = world_path(world)
    for seed in np.random.SeedSequence(scenario.seed + offset).spawn(n):
        data = simulate(scenario, world, seed, shared)
        tl = from_run(data, world, scenario.record_every)
        yield tl, data.truth.x[scenario.record_every :: scenario.record_every]


for path in paths:
    scenario = parse_scenario(read_scenario_document(path), path)
    world = resolve_world(scenario.world, path.parent)
    specs = {s.name: s for s in scenario.filters}
    aug, known = specs["ekf-aug"], specs["ekf-aug-known"]
    ends = []
    for tl, _ in runs(scenario, world, TRAIN_OFFSET, TRAIN_RUNS):
        _, theta = fast.augmented_run(aug, filter_context(aug, scenario, world), tl)
        ends.append(theta[-1])
    m, s = np.mean(ends, axis=0), np.std(ends, axis=0, ddof=1)
    present = [p for i, p in enumerate(PARAMETERS) if abs(m[i] - NOMINAL[i]) > TOLERANCE[i]]
    start = tuple(float(m[i]) if p in present else NOMINAL[i] for i, p in enumerate(PARAMETERS))
    sigma0 = tuple(float(max(s[i], 1e-9)) if p in present else aug.sigma0[i]
                   for i, p in enumerate(PARAMETERS))  # fmt: skip
    variants = {
        "config": aug,
        "selected": aug.model_copy(update={"estimate": present}),
        "calibrated": aug.model_copy(
            update={"estimate": present, "start": start, "sigma0": sigma0}
        ),
    }
    print(
        f"\n{scenario.name}: training ({TRAIN_RUNS} runs, seed + {TRAIN_OFFSET}) mean"
        f" {np.round(m, 4).tolist()} sd {np.round(s, 4).tolist()}; present: {present}"
    )
    sq = {name: [] for name in [*variants, "known"]}
    for tl, x_true in runs(scenario, world, DEV_OFFSET, DEV_RUNS):
        for name, spec in [*variants.items(), ("known", known)]:
            out = fast.run_filter_fast(spec, filter_context(spec, scenario, world), tl)
            sq[name].append(np.sum((out["x"][:, :2] - x_true[:, :2]) ** 2, axis=1))
    ref = np.array(sq["known"])
    print(f"  development runs ({DEV_RUNS}, seed + {DEV_OFFSET}): ratio to ekf-aug-known")
    for name in variants:
        e = np.array(sq[name])
        pooled, lo, hi = pooled_ratio(e, ref, rng)
        print(f"  {name:11s} {pooled:6.3f} [{lo:.3f}, {hi:.3f}]")
