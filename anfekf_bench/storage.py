"""Result files: written atomically (temporary name, then rename), read with clear errors.

A scenario's folder holds steps.parquet, summary.parquet, summary.json and, written LAST,
manifest.json. A folder without manifest.json is not a complete result.

Also here: the layout's own names (`RESERVED_NAMES`: a scenario may not be called like them), the
lock a batch holds on its folder (`folder_lock`), what a folder of ours may hold (`foreign_entries`,
`is_result_manifest`), how a finished batch replaces the previous result (`install_result`),
the run store's file format (`write_run_file` / `read_run_file`: npz without pickle, keyed to the
fingerprint), and `open_regular`, through which every file a user names is read (a FIFO, device or
folder is refused instead of hanging the command).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import io
import json
import math
import os
import re
import stat
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

from .provenance import git_commit, package_version

STEPS_FILE = "steps.parquet"
SUMMARY_PARQUET = "summary.parquet"
SUMMARY_JSON = "summary.json"
MANIFEST_FILE = "manifest.json"
RUNS_FILE = "runs.parquet"  # one row per (filter, run): SPEC 8's per-run metrics
COMPARISONS_FILE = "comparisons.parquet"  # paired ratios with intervals (analysis/comparisons)
CLAIMS_FILE = "claims.json"  # the scenario's claims and their verdicts
PHASES_FILE = "phases.parquet"  # per-phase metrics of a noise schedule (analysis/phases)
RUNS_DIR = ".runs"  # finished runs of an unfinished batch (experiment.py)
RUN_FILE_PATTERN = "run-*.npz"  # a finished run in RUNS_DIR (write_run_file)
LOCK_FILE = ".lock"  # held (flock) by the batch writing a scenario folder
_NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC  # where none is
SWEEP_KIND = "anfekf-bench sweep"  # a sweep folder's manifest.json says `kind: SWEEP_KIND`
SWEEP_CELLS_DIR = "cells"  # a sweep's cells: <sweep>/cells/<cell>/, each a scenario result
SWEEP_FILE = "sweep.parquet"  # a sweep's table: one row per cell and filter
STAGING_DIR = "result"  # in RUNS_DIR: a finished batch's files before they replace the old ones
RESULT_FORMAT = "anfekf-bench result v1"  # manifest.json's "format": what marks a folder as ours
# A problem beyond the robot's result (SPEC 17, problems.experiment): its manifest's format, tables
PROBLEM_FORMAT = "anfekf-bench problem result v1"
PROBLEM_TABLES = {t: f"problem_{t}.parquet" for t in ("summary", "runs", "noise", "timing")}
# The drive audit's tables (drive_audit, SPEC 18): a `protocol: drives` result only
AUDIT_FILES = {
    "drives": "audit_drives.parquet",
    "odometry": "audit_odometry.parquet",
    "measurements": "audit_measurements.parquet",
    "whiteness": "audit_whiteness.parquet",
    "episodes": "audit_episodes.parquet",
}
RESULT_FILES = (STEPS_FILE, RUNS_FILE, SUMMARY_PARQUET, SUMMARY_JSON, COMPARISONS_FILE, CLAIMS_FILE,
                PHASES_FILE, *AUDIT_FILES.values())  # fmt: skip

# Names a scenario may not take: its folder is a direct child of --out, beside these.
RESERVED_NAMES = frozenset(
    {"report", "baselines", "bench.json", "readme.md", "ci-gate", RUNS_DIR, LOCK_FILE}
    | {STEPS_FILE, SUMMARY_PARQUET, SUMMARY_JSON, MANIFEST_FILE, RUNS_FILE, COMPARISONS_FILE}
    | {CLAIMS_FILE}
)
RESERVED_SUFFIXES = (".parquet", ".json", ".md", ".tmp", ".lock", ".npz", ".yaml", ".yml")
NAME_MAX = 64  # characters of a scenario name (one path component: far below NAME_MAX 255)
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")

# Upper bounds of files we read whole (a result file is read whole anyway; these stop a file
# named by mistake, e.g. a disk image, from exhausting memory).
JSON_LIMIT = 256 * 2**20
PARQUET_LIMIT = 16 * 2**30


class ResultsError(Exception):
    """Saved results are missing or unreadable; `str()` is the one-line message for the user."""


class FileProblem(Exception):
    """Why a file cannot be read; `str()` is a short phrase without the path (callers add it)."""


def scenario_name_problem(name: str) -> str | None:
    """Why `name` cannot name a scenario folder (a direct child of --out), or None."""
    if not NAME_PATTERN.fullmatch(name):
        return "must start with a letter or digit and hold only letters, digits, '_', '.' and '-'"
    if len(name) > NAME_MAX:
        return f"at most {NAME_MAX} characters (got {len(name)})"
    folded = name.casefold()
    if folded in RESERVED_NAMES or folded.endswith(RESERVED_SUFFIXES):
        return (
            f"{name!r} is reserved by the results layout (not allowed: "
            f"{', '.join(sorted(RESERVED_NAMES - {RUNS_DIR, LOCK_FILE}))}, or a name ending in"
            f" {', '.join(RESERVED_SUFFIXES)})"
        )
    return None


def _file_kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "folder"
    if stat.S_ISFIFO(mode):
        return "FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "device"
    if stat.S_ISSOCK(mode):
        return "socket"
    return "special file"


def _size(n: float) -> str:
    for unit in ("bytes", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.1f}".rstrip("0").rstrip(".") + f" {unit}"
        n /= 1024
    return f"{n} bytes"  # pragma: no cover


def open_regular(path: Path, *, limit: int | None = None) -> BinaryIO:
    """Open `path` for reading if it is a regular file (following symlinks) of at most `limit`
    bytes; FileProblem otherwise. Opened non-blocking, so a FIFO is refused, never waited on."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise FileProblem("file not found") from None
    except PermissionError:
        raise FileProblem("permission denied") from None
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            raise FileProblem("path too long") from None
        if exc.errno == errno.ENXIO:
            raise FileProblem("is a socket or device, not a regular file") from None
        raise FileProblem(f"cannot open ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileProblem(f"is a {_file_kind(st.st_mode)}, not a regular file")
        if limit is not None and st.st_size > limit:
            raise FileProblem(f"is {_size(st.st_size)}; at most {_size(limit)} allowed")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular_bytes(path: Path, limit: int) -> bytes:
    """The bytes of a regular file of at most `limit` bytes (FileProblem otherwise)."""
    with open_regular(path, limit=limit) as fh:
        try:
            data = fh.read(limit + 1)
        except OSError as exc:
            raise FileProblem(f"cannot read ({exc.strerror})") from None
    if len(data) > limit:
        raise FileProblem(f"is larger than {_size(limit)}")
    return data


def _new_temp(folder: Path, prefix: str) -> tuple[int, str]:
    """A new empty file of a random name in `folder`: (a descriptor open for writing, its path),
    mode 0666 less the umask of the moment as `open()` gives (never mkstemp's 0600)."""
    for _ in range(100):
        name = os.path.join(folder, f"{prefix}{os.urandom(4).hex()}.tmp")  # mkstemp's length
        try:
            return os.open(name, _NEW_FILE, 0o666), name
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary file name", str(folder))


def write_atomic(path: Path, write: Callable[[Path], None], *, durable: bool = True) -> None:
    """Call `write(tmp)` on a temporary file beside `path`, fsync it (when `durable`), then
    rename onto `path`. The rename alone makes the file appear whole or not at all to any
    process, a killed one included; the fsync puts its bytes on disk before the rename, so a
    power cut leaves the old file or the new one, not a renamed file with missing data."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = _new_temp(path.parent, f".{path.name}.")
    os.close(fd)  # `write` opens it by name
    tmp = Path(tmp_name)
    try:
        write(tmp)
        if durable:
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_new(path: Path, data: bytes) -> None:
    """Create `path` holding `data`, whole, only where nothing is: FileExistsError when anything
    is there (a file, a folder, a symlink, a dangling one included). The bytes go to a
    temporary file beside it first, which is then hard-linked to `path`: the link is created, or
    fails because `path` exists, in one step, so of two writers racing for one path exactly one
    succeeds and no reader sees a partial file (no check-then-rename race). On a file system
    without hard links, `O_CREAT | O_EXCL` (exclusive as well; the bytes follow the creation)."""
    path = Path(path)
    fd, tmp_name = _new_temp(path.parent, ".anfekf-new-")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        try:
            os.link(tmp_name, path)
        except OSError as exc:
            if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
                raise
            with os.fdopen(os.open(path, _NEW_FILE, 0o666), "wb") as fh:
                fh.write(data)
    finally:
        os.unlink(tmp_name)


def output_path_problem(path: Path, *, folder: bool, option: str = "--out") -> str | None:
    """Why `path` cannot be written as an output folder (or file), checked before long work;
    None when it can. The sentence names the option it came from (`out` in the Python API)."""
    path = Path(path)
    try:
        name_max = os.pathconf(path.anchor or ".", "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    for part in path.parts:
        if len(os.fsencode(part)) > name_max:
            return f"{option} has a component longer than {name_max} bytes"
    if len(os.fsencode(str(path))) > 3000:
        return f"{option} is too long a path"
    try:
        return _output_path_problem(path, folder, option)
    except OSError as exc:
        return f"{option} cannot be used ({exc.strerror or exc})"


def _output_path_problem(path: Path, folder: bool, option: str) -> str | None:
    if path.exists() and path.is_dir() != folder:
        return (
            f"{option} must be a folder, but a file of that name exists"
            if folder
            else f"{option} must be a file path, but it is a folder"
        )
    probe = path if folder else path.parent
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        return f"{option} cannot be created: {probe} is a file, not a folder"
    if not os.access(probe, os.W_OK):
        return f"{option} is not writable"
    return None


def _json_safe(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def write_json(path: Path, obj, *, durable: bool = True) -> None:
    """`obj` as JSON, atomically; `durable=False`: no fsync (the caller flushes the file later,
    as `install_result` does for a staged result)."""
    text = json.dumps(_json_safe(obj), indent=2, sort_keys=False) + "\n"
    write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), durable=durable)


PARQUET_KEY_PREFIX = "anfekf."  # our keys in a Parquet file's key-value metadata


def _arrow():
    """pyarrow and its Parquet module, imported on first use: a worker process imports this
    module (through config) but writes no table, and these cost a quarter of its start."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    return pa, pq


@contextmanager
def _arrow_file(fh: BinaryIO) -> Iterator[object]:
    """A native Arrow file over an opened regular file, for pyarrow to read.

    Never the Python file object itself: pyarrow finishes with one (closing it needs the GIL) on
    its own threads after a read returns, and a process that exits meanwhile aborts with
    "terminate called without an active exception" (exit 134; apache/arrow#33975, #34314). The
    file is reopened through /proc/self/fd (the same inode open_regular checked), mapped, not
    copied; where there is no /proc its bytes are read into memory."""
    pa, _ = _arrow()
    proc = f"/proc/self/fd/{fh.fileno()}"
    source = pa.memory_map(proc) if os.path.exists(proc) else pa.BufferReader(fh.read())
    try:
        yield source
    finally:
        source.close()


def parquet_provenance(path: Path) -> dict[str, str]:
    """A Parquet file's `anfekf.*` key-value metadata (version, git_commit, seed, fingerprint,
    units as JSON, ...), read from its footer: what a copied file says about its origin."""
    pa, pq = _arrow()
    with _open_result(Path(path), PARQUET_LIMIT) as fh, _arrow_file(fh) as source:
        try:
            meta = pq.read_metadata(source).metadata or {}
        except (pa.ArrowException, OSError, ValueError) as exc:
            raise ResultsError(f"{path}: not a readable Parquet file ({exc})") from None
    prefix = PARQUET_KEY_PREFIX.encode()
    return {
        k[len(prefix) :].decode("utf-8", "replace"): v.decode("utf-8", "replace")
        for k, v in meta.items()
        if k.startswith(prefix)
    }


def write_parquet(
    path: Path, df: pd.DataFrame, metadata: dict[str, object] | None = None, *,
    durable: bool = True,
) -> None:  # fmt: skip
    """Write `df` atomically, with `anfekf.<key>` entries in the file's key-value metadata: this
    package's version and git commit always, then `metadata` (text, or JSON for others);
    `durable=False`: no fsync (see `write_json`)."""
    pa, pq = _arrow()
    table = pa.Table.from_pandas(df, preserve_index=False)
    found = {"version": package_version(), "git_commit": git_commit() or "unknown"}
    found.update(metadata or {})
    ours = {
        f"{PARQUET_KEY_PREFIX}{k}".encode(): (
            v if isinstance(v, str) else json.dumps(v, sort_keys=True)
        ).encode()
        for k, v in found.items()
    }
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **ours})
    # Dictionary pages for the names and counters, not for measured floats (nearly all distinct:
    # 7x the whole write's time, a larger file); the floats' bytes split by significance, then
    # LZ4: on a zoo scenario's steps (1.6 M rows), against zstd, 142 MB not 156, written in
    # 0.74 s not 0.87 and read in 0.21 s not 0.81 (lead, 2026-11-28).
    floats = [f.name for f in table.schema if pa.types.is_floating(f.type)]
    coded = [f.name for f in table.schema if f.name not in floats]
    options = {"compression": "lz4", "use_dictionary": coded, "use_byte_stream_split": floats}
    write_atomic(path, lambda tmp: pq.write_table(table, tmp, **options), durable=durable)


