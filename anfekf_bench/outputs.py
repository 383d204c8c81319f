"""A batch's output folder, the same for every source (simulated or recorded): where it goes,
what may already be there and whose it is, the run store, the staged result and its swap into
place, and the tables and provenance every result writes (docs/HARDENING.md).
`experiment`'s one pipeline builds on it for every source (simulated or recorded).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import re
import shutil
import time
import warnings
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Protocol

import pandas as pd

from .analysis.tables import (
    column_units,
    parquet_frame,
)
from .config import one_line
from .provenance import source_files
from .storage import (
    CLAIMS_FILE,
    COMPARISONS_FILE,
    LOCK_FILE,
    MANIFEST_FILE,
    PHASES_FILE,
    RUN_FILE_PATTERN,
    RUNS_DIR,
    RUNS_FILE,
    STAGING_DIR,
    STEPS_FILE,
    SUMMARY_JSON,
    SUMMARY_PARQUET,
    SWEEP_CELLS_DIR,
    SWEEP_KIND,
    FileProblem,
    ResultsError,
    RunFileRefused,
    foreign_entries,
    install_result,
    is_result_manifest,
    read_json,
    read_regular_bytes,
    read_run_file,
    scenario_name_problem,
    write_atomic,
    write_json,
    write_parquet,
    write_run_file,
)


class BatchPlan(Protocol):
    """What the output folder needs of a plan (`experiment.Plan`, whatever its source)."""

    name: str
    runs: int
    seed: int

    def filter_names(self) -> list[str]: ...

    def fingerprint(self) -> str: ...


_PACKAGES = (
    "anfekf-bench",
    "numpy",
    "scipy",
    "filterpy",
    "pandas",
    "pyarrow",
    "joblib",
    "pydantic",
)


class OutputExists(Exception):
    """The output folder holds results we must not overwrite silently."""


class PlanError(ValueError):
    """Command-line overrides that do not fit together; `str()` is the one-line message."""


@functools.cache  # the imported code cannot change under a running process; hashing it is ~50 ms
def code_version(package: Path | None = None) -> str:
    """Hash of this package's source: runs saved by other code must not be resumed into a batch.
    Files under __pycache__ are not source (the fast engine writes its generated loops there:
    engines/loop.py), so a first fast run does not change the version mid-batch."""
    digest = hashlib.sha256()
    package = Path(__file__).parent if package is None else package
    for path in source_files(package):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def machine_info() -> dict:
    """Cores this process may use, the CPU model (from /proc/cpuinfo) and the platform."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        model = platform.processor() or "unknown"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cores": cores, "cpu_model": model, "platform": platform.platform()}


def package_versions() -> dict[str, str]:
    return dict(_package_versions())


@functools.cache  # installed versions are fixed for a running process; reading metadata is ~100 ms
def _package_versions() -> tuple[tuple[str, str], ...]:
    out = {"python": platform.python_version()}
    for pkg in _PACKAGES:
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return tuple(out.items())


# --------------------------------------------------------------------------------------------
# Validate first: values, route and memory (nothing on disk is touched)

# Memory model of a batch (see check_plan): what one filter records per step (x 3, P 9, R and Q
# diagonals 4, errors and NEES 3, with room for more), what the steps table costs per row (its
# columns, twice while pandas assembles it), one worker process with its libraries loaded.
FINGERPRINT_FILE = "fingerprint"  # in RUNS_DIR: the batch its saved runs belong to
_RUN_FILE = re.compile(r"run-([0-9]{6,9})\.npz")


def scenario_folder(out_dir: Path, name: str) -> Path:
    """<out>/<name>, a direct child of --out with a safe name, not a symlink, not a file."""
    problem = scenario_name_problem(name)
    if problem:
        raise OutputExists(f"name {name!r}: {problem}")
    target = Path(out_dir) / name
    if target.is_symlink():
        raise OutputExists(
            f"{target}: is a symbolic link; results are never written (or removed) through one"
        )
    if os.path.lexists(target) and not target.is_dir():
        raise OutputExists(f"{target}: exists and is not a folder")
    return target


def _stamp(runs_dir: Path) -> str | None:
    """The fingerprint of the saved runs, None without one (OutputExists if unreadable)."""
    path = runs_dir / FINGERPRINT_FILE
    if not os.path.lexists(path):
        return None
    try:
        return read_regular_bytes(path, 1024).decode("ascii", "replace").strip()
    except FileProblem as exc:
        raise OutputExists(f"{path}: {exc}") from None


