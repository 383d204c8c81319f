"""`anfekf init`: a commented starter scenario that `anfekf run` accepts, named after its file.

Any file name gives a valid scenario name (`starter_name`): accents dropped, other characters
outside letters, digits, `_ . -` turned into `_`, the leading and trailing `_ . -` removed, cut
to `storage.NAME_MAX` characters; a name of the results layout (`report`, `ci-gate`,
`steps.parquet`, ...) gets `-scenario` appended, and a name with nothing left is `scenario`.
The name is written quoted, so that `1.yaml` or `null.yaml` name the scenario "1" or "null"
(text), never a number or nothing. The file is created only where nothing is
(`storage.write_new`: exclusive, whole).
"""

from __future__ import annotations

import json
import re
import unicodedata
from pathlib import Path

from .config import BUILTIN_MAP
from .storage import NAME_MAX, scenario_name_problem, write_new

FALLBACK_NAME = "scenario"
RESERVED_TAIL = "-scenario"  # appended to a name of the results layout

# Every line starting with `# <key>:` is an option the user may uncomment as it stands
# (tests/test_hardening4_inputs.py uncomments each one and validates the scenario).
STARTER_SCENARIO = """\
# A starter scenario for `anfekf run` (written by `anfekf init`). Every key below is optional
# except `name`; `anfekf kinds` lists the filter kinds with their parameters and defaults.
name: {name}                  # results go to OUT/<name>/
description: The EKF against the ANFEKF when the filters assume a wrong measurement noise R
seed: 1                       # root seed: the same seed gives the same bytes
runs: 20                      # Monte Carlo runs (the paper's scenarios use 50)
record_every: 8               # steps.parquet keeps every 8th control step (one per sensor scan)
# engine: fast                # the compiled engine (numba) for the kinds it runs; filterpy: all
# The noise the simulator draws (true_noise) and the noise the filters assume (filter_noise):
# standard deviations; angles in degrees.
true_noise:   {{sigma_v: 0.3, sigma_gamma_deg: 3.0, sigma_range: 0.1, sigma_bearing_deg: 1.0}}
filter_noise: {{sigma_v: 0.3, sigma_gamma_deg: 3.0, sigma_range: 2.0, sigma_bearing_deg: 0.1}}
# world: {{landmarks: {builtin}, waypoints: {builtin}}}   # or CSV files of x,y rows
filters:
  - {{name: ekf, kind: ekf}}                     # fixed noise: the assumed one
  - {{name: anfekf, kind: anfekf, adapt: R}}     # adapts R (Q: the control noise; RQ: both)
  - {{name: sage-husa, kind: sage-husa}}         # a baseline that adapts R
  - {{name: ekf-oracle, kind: ekf-oracle}}       # the reference: given the TRUE noise
# Claims the run checks (and `anfekf check` gates), decided on the paired 95 % interval:
claims:
  - {{filter: anfekf, vs: ekf, metric: rmse_pos, at_most: 0.8}}
"""


def starter_name(file_name: str) -> str:
    """The scenario name `anfekf init` gives a file called `file_name` (module doc): always one
    that `storage.scenario_name_problem` accepts."""
    stem = Path(file_name).stem
    ascii_only = unicodedata.normalize("NFKD", stem).encode("ascii", "ignore").decode("ascii")
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", ascii_only).strip("_.-")[:NAME_MAX].rstrip("_.-")
    if not name:
        return FALLBACK_NAME
    if scenario_name_problem(name):  # a name of the results layout
        name = name[: NAME_MAX - len(RESERVED_TAIL)].rstrip("_.-") + RESERVED_TAIL
    return FALLBACK_NAME if scenario_name_problem(name) else name


def starter_text(name: str) -> str:
    # JSON's double-quoted string is YAML too: the name stays text whatever it looks like.
    return STARTER_SCENARIO.format(name=json.dumps(name), builtin=BUILTIN_MAP)


def write_starter(path: Path) -> str:
    """Write the starter scenario to `path` where nothing is (FileExistsError otherwise; other
    OSErrors as they come); returns the scenario's name."""
    name = starter_name(Path(path).name)
    write_new(path, starter_text(name).encode("utf-8"))
    return name
