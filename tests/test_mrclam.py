"""Recorded logs: the built-in MRCLAM copy, its cleaning, ground-truth quality, user logs."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from anfekf_bench.models import wrap_angle
from anfekf_bench.sources import mrclam as m
from anfekf_bench.sources import user_log
from anfekf_bench.sources.mrclam import LogError, RobotLog

SHARED = Path(
    os.environ.get("ANFEKF_MRCLAM_SHARED", "/work/shared/data/utias-mrclam-dataset9-robot3")
)
needs_shared = pytest.mark.skipif(
    not (SHARED / "Groundtruth.dat").is_file(), reason="shared MRCLAM originals not available"
)

# Reference levels from the Dataset 9 research notes.
NOTES_GAP_STARTS = [158, 161, 350, 359, 374, 401, 950, 969, 989]
NOTES_MISFITS = [(356.1, 358.8), (757.2, 836.2), (991.0, 1046.0)]


@pytest.fixture(scope="module")
def log() -> RobotLog:
    return m.load_builtin()


def robust_std(x: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


# ------------------------------------------------------------------ the built-in copy


def test_counts_after_cleaning(log):
    c = log.counts()
    assert c == {
        "odometry": 11_524,
        "measurements": 5_114,
        "landmarks": 15,
        "groundtruth": 125_925,
        "dropped_robot": 1_053,
        "dropped_unknown": 0,
        "dropped_odometry": 0,
    }
    assert c["measurements"] + c["dropped_robot"] + c["dropped_unknown"] == 6_167
    assert log.landmark_id.tolist() == list(range(6, 21))
    assert set(np.unique(log.meas_landmark)) <= set(range(6, 21))
    assert np.all(np.diff(log.meas_t) >= 0)
    assert len(np.unique(log.meas_t)) == 4_535
    assert log.t_origin == pytest.approx(1288971842.054, abs=1e-6)
    assert (log.t_start, log.t_end) == (0.0, pytest.approx(1386.995, abs=1e-9))
    assert np.all(np.abs(log.truth_phi) <= math.pi)
    assert not log.odo_t.flags.writeable and not log.truth_x.flags.writeable


def test_shipped_copy_is_compact_and_documented():
    folder = m.builtin_folder()
    sizes = {p.name: p.stat().st_size for p in folder.glob("*.parquet")}
    assert set(sizes) == {f"{n}.parquet" for n in m.PARQUET_SCHEMAS}
    assert sum(sizes.values()) < 4_000_000
    text = (folder / "PROVENANCE.md").read_text(encoding="utf-8")
    assert "Leung" in text and "Dataset 9" in text and "convert_mrclam_to_parquet" in text


@needs_shared
def test_builtin_equals_the_originals(log):
    orig = m.read_mrclam(SHARED)
    for name in RobotLog.__dataclass_fields__:
        if name in ("name", "_cache"):
            continue
        a, b = getattr(orig, name), getattr(log, name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name


@needs_shared
def test_conversion_reproduces_the_shipped_tables(tmp_path):
    sums = m.convert_mrclam_to_parquet(SHARED, tmp_path)
    shipped = m.builtin_folder()
    for name in m.PARQUET_SCHEMAS:
        new = pq.read_table(tmp_path / f"{name}.parquet")
        old = pq.read_table(shipped / f"{name}.parquet")
        assert new.equals(old), name
    provenance = (shipped / "PROVENANCE.md").read_text(encoding="utf-8")
    for file, digest in sums.items():
        assert re.search(rf"{re.escape(file)} \|[^|]*\| {digest}", provenance), file


def test_read_mrclam_maps_barcodes_and_drops_robots(tmp_path):
    hdr = "# UTIAS\n# test\n# format\n# columns\n"
    (tmp_path / "Barcodes.dat").write_text(hdr + "1 5\n2 14\n3 41\n6 63\n7 25\n")
    (tmp_path / "Landmark_Groundtruth.dat").write_text(hdr + "6 1.0 2.0 0 0\n7 -1.0 0.5 0 0\n")
    (tmp_path / "Odometry.dat").write_text(hdr + "100.100 0.1 0.0\n100.200 0.1 0.5\n")
    (tmp_path / "Groundtruth.dat").write_text(
        hdr + "100.000 0 0 3.0\n100.050 0 0 3.1\n100.300 0 0 -3.1\n"
    )
    # barcode 14 = robot 2, 99 unknown, 63 / 25 = landmarks 6 / 7; the 2nd column is a BARCODE
    (tmp_path / "Measurement.dat").write_text(
        hdr + "100.150 63 1.5 0.1\n100.150 14 2.0 0.2\n100.150 99 1.0 0.0\n100.250 25 3.0 -0.3\n"
    )
    out = m.read_mrclam(tmp_path)
    assert out.meas_landmark.tolist() == [6, 7]
    assert out.meas_range.tolist() == [1.5, 3.0]
    assert (out.dropped_robot, out.dropped_unknown) == (1, 1)
    assert out.t_origin == pytest.approx(100.0)
    np.testing.assert_allclose(out.meas_t, [0.15, 0.25])
    np.testing.assert_allclose(out.odo_t, [0.1, 0.2])

    (tmp_path / "Odometry.dat").write_text(hdr + "100.100 0.1 0.0\n100.200 0.1\n")
    with pytest.raises(LogError, match=r"Odometry\.dat: line 6: 2 fields, expected 3"):
        m.read_mrclam(tmp_path)


# ------------------------------------------------------------------ ground-truth quality


def test_vicon_gaps(log):
    ex = m.exclusions(log)
    assert len(ex.gaps) == 9
    assert ex.gap_seconds == pytest.approx(39.2, abs=0.05)
    assert [round(a) for a in ex.gaps[:, 0]] == NOTES_GAP_STARTS
    assert np.max(ex.gaps[:, 1] - ex.gaps[:, 0]) == pytest.approx(7.53, abs=0.01)


def test_vicon_misfits_near_the_notes(log):
    ex = m.exclusions(log)
    assert len(ex.misfits) == 3
    for (a, b), (na, nb) in zip(ex.misfits, NOTES_MISFITS, strict=True):
        assert abs(a - na) < 0.5 and abs(b - nb) < 0.5
    assert ex.misfit_seconds == pytest.approx(136.7, abs=2.0)
    # deterministic and not fragile: a slightly different window finds the same intervals
    other = m.find_misfits(log, m.MisfitRule(window_s=0.3))
    np.testing.assert_allclose(other, ex.misfits, atol=0.5)


def test_no_scorable_time_inside_a_gap_or_outside_the_span(log):
    ex = m.exclusions(log)
    rng = np.random.default_rng(3)
    for a, b in ex.gaps:
        inside = np.concatenate([rng.uniform(a, b, 200), [a + 1e-6, b - 1e-6]])
        assert not m.scorable(log, inside).any()
    assert not m.scorable(log, np.array([-0.01, log.t_end + 0.01])).any()
    assert m.scorable(log, log.t_start)
    t = rng.uniform(log.t_start, log.t_end, 20_000)
    ok = m.scorable(log, t)
    i = np.searchsorted(log.truth_t, t, side="right") - 1
    bracket = log.truth_t[np.minimum(i + 1, len(log.truth_t) - 1)] - log.truth_t[i]
    assert np.all(bracket[ok] <= 0.5)
    for a, b in ex.misfits:
        assert not ok[(t >= a) & (t <= b)].any()


def test_scorable_evaluation_stamps_per_half(log):
    train, test = m.split(log, 693.5)
    ex = m.exclusions(log)
    counts = []
    for span in (train, test):
        stamps = log.odo_t[(log.odo_t >= span.start) & (log.odo_t < span.end)]
        counts.append((int(ex.scorable(stamps).sum()), len(stamps)))
    assert counts[0][1] == 5_765 and abs(counts[0][0] - 5_558) <= 10
    assert counts[1][1] == 5_759 and abs(counts[1][0] - 4_508) <= 10
    assert ex.scorable_seconds(test.start, test.end) == pytest.approx(541, abs=5)


def test_measured_noise_levels(log):
    r = m.residuals(log)
    assert 4_300 <= len(r["t"]) <= 4_600
    assert robust_std(r["d_range"]) == pytest.approx(0.097, rel=0.2)
    assert robust_std(r["d_bearing"]) == pytest.approx(0.014, rel=0.2)
    assert np.median(r["d_bearing"]) == pytest.approx(-0.021, abs=0.004)
    assert np.max(np.abs(r["d_bearing"])) < 0.2  # once the mis-fits are out
    # with the gaps but not the mis-fits removed, heavy bearing outliers remain
    everything = m.residuals(log, only_scorable=False)
    gaps_only = m.scorable(log, everything["t"], misfit=None)
    assert np.quantile(everything["d_bearing"][gaps_only], 0.99) > 1.0


# ------------------------------------------------------------------ interpolation


def _tiny_log(truth_phi, truth_t=(0.0, 1.0, 2.0), **extra) -> RobotLog:
    n = len(truth_t)
    fields = dict(
        name="tiny",
        t_origin=0.0,
        odo_t=[0.5, 1.5],
        odo_v=[0.1, 0.2],
        odo_w=[0.0, 0.5],
        meas_t=[0.5, 1.5, 1.5],
        meas_landmark=[1, 2, 1],
        meas_range=[1.0, 2.0, 3.0],
        meas_bearing=[0.1, -0.2, 0.3],
        landmark_id=[1, 2],
        landmark_x=[1.0, 2.0],
        landmark_y=[0.0, 1.0],
        truth_t=truth_t,
        truth_x=np.arange(n, dtype=float),
        truth_y=np.zeros(n),
        truth_phi=truth_phi,
    )
    fields.update(extra)
    return RobotLog(**fields)


def test_heading_interpolation_across_the_wrap():
    tiny = _tiny_log([3.0, -3.0, -2.5])  # turning left through +pi
    x, y, phi = m.interpolate_truth(tiny, np.array([0.5, 0.25, 1.5]))
    assert abs(phi[0]) == pytest.approx(math.pi, abs=1e-9)  # through pi, not through 0
    assert phi[1] == pytest.approx(3.0 + 0.25 * (2 * math.pi - 6.0))
    assert phi[2] == pytest.approx(-2.75)
    np.testing.assert_allclose(x, [0.5, 0.25, 1.5])
    right = _tiny_log([-3.0, 3.0, 2.5])  # turning right through -pi
    assert abs(m.interpolate_truth(right, 0.5)[2]) == pytest.approx(math.pi, abs=1e-9)
    assert all(math.isnan(v) for v in m.interpolate_truth(tiny, 2.5))


def test_interpolation_hits_the_samples(log):
    i = np.arange(0, len(log.truth_t), 997)
    x, y, phi = m.interpolate_truth(log, log.truth_t[i])
    np.testing.assert_allclose(x, log.truth_x[i], atol=1e-12)
    np.testing.assert_allclose(y, log.truth_y[i], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(phi - log.truth_phi[i]), 0, atol=1e-9)


# ------------------------------------------------------------------ spans and events


def test_split_segments_and_cold_start(log):
    train, test = m.split(log)
    assert train.end == test.start == pytest.approx(693.4975)
    segs = m.segments(test.start, test.end, 60.0)
    assert len(segs) == 12
    assert segs[0].start == test.start and segs[-1].end == test.end
    assert all(a.end == b.start for a, b in zip(segs[:-1], segs[1:], strict=True))
    assert all(s.duration == pytest.approx(test.duration / 12) for s in segs)
    assert len(m.segments(0.0, 10.0, 60.0)) == 1
    with pytest.raises(ValueError):
        m.split(log, 2000.0)

    gap = m.exclusions(log).gaps[4]  # 374.4 .. 381.9 s
    t0, pose = m.cold_start(log, gap[0] + 1.0)
    assert t0 == pytest.approx(gap[1]) and m.scorable(log, t0)
    np.testing.assert_allclose(pose, m.interpolate_truth(log, t0))
    t0, _ = m.cold_start(log, 100.0)
    assert t0 == 100.0


def test_events_hold_the_command_and_partition(log):
    ev = m.events(log, -1.0, log.t_end)
    assert len(ev) == 11_524 + 5_114
    assert np.all(np.diff(ev.t) >= 0)
    odo = ev.kind == m.ODOMETRY
    np.testing.assert_array_equal(ev.t[odo], log.odo_t)
    np.testing.assert_array_equal(ev.v[odo], log.odo_v)
    lmk = ~odo
    np.testing.assert_array_equal(ev.landmark[lmk], log.meas_landmark)
    np.testing.assert_array_equal(ev.range[lmk], log.meas_range)
    # a measurement carries the last odometry command at or before it (zero-order hold)
    k = np.searchsorted(log.odo_t, ev.t[lmk], side="right") - 1
    np.testing.assert_array_equal(ev.w[lmk], np.where(k >= 0, log.odo_w[np.maximum(k, 0)], 0.0))
    assert ev.u_start == (0.0, 0.0)

    # consecutive spans partition the events; u_start is the command held at the start
    a, b = m.events(log, 100.0, 400.0), m.events(log, 400.0, 700.0)
    whole = m.events(log, 100.0, 700.0)
    np.testing.assert_array_equal(np.concatenate([a.t, b.t]), whole.t)
    j = np.searchsorted(log.odo_t, 400.0, side="right") - 1
    assert b.u_start == (log.odo_v[j], log.odo_w[j])
    assert a.v[-1] == b.u_start[0] and a.w[-1] == b.u_start[1]


def test_events_order_at_equal_times():
    tiny = _tiny_log([0.0, 0.1, 0.2])
    ev = m.events(tiny, 0.0, 2.0)
    assert ev.kind.tolist() == [m.ODOMETRY, m.LANDMARK, m.ODOMETRY, m.LANDMARK, m.LANDMARK]
    assert ev.landmark.tolist() == [-1, 1, -1, 2, 1]
    assert ev.w.tolist() == [0.0, 0.0, 0.5, 0.5, 0.5]
    np.testing.assert_array_equal(ev.landmark_xy[3], [2.0, 1.0])
    assert np.isnan(ev.range[0]) and ev.range[4] == 3.0


# ------------------------------------------------------------------ user logs


def _write_user_csv(folder: Path, *, extra_column: bool = False) -> dict[str, pd.DataFrame]:
    """A small log in the documented schema, written the way a user would."""
    folder.mkdir(parents=True, exist_ok=True)
    t = np.round(np.arange(0.0, 20.0, 0.1), 3)
    phi = np.unwrap(0.3 * t + 2.5)  # passes through +pi
    tables = {
        "odometry": pd.DataFrame({"t": t[::2] + 0.01, "v": 0.2, "w": 0.3}),
        "landmarks": pd.DataFrame({"landmark": [4, 2, 9], "x": [1.0, -2.0, 0.5], "y": [3, 1, -1]}),
        "measurements": pd.DataFrame(
            {
                "t": [0.5, 0.5, 3.25, 7.0],
                "landmark": [2, 9, 4, 2],
                "range": [1.25, 2.5, 0.75, 3.0],
                "bearing": [0.1, -1.2, 3.0, -0.4],
            }
        ),
        "groundtruth": pd.DataFrame(
            {"t": t, "x": np.cos(0.3 * t), "y": np.sin(0.3 * t), "phi": phi}
        ),
    }
    for name, df in tables.items():
        out = df[df.columns[::-1]] if name == "landmarks" else df  # any column order
        if extra_column:
            out = out.assign(note=1)
        out.to_csv(folder / f"{name}.csv", index=False, float_format="%.17g")
    return tables


def test_user_log_loads_and_round_trips(tmp_path):
    src = _write_user_csv(tmp_path / "mine", extra_column=True)
    log = user_log.read_user_log(tmp_path / "mine")
    assert log.name == "mine" and log.t_origin == 0.0
    np.testing.assert_array_equal(log.odo_t, src["odometry"]["t"])
    np.testing.assert_array_equal(log.landmark_id, [2, 4, 9])
    np.testing.assert_array_equal(log.landmark_x, [-2.0, 1.0, 0.5])
    np.testing.assert_array_equal(log.meas_landmark, [2, 9, 4, 2])
    np.testing.assert_array_equal(log.meas_xy[1], [0.5, -1.0])
    np.testing.assert_allclose(log.truth_phi, wrap_angle(src["groundtruth"]["phi"]))
    assert np.all(np.abs(log.truth_phi) <= math.pi)

    for fmt in ("csv", "parquet"):
        back = user_log.read_user_log(user_log.write_user_log(log, tmp_path / f"again-{fmt}", fmt))
        for name in RobotLog.__dataclass_fields__:
            a, b = getattr(log, name), getattr(back, name)
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b, err_msg=f"{fmt}: {name}")


@pytest.mark.slow
def test_builtin_round_trips_through_the_user_schema(tmp_path, log):
    back = user_log.read_user_log(user_log.write_user_log(log, tmp_path / "d9", "csv"))
    np.testing.assert_array_equal(back.truth_phi, log.truth_phi)
    np.testing.assert_array_equal(back.meas_bearing, log.meas_bearing)
    np.testing.assert_allclose(m.exclusions(back).misfits, m.exclusions(log).misfits)


SECRET = "s3cr3t"


def _edit(folder: Path, file: str, old: str, new: str) -> None:
    path = folder / file
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def _set_cell(folder: Path, file: str, row: int, column: str, value: str) -> None:
    path = folder / file
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    fields = lines[row + 1].split(",")
    fields[header.index(column)] = value
    lines[row + 1] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")


MALFORMED = {
    "missing file": (lambda d: (d / "landmarks.csv").unlink(), "landmarks.csv", "file not found"),
    "missing column": (
        lambda d: _edit(d, "odometry.csv", "t,v,w", "t,v,omega"),
        "odometry.csv",
        "missing column 'w'",
    ),
    "non-numeric": (
        lambda d: _set_cell(d, "groundtruth.csv", 3, "x", SECRET),
        "groundtruth.csv",
        "column 'x', line 5: not a number",
    ),
    "empty value": (
        lambda d: _set_cell(d, "odometry.csv", 0, "v", ""),
        "odometry.csv",
        "column 'v', line 2: empty value",
    ),
    "nan": (
        lambda d: _set_cell(d, "measurements.csv", 1, "range", "nan"),
        "measurements.csv",
        "column 'range', line 3: not finite",
    ),
    "inf": (
        lambda d: _set_cell(d, "groundtruth.csv", 0, "phi", "-inf"),
        "groundtruth.csv",
        "column 'phi', line 2: not finite",
    ),
    "time not increasing": (
        lambda d: _set_cell(d, "odometry.csv", 4, "t", "0.01"),
        "odometry.csv",
        "column 't', line 6: times must strictly increase",
    ),
    "duplicate truth time": (
        lambda d: _set_cell(d, "groundtruth.csv", 1, "t", "0"),
        "groundtruth.csv",
        "column 't', line 3: times must strictly increase",
    ),
    "measurement times decrease": (
        lambda d: _set_cell(d, "measurements.csv", 3, "t", "1"),
        "measurements.csv",
        "column 't', line 5: times must not decrease",
    ),
    "landmark not in map": (
        lambda d: _set_cell(d, "measurements.csv", 2, "landmark", "77"),
        "measurements.csv",
        "column 'landmark', line 4: landmark id not in landmarks.csv",
    ),
    "landmark id not integer": (
        lambda d: _set_cell(d, "landmarks.csv", 0, "landmark", "4.5"),
        "landmarks.csv",
        "column 'landmark', line 2: must be an integer id",
    ),
    "duplicate landmark": (
        lambda d: _set_cell(d, "landmarks.csv", 2, "landmark", "4"),
        "landmarks.csv",
        "id listed twice",
    ),
    "negative range": (
        lambda d: _set_cell(d, "measurements.csv", 0, "range", "-1"),
        "measurements.csv",
        "column 'range', line 2: must be >= 0",
    ),
    "bearing in degrees": (
        lambda d: _set_cell(d, "measurements.csv", 0, "bearing", "45"),
        "measurements.csv",
        "column 'bearing', line 2: must be radians",
    ),
    "header only": (
        lambda d: (d / "measurements.csv").write_text("t,landmark,range,bearing\n"),
        "measurements.csv",
        "no data rows",
    ),
    "empty file": (lambda d: (d / "odometry.csv").write_text(""), "odometry.csv", "is empty"),
    "ragged row": (
        lambda d: _edit(d, "landmarks.csv", "\n", f"\n{SECRET},1,2,3\n"),
        "landmarks.csv",
        "line 2: 4 fields, but the header line has 3",
    ),
    "not utf-8": (
        lambda d: (d / "landmarks.csv").write_bytes(b"landmark,x,y\n\xff\xfe,1,2\n"),
        "landmarks.csv",
        "not UTF-8",
    ),
    "directory": (
        lambda d: ((d / "odometry.csv").unlink(), (d / "odometry.csv").mkdir()),
        "odometry.csv",
        "not a regular file",
    ),
    "fifo": (
        lambda d: ((d / "groundtruth.csv").unlink(), os.mkfifo(d / "groundtruth.csv")),
        "groundtruth.csv",
        "not a regular file",
    ),
    "csv and parquet": (
        lambda d: pd.DataFrame({"t": [0.0], "v": [0.0], "w": [0.0]}).to_parquet(
            d / "odometry.parquet"
        ),
        "odometry",
        "both odometry.csv and odometry.parquet",
    ),
    "parquet of text": (
        lambda d: (
            (d / "odometry.csv").unlink(),
            pd.DataFrame({"t": [0.0, 1.0], "v": ["a", SECRET], "w": [0.0, 0.0]}).to_parquet(
                d / "odometry.parquet"
            ),
        ),
        "odometry.parquet",
        "column 'v': must be of a numeric",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_user_log_gives_one_line(tmp_path, case):
    if case == "fifo" and not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    folder = tmp_path / "bad"
    _write_user_csv(folder)
    mutate, file, message = MALFORMED[case]
    mutate(folder)
    with pytest.raises(LogError) as info:
        user_log.read_user_log(folder)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(str(folder / file)), text
    assert message in text, text
    assert SECRET not in text


def test_missing_folder(tmp_path):
    with pytest.raises(LogError, match="no such folder"):
        user_log.read_user_log(tmp_path / "nope")
