"""ekf-aug's estimates of each drive's odometry scale factors and turn-rate bias at the drive's
end (SPEC 18, docs/results/bias.md), from each naive start, on the fast engine:

    python examples/bias/drive_estimates.py [configs/bias-drives/mrclam-drives-aug.yaml]
"""

import sys
from pathlib import Path

import numpy as np

from anfekf_bench.engines import fast
from anfekf_bench.filters import FilterContext
from anfekf_bench.filters.ekf import gate_threshold
from anfekf_bench.models import Unicycle
from anfekf_bench.real_experiment import segment_inputs
from anfekf_bench.scenarios import load_scenario
from anfekf_bench.sources.recorded import naive_covariances, p0

default = Path(__file__).resolve().parents[2] / "configs/bias-drives/mrclam-drives-aug.yaml"
scenario, world = load_scenario(sys.argv[1] if len(sys.argv) > 1 else default)
specs = [s for s in scenario.filters if s.kind == "ekf-aug"]
print("drive   filter      start  speed_scale turn_scale turn_bias[rad/s] range_bias[m]")
for drive in world.drives:
    inputs = segment_inputs(drive, drive.segment, scenario.eval_period_s)
    for spec in specs:
        for m in scenario.starts:
            Qu, R = naive_covariances(scenario, m)
            ctx = FilterContext(
                x0=np.array(drive.segment.pose, dtype=float), P0=p0(scenario), Qu=Qu, R=R,
                model=Unicycle(scenario.odometry_period_s), dt=scenario.odometry_period_s,
                gate=gate_threshold(scenario.gate_probability),
            )  # fmt: skip
            out, theta = fast.augmented_run(spec, ctx, inputs.timeline)
            last = theta[np.isfinite(theta).all(axis=1)][-1]
            print(f"{drive.id:7s} {spec.name:11s} x{m:<5g}" + "".join(f" {v:+11.4f}" for v in last))
