"""Result files: written atomically (temporary name, then rename), read with clear errors.

A scenario's folder holds steps.parquet, summary.parquet, summary.json and, written LAST,
manifest.json. A folder without manifest.json is not a complete result.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

STEPS_FILE = "steps.parquet"
SUMMARY_PARQUET = "summary.parquet"
SUMMARY_JSON = "summary.json"
MANIFEST_FILE = "manifest.json"
RUNS_DIR = ".runs"  # finished runs of an unfinished batch (experiment.py)


class ResultsError(Exception):
    """Saved results are missing or unreadable; `str()` is the one-line message for the user."""


def _file_mode() -> int:
    """The mode `open()` would give a new file: mkstemp's private 0600 is not wanted for results."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def write_atomic(path: Path, write: Callable[[Path], None]) -> None:
    """Call `write(tmp)` on a temporary file beside `path`, fsync it, then rename onto `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, _file_mode())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def output_path_problem(path: Path, *, folder: bool) -> str | None:
    """Why `path` cannot be written as an output folder (or file), checked before long work;
    None when it can. The sentence names the --out option it came from."""
    path = Path(path)
    if path.exists() and path.is_dir() != folder:
        return (
            "--out must be a folder, but a file of that name exists"
            if folder
            else "--out must be a file path, but it is a folder"
        )
    probe = path if folder else path.parent
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        return f"--out cannot be created: {probe} is a file, not a folder"
    if not os.access(probe, os.W_OK):
        return "--out is not writable"
    return None


def _json_safe(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def write_json(path: Path, obj) -> None:
    text = json.dumps(_json_safe(obj), indent=2, sort_keys=False) + "\n"
    write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_parquet(path: Path, df: pd.DataFrame) -> None:
    table = pa.Table.from_pandas(df, preserve_index=False)
    write_atomic(path, lambda tmp: pq.write_table(table, tmp, compression="zstd"))


def read_parquet(path: Path) -> pd.DataFrame:
    path = Path(path)
    if not path.is_file():
        raise ResultsError(f"{path}: file not found")
    try:
        return pq.read_table(path).to_pandas()
    except (pa.ArrowException, OSError, ValueError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ResultsError(f"{path}: not a readable Parquet file ({first})") from None


def read_json(path: Path) -> dict | list:
    path = Path(path)
    if not path.is_file():
        raise ResultsError(f"{path}: file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultsError(f"{path}: not readable JSON ({exc})") from None


def scenario_dirs(results_dir: Path) -> list[Path]:
    """The complete scenario folders under `results_dir` (itself one, or its children)."""
    results_dir = Path(results_dir)
    if not results_dir.exists():
        raise ResultsError(f"{results_dir}: results folder does not exist")
    if not results_dir.is_dir():
        raise ResultsError(f"{results_dir}: not a folder")
    if _is_result_dir(results_dir):
        candidates = [results_dir]
    else:
        candidates = sorted(p for p in results_dir.iterdir() if _is_result_dir(p))
    if not candidates:
        raise ResultsError(
            f"{results_dir}: no results found (expected {STEPS_FILE} in it or in its sub-folders;"
            " run `anfekf run` first)"
        )
    for folder in candidates:
        _require_manifest(folder)
        for name in (STEPS_FILE, SUMMARY_PARQUET):
            _check_parquet_footer(folder / name)
    return candidates


def _require_manifest(folder: Path) -> Path:
    """manifest.json is written last: without it the other files may be partial or stale."""
    path = Path(folder) / MANIFEST_FILE
    if not path.is_file():
        raise ResultsError(
            f"{folder}: incomplete result (no {MANIFEST_FILE}; the run was interrupted or is"
            " still going); rerun the same `anfekf run` command to resume it"
        )
    return path


def read_manifest(folder: Path) -> dict:
    """A complete scenario folder's manifest (a JSON object), or ResultsError."""
    path = _require_manifest(folder)
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise ResultsError(f"{path}: expected a JSON object")
    return doc


def _check_parquet_footer(path: Path) -> None:
    """A cheap look at a Parquet file's footer (which a truncated file lacks), if it exists.

    report reads steps.parquet and check reads summary.parquet; this makes both refuse a folder
    whose other file is damaged, instead of passing on half a result.
    """
    if not path.exists():
        return
    try:
        pq.read_metadata(path)
    except (pa.ArrowException, OSError, ValueError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ResultsError(f"{path}: not a readable Parquet file ({first})") from None


def _is_result_dir(path: Path) -> bool:
    """A scenario folder, complete or not: it has a results file or saved runs."""
    return (path / STEPS_FILE).exists() or (path / RUNS_DIR).is_dir()


def read_steps(scenario_dir: Path) -> pd.DataFrame:
    df = read_parquet(Path(scenario_dir) / STEPS_FILE)
    missing = {"scenario", "filter", "run", "step", "pos_err", "nees"} - set(df.columns)
    if missing:
        raise ResultsError(
            f"{Path(scenario_dir) / STEPS_FILE}: missing columns {', '.join(sorted(missing))}"
        )
    if len(df) == 0:
        raise ResultsError(f"{Path(scenario_dir) / STEPS_FILE}: holds no rows")
    if not isinstance(df["filter"].dtype, pd.CategoricalDtype):
        df["filter"] = pd.Categorical(df["filter"], categories=list(dict.fromkeys(df["filter"])))
    return df


def read_summary(scenario_dir: Path) -> pd.DataFrame:
    return read_parquet(Path(scenario_dir) / SUMMARY_PARQUET)