def _is_temporary(name: str) -> bool:
    return name.startswith(".") and name.endswith(".tmp")  # storage.write_atomic's names


def _is_our_manifest(target: Path) -> bool:
    try:
        doc = read_json(target / MANIFEST_FILE)
    except ResultsError:
        return False
    return is_result_manifest(doc)


def _is_our_store(runs_dir: Path) -> bool:
    """A run store of this tool: stamped with a batch's fingerprint, or what a kill before the
    stamp leaves (an empty store, or one holding only temporaries)."""
    if runs_dir.is_symlink() or not runs_dir.is_dir():
        return False
    if os.path.lexists(runs_dir / FINGERPRINT_FILE):
        return True
    return all(_is_temporary(e.name) for e in os.scandir(runs_dir))


def _what_folder_holds(folder: Path) -> str | None:
    """'result' or 'sweep' when `folder` is one of this tool's (its manifest says so, or it holds
    a stamped run store: a batch in progress), else None. Reads only; unreadable: None."""
    try:
        if os.path.lexists(folder / RUNS_DIR / FINGERPRINT_FILE):
            return "result"
        if not os.path.lexists(folder / MANIFEST_FILE):
            return None
        doc = read_json(folder / MANIFEST_FILE)
    except (ResultsError, OSError, ValueError):
        return None
    if is_result_manifest(doc):
        return "result"
    return "sweep" if isinstance(doc, dict) and doc.get("kind") == SWEEP_KIND else None


def check_not_nested(target: Path) -> None:
    """OutputExists when <out>/<name> would sit inside another result: in its folder or its run
    store (which --force and a finished batch remove), or in a sweep's folder other than as
    one of its cells (<sweep>/cells/<cell>). Every ancestor is looked at, symbolic links
    resolved. Reads only."""
    real = Path(os.path.realpath(target))
    for folder in real.parents:
        kind = _what_folder_holds(folder)
        if kind is None or (kind == "sweep" and real.parent == folder / SWEEP_CELLS_DIR):
            continue
        inner = real.relative_to(folder).parts[0]
        where = f"the run store of the {kind} in {folder}" if inner == RUNS_DIR else (
            f"the {kind} folder {folder}")  # fmt: skip
        raise OutputExists(
            f"{target}: would be inside {where}; results are never written inside another"
            " result (its --force or its next batch would remove them): use another --out"
        )


def _is_staging(folder: str | os.PathLike) -> bool:
    """The run store's staged result (STAGING_DIR): regular files of ours only, no lock (a
    result folder has one), no sub-folder."""
    with os.scandir(folder) as entries:
        return all(e.is_file(follow_symlinks=False) and e.name != LOCK_FILE for e in entries)


def nested_in_store(runs_dir: Path) -> list[str]:
    """Folders in a run store that this tool did not put there (a result nested in it by an
    older version: `--out <result>/.runs`). Neither --force nor a finished batch removes them.
    A folder under a run file's name is a run file planted wrong (no scenario name ends in
    .npz): the resume refuses it and redoes the run (_load_saved_runs)."""
    if runs_dir.is_symlink() or not runs_dir.is_dir():
        return []
    with os.scandir(runs_dir) as entries:
        return sorted(
            f"{RUNS_DIR}/{e.name}"
            for e in entries
            if e.is_dir(follow_symlinks=False)
            and not (e.name == STAGING_DIR and _is_staging(e))
            and not _RUN_FILE.fullmatch(e.name)
        )


def remove_run_store(runs_dir: Path) -> None:
    """Remove a run store entry by entry, never wholesale: its files and its staged result; a
    folder of anything else stays, and with it the store."""
    if runs_dir.is_symlink() or not runs_dir.is_dir():
        return
    with os.scandir(runs_dir) as entries:
        for entry in entries:
            if not entry.is_dir(follow_symlinks=False):
                os.unlink(entry.path)
            elif entry.name == STAGING_DIR and _is_staging(entry):
                for staged in os.scandir(entry.path):
                    os.unlink(staged.path)
                os.rmdir(entry.path)
    with suppress(OSError):  # not empty: something nested stays
        os.rmdir(runs_dir)


