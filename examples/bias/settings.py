"""Where ekf-aug's RMSE over the oracle of the errors goes, and whether its settings move it
(SPEC 18, issue 35; docs/results/bias.md). Development seeds only: the runs of
SeedSequence(seed + 7000), disjoint from the scored runs of SeedSequence(seed).

For each scenario named (default: steering bias, range bias, speed scale of configs/bias/) and
each variant of ekf-aug (its config's settings; start standard deviations x3 and /3; drift x10
and /10; only the injected parameter estimated, a diagnostic that knows which error is there):
the pooled position RMSE ratio to ekf-aug-known with a 95 % bootstrap interval over runs, the
geometric mean of per-run ratios, and the ratio of the mean squared error by fifths of the run
(where the excess is).

    python examples/bias/settings.py [--runs 16] [configs/bias/steering_bias.yaml ...]
"""

import argparse
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

DEV_OFFSET = 7000  # development seeds: seed + 7000 (disjoint from the scored runs)
configs = Path(__file__).resolve().parents[2] / "configs" / "bias"
parser = argparse.ArgumentParser()
parser.add_argument("--runs", type=int, default=16)
parser.add_argument("--only", nargs="*", help="variants to run (default: all)")
parser.add_argument("paths", nargs="*")
args = parser.parse_args()
paths = [Path(p) for p in args.paths] or [
    configs / f"{n}.yaml" for n in ("steering_bias", "range_bias", "speed_scale")
]


def variants(aug, known):
    injected = [p for i, p in enumerate(PARAMETERS) if known.start[i] != (1.0, 1.0, 0.0, 0.0)[i]]
    s0, dr = np.array(aug.sigma0), np.array(aug.drift)
    return {
        "config": aug,
        "sigma0 x3": aug.model_copy(update={"sigma0": tuple(3 * s0)}),
        "sigma0 /3": aug.model_copy(update={"sigma0": tuple(s0 / 3)}),
        "drift x10": aug.model_copy(update={"drift": tuple(10 * dr)}),
        "drift /10": aug.model_copy(update={"drift": tuple(dr / 10)}),
        "turn scale sd 0.1": aug.model_copy(update={"sigma0": (s0[0], 0.1, s0[2], s0[3])}),
        "sd /3 but range": aug.model_copy(
            update={"sigma0": (s0[0] / 3, s0[1] / 3, s0[2] / 3, s0[3])}
        ),
        "kind default (no range)": aug.model_copy(
            update={"estimate": ["speed_scale", "turn_scale", "turn_bias"]}
        ),
        "no speed scale": aug.model_copy(
            update={"estimate": ["turn_scale", "turn_bias", "range_bias"]}
        ),
        "only injected": aug.model_copy(update={"estimate": injected}),
    }


rng = np.random.default_rng(0)
for path in paths:
    scenario = parse_scenario(read_scenario_document(path), path)
    world = resolve_world(scenario.world, path.parent)
    specs = {s.name: s for s in scenario.filters}
    known = specs["ekf-aug-known"]
    vs = variants(specs["ekf-aug"], known)
    if args.only:
        vs = {k: v for k, v in vs.items() if k in args.only}
    shared = world_path(world)
    sq = {name: [] for name in [*vs, "known"]}
    for seed in np.random.SeedSequence(scenario.seed + DEV_OFFSET).spawn(args.runs):
        data = simulate(scenario, world, seed, shared)
        tl = from_run(data, world, scenario.record_every)
        x_true = data.truth.x[scenario.record_every :: scenario.record_every]
        for name, spec in [*vs.items(), ("known", known)]:
            out = fast.run_filter_fast(spec, filter_context(spec, scenario, world), tl)
            sq[name].append(np.sum((out["x"][:, :2] - x_true[:, :2]) ** 2, axis=1))
    ref = np.array(sq["known"])
    print(f"\n{scenario.name}: {args.runs} development runs (seed {scenario.seed + DEV_OFFSET})")
    print("  variant          pooled ratio [95 %]     per-run gm   by fifths of the run")
    for name in vs:
        e = np.array(sq[name])
        pooled, lo, hi = pooled_ratio(e, ref, rng)
        gm = np.exp(np.mean(np.log(np.sqrt(e.mean(axis=1) / ref.mean(axis=1)))))
        fifths = [
            np.sqrt(a.mean() / b.mean())
            for a, b in zip(np.array_split(e, 5, 1), np.array_split(ref, 5, 1), strict=True)
        ]
        print(
            f"  {name:15s} {pooled:6.3f} [{lo:.3f}, {hi:.3f}]   {gm:6.3f}     "
            + " ".join(f"{f:.2f}" for f in fifths)
        )
