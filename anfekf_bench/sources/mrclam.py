"""Recorded robot logs: the UTIAS MRCLAM data, its built-in copy, and what any log offers.

A recorded log is four tables (SPEC 9, docs/REAL_DATA.md):

- odometry      t [s], v [m/s], w [rad/s]: commands, each held until the next (zero-order hold)
- measurements  t [s], landmark id, range [m], bearing [rad]: of known landmarks only
- landmarks     landmark id, x [m], y [m]: the map
- groundtruth   t [s], x [m], y [m], phi [rad]: reference poses (Vicon for MRCLAM)

All of it is held in a `RobotLog` (frozen, read-only numpy arrays, times in seconds from
`t_origin`). Where it comes from:

- `load_builtin()`: UTIAS MRCLAM Dataset 9, Robot 3, shipped in the package as Parquet
  (`anfekf_bench/data/mrclam-dataset9-robot3/`, made once by `convert_mrclam_to_parquet`);
- `load_drive(drive)`: any of the eleven built-in drives (`DRIVES`: MRCLAM Datasets 6 and 7,
  Robots 1-5, in `anfekf_bench/data/mrclam-dataset<d>/robot<r>/`, and Dataset 9 Robot 3);
- `read_mrclam(folder)`: the original MRCLAM `.dat` files;
- `user_log.read_user_log(folder)`: a user's own log, four CSV or Parquet files in the
  documented schema (its own module).

On a log:

- `interpolate_truth(log, t)`: ground truth at any times (heading unwrapped, interpolated, wrapped);
- `exclusions(log)` / `scorable(log, t)`: where the ground truth may be used for scoring (outside
  Vicon gaps over 0.5 s and outside detected Vicon mis-fits, see `MisfitRule`);
- `split(log, at)`, `segments(t0, t1, length_s)`, `cold_start(log, t)`: training and held-out
  spans, the held-out span cut into segments that each start from ground truth;
- `events(log, t0, t1)`: the time-ordered odometry and landmark events a filter consumes;
- `residuals(log)`: measured minus true range and bearing, on scorable times.

Errors in a file raise `LogError`, whose `str()` is one line naming the file and the column and
line; no file content is ever echoed.
"""

from __future__ import annotations

import hashlib
import math
import os
import stat
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from ..models.angles import wrap_angle
from ..timeline import LANDMARK, ODOMETRY  # the event kinds (the contract's)

BUILTIN_NAME = "mrclam-dataset9-robot3"
ROBOT_SUBJECTS = range(1, 6)  # MRCLAM: subjects 1-5 are the robots, 6-20 the landmarks
MAX_FILE_BYTES = 1 << 30

# The four MRCLAM tables as stored in the built-in Parquet copy (see PROVENANCE.md there).
PARQUET_SCHEMAS = {
    "odometry": pa.schema([("t_ms", pa.int64()), ("v", pa.float64()), ("w", pa.float64())]),
    "measurements": pa.schema(
        [
            ("t_ms", pa.int64()),
            ("barcode", pa.int32()),
            ("subject", pa.int32()),
            ("range", pa.float64()),
            ("bearing", pa.float64()),
        ]
    ),
    "landmarks": pa.schema(
        [
            ("subject", pa.int32()),
            ("x", pa.float64()),
            ("y", pa.float64()),
            ("x_std", pa.float64()),
            ("y_std", pa.float64()),
        ]
    ),
    "groundtruth": pa.schema(
        [("t_ms", pa.int64()), ("x", pa.float64()), ("y", pa.float64()), ("phi", pa.float64())]
    ),
}
UNKNOWN_SUBJECT = -1  # `subject` of a barcode that Barcodes.dat does not list


def _one_line(text: str) -> str:
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class LogError(ValueError):
    """A log cannot be used; `str()` is one line: `<file>: <where>: <what is wrong / allowed>`."""

    def __init__(self, path: str | Path, where: str, message: str):
        self.path = str(path)
        self.where = where
        self.message = message
        text = f"{self.path}: {where}: {message}" if where else f"{self.path}: {message}"
        super().__init__(_one_line(text))


# --------------------------------------------------------------------------------------------
# The log
# --------------------------------------------------------------------------------------------