def survey_output(plan: BatchPlan, target: Path, force: bool) -> list[str]:
    """What preparing `target` may replace (--force), or OutputExists when it must not be
    touched. Reads only; run before anything is written and again under the folder's lock.

    A folder is this tool's only when its manifest.json says so (`is_result_manifest`) or it
    holds a run store of ours; a folder holding anything else is refused, with or without
    --force, and nothing in it is removed. Nor is a folder inside another result's, nor one
    holding another result in its run store."""
    check_not_nested(target)
    if not os.path.lexists(target):
        return []
    target = scenario_folder(target.parent, target.name)
    foreign = foreign_entries(target)
    nested = nested_in_store(target / RUNS_DIR)
    if nested:
        raise OutputExists(
            f"{target}: its run store holds folders this tool did not write there"
            f" ({', '.join(nested[:3])}{' and more' if len(nested) > 3 else ''}: a result nested"
            " in it?); nothing is removed, --force or not: move them away"
        )
    runs_dir = target / RUNS_DIR
    if foreign:
        shown = ", ".join(foreign[:3]) + (
            f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        )
        raise OutputExists(
            f"{target}: holds entries this tool did not write ({shown}); "
            + ("--force removes only anfekf results: " if force else "")
            + "move them away or use another --out"
        )
    ours = sorted(e.name for e in os.scandir(target) if e.name != LOCK_FILE)
    has_manifest = os.path.lexists(target / MANIFEST_FILE)
    if has_manifest and not _is_our_manifest(target):
        raise OutputExists(
            f"{target}: holds no anfekf result (its {MANIFEST_FILE} was not written by this"
            " tool); nothing is removed or overwritten: move it away or use another --out"
        )
    marked = has_manifest or _is_our_store(runs_dir)
    if not marked and any(not _is_temporary(name) for name in ours):
        raise OutputExists(
            f"{target}: holds no anfekf result (no {MANIFEST_FILE} of this tool, no saved runs)"
            " but other files; nothing is removed: move them away or use another --out"
            + (" (--force replaces only anfekf results)" if force else "")
        )
    if force:
        return ours
    if has_manifest:
        raise OutputExists(
            f"{target}: holds a complete result already; use --force to overwrite it"
            " or --out to write elsewhere"
        )
    stamp = _stamp(runs_dir)
    if stamp is not None and stamp != plan.fingerprint():
        raise OutputExists(
            f"{target}: holds runs of a different scenario or seed; use --force to discard them"
        )
    return []


def _load_saved_runs(plan: BatchPlan, runs_dir: Path) -> tuple[dict[int, dict], int]:
    """The saved runs of this batch, and how many files were refused (and removed: redone)."""
    done: dict[int, dict] = {}
    refused = 0
    names = plan.filter_names()
    fingerprint = plan.fingerprint()
    for path in sorted(runs_dir.glob(RUN_FILE_PATTERN)):
        match = _RUN_FILE.fullmatch(path.name)
        if match is None or int(match.group(1)) >= plan.runs:
            continue  # not a name we write, or a run this batch does not ask for
        run = int(match.group(1))
        try:
            result = read_run_file(path, fingerprint)
            if result.get("run") != run or not isinstance(result.get("filters"), dict):
                raise RunFileRefused("not the run its name says")
            if list(result["filters"]) != names:
                raise RunFileRefused("other filters")
        except RunFileRefused:
            refused += 1
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
            continue
        done[run] = result
    return done, refused


