"""The regression gate: compare scenario summaries with a committed baseline, check the claims.

`anfekf check RESULTS --baseline FILE` reads every scenario's summary under RESULTS and compares
each (scenario, filter, metric) with the baseline, within the tolerance the baseline file keeps for
that metric. Independently of any baseline it checks the claims each scenario declares (their
verdicts, decided on paired intervals when the scenario ran: claims.json): a claim that fails
breaks the gate, an inconclusive one only with --strict. With neither a baseline nor a claim the
gate has checked nothing and says so (exit 1). Exit codes: 0 pass, 1 a regression / change /
failed claim / nothing checked, 2 unusable input.

Verdicts, per row (every verdict but "ok" fails the gate; see RULES, also written into the file):
- ok: within tolerance.
- worse / better (refresh the baseline): beyond tolerance, in the bad / good direction. An
  improvement fails too: results must not change silently, and the baseline has to follow.
- changed: beyond tolerance for a metric without a direction.
- not comparable: the seed or run count differs; that scenario's metrics are not compared.
- missing: a scenario or filter of the baseline is not in the results.
- new (not in the baseline): a scenario or filter of the results that the baseline does not guard.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.table import Table
from rich.text import Text

from ..storage import (
    CLAIMS_FILE,
    COMPARISONS_FILE,
    MANIFEST_FILE,
    SUMMARY_PARQUET,
    SWEEP_CELLS_DIR,
    ResultsError,
    check_one_batch,
    check_simulated_manifest,
    is_sweep_folder,
    read_json,
    read_manifest,
    read_parquet,
    read_summary,
    scenario_dirs,
    scenario_name_problem,
    sweep_folders,
    write_json,
)
from ..text import one_line
from .comparisons import SHARE_METRICS, claim_text
from .comparisons import _point_verdict as point_verdict
from .shown import SHOWN_UNITS, fmt_value, in_shown_unit, shown_metric
from .statistics import DEGENERATE_RTOL
from .statistics import verdict as interval_verdict

BASELINE_FORMAT = "anfekf-bench baseline"
BASELINE_VERSION = 1

# Tight enough to catch a real change (results are deterministic for a seed), loose enough for
# float differences across numpy/BLAS builds, which can flip a rare gating decision in one run.
DEFAULT_TOLERANCES: dict[str, dict[str, float]] = {
    "rmse_pos": {"relative": 0.03},
    "rmse_heading": {"relative": 0.03},
    "anees": {"relative": 0.05},
    "nees_in_bounds": {"absolute": 0.03},
    "diverged": {"absolute": 0},
}

# Which way is better for each summary metric a baseline may guard: "lower", "higher", a number
# (the ideal value: closer is better, measured as |log(value / ideal)|, since NEES is a ratio),
# or None (no better side: any change beyond tolerance is just "changed").
METRIC_SENSE: dict[str, str | float | None] = {
    "rmse_pos": "lower",
    "rmse_heading": "lower",
    "diverged": "lower",
    "runs_used": "higher",
    "nees_in_bounds": "higher",
    "anees": 3.0,  # the pose dimension: a consistent filter's mean NEES
    "anis": 2.0,  # the measurement dimension
    "gate_rejected": None,
}

RULES = [
    "Each (scenario, filter, metric) of the results is compared with this file's value within the"
    " metric's tolerance: relative = |now - baseline| / |baseline|, absolute = |now - baseline|.",
    "Every verdict but 'ok' fails the gate (exit 1): 'worse' and 'better (refresh the baseline)'"
    " (beyond tolerance either way: results must not change silently), 'changed' (no better"
    " side), 'not comparable' (other seed or runs: the metrics are not compared), 'missing' and"
    " 'new' (scenario or filter only on one side).",
    "Better is lower for rmse_pos, rmse_heading and diverged, higher for nees_in_bounds and"
    " runs_used, closer to 3 for anees (a problem's: to its anees_ideal, the state dimension)"
    " and to 2 for anis (as |log(value / ideal)|).",
    "A null value means undefined (every run diverged); becoming undefined counts as 'worse'.",
    "Refresh on purpose only: anfekf check RESULTS --baseline FILE --update (README, Regression"
    " gate).",
]


class BaselineError(Exception):
    """The baseline file cannot be used; `str()` is the one-line message for the user."""


@dataclass(frozen=True)
class Tolerance:
    """How far a metric may move from its baseline value before the gate fails."""

    kind: str  # "relative" or "absolute"
    limit: float

    def change(self, base: float, now: float) -> float:
        """The signed change in this tolerance's unit (a fraction of |base| if relative)."""
        if self.kind == "absolute":
            return now - base
        if base == 0:
            return 0.0 if now == 0 else math.copysign(math.inf, now)
        return (now - base) / abs(base)

    def exceeded(self, base: float, now: float) -> bool:
        # A hair of slack so a limit of exactly 0 (diverged) is not broken by float noise.
        return abs(self.change(base, now)) > self.limit + 1e-12

    def describe(self) -> str:
        if self.kind == "relative":
            return f"±{100 * self.limit:g} % relative"
        return f"±{self.limit:g} absolute"

    def as_json(self) -> dict[str, float]:
        return {self.kind: self.limit}


