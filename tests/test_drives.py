"""The eleven built-in drives (MRCLAM Datasets 6 and 7, Robots 1-5, and Dataset 9 Robot 3):
the shipped copies, the cleaning, and data checks against ground truth and each dataset's map."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from anfekf_bench.sources import mrclam as m

SHARED = Path(os.environ.get("ANFEKF_MRCLAM_SHARED_ROOT", "/work/shared/data"))
needs_shared = pytest.mark.skipif(
    not (SHARED / "utias-mrclam-dataset6" / "Robot1_Groundtruth.dat").is_file(),
    reason="shared MRCLAM Dataset 6/7 originals not available",
)

# drive: (odometry, landmark measurements, ground truth, dropped other robots, dropped misread
# barcodes, dropped repeated odometry stamps), after cleaning. The raw row counts are those of
# shared/data/utias-mrclam-datasets-6-7-PROVENANCE.md.
COUNTS = {
    "d6-r1": (61_785, 1_534, 49_241, 407, 1, 0),
    "d6-r2": (65_004, 3_239, 59_705, 792, 0, 1),
    "d6-r3": (61_150, 4_348, 56_977, 1_277, 2, 8),
    "d6-r4": (52_906, 2_023, 61_714, 373, 3, 10),
    "d6-r5": (60_563, 4_239, 57_467, 1_139, 0, 4),
    "d7-r1": (58_598, 2_578, 58_389, 650, 0, 0),
    "d7-r2": (60_932, 3_818, 56_529, 700, 0, 4),
    "d7-r3": (55_078, 4_425, 53_545, 965, 9, 7),
    "d7-r4": (62_200, 1_822, 63_081, 555, 0, 7),
    "d7-r5": (59_776, 3_424, 58_414, 1_336, 0, 11),
    "d9-r3": (11_524, 5_114, 125_925, 1_053, 0, 0),
}
RAW_ROWS = {  # (odometry, measurement) rows of the original files
    "d6-r1": (61_785, 1_942), "d6-r2": (65_005, 4_031), "d6-r3": (61_158, 5_627),
    "d6-r4": (52_916, 2_399), "d6-r5": (60_567, 5_378), "d7-r1": (58_598, 3_228),
    "d7-r2": (60_936, 4_518), "d7-r3": (55_085, 5_399), "d7-r4": (62_207, 2_377),
    "d7-r5": (59_787, 4_760), "d9-r3": (11_524, 6_167),
}  # fmt: skip


@pytest.fixture(scope="module")
def logs() -> dict[str, m.RobotLog]:
    return {d: m.load_drive(d) for d in m.DRIVES}


def robust_std(x: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def test_eleven_drives_on_three_maps(logs):
    assert len(m.DRIVES) == 11
    assert {m.drive_dataset(d) for d in m.DRIVES} == {6, 7, 9}
    maps = {
        m.drive_dataset(d): np.column_stack([lg.landmark_x, lg.landmark_y])
        for d, lg in logs.items()
    }
    for d, lg in logs.items():  # every robot of a dataset reads that dataset's map
        assert lg.landmark_id.tolist() == list(range(6, 21))
        assert np.array_equal(np.column_stack([lg.landmark_x, lg.landmark_y]), maps[lg_ds(d)])
    assert not np.allclose(maps[6], maps[7])  # the landmarks were placed anew: never mixed
    with pytest.raises(ValueError, match="unknown drive"):
        m.load_drive("d8-r1")


def lg_ds(drive: str) -> int:
    return m.drive_dataset(drive)


@pytest.mark.parametrize("drive", list(m.DRIVES))
def test_counts_after_cleaning(logs, drive):
    lg = logs[drive]
    c = lg.counts()
    odo, meas, truth, robots, unknown, repeated = COUNTS[drive]
    assert (c["odometry"], c["measurements"], c["groundtruth"]) == (odo, meas, truth)
    assert (c["dropped_robot"], c["dropped_unknown"], c["dropped_odometry"]) == (
        robots,
        unknown,
        repeated,
    )
    raw_odo, raw_meas = RAW_ROWS[drive]
    assert odo + repeated == raw_odo
    assert meas + robots + unknown == raw_meas
    assert set(np.unique(lg.meas_landmark)) <= set(range(6, 21))
    assert np.all(np.diff(lg.odo_t) > 0) and np.all(np.diff(lg.meas_t) >= 0)
    assert lg.t_start == 0.0


@pytest.mark.parametrize("drive", list(m.DRIVES))
def test_residual_spreads_against_truth_and_map(logs, drive):
    """Range and bearing residuals against interpolated Vicon and the drive's own map: medians
    within a band (range: |error| median 5-15 cm, signed median within +-7 cm; bearing: |error|
    median 0.003-0.03 rad, signed median within +-0.025 rad, Dataset 9's -0.021 rad bias
    included; robust std 5-20 cm and 0.004-0.02 rad). The wrong map would miss by metres."""
    res = m.residuals(logs[drive])
    dr, db = res["d_range"], res["d_bearing"]
    assert len(dr) > 1_000
    assert 0.05 <= np.median(np.abs(dr)) <= 0.15
    assert abs(np.median(dr)) <= 0.07
    assert 0.05 <= robust_std(dr) <= 0.20
    assert 0.003 <= np.median(np.abs(db)) <= 0.03
    assert abs(np.median(db)) <= 0.025
    assert 0.004 <= robust_std(db) <= 0.02


def test_where_ground_truth_is_missing(logs):
    """Dataset 6 Robot 1's Vicon ends 128 s before its odometry; Dataset 6 Robot 4 has a 2 s
    gap (and one of 0.5 s); nothing of Datasets 6 and 7 is a detected mis-fit."""
    r1 = logs["d6-r1"]
    assert r1.odo_t[-1] - r1.t_end == pytest.approx(128.127, abs=1e-3)
    ex = m.exclusions(r1)
    assert not ex.scorable(r1.odo_t[r1.odo_t > r1.t_end]).any()
    gaps = m.exclusions(logs["d6-r4"]).gaps
    assert len(gaps) == 2 and gaps[1, 1] - gaps[1, 0] == pytest.approx(2.03, abs=0.01)
    for d in m.DRIVES:
        if d != "d9-r3":
            assert len(m.exclusions(logs[d]).misfits) == 0, d
            if d != "d6-r4":
                assert len(m.exclusions(logs[d]).gaps) == 0, d


def test_shipped_copies_are_compact_and_documented():
    total = 0
    for d in m.DRIVE_DATASETS:
        folder = m.drive_folder(f"d{d}-r1").parent
        for r in range(1, 6):
            files = sorted(p.name for p in (folder / f"robot{r}").glob("*.parquet"))
            assert files == sorted(f"{n}.parquet" for n in m.PARQUET_SCHEMAS)
            total += sum(p.stat().st_size for p in (folder / f"robot{r}").glob("*.parquet"))
        sha = m.provenance_sha256(folder / "PROVENANCE.md")
        assert len(sha) == 17  # Barcodes, Landmark_Groundtruth and 3 files per robot
        text = (folder / "PROVENANCE.md").read_text(encoding="utf-8")
        assert "Leung" in text and "regenerate_drive_copies" in text
    assert total < 20_000_000


def test_package_data_ships_the_drive_folders():
    text = (Path(__file__).parents[1] / "pyproject.toml").read_text(encoding="utf-8")
    assert '"data/*/*/*.parquet"' in text


@needs_shared
def test_copy_equals_the_originals_d6_r1(logs):
    """The copy is lossless (nothing thinned): the loader gives exactly what read_mrclam gives
    on the original .dat files, so ground truth at any scoring time is the originals' (0 mm)."""
    orig = m.read_mrclam(SHARED / "utias-mrclam-dataset6", robot=1)
    _same(orig, logs["d6-r1"])


