"""Problem results in the regression gate (`anfekf check`, analysis.gate; SPEC 17).

A problem result joins the robot's scenarios as a `gate.ScenarioSummary` of the metrics its
summary shares with them: `rmse_pos`, `anees` (judged against the problem's state dimension,
what a consistent filter's ANEES is, as the robot's is against 3) and `nees_in_bounds`; its
`rmse_pos` is shown in the problem's unit (the manifest's `position_unit`: none for `linear`). A
baseline guards whichever of them its tolerances list; the robot's others (`rmse_heading`,
`diverged`) do not exist here and are not asked for.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from ..analysis.gate import ScenarioSummary
from ..storage import ResultsError, scenario_name_problem
from .experiment import problem_result_folders, read_problem_result
from .filters import NAME_PATTERN
from .module import UNIT

METRICS = ("rmse_pos", "anees", "nees_in_bounds")
PLAIN_NAME = re.compile(NAME_PATTERN)  # as the scenario schema allows a filter's name


def state_dimension(manifest: dict, folder: Path) -> int:
    """The problem's state dimension: the manifest's (written since the gate reads problem
    results), else from its scenario (a module's file is not beside its result: rerun)."""
    n = manifest.get("state_dimension")
    if isinstance(n, int) and not isinstance(n, bool) and n > 0:
        return n
    from .schema import parse_problem_scenario

    try:
        scenario = parse_problem_scenario(manifest["scenario"], folder / "scenario.yaml")
        return scenario.build_problem().n
    except Exception:  # any failure means the same: the dimension cannot be known
        raise ResultsError(f"{folder}: manifest.json has no state_dimension (written by an"
                           " older version); run it again with `anfekf run`") from None  # fmt: skip


def position_unit(manifest: dict) -> str:
    """The unit of the problem's position components as the manifest records it (since the
    gate shows it); none where it does not (an older result: no unit is shown)."""
    unit = manifest.get("position_unit", "")
    if not (isinstance(unit, str) and UNIT.fullmatch(unit)):
        raise ValueError(f"position_unit {str(unit)[:20]!r} is not a unit name")
    return unit


def read_problem_summaries(results_dir: Path) -> dict[str, ScenarioSummary]:
    """Every problem result under `results_dir` (itself, or its children), by scenario name."""
    out: dict[str, ScenarioSummary] = {}
    try:
        folders = problem_result_folders([Path(results_dir)])
    except OSError as exc:  # a name or path too long, no permission: as storage.scenario_dirs
        raise ResultsError(f"{results_dir}: cannot be read ({exc.strerror or exc})") from None
    for folder in folders:
        summary = read_summary(folder)
        if summary.name in out:
            raise ResultsError(f"{folder}: scenario {summary.name!r} appears in two folders")
        out[summary.name] = summary
    return out


def read_summary(folder: Path) -> ScenarioSummary:
    """One problem result as the gate sees it; ResultsError (one line) for anything that is
    not as `anfekf run` writes it (names are printed in the gate's tables: plain text only)."""
    result = read_problem_result(folder)
    manifest, summary = result["manifest"], result["summary"]
    try:
        name = str(manifest["scenario"]["name"])
        if scenario_name_problem(name):
            raise ValueError(f"scenario name {name[:40]!r} is not a valid name")
        filters = {}
        for record in summary.to_dict(orient="records"):
            filt = str(record["filter"])
            if not PLAIN_NAME.fullmatch(filt):
                raise ValueError(f"filter name {filt[:40]!r} is not plain text")
            filters[filt] = {m: float(record[m]) for m in METRICS}
            if any(math.isinf(v) for v in filters[filt].values()):
                raise ValueError(f"a metric of {filt!r} is infinite")
        return ScenarioSummary(
            name=name, seed=int(manifest["seed"]), runs=int(manifest["runs"]), filters=filters,
            fingerprint=manifest.get("fingerprint"), folder=folder,
            problem=str(manifest["problem"]), anees_ideal=float(state_dimension(manifest, folder)),
            units={"rmse_pos": position_unit(manifest)},
        )  # fmt: skip
    except (KeyError, TypeError, ValueError) as exc:
        raise ResultsError(f"{folder}: not a problem result as `anfekf run` writes it ({exc})"
                           ) from None  # fmt: skip