@dataclass(frozen=True)
class ScenarioSummary:
    """One scenario as the gate sees it: how it was run and each filter's metrics (NaN = null)."""

    name: str
    seed: int
    runs: int
    filters: dict[str, dict[str, float]]
    fingerprint: str | None = None
    versions: dict | None = None
    folder: Path | None = None  # where it was read from (None: from the baseline)
    # A problem beyond the robot (SPEC 17; read by problems.gate): it guards only the metrics
    # its summary holds, and a consistent filter's ANEES is its state dimension.
    problem: str | None = None
    anees_ideal: float = 3.0
    units: dict[str, str] | None = None  # its own unit of a metric (analysis.shown)


@dataclass(frozen=True)
class Baseline:
    tolerances: dict[str, Tolerance]
    scenarios: dict[str, ScenarioSummary]


@dataclass(frozen=True)
class Row:
    """One line of the comparison table; `detail` is the sentence printed for a failing row."""

    scenario: str
    filter: str
    metric: str
    baseline: float | None
    now: float | None
    delta: str
    verdict: str
    detail: str = ""
    shown: str = ""  # the metric with its unit (analysis.shown); "": the metric as it is

    @property
    def passed(self) -> bool:
        return self.verdict == "ok"


@dataclass(frozen=True)
class ClaimResult:
    """A claim the scenario declared (claims.json), decided on its interval when it was run."""

    scenario: str
    text: str
    estimate: float | None
    lo: float | None
    hi: float | None
    verdict: str  # "holds", "fails", "inconclusive" or "missing" (declared, no result: fails)
    note: str = ""

    def passed(self, strict: bool) -> bool:
        return self.verdict == "holds" or (self.verdict == "inconclusive" and not strict)

    @property
    def detail(self) -> str:
        shown = fmt_value(self.estimate)
        if self.lo is not None and self.hi is not None:
            shown += f" [{fmt_value(self.lo)}, {fmt_value(self.hi)}]"
        return f"claim {self.scenario}: {self.text}: {self.verdict} ({shown})"


@dataclass(frozen=True)
class Report:
    """Everything `check` found; `updated` means the baseline was rewritten from the results."""

    results_dir: Path
    baseline_path: Path | None
    rows: list[Row]
    claims: list[ClaimResult]
    updated: bool = False
    dropped: tuple[str, ...] = ()
    strict: bool = False

    @property
    def failed_rows(self) -> list[Row]:
        return [] if self.updated else [r for r in self.rows if not r.passed]

    @property
    def broken_claims(self) -> list[ClaimResult]:
        return [c for c in self.claims if not c.passed(self.strict)]

    @property
    def checked_nothing(self) -> bool:
        """No baseline row and no claim: a pass would say nothing."""
        return not self.rows and not self.claims and not self.updated

    @property
    def exit_code(self) -> int:
        return 1 if self.failed_rows or self.broken_claims or self.checked_nothing else 0


# ---------------------------------------------------------------------------------------------
# Reading results


def _number(value) -> float:
    """A summary cell or JSON value as a float; None and NaN both become NaN."""
    if value is None:
        return math.nan
    return float(value)


def _manifest_int(manifest: dict, key: str, path: Path) -> int:
    value = manifest.get(key) if isinstance(manifest, dict) else None
    if isinstance(value, bool) or not isinstance(value, int):
        raise ResultsError(f"{path}: field {key!r} must be an integer, found {value!r}")
    return value


def read_scenario(folder: Path, metrics: Iterable[str]) -> ScenarioSummary:
    """A scenario folder's summary and run settings; `metrics` must all be in the summary."""
    manifest_path = folder / MANIFEST_FILE
    manifest = read_manifest(folder)
    check_simulated_manifest(manifest_path, manifest)  # as `report` does: no half-valid input
    check_one_batch(folder, manifest)
    seed = _manifest_int(manifest, "seed", manifest_path)
    runs = _manifest_int(manifest, "runs", manifest_path)
    summary = read_summary(folder)
    where = folder / SUMMARY_PARQUET
    required = ["scenario", "filter", *metrics]
    missing = [c for c in required if c not in summary.columns]
    if missing:
        raise ResultsError(f"{where}: missing columns {', '.join(missing)}")
    names = summary["scenario"].astype(str).unique().tolist()
    if len(names) != 1:
        raise ResultsError(f"{where}: expected one scenario name, found {names or 'none'}")
    if summary["filter"].duplicated().any():
        raise ResultsError(f"{where}: a filter appears twice")
    _plain_names(where, names[0], summary["filter"].astype(str).tolist())
    declared = manifest.get("scenario")
    if isinstance(declared, dict) and declared.get("name") != names[0]:
        declared = declared.get("name")
        raise ResultsError(
            f"{where}: holds scenario {names[0]!r} but {manifest_path} names {declared!r};"
            " the two files come from different runs"
        )
    if "runs" in summary.columns and not (summary["runs"] == runs).all():
        raise ResultsError(f"{where}: run counts differ from {manifest_path} (runs {runs})")
    stored = [m for m in METRIC_SENSE if m in summary.columns]
    filters = {}
    for rec in summary.to_dict(orient="records"):
        values = {}
        for m in stored:
            try:
                values[m] = _number(rec[m])
            except (TypeError, ValueError):
                raise ResultsError(f"{where}: {m} of {rec['filter']!r} is not a number") from None
            if math.isinf(values[m]):
                raise ResultsError(f"{where}: {m} of {rec['filter']!r} is infinite")
        filters[str(rec["filter"])] = values
    return ScenarioSummary(
        name=names[0],
        seed=seed,
        runs=runs,
        filters=filters,
        fingerprint=manifest.get("fingerprint"),
        versions=manifest.get("versions"),
        folder=Path(folder),
    )