# `make test` regenerates Dataset 6's five drives, `make test-all` (heavy) both datasets' ten.
@needs_shared
@pytest.mark.slow
@pytest.mark.parametrize(
    "datasets", [(6,), pytest.param((6, 7), marks=pytest.mark.heavy)], ids=["dataset6", "both"]
)
def test_regenerated_copies_match_shipped_and_checksums(tmp_path, datasets):
    found = m.regenerate_drive_copies(SHARED, tmp_path, datasets=datasets)
    want = [d for d, (ds, _) in m.DRIVES.items() if ds in datasets]
    assert sorted(found) == sorted(want) and len(found) == 5 * len(datasets)
    for drive in found:
        ds, r = m.DRIVES[drive]
        for name in m.PARQUET_SCHEMAS:
            new = m.read_parquet_tables(tmp_path / f"mrclam-dataset{ds}" / f"robot{r}")[name]
            old = m.read_parquet_tables(m.drive_folder(drive))[name]
            assert new.equals(old), (drive, name)


@needs_shared
def test_regenerate_refuses_a_changed_original(tmp_path):
    """One changed digit in an original: the SHA-256 check against PROVENANCE.md refuses it."""
    src = tmp_path / "shared" / "utias-mrclam-dataset6"
    src.mkdir(parents=True)
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat", "Robot1_Odometry.dat",
                 "Robot1_Groundtruth.dat"):  # fmt: skip
        (src / name).write_bytes((SHARED / "utias-mrclam-dataset6" / name).read_bytes())
    text = (SHARED / "utias-mrclam-dataset6" / "Robot1_Measurement.dat").read_text()
    lines = text.splitlines(keepends=True)
    lines[10] = lines[10].replace("\t", " \t", 1)  # same numbers, other bytes
    (src / "Robot1_Measurement.dat").write_text("".join(lines))
    with pytest.raises(m.LogError, match="Robot1_Measurement.dat: SHA-256 differs"):
        m.regenerate_drive_copies(tmp_path / "shared", tmp_path / "out", datasets=(6,))


def _same(a: m.RobotLog, b: m.RobotLog) -> None:
    for name in m.RobotLog.__dataclass_fields__:
        if name in ("name", "_cache"):
            continue
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y), name
        else:
            assert x == y, name
