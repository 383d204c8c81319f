"""A user's own recorded log (SPEC 9, docs/REAL_DATA.md): four CSV or Parquet files in the
documented schema (`USER_SCHEMA`), read into the same `mrclam.RobotLog` as the MRCLAM data
(`read_user_log`), and a log written in that schema (`write_user_log`). Errors in a file raise
`mrclam.LogError`: one line naming the file, the column and the line; no file content is echoed.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from ..models.angles import wrap_angle
from .mrclam import LogError, RobotLog, _read_parquet, _read_regular_file

# The user-log schema: file stem -> required columns, in order.
USER_SCHEMA = {
    "odometry": ("t", "v", "w"),
    "measurements": ("t", "landmark", "range", "bearing"),
    "landmarks": ("landmark", "x", "y"),
    "groundtruth": ("t", "x", "y", "phi"),
}


def _csv_columns(path: Path, required: tuple[str, ...]) -> tuple[dict[str, list[str]], list[int]]:
    """Required columns of a CSV file with a header line, as text, and each row's line number."""
    raw = _read_regular_file(path)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise LogError(path, "", "is not UTF-8 text") from None
    reader = csv.reader(io.StringIO(text, newline=""), skipinitialspace=True, strict=True)
    header: list[str] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        for row in reader:
            if not row or all(not f.strip() for f in row):
                continue  # blank line
            if header is None:
                header = [f.strip() for f in row]
                header_line = reader.line_num
                continue
            if len(row) != len(header):
                raise LogError(
                    path,
                    f"line {reader.line_num}",
                    f"{len(row)} fields, but the header line has {len(header)}",
                )
            rows.append(row)
            lines.append(reader.line_num)
    except csv.Error:
        raise LogError(path, f"line {reader.line_num}", "is not valid CSV") from None
    if header is None:
        raise LogError(path, "", f"is empty: expected a header line {','.join(required)}")
    _check_header(path, header, required, f"header (line {header_line})")
    if not rows:
        raise LogError(path, "", "has no data rows (only a header line)")
    idx = {name: header.index(name) for name in required}
    return {name: [r[idx[name]] for r in rows] for name in required}, lines


def _check_header(path: Path, header: list[str], required: tuple[str, ...], where: str) -> None:
    for name in required:
        n = header.count(name)
        if n == 0:
            raise LogError(
                path, where, f"missing column '{name}' (required: {', '.join(required)})"
            )
        if n > 1:
            raise LogError(path, where, f"column '{name}' appears more than once")


def _numbers(path: Path, column: str, text: list[str], where) -> np.ndarray:
    """Text values as finite floats; `where(i)` names row i in messages."""
    try:
        values = np.array(text, dtype=float)
    except ValueError:
        for i, s in enumerate(text):
            if not s.strip():
                raise LogError(path, f"column '{column}', {where(i)}", "empty value") from None
            try:
                float(s)
            except ValueError:
                raise LogError(
                    path, f"column '{column}', {where(i)}", "not a number (decimal numbers only)"
                ) from None
        raise  # pragma: no cover - numpy and float() disagree
    _finite(path, column, values, where)
    return values


def _finite(path: Path, column: str, values: np.ndarray, where) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if len(bad):
        raise LogError(
            path, f"column '{column}', {where(int(bad[0]))}", "not finite (nan or inf not allowed)"
        )


