"""How close ekf-aug's estimates come to the injected errors (SPEC 18, docs/results/bias.md).

For each scenario of configs/bias/ (or those named on the command line): the same runs as
`anfekf run` (run i from SeedSequence(seed).spawn(runs)[i]), ekf-aug and ekf-aug-known on the
fast engine. Prints per parameter the mean and standard deviation over runs of the estimate at
the run's end, the largest error, the share of runs within the stated tolerance, and the
position RMSE ratio of ekf-aug to ekf-aug-known (geometric mean over runs) over the whole run
and over its second half (after the estimates settle).

    python examples/bias/estimates.py [--family vb-r|sage-husa | --filter NAME] [configs/bias/...]

--family: the same for that adaptive family with `augment:` set to ekf-aug's states and
settings (sage-husa adapts R), against the same oracle. --filter: another augmented filter of
the scenario in ekf-aug's place (`ekf-aug-calibrated`: fitted first on the scenario's training
runs, as `anfekf run` fits it; a parameter it does not estimate is its start at the end).
"""

import math
import sys
from pathlib import Path

import numpy as np

from anfekf_bench.config import parse_scenario, read_scenario_document, resolve_world
from anfekf_bench.engines import fast
from anfekf_bench.filters.augmented import PARAMETERS, AugmentParams
from anfekf_bench.filters.context import filter_context
from anfekf_bench.filters.registry import SPEC_BY_KIND
from anfekf_bench.fitting.fit import fit_specs
from anfekf_bench.fitting.simulated import TrainingSet
from anfekf_bench.runner import simulate
from anfekf_bench.sources.simulator import world_path
from anfekf_bench.timeline import from_run

# Stated tolerances on the estimate at the run's end: scales, steering bias [rad], range bias [m]
TOLERANCE = np.array([0.03, 0.03, math.radians(0.25), 0.05])
configs = Path(__file__).resolve().parents[2] / "configs" / "bias"
argv = sys.argv[1:]
family, chosen = None, "ekf-aug"
if argv[:1] == ["--family"]:
    family, argv = argv[1], argv[2:]
elif argv[:1] == ["--filter"]:
    chosen, argv = argv[1], argv[2:]
paths = [Path(p) for p in argv] or sorted(configs.glob("*.yaml"))

for path in paths:
    scenario = parse_scenario(read_scenario_document(path), path)
    world = resolve_world(scenario.world, path.parent)
    specs = {s.name: s for s in scenario.filters}
    if chosen not in specs:
        continue
    aug, known = specs[chosen], specs["ekf-aug-known"]
    if aug.fitted_on_training:  # ekf-aug-calibrated: on the training runs, never these
        training = TrainingSet(scenario=scenario, world=world, seed=scenario.seed)
        aug = aug.with_fit(fit_specs([(aug, training)], None)[0].fitted)
        print(
            f"\n{scenario.name}: {chosen} fitted on {scenario.training.runs} training runs:"
            f" estimates {aug.augment.estimate}, start {np.round(aug.augment.start, 4).tolist()}"
        )
    if family is not None:
        params = AugmentParams(**aug.model_dump(include=set(AugmentParams.model_fields)))
        aug = SPEC_BY_KIND[family](name="ekf-aug", kind=family, augment=params)
    truth = np.array(known.start)
    shared = world_path(world)
    ends, ratio_all, ratio_late = [], [], []
    for seed in np.random.SeedSequence(scenario.seed).spawn(scenario.runs):
        data = simulate(scenario, world, seed, shared)
        tl = from_run(data, world, scenario.record_every)
        x_true = data.truth.x[scenario.record_every :: scenario.record_every]
        rmse = {}
        for spec in (aug, known):
            out, theta = fast.augmented_run(spec, filter_context(spec, scenario, world), tl)
            err = np.hypot(*(out["x"][:, :2] - x_true[:, :2]).T)
            late = err[len(err) // 2 :]
            rmse[spec.name] = (np.sqrt(np.mean(err**2)), np.sqrt(np.mean(late**2)))
            if spec is aug:
                ends.append(theta[-1])
        ratio_all.append(rmse[aug.name][0] / rmse["ekf-aug-known"][0])
        ratio_late.append(rmse[aug.name][1] / rmse["ekf-aug-known"][1])
    ends = np.array(ends)
    print(f"\n{scenario.name} ({scenario.runs} runs): injected {np.round(truth, 4).tolist()}")
    for i, name in enumerate(PARAMETERS):
        err = np.abs(ends[:, i] - truth[i])
        within = np.mean(err < TOLERANCE[i])
        print(
            f"  {name:12s} end {ends[:, i].mean():+.4f} sd {ends[:, i].std(ddof=1):.4f}"
            f"  max |error| {err.max():.4f}  within {TOLERANCE[i]:.4f}: {within:.0%}"
        )
    whole, late = (math.exp(np.mean(np.log(r))) for r in (ratio_all, ratio_late))
    print(
        f"  RMSE ratio {aug.name} / ekf-aug-known: whole run {whole:.3f}"
        f" (max {max(ratio_all):.2f});"
        f" second half {late:.3f} (max {max(ratio_late):.2f})"
    )
