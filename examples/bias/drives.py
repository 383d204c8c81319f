"""Lost lock and single-run NEES on the drives, per filter and start (SPEC 18,
docs/results/bias.md), from a drives result's steps table:

    anfekf run configs/bias-drives --engine fast --out OUT
    python examples/bias/drives.py OUT/mrclam-drives-aug

Per instance: the drives with lost lock (position error above 1 m at some scored time), the
median RMSE, and the NEES "in bounds" share measured on each drive alone: each scored step's
NEES against the single-run chi-square(3) 95 % bounds [0.216, 9.35], pooled over drives and
steps, with the lowest per-drive share. (The ratio to ekf-tuned with its interval is the
result's own comparisons table, printed last.)
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2

folder = Path(sys.argv[1])
steps = pd.read_parquet(folder / "steps.parquet", columns=["filter", "run", "pos_err", "nees"])
lo, hi = chi2.ppf(0.025, 3), chi2.ppf(0.975, 3)
rows = []
for name, sub in steps.groupby("filter", observed=True, sort=False):
    scored = sub[np.isfinite(sub["pos_err"])]
    per_drive = scored.groupby("run")
    rmse = per_drive["pos_err"].apply(lambda e: float(np.sqrt(np.mean(e**2))))
    lost = int((per_drive["pos_err"].max() > 1.0).sum())
    nees = scored["nees"].to_numpy()
    inside = (nees >= lo) & (nees <= hi)
    share = per_drive["nees"].apply(lambda v: float(np.mean((v >= lo) & (v <= hi))))
    rows.append(
        {
            "filter": name,
            "lost lock": f"{lost}/{len(rmse)}",
            "median RMSE [m]": round(float(rmse.median()), 3),
            "NEES in bounds, pooled": round(float(np.mean(inside)), 3),
            "lowest drive": round(float(share.min()), 3),
        }
    )
print(pd.DataFrame(rows).to_string(index=False))
comparisons = folder / "comparisons.parquet"
if comparisons.exists():
    table = pd.read_parquet(comparisons)
    table = table[table["metric"] == "rmse_pos"] if "metric" in table else table
    print(table.to_string(index=False, max_colwidth=30))