def _plain_names(where: Path, scenario: str, filters: list[str]) -> None:
    """Names are printed in the gate's tables: plain text only (never escape sequences or
    markup a terminal would act on)."""
    from ..config import FILTER_NAME_PATTERN

    if scenario_name_problem(scenario):
        raise ResultsError(f"{where}: scenario name {scenario[:40]!r} is not a valid name")
    for name in filters:
        if not FILTER_NAME_PATTERN.fullmatch(name):
            raise ResultsError(f"{where}: filter name {name[:40]!r} is not plain text")


def read_results(
    results_dir: Path, metrics: Iterable[str], problems: dict | None = None
) -> dict[str, ScenarioSummary]:
    """Every complete scenario under `results_dir`, by scenario name; a sweep's cells count as
    scenarios named `<sweep>/<cell>` (`results_dir` may be a sweep folder or hold some), and
    `problems` (the problem results there, read by the caller) join them."""
    metrics = list(metrics)
    out: dict[str, ScenarioSummary] = dict(problems or {})
    sweeps = sweep_folders(results_dir)
    alone = (sweeps or out) and not _holds_results(results_dir)
    folders = [] if alone else scenario_dirs(results_dir)
    for folder in folders:
        scenario = read_scenario(folder, metrics)
        if scenario.name in out:
            raise ResultsError(f"{folder}: scenario {scenario.name!r} appears in two folders")
        out[scenario.name] = scenario
    for sweep in sweeps:
        for folder in scenario_dirs(sweep / SWEEP_CELLS_DIR):
            cell = read_scenario(folder, metrics)
            name = f"{sweep.name}/{cell.name}"
            if name in out:
                raise ResultsError(f"{folder}: scenario {name!r} appears in two folders")
            out[name] = dataclasses.replace(cell, name=name)
    return out


def _holds_results(results_dir: Path) -> bool:
    """Whether `results_dir` is or holds an ordinary scenario result (besides its sweeps)."""

    def is_result(p: Path) -> bool:
        return (p / MANIFEST_FILE).is_file() and (
            (p / SUMMARY_PARQUET).is_file() or (p / "steps.parquet").is_file()
        )

    results_dir = Path(results_dir)
    if is_sweep_folder(results_dir):
        return False
    return is_result(results_dir) or any(
        is_result(p) for p in results_dir.iterdir() if p.is_dir() and not is_sweep_folder(p)
    )


# ---------------------------------------------------------------------------------------------
# The baseline file


def _tolerance(path: Path, metric: str, spec) -> Tolerance:
    where = f"{path}: tolerances.{metric}"
    if metric not in METRIC_SENSE:
        raise BaselineError(f"{where}: unknown metric (allowed: {', '.join(METRIC_SENSE)})")
    if not isinstance(spec, dict) or len(spec) != 1:
        raise BaselineError(f'{where}: expected {{"relative": x}} or {{"absolute": x}}')
    ((kind, limit),) = spec.items()
    if kind not in ("relative", "absolute"):
        raise BaselineError(f"{where}: unknown kind {kind!r} (allowed: relative, absolute)")
    ok = isinstance(limit, (int, float)) and not isinstance(limit, bool)
    if not ok or not math.isfinite(limit) or limit < 0:
        raise BaselineError(f"{where}.{kind}: must be a number >= 0, found {limit!r}")
    return Tolerance(kind, float(limit))


def parse_tolerances(path: Path, doc) -> dict[str, Tolerance]:
    if not isinstance(doc, dict) or not doc:
        raise BaselineError(f"{path}: tolerances: expected a mapping of metric to tolerance")
    return {metric: _tolerance(path, metric, spec) for metric, spec in doc.items()}