def _open_result(path: Path, limit: int) -> BinaryIO:
    try:
        return open_regular(path, limit=limit)
    except FileProblem as exc:
        raise ResultsError(f"{path}: {exc}") from None


def read_parquet(path: Path, columns: list[str] | None = None) -> pd.DataFrame:
    """A result's Parquet table, or only its `columns` (a missing one: ResultsError)."""
    pa, pq = _arrow()
    path = Path(path)
    with _open_result(path, PARQUET_LIMIT) as fh, _arrow_file(fh) as source:
        try:
            return pq.read_table(source, columns=columns).to_pandas()
        except (pa.ArrowException, OSError, ValueError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ResultsError(f"{path}: not a readable Parquet file ({first})") from None


class _BadJSON(ValueError):
    pass


def _no_duplicate_keys(pairs: list[tuple[str, object]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _BadJSON(f"key {key!r} appears twice in one object")
        out[key] = value
    return out


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _BadJSON(f"number {text[:20]} is out of range")
    return value


INT_DIGITS = 30  # far beyond any count or seed we write (seeds < 2^63: 19 digits)


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > INT_DIGITS:
        raise _BadJSON(f"an integer of {len(text)} digits is out of range (at most {INT_DIGITS})")
    return int(text)


def _no_constant(text: str):
    raise _BadJSON(f"{text} is not a number JSON allows (write null for undefined)")


def parse_strict_json(text: str) -> object:
    """JSON without duplicate keys and without NaN, Infinity or numbers that overflow a float:
    our writers never produce them, so a file holding them was made or edited by hand."""
    return json.loads(
        text,
        object_pairs_hook=_no_duplicate_keys,
        parse_float=_finite_float,
        parse_int=_bounded_int,
        parse_constant=_no_constant,
    )


def read_json(path: Path) -> dict | list:
    path = Path(path)
    with _open_result(path, JSON_LIMIT) as fh:
        try:
            return parse_strict_json(fh.read().decode("utf-8"))
        except _BadJSON as exc:
            raise ResultsError(f"{path}: not usable JSON ({exc})") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            msg = exc.strerror if isinstance(exc, OSError) else str(exc).splitlines()[0]
            raise ResultsError(f"{path}: not readable JSON ({msg})") from None
        except RecursionError:
            raise ResultsError(f"{path}: not usable JSON (nested too deeply)") from None


def scenario_dirs(results_dir: Path) -> list[Path]:
    """The complete scenario folders under `results_dir` (itself one, or its children)."""
    results_dir = Path(results_dir)
    try:
        if not results_dir.exists():
            raise ResultsError(f"{results_dir}: results folder does not exist")
        if not results_dir.is_dir():
            raise ResultsError(f"{results_dir}: not a folder")
        if _is_result_dir(results_dir):
            candidates = [results_dir]
        else:
            candidates = sorted(p for p in results_dir.iterdir() if _is_result_dir(p))
    except OSError as exc:  # a name or path too long (ENAMETOOLONG), no permission, ...
        raise ResultsError(f"{results_dir}: cannot be read ({exc.strerror or exc})") from None
    if not candidates:
        raise ResultsError(
            f"{results_dir}: no results found (expected {STEPS_FILE} or {SUMMARY_PARQUET} in"
            " it or in its sub-folders; run `anfekf run` first)"
        )
    for folder in candidates:
        _require_manifest(folder)
        for name in (STEPS_FILE, SUMMARY_PARQUET):
            _check_parquet_footer(folder / name)
    return candidates


def _require_manifest(folder: Path) -> Path:
    """manifest.json is written last: without it the other files may be partial or stale."""
    path = Path(folder) / MANIFEST_FILE
    if os.path.lexists(path) and not path.is_file():  # a FIFO, device or folder: never opened
        raise ResultsError(f"{path}: not a regular file")
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


COORDINATE_LIMIT = 1e7  # metres: a map further out is not a robot's (and 1e308 overflows a plot)


def check_manifest_text(path: Path, manifest: dict) -> None:
    """ResultsError unless every text of a manifest is valid Unicode: a hand-edited lone
    surrogate (`"\\ud800"` is valid JSON) would end a report or a table in UnicodeEncodeError."""
    try:
        json.dumps(manifest, ensure_ascii=False).encode("utf-8")
    except UnicodeEncodeError:
        raise ResultsError(f"{path}: holds text that is not valid Unicode") from None


def check_simulated_manifest(path: Path, manifest: dict) -> None:
    """ResultsError unless the parts of a simulated result's manifest that `report` draws and
    `check` prints are as `anfekf run` writes them: valid Unicode, and the map (world.landmarks,
    world.waypoints, where present) lists of [x, y] finite within COORDINATE_LIMIT metres."""
    check_manifest_text(path, manifest)
    world = manifest.get("world")
    if world is None:
        return
    if not isinstance(world, dict):
        raise ResultsError(f"{path}: world: expected an object")
    for key in ("landmarks", "waypoints"):
        points = world.get(key)
        if points is None:
            continue
        ok = isinstance(points, list) and all(
            isinstance(p, list)
            and len(p) == 2
            and all(
                isinstance(v, (int, float))
                and not isinstance(v, bool)
                and math.isfinite(v)
                and abs(v) <= COORDINATE_LIMIT
                for v in p
            )
            for p in points
        )
        if not ok:
            raise ResultsError(
                f"{path}: world.{key}: expected a list of [x, y] points, finite numbers within"
                f" {COORDINATE_LIMIT:g} m"
            )


BATCH_FILES = (STEPS_FILE, RUNS_FILE, SUMMARY_PARQUET, COMPARISONS_FILE)


def check_one_batch(folder: Path, manifest: dict) -> None:
    """ResultsError unless every Parquet result file of `folder` says, in its metadata, that it
    belongs to the batch its manifest describes (the same seed and fingerprint): a file copied
    in from another batch is refused, not averaged. Files of results written before the
    manifest had a format are checked only where their metadata holds the keys."""
    folder = Path(folder)
    seed = manifest.get("seed")
    seed = None if seed is None else str(seed)
    wanted = {"fingerprint": manifest.get("fingerprint"), "seed": seed}
    strict = manifest.get("format") == RESULT_FORMAT
    for name in BATCH_FILES:
        path = folder / name
        if not os.path.lexists(path):
            continue
        found = parquet_provenance(path)
        for key, want in wanted.items():
            got = found.get(key)
            if got is None and not strict:
                continue
            if got != want:
                raise ResultsError(
                    f"{path}: {key} {str(got)[:20]!r} in its metadata, but {folder / MANIFEST_FILE}"
                    f" says {str(want)[:20]!r}; the files come from different batches"
                )


def is_result_manifest(doc: object) -> bool:
    """A manifest this tool wrote for a result: its format (or, written before the format key,
    this package's version) and a fingerprint. Ownership is decided by this, never by names."""
    if not isinstance(doc, dict) or not isinstance(doc.get("fingerprint"), str):
        return False
    if "format" in doc:
        return doc["format"] == RESULT_FORMAT
    versions = doc.get("versions")
    return isinstance(versions, dict) and isinstance(versions.get("anfekf-bench"), str)


def sync_files(paths: list[Path]) -> None:
    """fsync every file of `paths`, all at once from threads: the file system commits them
    together (one journal commit rather than one a file: a staged result's eight flushes took
    30-55 ms one after the other, 16-26 ms together, on this project's ext4 machine)."""

    def flush(path: Path) -> None:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    if len(paths) <= 1:
        for path in paths:
            flush(path)
        return
    with ThreadPoolExecutor(max_workers=min(len(paths), 16)) as pool:
        list(pool.map(flush, paths))  # the first error is raised here


def install_result(target: Path, staging: Path) -> None:
    """Replace the result in `target` by the complete one in `staging` (manifest written last).

    The staged files are flushed to disk first, together (`sync_files`; they may be written
    without a flush of their own), so that a power cut during or after the renames cannot leave
    a manifest in place over tables whose bytes never reached the disk. Until this is called
    the old result stays whole, whatever fails during a batch. The old
    manifest goes first, so a kill during these few renames leaves a folder that reads as
    incomplete (never a mix under an old manifest); the run store is still there, and the same
    command resumes from it (every run saved, but a fast batch's first ten seconds: RunStore).
    """
    target, staging = Path(target), Path(staging)
    new = {p.name for p in staging.iterdir()}
    if MANIFEST_FILE not in new:
        raise ResultsError(f"{staging}: incomplete staged result (no {MANIFEST_FILE})")
    sync_files([staging / name for name in sorted(new)])  # on disk before the first rename
    manifest = target / MANIFEST_FILE
    if manifest.is_file() and not manifest.is_symlink():
        os.unlink(manifest)
    for name in RESULT_FILES:
        old = target / name
        if name not in new and old.is_file() and not old.is_symlink():
            os.unlink(old)  # e.g. steps.parquet of a batch that recorded steps, this one does not
    for name in sorted(new - {MANIFEST_FILE}):
        os.replace(staging / name, target / name)
    os.replace(staging / MANIFEST_FILE, manifest)


def _check_parquet_footer(path: Path) -> None:
    """A cheap look at a Parquet file's footer (which a truncated file lacks), if it exists.

    report reads steps.parquet and check reads summary.parquet; this makes both refuse a folder
    whose other file is damaged, instead of passing on half a result.
    """
    if not os.path.lexists(path):
        return
    pa, pq = _arrow()
    try:
        with _open_result(path, PARQUET_LIMIT) as fh, _arrow_file(fh) as source:
            pq.read_metadata(source)
    except (pa.ArrowException, OSError, ValueError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ResultsError(f"{path}: not a readable Parquet file ({first})") from None


def _is_result_dir(path: Path) -> bool:
    """A scenario folder, complete or not: it has a results file or saved runs (a result of a
    scenario with `steps_table: false` has summary.parquet but no steps.parquet)."""
    return (
        (path / STEPS_FILE).exists()
        or (path / SUMMARY_PARQUET).exists()
        or (path / RUNS_DIR).is_dir()
    )


def read_steps(scenario_dir: Path, columns: list[str] | None = None) -> pd.DataFrame:
    """A result's steps table (or its `columns`: read_parquet refuses a missing one)."""
    import pandas as pd

    df = read_parquet(Path(scenario_dir) / STEPS_FILE, columns)
    missing = {"scenario", "filter", "run", "step", "pos_err", "nees"} - set(df.columns)
    if missing and columns is None:
        raise ResultsError(
            f"{Path(scenario_dir) / STEPS_FILE}: missing columns {', '.join(sorted(missing))}"
        )
    if len(df) == 0:
        raise ResultsError(f"{Path(scenario_dir) / STEPS_FILE}: holds no rows")
    for column in ("scenario", "filter", "run", "step"):
        if column in df.columns and df[column].isna().any():
            raise ResultsError(f"{Path(scenario_dir) / STEPS_FILE}: {column}: empty cells")
    if not isinstance(df["filter"].dtype, pd.CategoricalDtype):
        # the filters in order of first appearance (one hash pass over the rows, no Python loop)
        codes, names = pd.factorize(df["filter"])
        df["filter"] = pd.Categorical.from_codes(codes, categories=list(names))
    return df


def read_summary(scenario_dir: Path) -> pd.DataFrame:
    return read_parquet(Path(scenario_dir) / SUMMARY_PARQUET)


# ---------------------------------------------------------------------------------------------
# A scenario folder: its lock, and what --force may remove


class FolderBusy(Exception):
    """Another process holds a scenario folder's lock; `str()` is the one-line message."""


@contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Hold an exclusive lock on `folder` (created if missing) while the block runs.

    The lock is `flock` on `<folder>/.lock`: the kernel releases it when the holding process
    ends, even by kill -9, so it never goes stale. Not inherited by worker processes (the file
    is opened close-on-exec). The file stays (removing a lock file races with its next user).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise FolderBusy(f"{path}: a symbolic link; refusing to use it as the lock") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise FolderBusy(f"{path}: not a regular file; refusing to use it as the lock")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            who = f" (pid {holder})" if holder.isdigit() else ""
            raise FolderBusy(
                f"{folder}: another anfekf command is writing this folder{who}; wait for it to"
                " finish, or use another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _is_ours(folder: Path, entry: os.DirEntry) -> bool:
    """An entry of a scenario folder that this tool writes (never a symlink)."""
    name = entry.name
    if entry.is_symlink():
        return False
    if name == RUNS_DIR:
        return entry.is_dir(follow_symlinks=False)
    if not entry.is_file(follow_symlinks=False):
        return False
    return (
        name == LOCK_FILE
        or name.endswith((".parquet", ".json"))
        or (name.startswith(".") and name.endswith(".tmp"))
    )


def foreign_entries(folder: Path) -> list[str]:
    """Entries of a scenario folder that this tool did not write: sub-folders other than the run
    store, symlinks, special files, files of other kinds. --force removes nothing if any."""
    with os.scandir(folder) as entries:
        return sorted(e.name for e in entries if not _is_ours(folder, e))


# ---------------------------------------------------------------------------------------------
# The run store: one finished run per file, a data format that cannot execute code
#
# A run result is a nested structure of dicts (str or int keys), lists/tuples, numpy arrays and
# scalars, and Python bool/int/float/str/None. It is stored as an uncompressed .npz (loaded with
# allow_pickle=False) of two uint8 members: a JSON header describing the tree (each array's
# dtype, shape and memory order in its place) with the batch's fingerprint and a SHA-256 over
# the fingerprint, the tree and the data, and the data: every array's bytes, one after the other
# in the tree's order. A file whose format, fingerprint or checksum does not match, or whose
# data is not exactly its arrays' bytes, is refused (the run is redone); nothing in it is ever
# executed. (v1 stored each array as its own member: writing 30 members cost ~5 ms a run, most
# of a fast-engine run's own time.)

RUN_FORMAT = "anfekf-bench run v2"
HEADER_KEY = "header"
DATA_KEY = "data"
RUN_FILE_LIMIT = 4 * 2**30
_HEADER_LIMIT = 64 * 2**20
# numbers, booleans, strings, dates: never objects (nor structured types)
_DTYPE = re.compile(r"[<>|=](?:[biufc][0-9]{1,2}|[US][0-9]{1,9}|[mM]8(?:\[[0-9]*[a-zA-Z]+\])?)")
_MAX_DIMS = 32


class RunFileRefused(Exception):
    """A saved run cannot be used; `str()` says why (the caller redoes the run)."""


def _array_node(arr: np.ndarray, chunks: list[bytes]) -> list:
    """[dtype, shape, order] of an array whose bytes go to `chunks` (F: Fortran order)."""
    if arr.dtype.hasobject:
        raise TypeError("run result holds an object array: only plain arrays can be stored")
    if not _DTYPE.fullmatch(arr.dtype.str):
        raise TypeError(f"run result holds a {arr.dtype} array, which cannot be stored")
    order = "F" if arr.ndim > 1 and arr.flags.f_contiguous and not arr.flags.c_contiguous else "C"
    flat = arr.ravel(order=order)  # a view where the array is contiguous in that order
    chunks.append(flat.view(np.uint8) if flat.dtype.itemsize else np.zeros(0, np.uint8))
    return [arr.dtype.str, list(arr.shape), order]


def _encode(node, chunks: list[bytes], depth: int = 0):
    if depth > 32:
        raise TypeError("run result nested deeper than 32 levels")
    if isinstance(node, dict):
        items = []
        for key, value in node.items():
            if isinstance(key, bool) or not isinstance(key, (str, int)):
                raise TypeError(f"run result key {key!r}: only str or int keys can be stored")
            items.append([key, _encode(value, chunks, depth + 1)])
        return {"dict": items}
    if isinstance(node, (list, tuple)):
        kind = "list" if isinstance(node, list) else "tuple"
        return {kind: [_encode(v, chunks, depth + 1) for v in node]}
    if isinstance(node, (np.ndarray, np.generic)):
        kind = "array" if isinstance(node, np.ndarray) else "scalar"
        return {kind: _array_node(np.asarray(node), chunks)}
    if node is None:
        return {"none": None}
    if isinstance(node, bool):
        return {"bool": node}
    if isinstance(node, int):
        return {"int": node}
    if isinstance(node, float):
        return {"float": node.hex()}  # exact, NaN and infinities included
    if isinstance(node, str):
        return {"str": node}
    raise TypeError(f"run result holds a {type(node).__name__}, which cannot be stored")


class _Data:
    """The data member read in the tree's order: each array takes the bytes its node declares."""

    def __init__(self, data: bytes):
        self.data, self.used = data, 0

    def take(self, value) -> np.ndarray:
        if not (isinstance(value, list) and len(value) == 3):
            raise RunFileRefused("malformed header")
        dtype, shape, order = value
        if not (isinstance(dtype, str) and _DTYPE.fullmatch(dtype) and order in ("C", "F")):
            raise RunFileRefused("malformed header")
        if not (isinstance(shape, list) and len(shape) <= _MAX_DIMS and all(
                type(n) is int and n >= 0 for n in shape)):  # fmt: skip
            raise RunFileRefused("malformed header")
        dt = np.dtype(dtype)
        size = math.prod(shape) * dt.itemsize
        if size > len(self.data) - self.used:
            raise RunFileRefused("its data is shorter than its header declares")
        arr = np.frombuffer(self.data, dtype=dt, count=math.prod(shape), offset=self.used)
        self.used += size
        return arr.reshape(shape, order=order).copy(order="K")  # writable, owning its memory


def _decode(node, data: _Data):
    if not isinstance(node, dict) or len(node) != 1:
        raise RunFileRefused("malformed header")
    ((kind, value),) = node.items()
    if kind == "dict" and isinstance(value, list):
        out = {}
        for item in value:
            if not (isinstance(item, list) and len(item) == 2):
                raise RunFileRefused("malformed header")
            key, child = item
            if isinstance(key, bool) or not isinstance(key, (str, int)):
                raise RunFileRefused("malformed header")
            out[key] = _decode(child, data)
        return out
    if kind in ("list", "tuple") and isinstance(value, list):
        items = [_decode(v, data) for v in value]
        return items if kind == "list" else tuple(items)
    if kind == "array":
        return data.take(value)
    if kind == "scalar":
        arr = data.take(value)
        if arr.ndim != 0:
            raise RunFileRefused("malformed header")
        return arr[()]
    if kind == "none" and value is None:
        return None
    if kind == "bool" and isinstance(value, bool):
        return value
    if kind == "int" and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind == "float" and isinstance(value, str):
        try:
            return float.fromhex(value)
        except ValueError:
            raise RunFileRefused("malformed header") from None
    if kind == "str" and isinstance(value, str):
        return value
    raise RunFileRefused("malformed header")


def _checksum(fingerprint: str, tree_json: str, data: bytes | np.ndarray) -> str:
    digest = hashlib.sha256()
    digest.update(RUN_FORMAT.encode() + b"\0" + fingerprint.encode() + b"\0")
    digest.update(tree_json.encode() + b"\0")
    digest.update(data)
    return digest.hexdigest()


def run_file_members(result: dict, fingerprint: str) -> dict[str, np.ndarray]:
    """The two uint8 members of a run's .npz (see above); the arrays' bytes copied just once."""
    chunks: list[np.ndarray] = []
    tree_json = json.dumps(_encode(result, chunks), separators=(",", ":"))
    data = np.concatenate(chunks) if chunks else np.zeros(0, np.uint8)
    header = {
        "format": RUN_FORMAT,
        "fingerprint": fingerprint,
        "tree": tree_json,
        "sha256": _checksum(fingerprint, tree_json, data),
    }
    raw = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    return {HEADER_KEY: raw, DATA_KEY: data}


def write_run_file(path: Path, result: dict, fingerprint: str) -> None:
    """Save one finished run atomically (the file appears whole or not at all). No fsync: a run
    file torn by a power cut fails its checksum on resume and the run is done again, so
    durability would buy nothing but a disk flush per run (a fifth of a fast batch)."""
    members = run_file_members(result, fingerprint)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:  # a file object: np.savez would add .npz to a path's name
            np.savez(fh, **members)

    write_atomic(path, write, durable=False)


def _read_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> np.ndarray:
    """One .npy member, its declared size checked against its stored size before allocating."""
    if info.compress_type != zipfile.ZIP_STORED:
        raise RunFileRefused(f"member {info.filename} is compressed (we never write that)")
    with archive.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise RunFileRefused(f"member {info.filename}: unknown .npy version")
        if dtype.hasobject:
            raise RunFileRefused(f"member {info.filename} holds Python objects")
        declared = math.prod(shape) * dtype.itemsize
        if declared != info.file_size - fh.tell():
            raise RunFileRefused(f"member {info.filename}: size does not match its header")
        data = fh.read(declared)
    arr = np.frombuffer(data, dtype=dtype).reshape(shape, order="F" if fortran else "C")
    if arr.dtype != np.uint8 or arr.ndim != 1:
        raise RunFileRefused(f"member {info.filename}: not bytes (uint8, one dimension)")
    return arr


def read_run_file(path: Path, fingerprint: str) -> dict:
    """A run saved by `write_run_file` for the batch with `fingerprint`; RunFileRefused if the
    file is not a regular file, not ours, of another batch, damaged or tampered with."""
    try:
        with open_regular(path, limit=RUN_FILE_LIMIT) as fh:
            content = fh.read()
    except (FileProblem, OSError) as exc:
        raise RunFileRefused(str(exc)) from None
    try:
        with zipfile.ZipFile(io.BytesIO(content)) as archive:
            infos = {info.filename: info for info in archive.infolist()}
            if len(infos) != len(archive.infolist()):
                raise RunFileRefused("duplicate members")
            head = infos.get(f"{HEADER_KEY}.npy")
            if head is None or head.file_size > _HEADER_LIMIT:
                raise RunFileRefused("no header")
            unexpected = set(infos) - {f"{HEADER_KEY}.npy", f"{DATA_KEY}.npy"}
            if unexpected:
                raise RunFileRefused(f"unexpected member {sorted(unexpected)[0][:40]!r}")
            if f"{DATA_KEY}.npy" not in infos:
                raise RunFileRefused("no data")
            raw = _read_member(archive, head)
            header = parse_strict_json(raw.tobytes().decode("utf-8"))
            if not isinstance(header, dict) or header.get("format") != RUN_FORMAT:
                raise RunFileRefused("not an anfekf-bench run file")
            if header.get("fingerprint") != fingerprint:
                raise RunFileRefused("saved by another scenario, seed or code version")
            tree_json = header.get("tree")
            if not isinstance(tree_json, str):
                raise RunFileRefused("malformed header")
            data = _read_member(archive, infos[f"{DATA_KEY}.npy"]).tobytes()
    except RunFileRefused:
        raise
    except (zipfile.BadZipFile, ValueError, EOFError, OSError, RecursionError) as exc:
        raise RunFileRefused(f"damaged ({type(exc).__name__})") from None
    if header.get("sha256") != _checksum(fingerprint, tree_json, data):
        raise RunFileRefused("checksum mismatch")
    reader = _Data(data)
    try:
        tree = _decode(json.loads(tree_json), reader)
    except (ValueError, RecursionError, TypeError):
        raise RunFileRefused("malformed header") from None
    if reader.used != len(data) or not isinstance(tree, dict):
        raise RunFileRefused("malformed header")
    return tree


def is_sweep_folder(folder: Path) -> bool:
    """A folder `anfekf run` wrote for a sweep: its manifest says so, and it holds its cells or
    its table."""
    folder = Path(folder)
    manifest = folder / MANIFEST_FILE
    if not manifest.is_file() or not (
        (folder / SWEEP_CELLS_DIR).is_dir() or (folder / SWEEP_FILE).is_file()
    ):
        return False
    try:
        doc = read_json(manifest)
    except ResultsError:
        return False
    return isinstance(doc, dict) and doc.get("kind") == SWEEP_KIND


def sweep_folders(results_dir: Path) -> list[Path]:
    """The sweep folders `results_dir` is or holds (`anfekf run` of a scenario with a sweep)."""
    results_dir = Path(results_dir)
    try:
        if is_sweep_folder(results_dir):
            return [results_dir]
        if not results_dir.is_dir():
            return []
        return sorted(p for p in results_dir.iterdir() if p.is_dir() and is_sweep_folder(p))
    except OSError as exc:  # a name or path too long (ENAMETOOLONG), no permission, ...
        raise ResultsError(f"{results_dir}: cannot be read ({exc.strerror or exc})") from None