def _frozen(a, dtype) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True).reshape(-1)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class RobotLog:
    """One robot's recorded log, cleaned. All times in seconds from `t_origin`, all angles rad.

    Odometry `odo_*` (commands, held until the next sample), landmark measurements `meas_*`
    (time-sorted, several may share a stamp; only landmarks of the map), the map `landmark_*`
    (sorted by id) and ground truth `truth_*` (phi wrapped to (-pi, pi] here). Odometry and
    ground-truth times strictly increase, measurement times do not decrease; the constructor
    checks this (ValueError) and makes every array read-only. `dropped_robot` and
    `dropped_unknown` count the measurements cleaning removed: of other robots, and of barcodes
    or subjects that are neither a robot nor a landmark of the map (always 0 for user logs).
    """

    name: str
    t_origin: float  # the source clock's time of t = 0 [s] (Unix time for MRCLAM, 0 for users)
    odo_t: np.ndarray
    odo_v: np.ndarray
    odo_w: np.ndarray
    meas_t: np.ndarray
    meas_landmark: np.ndarray
    meas_range: np.ndarray
    meas_bearing: np.ndarray
    landmark_id: np.ndarray
    landmark_x: np.ndarray
    landmark_y: np.ndarray
    truth_t: np.ndarray
    truth_x: np.ndarray
    truth_y: np.ndarray
    truth_phi: np.ndarray
    dropped_robot: int = 0
    dropped_unknown: int = 0
    dropped_odometry: int = 0  # odometry rows replaced by a later row at the same stamp
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        ints = {"meas_landmark", "landmark_id"}
        for name in (
            "odo_t odo_v odo_w meas_t meas_landmark meas_range meas_bearing landmark_id "
            "landmark_x landmark_y truth_t truth_x truth_y truth_phi"
        ).split():
            value = getattr(self, name)
            if name == "truth_phi":
                value = wrap_angle(value)
            object.__setattr__(self, name, _frozen(value, np.int64 if name in ints else float))
        for prefix, names in {
            "odo": ("t", "v", "w"),
            "meas": ("t", "landmark", "range", "bearing"),
            "landmark": ("id", "x", "y"),
            "truth": ("t", "x", "y", "phi"),
        }.items():
            sizes = {len(getattr(self, f"{prefix}_{n}")) for n in names}
            if len(sizes) != 1:
                raise ValueError(f"RobotLog: the {prefix}_* arrays differ in length")
        if len(self.truth_t) == 0:
            raise ValueError("RobotLog: ground truth is empty")
        for name in ("odo_t", "truth_t"):
            if np.any(np.diff(getattr(self, name)) <= 0):
                raise ValueError(f"RobotLog: {name} must be strictly increasing")
        if np.any(np.diff(self.meas_t) < 0):
            raise ValueError("RobotLog: meas_t must not decrease")
        if np.any(np.diff(self.landmark_id) <= 0):
            raise ValueError("RobotLog: landmark_id must be sorted and unique")
        rows = np.searchsorted(self.landmark_id, self.meas_landmark)
        rows = np.minimum(rows, max(len(self.landmark_id) - 1, 0))
        if len(self.meas_landmark) and not np.array_equal(
            self.landmark_id[rows], self.meas_landmark
        ):
            raise ValueError("RobotLog: a measurement names a landmark absent from the map")
        xy = (
            np.column_stack([self.landmark_x[rows], self.landmark_y[rows]])
            if len(rows)
            else np.zeros((0, 2))
        )
        xy.setflags(write=False)
        self._cache["meas_xy"] = xy
        self._cache["phi_unwrapped"] = np.unwrap(self.truth_phi)

    @property
    def meas_xy(self) -> np.ndarray:
        """(m, 2) map coordinates of the landmark of each measurement."""
        return self._cache["meas_xy"]

    @property
    def landmarks(self) -> dict[int, tuple[float, float]]:
        """The map as {landmark id: (x, y)}."""
        return {
            int(i): (float(x), float(y))
            for i, x, y in zip(self.landmark_id, self.landmark_x, self.landmark_y, strict=True)
        }

    @property
    def t_start(self) -> float:
        """First ground-truth time: the start of the scorable window."""
        return float(self.truth_t[0])

    @property
    def t_end(self) -> float:
        """Last ground-truth time."""
        return float(self.truth_t[-1])

    @property
    def span(self) -> Span:
        """[t_start, t_end]: the ground-truth span."""
        return Span(self.t_start, self.t_end)

    def counts(self) -> dict[str, int]:
        """Sizes of the tables and what cleaning dropped."""
        return {
            "odometry": len(self.odo_t),
            "measurements": len(self.meas_t),
            "landmarks": len(self.landmark_id),
            "groundtruth": len(self.truth_t),
            "dropped_robot": self.dropped_robot,
            "dropped_unknown": self.dropped_unknown,
            "dropped_odometry": self.dropped_odometry,
        }


# --------------------------------------------------------------------------------------------
# Reading files safely
# --------------------------------------------------------------------------------------------


