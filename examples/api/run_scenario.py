"""Run a scenario from Python, read its tables and write its report (docs/API.md)."""

import sys
from pathlib import Path

from anfekf_bench import api

out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("results/api")
# The repository's configs/, found from this file: the example runs from any working directory.
configs = Path(__file__).resolve().parents[2] / "configs"

# A scenario file, or a dict shaped like one (relative paths in a dict: base=...).
experiment = api.load(configs / "wrong_r.yaml")
result = api.run(experiment, out=out, runs=4, engine="fast", force=True)

summary = result.summary()  # one row per filter
print(summary[["filter", "rmse_pos", "anees", "nees_in_bounds"]].to_string(index=False))
ratios = result.comparisons()  # paired ratios with their 95 % bootstrap intervals
print(ratios[["filter", "vs", "metric", "estimate", "lo", "hi"]].to_string(index=False))

print("report:", api.report([result], out=out / "report"))