def prepare_output(
    plan: BatchPlan, out_dir: Path, force: bool
) -> tuple[Path, dict[int, dict], str]:
    """Prepare <out>/<name> for the batch (call with its lock held: see execute): find the saved
    runs to resume. A previous complete result (--force) is left whole: the new batch's files
    are staged in the run store and replace it only once complete (`finish_result`). Returns
    the folder, the runs to resume and a sentence saying what we do."""
    target = scenario_folder(out_dir, plan.name)
    target.mkdir(parents=True, exist_ok=True)
    survey_output(plan, target, force)
    runs_dir = target / RUNS_DIR
    complete = os.path.lexists(target / MANIFEST_FILE)  # ours: survey_output checked it
    stamp = _stamp(runs_dir)
    if stamp is not None and stamp != plan.fingerprint():  # --force: another batch's runs
        remove_run_store(runs_dir)
        stamp = None
    action = "new results"
    if complete:
        action = (
            f"replacing the previous result in {target} (--force); it stays whole until the"
            " new batch is complete"
        )
    done: dict[int, dict] = {}
    if stamp is not None:
        done, refused = _load_saved_runs(plan, runs_dir)
        action = f"resuming: {len(done)} of {plan.runs} runs already done in {runs_dir}"
        if refused:
            action += f" ({refused} saved run files refused and redone)"
        if complete:
            action += "; the previous result is replaced once the batch is complete"
    runs_dir.mkdir(parents=True, exist_ok=True)
    staging = runs_dir / STAGING_DIR
    if staging.is_symlink() or staging.is_file():
        staging.unlink()
    elif staging.is_dir():  # files of a batch killed before it replaced the result
        for staged in os.scandir(staging):
            os.unlink(staged.path)  # files only (survey_output refused anything else)
        staging.rmdir()
    stamp_path = runs_dir / FINGERPRINT_FILE
    write_atomic(stamp_path, lambda tmp: tmp.write_text(plan.fingerprint() + "\n"))
    # Without a manifest the folder is ours by its run store: results of an earlier, unfinished
    # attempt (not complete) go, and temporary files of writes a kill cut short
    # (storage.write_atomic names them .<name>.*.tmp) go always.
    for entry in os.scandir(target):
        stale = _is_temporary(entry.name) or (
            not complete and entry.name.endswith((".parquet", ".json"))
        )
        if stale and entry.is_file(follow_symlinks=False):
            os.unlink(entry.path)
    for torn in runs_dir.glob(".*.tmp"):
        torn.unlink(missing_ok=True)
    return target, done, action


def result_staging(target: Path) -> Path:
    """The folder a finished batch writes its files to before they replace the result."""
    staging = Path(target) / RUNS_DIR / STAGING_DIR
    staging.mkdir(parents=True, exist_ok=True)
    return staging


def finish_result(target: Path, staging: Path, store: RunStore | None = None) -> None:
    """Swap the staged complete result in, then drop the run store (and the runs `store` still
    holds: with the result in place there is nothing to resume)."""
    install_result(target, staging)
    if store is not None:
        store.held.clear()
    with suppress(OSError):  # the result is in place; a store left behind is redone or removed
        remove_run_store(Path(target) / RUNS_DIR)


def save_run(target: Path, result: dict, fingerprint: str) -> None:
    """Save a finished run in the run store (a data file keyed to the batch's fingerprint)."""
    write_run_file(target / RUNS_DIR / f"run-{result['run']:06d}.npz", result, fingerprint)


# A fast-engine batch's first ten seconds of runs are held in memory, not saved (RunStore). A run
# file costs a few milliseconds (its checksum, the archive, the rename): as much as a fast-engine
# run, a fifth of a 50-run paper scenario's end-to-end time and a tenth of a zoo scenario's CPU
# (29 filters, 5 MB a run), spent on files that the finished batch removes unread (a
# filterpy-engine run takes a tenth of a second or more: its runs are saved at once). What a
# kill -9 in those seconds loses is at most those seconds of runs (a resume redoes them, with the
# same bytes); an interruption or an error saves them first.
STORE_AFTER_S = 10.0


class RunStore:
    """Where `execute` keeps each finished run for a resume: `keep(result)` saves it in the run
    store (`save_run`) once the batch has run `hold_s` (STORE_AFTER_S on the fast engine, else
    0), with every run held before then; `flush()` saves the held runs now (the batch was
    interrupted or failed)."""

    def __init__(
        self, target: Path, fingerprint: str, hold_s: float = 0.0, clock=time.perf_counter
    ) -> None:
        self.target, self.fingerprint, self.clock = Path(target), fingerprint, clock
        self.until = clock() + hold_s
        self.held: list[dict] = []

    def keep(self, result: dict) -> None:
        self.held.append(result)
        if self.clock() >= self.until:
            self.flush()

    def flush(self) -> None:
        while self.held:
            save_run(self.target, self.held[0], self.fingerprint)
            self.held.pop(0)


@dataclass(frozen=True)
class ResultTables:
    """What a finished batch writes (besides the manifest), all computed from its runs."""

    steps: pd.DataFrame
    runs: pd.DataFrame
    summary: list[dict]
    comparisons: pd.DataFrame
    claims: list[dict]
    phases: pd.DataFrame | None = None  # a scenario with a noise schedule (SPEC 14)


def write_result_table(
    path: Path, df: pd.DataFrame, metadata: dict | None = None, *, durable: bool = True
) -> None:
    """One result table as `write_result_tables` writes it: the key columns as plain strings,
    `metadata` and the columns' units in the file's key-value metadata, written atomically."""
    df = parquet_frame(df)
    write_parquet(path, df, {**(metadata or {}), "units": column_units(df)}, durable=durable)