def _read_regular_file(path: Path) -> bytes:
    """The bytes of a regular file; anything else (FIFO, directory, device) is a LogError."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise LogError(path, "", "file not found") from None
    except IsADirectoryError:
        raise LogError(path, "", "is a directory, not a regular file") from None
    except OSError as exc:
        raise LogError(path, "", f"cannot be opened ({exc.strerror or 'error'})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise LogError(path, "", "is not a regular file (a FIFO, directory or device)")
        if st.st_size > MAX_FILE_BYTES:
            raise LogError(path, "", f"is larger than {MAX_FILE_BYTES >> 20} MiB")
        chunks = []
        while chunk := os.read(fd, 1 << 20):
            chunks.append(chunk)
        return b"".join(chunks)
    except OSError as exc:
        raise LogError(path, "", f"cannot be read ({exc.strerror or 'error'})") from None
    finally:
        os.close(fd)


def _sha256(path: Path) -> str:
    return hashlib.sha256(_read_regular_file(path)).hexdigest()


def _read_parquet(path: Path) -> pa.Table:
    data = _read_regular_file(path)
    try:
        return pq.read_table(pa.BufferReader(data))  # not a Python file object: arrow#33975
    except (pa.ArrowException, OSError, ValueError):
        raise LogError(path, "", "is not a readable Parquet file") from None


# --------------------------------------------------------------------------------------------
# MRCLAM .dat files and the built-in Parquet copy
# --------------------------------------------------------------------------------------------


def _read_dat(path: Path, columns: tuple[str, ...]) -> np.ndarray:
    """A whitespace-separated MRCLAM table ('#' lines are comments) as floats, one row per line."""
    text = _read_regular_file(path)
    try:
        lines = text.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise LogError(path, "", "is not an ASCII MRCLAM .dat file") from None
    rows = []
    for number, line in enumerate(lines, start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split()
        if len(fields) != len(columns):
            raise LogError(
                path,
                f"line {number}",
                f"{len(fields)} fields, expected {len(columns)} ({', '.join(columns)})",
            )
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise LogError(path, f"line {number}", "a field is not a number") from None
        if not all(math.isfinite(v) for v in values):
            raise LogError(path, f"line {number}", "a field is not finite (nan or inf)")
        rows.append(values)
    if not rows:
        raise LogError(path, "", "no data rows")
    return np.array(rows, dtype=float)


def _ms(path: Path, t: np.ndarray) -> np.ndarray:
    """MRCLAM stamps (seconds with 3 decimals) as integer milliseconds, exactly."""
    ms = np.rint(t * 1000.0)
    if np.any(np.abs(ms - t * 1000.0) > 0.01):
        raise LogError(path, "column 1", "times must be seconds with at most 3 decimals (ms)")
    return ms.astype(np.int64)


def _mrclam_paths(
    folder: str | Path, robot_barcode_file: str | Path | None = None, robot: int | None = None
) -> dict[str, Path]:
    folder = Path(folder)
    prefix = f"Robot{robot}_" if robot is not None else ""
    return {
        "barcodes": Path(robot_barcode_file) if robot_barcode_file else folder / "Barcodes.dat",
        "odometry": folder / f"{prefix}Odometry.dat",
        "measurements": folder / f"{prefix}Measurement.dat",
        "groundtruth": folder / f"{prefix}Groundtruth.dat",
        "landmarks": folder / "Landmark_Groundtruth.dat",
    }


def _mrclam_tables(
    folder: str | Path, robot_barcode_file: str | Path | None = None, robot: int | None = None
) -> dict[str, pd.DataFrame]:
    """The four MRCLAM tables as read (barcodes mapped to subjects, nothing dropped yet)."""
    paths = _mrclam_paths(folder, robot_barcode_file, robot)
    barcode_path, odo_path, meas_path = paths["barcodes"], paths["odometry"], paths["measurements"]
    truth_path, lm_path = paths["groundtruth"], paths["landmarks"]

    bc = _read_dat(barcode_path, ("subject", "barcode")).astype(np.int64)
    if len(np.unique(bc[:, 1])) != len(bc):
        raise LogError(barcode_path, "column 2", "a barcode is listed twice")
    odo = _read_dat(odo_path, ("time", "v", "w"))
    meas = _read_dat(meas_path, ("time", "barcode", "range", "bearing"))
    truth = _read_dat(truth_path, ("time", "x", "y", "orientation"))
    lm = _read_dat(lm_path, ("subject", "x", "y", "x std", "y std"))

    barcode = meas[:, 1]
    if np.any(barcode != np.rint(barcode)):
        raise LogError(meas_path, "column 2", "barcodes must be integers")
    barcode = barcode.astype(np.int64)
    order = np.argsort(bc[:, 1])
    pos = np.minimum(np.searchsorted(bc[order, 1], barcode), len(bc) - 1)
    known = bc[order, 1][pos] == barcode
    subject = np.where(known, bc[order, 0][pos], UNKNOWN_SUBJECT)
    if np.any(lm[:, 0] != np.rint(lm[:, 0])):
        raise LogError(lm_path, "column 1", "subjects must be integers")

    return {
        "odometry": pd.DataFrame(
            {"t_ms": _ms(odo_path, odo[:, 0]), "v": odo[:, 1], "w": odo[:, 2]}
        ),
        "measurements": pd.DataFrame(
            {
                "t_ms": _ms(meas_path, meas[:, 0]),
                "barcode": barcode.astype(np.int32),
                "subject": subject.astype(np.int32),
                "range": meas[:, 2],
                "bearing": meas[:, 3],
            }
        ),
        "landmarks": pd.DataFrame(
            {
                "subject": lm[:, 0].astype(np.int32),
                "x": lm[:, 1],
                "y": lm[:, 2],
                "x_std": lm[:, 3],
                "y_std": lm[:, 4],
            }
        ),
        "groundtruth": pd.DataFrame(
            {
                "t_ms": _ms(truth_path, truth[:, 0]),
                "x": truth[:, 1],
                "y": truth[:, 2],
                "phi": truth[:, 3],
            }
        ),
    }


def _strictly_increasing(path: Path, t: np.ndarray, column: str) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        raise LogError(
            path, f"column '{column}', data row {int(bad[0]) + 2}", "times must be increasing"
        )


def _log_from_mrclam_tables(
    tables: dict[str, pd.DataFrame], name: str, paths: dict[str, Path]
) -> RobotLog:
    """Clean the MRCLAM tables into a RobotLog (the one place where cleaning happens)."""
    odo, meas = tables["odometry"], tables["measurements"]
    lm, truth = tables["landmarks"], tables["groundtruth"]
    # Datasets 6 and 7 log a few odometry rows twice at one stamp (sometimes with another
    # command): under the zero-order hold only the last command at a stamp is ever in force.
    repeated = np.r_[odo["t_ms"].to_numpy()[1:] == odo["t_ms"].to_numpy()[:-1], False]
    odo = odo[~repeated]
    _strictly_increasing(paths["odometry"], odo["t_ms"].to_numpy(), "time")
    _strictly_increasing(paths["groundtruth"], truth["t_ms"].to_numpy(), "time")
    lm = lm.sort_values("subject", kind="stable")
    if lm["subject"].duplicated().any():
        raise LogError(paths["landmarks"], "subject", "a subject is listed twice")

    subject = meas["subject"].to_numpy()
    is_robot = np.isin(subject, np.array(ROBOT_SUBJECTS))
    is_landmark = np.isin(subject, lm["subject"].to_numpy())
    keep = meas[is_landmark & ~is_robot].sort_values("t_ms", kind="stable")

    origin_ms = int(truth["t_ms"].iloc[0])

    def rel(t_ms: pd.Series) -> np.ndarray:
        return (t_ms.to_numpy() - origin_ms) / 1000.0

    return RobotLog(
        name=name,
        t_origin=origin_ms / 1000.0,
        odo_t=rel(odo["t_ms"]),
        odo_v=odo["v"].to_numpy(),
        odo_w=odo["w"].to_numpy(),
        meas_t=rel(keep["t_ms"]),
        meas_landmark=keep["subject"].to_numpy(),
        meas_range=keep["range"].to_numpy(),
        meas_bearing=keep["bearing"].to_numpy(),
        landmark_id=lm["subject"].to_numpy(),
        landmark_x=lm["x"].to_numpy(),
        landmark_y=lm["y"].to_numpy(),
        truth_t=rel(truth["t_ms"]),
        truth_x=truth["x"].to_numpy(),
        truth_y=truth["y"].to_numpy(),
        truth_phi=wrap_angle(truth["phi"].to_numpy()),
        dropped_robot=int(is_robot.sum()),
        dropped_unknown=int((~is_robot & ~is_landmark).sum()),
        dropped_odometry=int(repeated.sum()),
    )


def read_mrclam(
    folder: str | Path, robot_barcode_file: str | Path | None = None, *, robot: int | None = None
) -> RobotLog:
    """Read and clean one robot of a UTIAS MRCLAM dataset from its original `.dat` files.

    `folder` holds `Odometry.dat`, `Measurement.dat`, `Groundtruth.dat` (or, with `robot=k`, the
    original dataset's `Robotk_Odometry.dat`, ...), `Landmark_Groundtruth.dat` and `Barcodes.dat`
    (or give its path as `robot_barcode_file`). Each file: '#' header lines, then whitespace-
    separated numbers. Measurement.dat's 2nd column holds BARCODES (despite its header): they are
    mapped to subjects with Barcodes.dat; measurements of subjects 1-5 (the robots) are dropped
    and counted in `dropped_robot`; those of barcodes Barcodes.dat does not list, or of subjects
    absent from the landmark map, are dropped and counted in `dropped_unknown`. Measurements are
    stably sorted by time. Times become seconds from the first ground-truth stamp (`t_origin`).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise LogError(folder, "", "no such folder")
    tables = _mrclam_tables(folder, robot_barcode_file, robot)
    paths = _mrclam_paths(folder, robot_barcode_file, robot)
    return _log_from_mrclam_tables(tables, folder.name, paths)


def convert_mrclam_to_parquet(
    src_folder: str | Path, dst_folder: str | Path, *, robot: int | None = None
) -> dict[str, str]:
    """Write the four MRCLAM tables of `src_folder` as zstd Parquet files into `dst_folder`.

    With `robot=k` the source is a whole original dataset and Robot<k>_*.dat are read.

    `odometry.parquet` (t_ms, v, w), `measurements.parquet` (t_ms, barcode, subject, range,
    bearing: ALL rows, robots and unknown barcodes kept, `subject` = -1 for an unknown barcode),
    `landmarks.parquet` (subject, x, y, x_std, y_std) and `groundtruth.parquet` (t_ms, x, y, phi).
    `t_ms` is the original stamp in integer milliseconds of Unix time (exact); every other value
    is the float64 the original text parses to, unchanged. Rows keep the files' order. Cleaning
    is left to the loader, so the copy holds everything the originals hold except Barcodes.dat,
    which is applied. Returns {original file name: sha256} of the files read.
    """
    src, dst = Path(src_folder), Path(dst_folder)
    tables = _mrclam_tables(src, robot=robot)
    dst.mkdir(parents=True, exist_ok=True)
    for name, df in tables.items():
        table = pa.Table.from_pandas(df, schema=PARQUET_SCHEMAS[name], preserve_index=False)
        pq.write_table(
            table,
            dst / f"{name}.parquet",
            compression="zstd",
            compression_level=19,
            use_dictionary=["barcode", "subject"],
            column_encoding={"t_ms": "DELTA_BINARY_PACKED"} if "t_ms" in df else None,
            write_statistics=False,
        )
    paths = _mrclam_paths(src, robot=robot)
    return {paths[key].name: _sha256(paths[key]) for key in paths}


def builtin_folder() -> Path:
    """Where the built-in copy lives inside the installed package."""
    return Path(str(resources.files("anfekf_bench") / "data" / BUILTIN_NAME))


def read_parquet_tables(folder: str | Path) -> dict[str, pd.DataFrame]:
    """The four tables of a converted copy, checked against `PARQUET_SCHEMAS`."""
    folder = Path(folder)
    out = {}
    for name, schema in PARQUET_SCHEMAS.items():
        path = folder / f"{name}.parquet"
        table = _read_parquet(path)
        if not table.schema.equals(schema, check_metadata=False):
            raise LogError(path, "", "columns or types differ from the built-in schema")
        out[name] = table.to_pandas()
    return out


def load_builtin() -> RobotLog:
    """UTIAS MRCLAM Dataset 9, Robot 3 (1387 s), from the Parquet copy shipped in the package.

    Identical to `read_mrclam` on the original files (see the copy's PROVENANCE.md).
    """
    folder = builtin_folder()
    paths = {name: folder / f"{name}.parquet" for name in PARQUET_SCHEMAS}
    return _log_from_mrclam_tables(read_parquet_tables(folder), BUILTIN_NAME, paths)


# --------------------------------------------------------------------------------------------
# The eleven built-in drives: MRCLAM Datasets 6 and 7 (Robots 1-5) and Dataset 9 Robot 3


def _drive_ids() -> dict[str, tuple[int, int]]:
    ids = {f"d{d}-r{r}": (d, r) for d in (6, 7) for r in range(1, 6)}
    ids["d9-r3"] = (9, 3)
    return ids


DRIVES: dict[str, tuple[int, int]] = _drive_ids()  # drive id -> (dataset, robot)
DRIVE_DATASETS = (6, 7)  # shipped as data/mrclam-dataset<d>/robot<r>/ (Dataset 9: BUILTIN_NAME)


def drive_folder(drive: str) -> Path:
    """The Parquet copy of a built-in drive ('d6-r1' .. 'd7-r5', 'd9-r3') in the package."""
    dataset, robot = _drive(drive)
    if dataset == 9:
        return builtin_folder()
    return Path(str(resources.files("anfekf_bench") / "data" / f"mrclam-dataset{dataset}")) / (
        f"robot{robot}"
    )


def _drive(drive: str) -> tuple[int, int]:
    if drive not in DRIVES:
        raise ValueError(f"unknown drive {drive!r} (built-in: {', '.join(DRIVES)})")
    return DRIVES[drive]


def drive_dataset(drive: str) -> int:
    """The MRCLAM dataset a built-in drive belongs to (its landmark map): 6, 7 or 9."""
    return _drive(drive)[0]


def load_drive(drive: str) -> RobotLog:
    """A built-in drive from its Parquet copy, cleaned as `read_mrclam` cleans the originals.

    Each dataset has its own map (`Landmark_Groundtruth.dat` of that dataset): never mixed.
    """
    dataset, robot = _drive(drive)
    if dataset == 9:
        return load_builtin()
    folder = drive_folder(drive)
    paths = {name: folder / f"{name}.parquet" for name in PARQUET_SCHEMAS}
    name = f"mrclam-dataset{dataset}-robot{robot}"
    return _log_from_mrclam_tables(read_parquet_tables(folder), name, paths)


def provenance_sha256(provenance: str | Path) -> dict[str, str]:
    """{original file name: SHA-256} from the table of a copy's PROVENANCE.md."""
    out = {}
    for line in Path(provenance).read_text(encoding="utf-8").splitlines():
        cells = [c.strip().strip("`") for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].endswith(".dat") and len(cells[2]) == 64:
            out[cells[0]] = cells[2]
    return out


def regenerate_drive_copies(
    shared: str | Path, dst: str | Path | None = None, datasets=DRIVE_DATASETS
) -> dict[str, dict[str, str]]:
    """Convert the original Datasets 6 and 7 (`shared`/utias-mrclam-dataset<d>/) into Parquet.

    Writes `dst`/mrclam-dataset<d>/robot<r>/ (default `dst`: the package's data folder) and
    checks the SHA-256 of every original read against the copy's PROVENANCE.md: a LogError if
    one differs (the copies are of those exact files). Returns {drive: {file: sha256}}.
    """
    shared = Path(shared)
    data = Path(str(resources.files("anfekf_bench") / "data"))
    dst = data if dst is None else Path(dst)
    out = {}
    for d in datasets:
        src = shared / f"utias-mrclam-dataset{d}"
        expected = provenance_sha256(data / f"mrclam-dataset{d}" / "PROVENANCE.md")
        for r in range(1, 6):
            target = dst / f"mrclam-dataset{d}" / f"robot{r}"
            found = convert_mrclam_to_parquet(src, target, robot=r)
            for file, sha in found.items():
                if expected.get(file) != sha:
                    raise LogError(src / file, "", "SHA-256 differs from PROVENANCE.md")
            out[f"d{d}-r{r}"] = found
    return out


# --------------------------------------------------------------------------------------------
# Ground truth: interpolation, gaps and mis-fits
# --------------------------------------------------------------------------------------------


def interpolate_truth(log: RobotLog, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth (x, y, phi) at times `t` (scalar or array), by linear interpolation.

    x and y are interpolated linearly; the heading is unwrapped over the whole log first, then
    interpolated, then wrapped to (-pi, pi], so a turn through +-pi is interpolated through +-pi
    and not the long way round. NaN outside [log.t_start, log.t_end]. Inside a Vicon gap the
    values are a straight line between the samples around it: check `scorable` before using them.
    """
    tt = np.asarray(t, dtype=float)
    tr = log.truth_t
    x = np.interp(tt, tr, log.truth_x)
    y = np.interp(tt, tr, log.truth_y)
    phi = wrap_angle(np.interp(tt, tr, log._cache["phi_unwrapped"]))
    outside = (tt < tr[0]) | (tt > tr[-1])
    if np.any(outside):
        x, y, phi = (np.where(outside, np.nan, a) for a in (x, y, phi))
    if tt.ndim == 0:
        return float(x), float(y), float(phi)
    return x, y, phi


@dataclass(frozen=True)
class MisfitRule:
    """Detection of intervals where the Vicon pose is visibly wrong (a mis-fit of the markers).

    A robot that only drives forward moves along its heading. At every ground-truth sample:

    1. course and speed over ground come from the positions at t - window_s/2 and t + window_s/2
       (linearly interpolated; the stamps are jittered, so a window of >= 0.1 s, not the raw
       sample spacing); a sample is *decidable* when its window lies in the ground-truth span,
       does not touch a gap longer than the gap limit, and min_speed <= speed <= max_speed (still
       or jumping poses say nothing about the heading);
    2. d = |wrap(course - heading)|. A mis-fit STARTS at a decidable sample with d > enter_rad and
       lasts until the next decidable sample with d < exit_rad (hysteresis: it is held through
       stops, gaps and a partly wrong fit);
    3. mis-fits lasting less than min_duration_s are dropped (a single position glitch turns the
       course for about one window); the rest are padded by pad_s on each side, merged where they
       overlap and clipped to the ground-truth span.
    """

    window_s: float = 0.2
    min_speed: float = 0.05
    max_speed: float = 0.4
    enter_rad: float = 1.0
    exit_rad: float = 0.25
    min_duration_s: float = 1.0
    pad_s: float = 0.5


@dataclass(frozen=True)
class Exclusions:
    """Where a log's ground truth must not be used for scoring.

    `gaps`: (k, 2) open intervals (t_before, t_after) between consecutive ground-truth samples
    more than `max_gap_s` apart. `misfits`: (m, 2) closed intervals from `MisfitRule`. Outside
    [t_start, t_end] nothing is scorable.
    """

    t_start: float
    t_end: float
    max_gap_s: float
    gaps: np.ndarray
    misfits: np.ndarray

    def scorable(self, t) -> np.ndarray:
        """True where ground truth at `t` is usable: in the span, not in a gap nor a mis-fit."""
        tt = np.asarray(t, dtype=float)
        ok = (tt >= self.t_start) & (tt <= self.t_end)
        ok &= ~_inside(tt, self.gaps, closed=False)
        ok &= ~_inside(tt, self.misfits, closed=True)
        return ok

    def scorable_seconds(self, t0: float | None = None, t1: float | None = None) -> float:
        """Length [s] of the scorable part of [t0, t1] (default: the ground-truth span)."""
        a = self.t_start if t0 is None else max(t0, self.t_start)
        b = self.t_end if t1 is None else min(t1, self.t_end)
        if b <= a:
            return 0.0
        bad = _union(np.vstack([self.gaps, self.misfits]), a, b)
        return float((b - a) - (bad[:, 1] - bad[:, 0]).sum())

    @property
    def gap_seconds(self) -> float:
        return float((self.gaps[:, 1] - self.gaps[:, 0]).sum())

    @property
    def misfit_seconds(self) -> float:
        return float((self.misfits[:, 1] - self.misfits[:, 0]).sum())


def _inside(t: np.ndarray, iv: np.ndarray, closed: bool) -> np.ndarray:
    """t in any of the sorted, disjoint intervals `iv`."""
    if len(iv) == 0:
        return np.zeros(np.shape(t), dtype=bool)
    k = np.searchsorted(iv[:, 0], t, side="right" if closed else "left") - 1
    kk = np.maximum(k, 0)
    if closed:
        return (k >= 0) & (t <= iv[kk, 1])
    return (k >= 0) & (t < iv[kk, 1])


def _union(iv: np.ndarray, a: float, b: float) -> np.ndarray:
    """The union of intervals, clipped to [a, b], as sorted disjoint intervals."""
    iv = np.clip(iv.reshape(-1, 2), a, b)
    iv = iv[iv[:, 1] > iv[:, 0]]
    iv = iv[np.argsort(iv[:, 0], kind="stable")]
    out: list[list[float]] = []
    for s, e in iv:
        if out and s <= out[-1][1]:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([s, e])
    return np.array(out, dtype=float).reshape(-1, 2)


def find_gaps(log: RobotLog, max_gap_s: float = 0.5) -> np.ndarray:
    """(k, 2) intervals between consecutive ground-truth samples more than `max_gap_s` apart."""
    t = log.truth_t
    i = np.flatnonzero(np.diff(t) > max_gap_s)
    return np.column_stack([t[i], t[i + 1]]).reshape(-1, 2)


def find_misfits(
    log: RobotLog, rule: MisfitRule = MisfitRule(), max_gap_s: float = 0.5
) -> np.ndarray:
    """(m, 2) Vicon mis-fit intervals by `rule` (see `MisfitRule`), sorted and disjoint."""
    t, x, y = log.truth_t, log.truth_x, log.truth_y
    if len(t) < 2:
        return np.zeros((0, 2))
    gaps = find_gaps(log, max_gap_s)
    a, b = t - rule.window_s / 2, t + rule.window_s / 2
    ok = (a >= t[0]) & (b <= t[-1])
    if len(gaps):  # the window overlaps a gap (g0, g1) when g0 < b and g1 > a
        ok &= ~(np.searchsorted(gaps[:, 0], b, "left") > np.searchsorted(gaps[:, 1], a, "right"))
    dx = np.interp(b, t, x) - np.interp(a, t, x)
    dy = np.interp(b, t, y) - np.interp(a, t, y)
    speed = np.hypot(dx, dy) / rule.window_s
    d = np.abs(wrap_angle(np.arctan2(dy, dx) - log.truth_phi))
    decidable = ok & (speed >= rule.min_speed) & (speed <= rule.max_speed)
    decisive = decidable & ((d > rule.enter_rad) | (d < rule.exit_rad))
    last = np.maximum.accumulate(np.where(decisive, np.arange(len(t)), -1))
    state = (last >= 0) & (d[np.maximum(last, 0)] > rule.enter_rad)

    edges = np.diff(np.concatenate([[0], state.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    keep = t[ends] - t[starts] >= rule.min_duration_s
    iv = np.column_stack([t[starts[keep]] - rule.pad_s, t[ends[keep]] + rule.pad_s])
    return _union(iv, float(t[0]), float(t[-1]))


def exclusions(
    log: RobotLog, max_gap_s: float = 0.5, misfit: MisfitRule | None = MisfitRule()
) -> Exclusions:
    """Gaps over `max_gap_s` and mis-fits by `misfit` (None: no mis-fit detection). Cached."""
    key = ("exclusions", max_gap_s, misfit)
    if key not in log._cache:
        misfits = find_misfits(log, misfit, max_gap_s) if misfit is not None else np.zeros((0, 2))
        log._cache[key] = Exclusions(
            t_start=log.t_start,
            t_end=log.t_end,
            max_gap_s=max_gap_s,
            gaps=find_gaps(log, max_gap_s),
            misfits=misfits,
        )
    return log._cache[key]


def scorable(
    log: RobotLog, t, max_gap_s: float = 0.5, misfit: MisfitRule | None = MisfitRule()
) -> np.ndarray:
    """Boolean mask: ground truth at `t` may be used for scoring (see `exclusions`)."""
    return exclusions(log, max_gap_s, misfit).scorable(t)


def residuals(log: RobotLog, only_scorable: bool = True) -> dict[str, np.ndarray]:
    """Measured minus true range [m] and bearing [rad, wrapped] of every landmark measurement.

    The truth is the interpolated ground-truth pose and the map. Returns arrays t, landmark,
    range (measured), d_range, d_bearing; with `only_scorable`, only at scorable times.
    """
    t = log.meas_t
    x, y, phi = interpolate_truth(log, t)
    dx, dy = log.meas_xy[:, 0] - x, log.meas_xy[:, 1] - y
    d_range = log.meas_range - np.hypot(dx, dy)
    d_bearing = wrap_angle(log.meas_bearing - wrap_angle(np.arctan2(dy, dx) - phi))
    keep = scorable(log, t) if only_scorable else np.isfinite(x)
    return {
        "t": t[keep],
        "landmark": log.meas_landmark[keep],
        "range": log.meas_range[keep],
        "d_range": d_range[keep],
        "d_bearing": d_bearing[keep],
    }


# --------------------------------------------------------------------------------------------
# Spans, segments, cold starts and events
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Span:
    """A time interval [start, end] of a log [s]."""

    start: float
    end: float

    @property
    def duration(self) -> float:
        return self.end - self.start


def split(log: RobotLog, at: float | None = None) -> tuple[Span, Span]:
    """Training and held-out spans: [t_start, at] and [at, t_end] (default `at`: the midpoint).

    Spans, not copies: feed them to `events`, `segments`, `Exclusions.scorable_seconds`. The
    held-out part is to be cold-started at `at` (see `cold_start`), not warmed up on training.
    """
    t0, t1 = log.t_start, log.t_end
    if at is None:
        at = 0.5 * (t0 + t1)
    if not (t0 < at < t1):
        raise ValueError(f"split time {at} s is outside the log ({t0} s .. {t1} s)")
    return Span(t0, float(at)), Span(float(at), t1)


def segments(t0: float, t1: float, length_s: float) -> list[Span]:
    """[t0, t1] cut into n = max(1, round((t1 - t0) / length_s)) equal consecutive segments.

    Each segment is run on its own, cold-started from ground truth at its start (`cold_start`),
    so a single log yields n runs for run-level statistics. They are NOT independent Monte Carlo
    runs: they share one robot, one sensor and its biases, and neighbours are correlated through
    the trajectory; they cover the span exactly once (no overlap, nothing left over).
    """
    if not (math.isfinite(length_s) and length_s > 0):
        raise ValueError(f"segment length must be a positive number of seconds, got {length_s}")
    if not t1 > t0:
        raise ValueError(f"empty span: {t0} s .. {t1} s")
    n = max(1, round((t1 - t0) / length_s))
    edges = np.linspace(t0, t1, n + 1)
    edges[0], edges[-1] = t0, t1
    return [Span(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def cold_start(
    log: RobotLog, t: float, max_gap_s: float = 0.5, misfit: MisfitRule | None = MisfitRule()
) -> tuple[float, np.ndarray]:
    """(t0, pose) to start a filter from ground truth at or after `t`.

    `t` itself when its ground truth is scorable, else the first scorable ground-truth sample
    after it (the start of a segment may fall in a gap or a mis-fit). ValueError if none.
    """
    ex = exclusions(log, max_gap_s, misfit)
    if bool(ex.scorable(t)):
        return float(t), np.array(interpolate_truth(log, t))
    later = log.truth_t[log.truth_t > t]
    ok = np.flatnonzero(ex.scorable(later))
    if not len(ok):
        raise ValueError(f"no scorable ground truth at or after {t} s")
    t0 = float(later[ok[0]])
    return t0, np.array(interpolate_truth(log, t0))


@dataclass(frozen=True, eq=False)
class Events:
    """The events of a log in (t_start, t_end], in time order, as parallel arrays.

    kind[k] is ODOMETRY (a new command; every odometry sample, even when it repeats the last)
    or LANDMARK (one landmark measurement; several may share a stamp). At equal times odometry
    comes first, then measurements in log order. `v`, `w` hold the command IN FORCE AFTER event k
    (zero-order hold: for a measurement, the last odometry sample at or before it); `u_start` is
    the command in force at t_start ((0, 0) before the first odometry sample). For LANDMARK events
    `landmark`, `range`, `bearing` and `landmark_xy` describe the measurement; for ODOMETRY events
    they are -1 / NaN. A filter runs::

        t_prev, u = ev.t_start, ev.u_start
        for k in range(len(ev)):
            predict(u, dt=ev.t[k] - t_prev)        # dt may be 0
            if ev.kind[k] == LANDMARK:
                update((ev.range[k], ev.bearing[k]), ev.landmark_xy[k])
            t_prev, u = ev.t[k], (ev.v[k], ev.w[k])
        predict(u, dt=ev.t_end - t_prev)           # to the end of the span, if wanted
    """

    t_start: float
    t_end: float
    u_start: tuple[float, float]
    t: np.ndarray
    kind: np.ndarray
    v: np.ndarray
    w: np.ndarray
    landmark: np.ndarray
    range: np.ndarray
    bearing: np.ndarray
    landmark_xy: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


def _held_command(log: RobotLog, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k = np.searchsorted(log.odo_t, t, side="right") - 1
    kk = np.maximum(k, 0)
    if len(log.odo_t) == 0:
        return np.zeros(np.shape(t)), np.zeros(np.shape(t))
    v = np.where(k >= 0, log.odo_v[kk], 0.0)
    w = np.where(k >= 0, log.odo_w[kk], 0.0)
    return v, w


def events(log: RobotLog, t_start: float, t_end: float) -> Events:
    """Odometry samples and landmark measurements with t_start < t <= t_end (see `Events`)."""
    if not t_end >= t_start:
        raise ValueError(f"t_end ({t_end}) is before t_start ({t_start})")
    io_ = np.flatnonzero((log.odo_t > t_start) & (log.odo_t <= t_end))
    im = np.flatnonzero((log.meas_t > t_start) & (log.meas_t <= t_end))
    t = np.concatenate([log.odo_t[io_], log.meas_t[im]])
    kind = np.concatenate(
        [np.full(len(io_), ODOMETRY, np.int8), np.full(len(im), LANDMARK, np.int8)]
    )
    order = np.lexsort((kind, t))  # by time, odometry first at equal times; stable otherwise
    t, kind = t[order], kind[order]
    v, w = _held_command(log, t)
    n_odo = len(io_)
    src = order - n_odo  # index into im for measurement events
    is_m = kind == LANDMARK
    landmark = np.full(len(t), -1, np.int64)
    rng = np.full(len(t), np.nan)
    brg = np.full(len(t), np.nan)
    xy = np.full((len(t), 2), np.nan)
    landmark[is_m] = log.meas_landmark[im[src[is_m]]]
    rng[is_m] = log.meas_range[im[src[is_m]]]
    brg[is_m] = log.meas_bearing[im[src[is_m]]]
    xy[is_m] = log.meas_xy[im[src[is_m]]]
    v0, w0 = _held_command(log, np.array([t_start]))
    arrays = dict(t=t, kind=kind, v=v, w=w, landmark=landmark, range=rng, bearing=brg)
    for a in (*arrays.values(), xy):
        a.setflags(write=False)
    return Events(
        t_start=float(t_start),
        t_end=float(t_end),
        u_start=(float(v0[0]), float(w0[0])),
        landmark_xy=xy,
        **arrays,
    )