def _parquet_columns(path: Path, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    table = _read_parquet(path)
    _check_header(path, table.column_names, required, "columns")
    if table.num_rows == 0:
        raise LogError(path, "", "has no data rows")
    out = {}
    for name in required:
        col = table.column(name)
        if not (pa.types.is_integer(col.type) or pa.types.is_floating(col.type)):
            raise LogError(path, f"column '{name}'", "must be of a numeric (int or float) type")
        if col.null_count:
            first = int(np.flatnonzero(col.is_null().to_numpy(zero_copy_only=False))[0])
            raise LogError(path, f"column '{name}', row {first + 1}", "empty value (null)")
        values = col.to_numpy().astype(float)
        _finite(path, name, values, lambda i: f"row {i + 1}")
        out[name] = values
    return out


def _user_table(
    folder: Path, stem: str
) -> tuple[Path, dict[str, np.ndarray], Callable[[int], str]]:
    required = USER_SCHEMA[stem]
    csv_path, pq_path = folder / f"{stem}.csv", folder / f"{stem}.parquet"
    has_csv, has_pq = os.path.lexists(csv_path), os.path.lexists(pq_path)
    if has_csv and has_pq:
        raise LogError(folder / stem, "", f"both {stem}.csv and {stem}.parquet exist: keep one")
    if not (has_csv or has_pq):
        raise LogError(
            csv_path,
            "",
            f"file not found (need {stem}.csv or {stem}.parquet: {','.join(required)})",
        )
    if has_pq:
        return pq_path, _parquet_columns(pq_path, required), lambda i: f"row {i + 1}"
    text, lines = _csv_columns(csv_path, required)

    def where(i: int) -> str:
        return f"line {lines[i]}"

    return csv_path, {c: _numbers(csv_path, c, text[c], where) for c in required}, where


def _integer_ids(path: Path, column: str, values: np.ndarray, where) -> np.ndarray:
    bad = np.flatnonzero((values != np.rint(values)) | (np.abs(values) > 2**53))
    if len(bad):
        raise LogError(path, f"column '{column}', {where(int(bad[0]))}", "must be an integer id")
    return values.astype(np.int64)


def read_user_log(folder: str | Path) -> RobotLog:
    """Read a user's own log: four tables in `folder`, each `<name>.csv` or `<name>.parquet`.

    odometry (t, v, w), measurements (t, landmark, range, bearing), landmarks (landmark, x, y),
    groundtruth (t, x, y, phi); SI units, radians, one time base in seconds (kept as is:
    `t_origin` = 0). CSV: comma-separated, a header line naming the columns (any order; extra
    columns are ignored), then one row per line. Rules (docs/REAL_DATA.md): every value a finite
    number; odometry and ground-truth times strictly increasing, measurement times non-decreasing;
    landmark ids integers, unique in the map, and every measured landmark in the map; range >= 0;
    bearing in [-pi, pi]; heading any finite value (wrapped on load). A broken rule raises a
    one-line `LogError` naming the file, the column and the line (CSV) or row (Parquet).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise LogError(folder, "", "no such folder (expected a folder holding the four tables)")
    tables = {stem: _user_table(folder, stem) for stem in USER_SCHEMA}

    path, odo, where = tables["odometry"]
    bad = np.flatnonzero(np.diff(odo["t"]) <= 0)
    if len(bad):
        raise LogError(
            path, f"column 't', {where(int(bad[0]) + 1)}", "times must strictly increase"
        )

    path, truth, where = tables["groundtruth"]
    bad = np.flatnonzero(np.diff(truth["t"]) <= 0)
    if len(bad):
        raise LogError(
            path, f"column 't', {where(int(bad[0]) + 1)}", "times must strictly increase"
        )

    lm_path, lm, lm_where = tables["landmarks"]
    ids = _integer_ids(lm_path, "landmark", lm["landmark"], lm_where)
    order = np.argsort(ids, kind="stable")
    dup = np.flatnonzero(np.diff(ids[order]) == 0)
    if len(dup):
        raise LogError(
            lm_path, f"column 'landmark', {lm_where(int(order[dup[0] + 1]))}", "id listed twice"
        )

    path, meas, where = tables["measurements"]
    bad = np.flatnonzero(np.diff(meas["t"]) < 0)
    if len(bad):
        raise LogError(
            path, f"column 't', {where(int(bad[0]) + 1)}", "times must not decrease (sort by t)"
        )
    landmark = _integer_ids(path, "landmark", meas["landmark"], where)
    missing = np.flatnonzero(~np.isin(landmark, ids))
    if len(missing):
        raise LogError(
            path,
            f"column 'landmark', {where(int(missing[0]))}",
            f"landmark id not in {lm_path.name} (every measured landmark must be in the map)",
        )
    bad = np.flatnonzero(meas["range"] < 0)
    if len(bad):
        raise LogError(path, f"column 'range', {where(int(bad[0]))}", "must be >= 0 (metres)")
    bad = np.flatnonzero(np.abs(meas["bearing"]) > math.pi + 1e-9)
    if len(bad):
        raise LogError(
            path, f"column 'bearing', {where(int(bad[0]))}", "must be radians in [-pi, pi]"
        )

    return RobotLog(
        name=folder.name,
        t_origin=0.0,
        odo_t=odo["t"],
        odo_v=odo["v"],
        odo_w=odo["w"],
        meas_t=meas["t"],
        meas_landmark=landmark,
        meas_range=meas["range"],
        meas_bearing=meas["bearing"],
        landmark_id=ids[order],
        landmark_x=lm["x"][order],
        landmark_y=lm["y"][order],
        truth_t=truth["t"],
        truth_x=truth["x"],
        truth_y=truth["y"],
        truth_phi=wrap_angle(truth["phi"]),
    )


def write_user_log(log: RobotLog, folder: str | Path, fmt: str = "csv") -> Path:
    """Write `log` in the user-log schema (`fmt` "csv" or "parquet"); times as in the log.

    Floats are written with full (round-trip) precision, so `read_user_log` gives back the same
    arrays. Handy as a template: `write_user_log(load_builtin(), "my-log")`.
    """
    if fmt not in ("csv", "parquet"):
        raise ValueError(f"fmt must be 'csv' or 'parquet', got {fmt!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    frames = {
        "odometry": pd.DataFrame({"t": log.odo_t, "v": log.odo_v, "w": log.odo_w}),
        "measurements": pd.DataFrame(
            {
                "t": log.meas_t,
                "landmark": log.meas_landmark,
                "range": log.meas_range,
                "bearing": log.meas_bearing,
            }
        ),
        "landmarks": pd.DataFrame(
            {"landmark": log.landmark_id, "x": log.landmark_x, "y": log.landmark_y}
        ),
        "groundtruth": pd.DataFrame(
            {"t": log.truth_t, "x": log.truth_x, "y": log.truth_y, "phi": log.truth_phi}
        ),
    }
    for stem, df in frames.items():
        if fmt == "csv":
            df.to_csv(folder / f"{stem}.csv", index=False, float_format="%.17g")
        else:
            df.to_parquet(folder / f"{stem}.parquet", index=False, compression="zstd")
    return folder