def _baseline_scenario(path: Path, name: str, doc, metrics: list[str]) -> ScenarioSummary:
    where = f"{path}: scenarios.{name}"
    if not isinstance(doc, dict):
        raise BaselineError(f"{where}: expected a mapping with seed, runs and filters")
    for key, least in (("seed", 0), ("runs", 1)):
        value = doc.get(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise BaselineError(f"{where}.{key}: must be an integer, found {_shown(value)}")
        if value < least:
            raise BaselineError(f"{where}.{key}: must be an integer >= {least}, found {value}")
    fingerprint = doc.get("fingerprint")
    if fingerprint is not None and not isinstance(fingerprint, str):
        raise BaselineError(
            f"{where}.fingerprint: must be text or null, found {_shown(fingerprint)}"
        )
    problem, ideal = doc.get("problem"), doc.get("anees_ideal", 3.0)
    if problem is not None and not isinstance(problem, str):
        raise BaselineError(f"{where}.problem: must be text or absent, found {_shown(problem)}")
    if isinstance(ideal, bool) or not isinstance(ideal, (int, float)) or not 0 < ideal < 1e9:
        raise BaselineError(f"{where}.anees_ideal: must be a positive number, found {ideal!r:.40}")
    filters = doc.get("filters")
    if not isinstance(filters, dict) or not filters:
        raise BaselineError(f"{where}.filters: expected a mapping of filter name to metrics")
    parsed: dict[str, dict[str, float]] = {}
    for fname, values in filters.items():
        if not isinstance(values, dict):
            raise BaselineError(f"{where}.filters.{fname}: expected a mapping of metric to value")
        for metric in metrics if problem is None else ():  # a problem: the metrics it holds
            if metric not in values:
                raise BaselineError(f"{where}.filters.{fname}: no value for {metric}")
        for metric, value in values.items():
            # A non-finite baseline would make every comparison pass (or none): refuse it.
            number = value is None or (
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and math.isfinite(value)
            )
            if not number:
                raise BaselineError(
                    f"{where}.filters.{fname}.{metric}: must be a finite number or null,"
                    f" found {_shown(value)}"
                )
        parsed[fname] = {m: _number(v) for m, v in values.items()}
    return ScenarioSummary(
        name=name,
        seed=doc["seed"],
        runs=doc["runs"],
        filters=parsed,
        fingerprint=doc.get("fingerprint"),
        problem=problem,
        anees_ideal=float(ideal),
    )


def _shown(value) -> str:
    """A value from a hand-edited file, short and on one line, for an error message."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def load_baseline(path: Path) -> Baseline:
    """Read and validate a baseline file; raises BaselineError (or ResultsError) in one line."""
    path = Path(path)
    if not os.path.lexists(path):
        raise BaselineError(
            f"{path}: baseline file not found (write one with `anfekf check RESULTS --baseline"
            f" {path} --update`)"
        )
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise BaselineError(f"{path}: expected a JSON object with tolerances and scenarios")
    if doc.get("format") != BASELINE_FORMAT or doc.get("version") != BASELINE_VERSION:
        raise BaselineError(
            f"{path}: not an anfekf-bench baseline (expected format {BASELINE_FORMAT!r},"
            f" version {BASELINE_VERSION}); write one with `anfekf check RESULTS --baseline"
            f" {path} --update`"
        )
    tolerances = parse_tolerances(path, doc.get("tolerances"))
    scenarios = doc.get("scenarios")
    if not isinstance(scenarios, dict) or not scenarios:
        raise BaselineError(f"{path}: scenarios: expected a mapping of scenario name to results")
    metrics = list(tolerances)
    return Baseline(
        tolerances=tolerances,
        scenarios={
            name: _baseline_scenario(path, name, sdoc, metrics) for name, sdoc in scenarios.items()
        },
    )


def baseline_document(
    results: dict[str, ScenarioSummary], tolerances: dict[str, Tolerance]
) -> dict:
    """The JSON document of a baseline made from `results` (NaN is written as null)."""
    first = next(iter(results.values()))
    return {
        "format": BASELINE_FORMAT,
        "version": BASELINE_VERSION,
        "rules": RULES,
        "tolerances": {m: t.as_json() for m, t in tolerances.items()},
        "made_with": first.versions or {},
        "scenarios": {
            s.name: {
                "seed": s.seed,
                "runs": s.runs,
                "fingerprint": s.fingerprint,
                "filters": {
                    f: {m: _json_value(m, v) for m, v in metrics.items()}
                    for f, metrics in s.filters.items()
                },
                **_problem_keys(s),
            }
            for s in results.values()
        },
    }


def _problem_keys(s: ScenarioSummary) -> dict:
    return {} if s.problem is None else {"problem": s.problem, "anees_ideal": s.anees_ideal}


def _json_value(metric: str, value: float) -> float | int | None:
    if not math.isfinite(value):
        return None
    # Counts read back from Parquet as floats; keep them integers in the file.
    return int(value) if metric in ("diverged", "runs_used") else value


# ---------------------------------------------------------------------------------------------
# Comparison


def _badness(metric: str, value: float, sense=None) -> float:
    """A number that grows as `metric` gets worse (NaN: undefined, the worst)."""
    sense = METRIC_SENSE.get(metric) if sense is None else sense
    if math.isnan(value):
        return math.inf
    if sense == "lower":
        return value
    if sense == "higher":
        return -value
    return abs(math.log(value / sense)) if value > 0 else math.inf


def judge(metric: str, tolerance: Tolerance, base: float, now: float, sense=None) -> str:
    """The verdict for one metric (see the module docstring); `sense` overrides METRIC_SENSE's
    (a problem's ANEES: its state dimension)."""
    if math.isnan(base) and math.isnan(now):
        return "ok"
    if not (math.isnan(base) or math.isnan(now)) and not tolerance.exceeded(base, now):
        return "ok"
    if METRIC_SENSE.get(metric) is None or math.isnan(base):
        return "changed"
    before, after = _badness(metric, base, sense), _badness(metric, now, sense)
    if math.isclose(after, before, rel_tol=1e-9):
        return "changed"
    if after > before:
        return "worse"
    if after < before:
        return "better (refresh the baseline)"
    return "changed"


def _fmt_delta(tolerance: Tolerance, base: float, now: float, metric: str = "") -> str:
    if math.isnan(base) or math.isnan(now):
        return "-"
    change = tolerance.change(base, now)
    if tolerance.kind == "relative":
        return f"{100 * change:+.1f} %"
    return f"{in_shown_unit(metric, change):+.3g}"


def _describe(tolerance: Tolerance, metric: str) -> str:
    """The tolerance as shown: an absolute one in the metric's shown unit."""
    if tolerance.kind == "relative" or metric not in SHOWN_UNITS:
        return tolerance.describe()
    return f"±{in_shown_unit(metric, tolerance.limit):g} absolute"


def compare_metric(
    scenario: str, filt: str, metric: str, tolerance: Tolerance, base: float, now: float,
    sense=None, units: dict[str, str] | None = None,
) -> Row:  # fmt: skip
    verdict = judge(metric, tolerance, base, now, sense)
    detail = ""
    shown = shown_metric(metric, units)
    if verdict != "ok":
        before, after = (fmt_value(in_shown_unit(metric, x)) for x in (base, now))
        detail = (
            f"{scenario} / {filt} / {shown}: {before} -> {after}"
            f" ({_fmt_delta(tolerance, base, now, metric)};"
            f" tolerance {_describe(tolerance, metric)}): {verdict}"
        )
    delta = _fmt_delta(tolerance, base, now, metric)
    return Row(scenario, filt, metric, base, now, delta, verdict, detail, shown)


NOT_COMPARABLE = "not comparable"


def _setup_rows(base: ScenarioSummary, now: ScenarioSummary) -> list[Row]:
    """Seed and run count must match, or the metrics are not comparable (and are not compared:
    a 50-run result judged against a 20-run baseline would list changes that mean nothing)."""
    rows = []
    for key in ("seed", "runs"):
        b, n = getattr(base, key), getattr(now, key)
        detail = ""
        if b != n:
            detail = (
                f"{base.name}: results made with {key} {n}, the baseline with {b}: not"
                f" comparable, metrics not compared (run it with the baseline's seed {base.seed}"
                f" and runs {base.runs}: anfekf run SCENARIO --seed {base.seed} --runs"
                f" {base.runs}; or, to make these results the baseline, --update deliberately)"
            )
        delta = "" if b == n else f"{n - b:+d}"
        rows.append(Row(base.name, "-", key, b, n, delta, "ok" if b == n else NOT_COMPARABLE,
                        detail))  # fmt: skip
    return rows


def _presence_row(scenario: str, filt: str, in_baseline: bool) -> Row:
    what = f"scenario {scenario}" if filt == "-" else f"{scenario} / filter {filt}"
    if in_baseline:
        verdict, detail = "missing", f"{what}: in the baseline but not in the results"
    else:
        verdict = "new (not in the baseline)"
        detail = f"{what}: in the results but not guarded by the baseline (refresh it)"
    return Row(scenario, filt, "-", None, None, "", verdict, detail)


def _union(first: Iterable[str], second: Iterable[str]) -> list[str]:
    return list(dict.fromkeys([*first, *second]))


def compare(baseline: Baseline, results: dict[str, ScenarioSummary]) -> list[Row]:
    """One row per (scenario, filter, metric) of the baseline, plus presence and setup rows."""
    rows: list[Row] = []
    for name in _union(baseline.scenarios, results):
        base, now = baseline.scenarios.get(name), results.get(name)
        if base is None or now is None:
            rows.append(_presence_row(name, "-", in_baseline=base is not None))
            continue
        setup = _setup_rows(base, now)
        rows.extend(setup)
        if not all(r.passed for r in setup):
            continue
        for filt in _union(base.filters, now.filters):
            if filt not in base.filters or filt not in now.filters:
                rows.append(_presence_row(name, filt, in_baseline=filt in base.filters))
                continue
            b, n = base.filters[filt], now.filters[filt]
            for metric, tolerance in baseline.tolerances.items():
                if base.problem is not None and metric not in b and metric not in n:
                    continue  # a metric problems do not have (rmse_heading, diverged)
                sense = now.anees_ideal if metric == "anees" else None
                rows.append(compare_metric(name, filt, metric, tolerance,
                                           b.get(metric, math.nan), n.get(metric, math.nan),
                                           sense, now.units))  # fmt: skip
    return rows


# ---------------------------------------------------------------------------------------------
# Claims


def _optional(value) -> float | None:
    return None if value is None else _number(value)


def interval_problem(estimate: float, lo: float, hi: float) -> str | None:
    """What is wrong with a stored (estimate, lo, hi) (NaN = null), or None: what `anfekf run`
    writes is finite numbers or null, lo <= estimate <= hi (within the writer's own slack), and
    no interval without an estimate. A hand-edited row is refused, never decided on."""
    if any(math.isinf(v) for v in (estimate, lo, hi)):
        return "estimate, lo and hi must be finite numbers or null"
    if math.isnan(lo) != math.isnan(hi):
        return "lo and hi must both be numbers or both null"
    if math.isnan(lo):
        return None  # no interval (a share, too few runs, a biased bootstrap): a point only
    shown = f"[{fmt_value(lo)}, {fmt_value(hi)}]"
    if lo > hi:
        return f"the interval {shown} is inverted; expected lo <= hi"
    if math.isnan(estimate):
        return f"an interval {shown} without an estimate"
    slack = DEGENERATE_RTOL * abs(estimate)
    if not lo - slack <= estimate <= hi + slack:
        return (
            f"estimate {fmt_value(estimate)} outside its interval {shown};"
            " expected lo <= estimate <= hi"
        )
    return None


def _stored_claims(path: Path) -> dict[str, dict]:
    """claims.json's records by claim text (their intervals; their verdicts are never trusted),
    each interval valid and one result per claim."""
    if not path.exists():
        return {}
    doc = read_json(path)
    if not isinstance(doc, list):
        raise ResultsError(f"{path}: expected a list of claims")
    out: dict[str, dict] = {}
    for i, item in enumerate(doc):
        try:
            record = {"claim": str(item["claim"]), "estimate": _optional(item["estimate"]),
                      "lo": _optional(item["lo"]), "hi": _optional(item["hi"]),
                      "verdict": str(item["verdict"]),
                      "warning": str(item.get("warning", ""))}  # fmt: skip
        except (KeyError, TypeError, ValueError, BaselineError):
            raise ResultsError(f"{path}: not a claims file written by anfekf run") from None
        found = tuple(_number(record[k]) for k in ("estimate", "lo", "hi"))
        problem = interval_problem(*found)
        if problem:
            raise ResultsError(f"{path}: {i} ({record['claim'][:60]}): {problem}")
        earlier = out.get(record["claim"])
        if earlier is not None and _interval_of(earlier) != _interval_of(record):
            # A scenario may declare one claim twice (two equal records); two different
            # results for one claim leave nothing to decide on.
            raise ResultsError(
                f"{path}: {i} ({record['claim'][:60]}): a second, different result for one claim;"
                " expected one result per claim"
            )
        out[record["claim"]] = record
    return out


def _interval_of(record: dict) -> tuple:
    return tuple(repr(record[k]) for k in ("estimate", "lo", "hi"))  # NaN equals NaN here


def _declared_claims(folder: Path) -> list:
    """The claims the scenario declares, from its manifest (what was run, whatever claims.json
    says)."""
    from ..config import ClaimSpec  # the scenario schema: imported only when claims are checked

    path = Path(folder) / MANIFEST_FILE
    scenario = read_manifest(folder).get("scenario")
    if not isinstance(scenario, dict):  # read as "no claims", a declared claim went unchecked
        raise ResultsError(f"{path}: scenario: expected the scenario's settings (an object)")
    declared = scenario.get("claims", [])
    if not isinstance(declared, list):
        raise ResultsError(f"{path}: scenario.claims: expected a list")
    out = []
    for i, item in enumerate(declared):
        try:
            out.append(ClaimSpec.model_validate(item))
        except ValueError:
            raise ResultsError(f"{path}: scenario.claims.{i}: not a claim") from None
    return out


Intervals = dict[tuple[str, str, str], tuple[float, float, float]]


def compared_intervals(folder: Path) -> Intervals:
    """comparisons.parquet's paired intervals by (filter, vs, metric), read once per scenario:
    every row valid (`interval_problem`) and one row per (filter, vs, metric)."""
    path = Path(folder) / COMPARISONS_FILE
    if not path.exists():
        return {}
    table = read_parquet(path)
    if not {"filter", "vs", "metric", "estimate", "lo", "hi"} <= set(table.columns):
        raise ResultsError(f"{path}: missing the filter, vs, metric or interval columns")
    keys = zip(*(table[k].astype(str).tolist() for k in ("filter", "vs", "metric")), strict=True)
    try:
        values = table[["estimate", "lo", "hi"]].to_numpy(dtype=float).tolist()
    except (TypeError, ValueError):
        raise ResultsError(f"{path}: estimate, lo, hi: expected numbers") from None
    out: Intervals = {}
    for i, (key, found) in enumerate(zip(keys, values, strict=True)):
        where = f"{path}: row {i} ({key[0][:40]} vs {key[1][:40]}, {key[2][:20]})"
        if key in out:
            raise ResultsError(f"{where}: a second row for one comparison; expected one row each")
        problem = interval_problem(*found)
        if problem:
            raise ResultsError(f"{where}: {problem}")
        out[key] = tuple(found)
    return out


def read_claims(folder: Path, scenario: str) -> list[ClaimResult]:
    """Every claim the scenario declares (SPEC 8), its verdict decided here again on its paired
    interval (comparisons.parquet, else claims.json) and the declared threshold: a verdict
    stored in claims.json is never trusted, and a declared claim without an interval fails.
    Both files are read once and every stored interval is validated before any is decided on."""
    declared = _declared_claims(folder)
    if not declared:
        return []
    stored = _stored_claims(Path(folder) / CLAIMS_FILE)
    compared = compared_intervals(folder)
    out = []
    for claim in declared:
        text = claim_text(claim)
        record = stored.get(text)
        found = None if claim.vs is None else compared.get((claim.filter, claim.vs, claim.metric))
        if found is None and record is not None:
            found = (record["estimate"], record["lo"], record["hi"])
        if found is None:
            out.append(ClaimResult(scenario, text, None, None, None, "missing",
                                   "declared by the scenario, but no result for it"))  # fmt: skip
            continue
        estimate, lo, hi = (math.nan if v is None else v for v in found)
        if claim.metric in SHARE_METRICS:  # a share (or a difference of shares): no interval
            verdict = point_verdict(estimate, claim.at_most, claim.at_least)
        else:
            verdict = interval_verdict(lo, hi, at_most=claim.at_most, at_least=claim.at_least)
        note = record["warning"] if record is not None else ""
        if record is not None and record["verdict"] != verdict:
            note = (note + "; " if note else "") + f"claims.json said {record['verdict']!r:.20}"
        out.append(ClaimResult(scenario, text, *found, verdict, note))
    return out


def check_claims(results: dict[str, ScenarioSummary]) -> list[ClaimResult]:
    """Every declared claim of the results' scenarios."""
    return [c for name, s in results.items() for c in read_claims(s.folder, name)]


# ---------------------------------------------------------------------------------------------
# The command


def run_check(
    results_dir: Path, baseline_path: Path | None, *, update: bool = False, strict: bool = False,
    problems: dict[str, ScenarioSummary] | None = None,
) -> Report:  # fmt: skip
    """Compare (and with `update`, rewrite the baseline), then check the declared claims;
    `problems`: the problem results under `results_dir` (`problems.gate`)."""
    results_dir = Path(results_dir)
    if baseline_path is None:
        if update:
            raise BaselineError("--update needs --baseline FILE (the file to write)")
        results = read_results(results_dir, [], problems)
        return Report(results_dir, None, [], check_claims(results), strict=strict)
    baseline_path = Path(baseline_path)
    baseline = None
    if not update or baseline_path.exists():
        # On --update an existing baseline keeps its (possibly hand-tuned) tolerances.
        baseline = load_baseline(baseline_path)
    tolerances = (
        baseline.tolerances
        if baseline is not None
        else {m: Tolerance(*next(iter(s.items()))) for m, s in DEFAULT_TOLERANCES.items()}
    )
    results = read_results(results_dir, tolerances, problems)
    rows = compare(baseline, results) if baseline is not None else []
    expected = baseline.scenarios if baseline is not None else ()
    claims = check_claims(results)
    if not update:
        return Report(results_dir, baseline_path, rows, claims, strict=strict)
    try:
        write_json(baseline_path, baseline_document(results, tolerances))
    except OSError as exc:
        raise BaselineError(f"{baseline_path}: cannot write the baseline: {exc}") from None
    dropped = tuple(s for s in expected if s not in results)
    return Report(
        results_dir, baseline_path, rows, claims, updated=True, dropped=dropped, strict=strict
    )


# ---------------------------------------------------------------------------------------------
# Printing


def _row_style(passed: bool) -> str:
    return "" if passed else "bold red"


# Rows drawn as a table at most; beyond it (a baseline of thousands of scenarios) the table holds
# the failing rows only, up to this many: drawing 27,000 rows took rich minutes. Every failing row
# still gets its plain FAIL line.
TABLE_ROWS = 200


def comparison_table(rows: list[Row], title: str) -> Table:
    table = Table(title=Text(one_line(title)), title_justify="left")
    for col in ("scenario", "filter", "metric", "baseline", "now", "delta", "verdict"):
        right = col in ("baseline", "now", "delta")
        table.add_column(col, justify="right" if right else "left", overflow="fold")
    for r in rows:
        cells = (
            r.scenario,
            r.filter,
            r.shown or shown_metric(r.metric),
            fmt_value(in_shown_unit(r.metric, r.baseline)),
            fmt_value(in_shown_unit(r.metric, r.now)),
            r.delta,
            r.verdict,
        )
        # Names come from hand-editable files: escaped, never acted on by the terminal.
        table.add_row(*(Text(one_line(c)) for c in cells), style=_row_style(r.passed))
    return table


def claims_table(claims: list[ClaimResult], strict: bool) -> Table:
    title = "Claims declared by the scenarios (decided on the 95 % interval)"
    table = Table(title=title, title_justify="left")
    for col in ("scenario", "claim", "estimate", "interval", "verdict", "note"):
        table.add_column(col, justify="right" if col == "estimate" else "left")
    for c in claims:
        interval = "" if c.lo is None or c.hi is None else f"[{fmt_value(c.lo)}, {fmt_value(c.hi)}]"
        cells = (c.scenario, c.text, fmt_value(c.estimate), interval, c.verdict, c.note)
        table.add_row(*(Text(one_line(x)) for x in cells), style=_row_style(c.passed(strict)))
    return table


def _shown_rows(rows: list, passed) -> tuple[list, str]:
    """The rows a table draws (all, or the first TABLE_ROWS failing ones) and a title note."""
    if len(rows) <= TABLE_ROWS:
        return rows, ""
    failing = [r for r in rows if not passed(r)]
    shown = failing[:TABLE_ROWS]
    return shown, f" ({len(shown)} of {len(rows)} rows: failing rows only; each one below too)"


def print_report(report: Report, console: Console) -> None:
    """The tables, then one plain line per failure (readable in CI logs), then the verdict."""

    def say(*lines: str) -> None:
        if lines:  # one print of every line: thousands of prints took rich seconds each 1,000
            text = "\n".join(one_line(line) for line in lines)
            console.print(text, markup=False, highlight=False, soft_wrap=True)

    if report.rows:
        rows, note = _shown_rows(report.rows, lambda r: r.passed)
        title = f"{report.results_dir} against {report.baseline_path}{note}"
        if rows:
            console.print(comparison_table(rows, title))
    if report.claims:
        claims, note = _shown_rows(report.claims, lambda c: c.passed(report.strict))
        table = claims_table(claims, report.strict)
        table.title = (table.title or "") + note
        if claims:
            console.print(table)
    say(*(f"FAIL {row.detail}" for row in report.failed_rows))
    say(*(f"FAIL {claim.detail}" for claim in report.broken_claims))
    if report.updated:
        say(f"baseline written to {report.baseline_path} from {report.results_dir}")
        if report.dropped:
            say(f"dropped from the baseline (not in the results): {', '.join(report.dropped)}")
    checked = sum(1 for r in report.rows if r.metric not in ("-", "seed", "runs"))
    held = sum(1 for c in report.claims if c.verdict == "holds")
    open_ = sum(1 for c in report.claims if c.verdict == "inconclusive")
    if report.checked_nothing:
        say(
            "regression gate checked NOTHING: no baseline (--baseline FILE) and no claims in the"
            " scenarios (claims: in the scenario file)"
        )
        return
    if report.exit_code == 0:
        what = f"{checked} metrics within tolerance, " if report.rows and not report.updated else ""
        tail = f", {open_} inconclusive (--strict fails them)" if open_ else ""
        say(f"regression gate passed: {what}{held} claims hold{tail}")
        return
    parts = []
    if report.failed_rows:
        parts.append(f"{len(report.failed_rows)} of {len(report.rows)} rows failed")
    if report.broken_claims:
        parts.append(f"{len(report.broken_claims)} claims failed")
    say(f"regression gate FAILED: {', '.join(parts)}")
    apart = sorted({r.scenario for r in report.failed_rows if r.verdict == NOT_COMPARABLE})
    if apart:
        say(
            f"not comparable: {', '.join(apart)} (another seed or run count than the baseline's;"
            " their metrics were not compared). Run them with the baseline's seed and runs; only"
            " if these results are meant to become the baseline, replace it deliberately:"
            f" anfekf check {report.results_dir} --baseline {report.baseline_path} --update"
        )
    if any(r.verdict != NOT_COMPARABLE for r in report.failed_rows):
        say(
            "if the change is intended, refresh the baseline on purpose:"
            f" anfekf check {report.results_dir} --baseline {report.baseline_path} --update"
            " (docs/how-to/regression-gate.md)"
        )