def write_result_tables(
    target: Path,
    tables: ResultTables,
    *,
    steps_table: bool,
    metadata: dict | None = None,
    extra: dict[str, pd.DataFrame] | None = None,
    durable: bool = True,
    steps_written: bool = False,
) -> None:
    """Write every table atomically; steps.parquet only when the scenario asks for it and
    `steps_written` does not say it is there already (`write_result_table`, while the other
    tables were computed). `durable=False`: without a flush per file, for a staged result
    (`storage.install_result` flushes them all together before they replace the old result).

    Every Parquet file has scenario and filter as plain strings (they join across files) and
    says in its key-value metadata where it came from: `metadata` (scenario, seed,
    fingerprint), the units of its columns, the package version and git commit.
    """

    def parquet(name: str, df: pd.DataFrame) -> None:
        write_result_table(target / name, df, metadata, durable=durable)

    if steps_table and not steps_written:
        parquet(STEPS_FILE, tables.steps)
    parquet(RUNS_FILE, tables.runs)
    parquet(SUMMARY_PARQUET, pd.DataFrame(tables.summary))
    write_json(target / SUMMARY_JSON, tables.summary, durable=durable)
    parquet(COMPARISONS_FILE, tables.comparisons)
    write_json(target / CLAIMS_FILE, tables.claims, durable=durable)
    if tables.phases is not None:
        parquet(PHASES_FILE, tables.phases)
    for name, df in (extra or {}).items():  # the source's own tables (the drive audit)
        parquet(name, df)


# --------------------------------------------------------------------------------------------
# Fitted filters' values in the run store (the fits of anfekf_bench.fitting)

FIT_FILE = "fit-{fingerprint}.json"
FIT_FORMAT = "anfekf-bench fit v2"  # v2: with the SHA-256 of the fingerprint and the fit


class CachedFitRefused(UserWarning):
    """A fit cache file that is there but cannot be used: the fit is computed again (the CLI
    shows the warning as one line; the file is replaced by the new fit)."""


def _plain(fitted: dict):
    """`fitted` as write_json writes it and read_json gives it back (non-finite numbers: null)."""
    return json.loads(json.dumps(fitted), parse_constant=lambda _: None)


def fit_digest(fingerprint: str, fitted) -> str:
    """The SHA-256 a fit cache file carries: over its fingerprint and its fit, canonical JSON."""
    text = json.dumps({"fingerprint": fingerprint, "fitted": fitted}, sort_keys=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def read_cached_fit(
    path: Path, fingerprint: str, problem: Callable[[dict], str | None] | None = None
) -> dict | None:
    """The fit `write_fit` saved at `path` for `fingerprint`, checked like a run file: its
    format, fingerprint and SHA-256, then `problem(fitted)` (the kind's own check: sigmas
    finite and positive, a network's shapes and hash; `FittedSpec.fit_problem`). None when
    there is no file, and when there is one that fails any check: then a `CachedFitRefused`
    warning says why, and the caller fits again. A refused file is never used."""
    if not os.path.lexists(path):
        return None
    why = _cached_fit_problem(path, fingerprint, problem)
    if why is None:
        return read_json(path)["fitted"]
    warnings.warn(
        CachedFitRefused(one_line(f"{path}: {why}; fitted again (the cached fit is not used)")),
        stacklevel=2,
    )
    return None


def _cached_fit_problem(path: Path, fingerprint: str, problem) -> str | None:
    try:
        doc = read_json(path)
    except ResultsError as exc:
        return str(exc).removeprefix(f"{path}: ")
    if not isinstance(doc, dict) or doc.get("format") != FIT_FORMAT:
        return f"not a fit cache file (format {FIT_FORMAT!r})"
    if doc.get("fingerprint") != fingerprint:
        return "the fit of another fingerprint"
    fitted = doc.get("fitted")
    if not isinstance(fitted, dict):
        return "fitted: must be a mapping"
    if doc.get("sha256") != fit_digest(fingerprint, fitted):
        return "its checksum does not match its content (damaged or edited)"
    return None if problem is None else problem(fitted)


def write_fit(path: Path, fingerprint: str, fitted: dict) -> None:
    plain = _plain(fitted)
    write_json(
        path,
        {"format": FIT_FORMAT, "fingerprint": fingerprint, "fitted": plain,
         "sha256": fit_digest(fingerprint, plain)},
    )  # fmt: skip
