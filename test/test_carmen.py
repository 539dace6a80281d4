"""CARMEN log parser: exact values, counts, malformed lines, strict mode, gzip, the real logs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from carmen_log import LOG_LINES, MALFORMED_LINES, write_log

from ptm_ros.errors import DataError
from ptm_ros.io.carmen import (
    FLASER,
    ODOM,
    ROBOTLASER1,
    LaserRecord,
    OdomRecord,
    ParseReport,
    flaser_angles,
    iter_records,
    odometry_track,
    parse_line,
    read_log,
)

COUNTS = {
    "comment": 2,
    "PARAM": 1,
    "blank": 1,
    "ODOM": 2,
    "FLASER": 2,
    "NEFF": 1,
    "ROBOTLASER1": 1,
    "SYNC": 1,
}


@pytest.fixture
def log_path(tmp_path: Path) -> Path:
    return write_log(tmp_path / "test.clf")


def check_log(log) -> None:
    rep = log.report
    assert rep.lines == 17
    assert rep.counts == COUNTS
    assert [m.line for m in rep.malformed] == MALFORMED_LINES
    assert [m.kind for m in rep.malformed] == [FLASER, ODOM, FLASER, ODOM, ROBOTLASER1, FLASER]
    assert "expected 13 fields" in rep.malformed[0].reason
    assert "field 3 is not a number: 'abc'" in rep.malformed[1].reason
    assert "non-negative integer" in rep.malformed[2].reason
    assert "non-finite" in rep.malformed[3].reason
    assert rep.params == {"robot_front_laser_max": "7.5"}
    assert rep.ignored() == {"comment": 2, "PARAM": 1, "blank": 1, "NEFF": 1, "SYNC": 1}

    assert [r.line for r in log.lasers] == [5, 7, 8]
    assert [r.line for r in log.odometry] == [4, 15]
    a, b, c = log.lasers
    assert all(isinstance(r, LaserRecord) for r in log.lasers)
    np.testing.assert_array_equal(a.ranges, [1.0, 2.0, 3.0, 4.5])
    assert (a.kind, a.angle_min, a.angle_increment, a.max_range) == (FLASER, -math.pi / 2, math.pi / 4, None)
    assert (a.pose, a.odom_pose) == ((1.1, 2.2, 0.3), (1.0, 2.0, 0.25))
    assert (a.ipc_timestamp, a.hostname, a.logger_timestamp) == (100.75, "hostA", 0.75)
    # odd count: both ends included, last beam at +90°
    assert b.angle_increment == math.pi / 4
    assert b.angle_min + 4 * b.angle_increment == pytest.approx(math.pi / 2, abs=1e-15)
    assert (b.pose, b.hostname, b.logger_timestamp) == ((0.0, 0.0, 3.2), "hostB", 1.0)
    np.testing.assert_array_equal(c.ranges, np.arange(1.0, 8.0))
    assert (c.kind, c.angle_min, c.angle_increment, c.max_range) == (ROBOTLASER1, -1.5, 0.5, 30.0)
    assert (c.pose, c.odom_pose) == ((1.0, 2.0, 0.1), (0.9, 1.9, 0.05))
    assert (c.ipc_timestamp, c.hostname, c.logger_timestamp) == (101.25, "hostC", 1.25)
    o1, o2 = log.odometry
    assert o1 == OdomRecord(4, 0.5, -0.25, 0.125, 0.3, -0.1, 0.0, 100.5, "hostA", 0.5)
    assert o2.pose == (2.0, 3.0, -3.0)
    assert o2.logger_timestamp == 2.0


def test_parse_handwritten_log_exact(log_path: Path) -> None:
    check_log(read_log(log_path))


def test_gzip_gives_the_same_result(tmp_path: Path) -> None:
    plain = read_log(write_log(tmp_path / "a.clf"))
    packed = read_log(write_log(tmp_path / "a.clf.gz", gz=True))
    check_log(packed)
    assert packed.odometry == plain.odometry
    assert [r.pose for r in packed.lasers] == [r.pose for r in plain.lasers]


def test_gzip_detected_by_content_not_name(tmp_path: Path) -> None:
    check_log(read_log(write_log(tmp_path / "compressed.log", gz=True)))


def test_strict_raises_with_line_number(log_path: Path) -> None:
    with pytest.raises(DataError, match=r"test\.clf:10: malformed FLASER: expected 13 fields"):
        read_log(log_path, strict=True)


def test_strict_accepts_a_clean_log(tmp_path: Path) -> None:
    clean = [line for i, line in enumerate(LOG_LINES, start=1) if i not in MALFORMED_LINES]
    log = read_log(write_log(tmp_path / "clean.clf", clean), strict=True)
    assert len(log.lasers) == 3
    assert len(log.odometry) == 2
    assert log.report.malformed == []


def test_streaming_fills_the_report_as_it_goes(log_path: Path) -> None:
    report = ParseReport(path=str(log_path))
    it = iter_records(log_path, report=report)
    first = next(it)
    assert isinstance(first, OdomRecord)
    assert report.lines == 4
    assert report.counts == {"comment": 1, "PARAM": 1, "blank": 1, "ODOM": 1}
    rest = list(it)
    assert len(rest) == 4
    assert report.lines == 17


def test_parse_line() -> None:
    assert parse_line("NEFF 1 2 3") is None
    assert parse_line("# comment") is None
    assert parse_line("") is None
    rec = parse_line("ODOM 1 2 3 4 5 6 7.5 h 8.5", lineno=3)
    assert isinstance(rec, OdomRecord)
    assert (rec.line, rec.pose, rec.tv, rec.rv, rec.accel, rec.logger_timestamp) == (
        3,
        (1, 2, 3),
        4,
        5,
        6,
        8.5,
    )
    with pytest.raises(DataError, match=r"line 9: malformed ODOM: expected 9 fields after the tag"):
        parse_line("ODOM 1 2 3", lineno=9)
    with pytest.raises(DataError, match=r"field 2 is not a number: '1,5'"):
        parse_line("ODOM 1 1,5 3 4 5 6 7 h 8")
    with pytest.raises(DataError, match="non-finite timestamp"):
        parse_line("ODOM 1 2 3 4 5 6 inf h 8")


@pytest.mark.parametrize(
    ("n", "step_deg", "last_deg"),
    [(180, 1.0, 89.0), (181, 1.0, 90.0), (360, 0.5, 89.5), (361, 0.5, 90.0), (2, 90.0, 0.0)],
)
def test_flaser_angles(n: int, step_deg: float, last_deg: float) -> None:
    angle_min, step = flaser_angles(n)
    assert angle_min == -math.pi / 2
    assert math.degrees(step) == pytest.approx(step_deg, rel=1e-14)
    assert math.degrees(angle_min + (n - 1) * step) == pytest.approx(last_deg, abs=1e-12)


def test_flaser_angles_rejects_empty() -> None:
    with pytest.raises(DataError, match="at least one beam"):
        flaser_angles(0)


def test_odometry_track_prefers_odom_lines(log_path: Path, tmp_path: Path) -> None:
    track = odometry_track(read_log(log_path))
    assert track.source == "ODOM"
    np.testing.assert_array_equal(track.stamps, [0.5, 2.0])
    np.testing.assert_array_equal(track.poses, [[0.5, -0.25, 0.125], [2.0, 3.0, -3.0]])
    np.testing.assert_array_equal(track.twists, [[0.3, -0.1], [0.0, 0.0]])
    no_odom = [line for line in LOG_LINES if not line.startswith("ODOM")]
    track = odometry_track(read_log(write_log(tmp_path / "lasers.clf", no_odom)))
    assert track.source == "laser odom pose"
    np.testing.assert_array_equal(track.stamps, [0.75, 1.0, 1.25])
    np.testing.assert_array_equal(track.poses, [[1.0, 2.0, 0.25], [0.0, 0.0, 3.2], [0.9, 1.9, 0.05]])
    np.testing.assert_array_equal(track.twists, np.zeros((3, 2)))


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="does not exist"):
        read_log(tmp_path / "nope.clf")


def test_truncated_gzip_raises_after_good_records(tmp_path: Path) -> None:
    lines = [f"ODOM {i} 0 0 0 0 0 {i} h {i}" for i in range(3000)]
    path = write_log(tmp_path / "cut.clf.gz", lines, gz=True)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    seen = []
    with pytest.raises(DataError, match=r"cannot read CARMEN log .*cut\.clf\.gz after line"):
        seen.extend(iter_records(path))
    assert 0 < len(seen) < 3000
    assert [r.x for r in seen] == list(range(len(seen)))


README_COUNTS = {
    "mit-csail/mit-csail.clf.gz": (1988, 361),
    "intel/intel-raw-910.clf.gz": (910, 180),
    "aces/aces-raw-440.clf.gz": (440, 180),
}


@pytest.mark.parametrize("name", sorted(README_COUNTS))
def test_real_logs(datasets_dir: Path, name: str) -> None:
    log = read_log(datasets_dir / name, strict=True)
    scans, beams = README_COUNTS[name]
    assert len(log.lasers) == scans
    assert log.odometry == ()
    assert log.report.counts == {"comment": 3, "FLASER": scans}
    assert {r.ranges.size for r in log.lasers} == {beams}
    # raw logs: laser pose = odometry pose in every line (README)
    assert all(r.pose == r.odom_pose for r in log.lasers)
    if name.startswith("mit"):
        first = log.lasers[0]
        assert first.odom_pose == (576.536523, 0.106594, -2.255213)
        assert (first.ipc_timestamp, first.hostname, first.logger_timestamp) == (
            1134864629.895182,
            "b21",
            0.086295,
        )
        assert log.lasers[-1].logger_timestamp == pytest.approx(424.077, abs=1e-3)
