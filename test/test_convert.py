"""``ptm-convert``: CARMEN log → rosbag2, checked message by message against the parsed log."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from carmen_log import LOG_LINES, write_log

from ptm_ros.io.bag import read_run, stamp_to_ns
from ptm_ros.io.carmen import odometry_track, read_log
from ptm_ros.tools.convert import main

REAL_LOGS = {  # README scan counts
    "mit-csail/mit-csail.clf.gz": 1988,
    "intel/intel-raw-910.clf.gz": 910,
    "aces/aces-raw-440.clf.gz": 440,
}


def in_bag_order(stamps: np.ndarray) -> np.ndarray:
    """The order a bag returns messages in: by ns log time, ties in write (file) order."""
    return np.argsort(np.array([stamp_to_ns(t) for t in stamps]), kind="stable")


def check_bag_against_log(bag: Path, log_path: Path) -> tuple[int, int]:
    log = read_log(log_path)
    data = read_run(bag, require=["/odom", "/scan"])
    assert set(data.topics) == {"/odom", "/scan"}
    track = odometry_track(log)
    o = in_bag_order(track.stamps)
    odo = data.odometry
    assert np.array_equal(odo.stamps, track.stamps[o])  # every stamp, bit-exact
    assert np.array_equal(odo.poses, track.poses[o])  # every pose, bit-exact
    assert np.array_equal(odo.twists, track.twists[o])
    assert (odo.frame_id, odo.child_frame_id) == ("odom", "base_link")
    lasers = log.lasers
    s = in_bag_order(np.array([r.logger_timestamp for r in lasers]))
    scans = data.scans
    assert np.array_equal(scans.stamps, [lasers[i].logger_timestamp for i in s])
    ranges = scans.ranges if isinstance(scans.ranges, list) else list(scans.ranges)
    for k, i in enumerate(s):
        assert np.array_equal(ranges[k], lasers[i].ranges.astype(np.float32))
    assert np.array_equal(scans.angle_min, np.float32([lasers[i].angle_min for i in s]))
    assert np.array_equal(scans.angle_increment, np.float32([lasers[i].angle_increment for i in s]))
    assert scans.frame_id == "base_laser"
    return len(odo.stamps), len(scans.stamps)


@pytest.mark.parametrize("name", sorted(REAL_LOGS))
def test_real_logs(datasets_dir: Path, tmp_path: Path, capsys, name: str) -> None:
    log_path = datasets_dir / name
    bag = tmp_path / "bag"
    storage = "sqlite3" if name.startswith("aces") else "mcap"
    assert main([str(log_path), str(bag), "--storage", storage]) == 0
    out = capsys.readouterr().out
    n = REAL_LOGS[name]
    assert f"{n} scans on /scan, {n} odometry messages on /odom (from laser odom pose)" in out
    assert "no malformed lines." in out
    assert next(bag.glob("*.mcap" if storage == "mcap" else "*.db3")).is_file()
    assert check_bag_against_log(bag, log_path) == (n, n)
    expected_max = {"mit": 81.91, "int": 81.83, "ace": 50.0}[name[:3]]
    assert np.all(read_run(bag).scans.range_max == np.float32(expected_max))


def test_handwritten_log_with_odom_and_malformed_lines(tmp_path: Path, capsys) -> None:
    log_path = write_log(tmp_path / "t.clf")
    bag = tmp_path / "bag"
    assert main([str(log_path), str(bag)]) == 0
    out = capsys.readouterr().out
    assert "3 scans on /scan, 2 odometry messages on /odom (from ODOM)" in out
    assert "6 malformed lines skipped (lines 10, 11, 12, 13, 14, …)" in out
    assert "ignored lines: 1 NEFF, 1 PARAM, 1 SYNC, 1 blank, 2 comment;" in out
    assert "FLASER range_max 7.5 m" in out  # from the PARAM line
    assert check_bag_against_log(bag, log_path) == (2, 3)
    data = read_run(bag)
    assert data.odometry.stamps.tolist() == [0.5, 2.0]
    assert data.odometry.poses.tolist() == [[0.5, -0.25, 0.125], [2.0, 3.0, -3.0]]
    assert data.odometry.twists.tolist() == [[0.3, -0.1], [0.0, 0.0]]
    assert data.scans.range_max.tolist() == [7.5, 7.5, 30.0]  # ROBOTLASER1 carries its own
    assert isinstance(data.scans.ranges, list)
    assert [r.size for r in data.scans.ranges] == [4, 5, 7]


def test_max_range_option_and_laser_offset(tmp_path: Path, capsys) -> None:
    log_path = write_log(tmp_path / "t.clf")
    assert main([str(log_path), str(tmp_path / "bag"), "--max-range", "12"]) == 0
    out = capsys.readouterr().out
    assert "FLASER range_max 12 m" in out
    assert "2 laser lines have a laser pose differing from the odometry" in out
    assert read_run(tmp_path / "bag").scans.range_max.tolist() == [12.0, 12.0, 30.0]


def test_strict_fails_without_creating_the_bag(tmp_path: Path, capsys) -> None:
    log_path = write_log(tmp_path / "t.clf")
    bag = tmp_path / "bag"
    assert main([str(log_path), str(bag), "--strict"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ptm-convert: error: ")
    assert "t.clf:10: malformed FLASER" in err
    assert not bag.exists()


def test_cli_errors(tmp_path: Path, capsys) -> None:
    log_path = write_log(tmp_path / "t.clf")
    existing = tmp_path / "existing"
    existing.mkdir()
    assert main([str(log_path), str(existing)]) == 2
    assert "exists already" in capsys.readouterr().err
    assert list(existing.iterdir()) == []
    assert main([str(tmp_path / "missing.clf"), str(tmp_path / "b1")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "b1").exists()
    empty = write_log(tmp_path / "empty.clf", ["# nothing", "PARAM a b c d"])
    assert main([str(empty), str(tmp_path / "b2")]) == 2
    assert "no FLASER, ROBOTLASER1 or ODOM records" in capsys.readouterr().err
    assert main([str(log_path), str(tmp_path / "b3"), "--max-range", "-1"]) == 2
    assert "max_range must be a positive finite number" in capsys.readouterr().err
    negative = write_log(tmp_path / "neg.clf", ["ODOM 0 0 0 0 0 0 1 h -5.0"])
    assert main([str(negative), str(tmp_path / "b4")]) == 2
    assert "outside [0, 2^31) s" in capsys.readouterr().err
    assert not (tmp_path / "b4").exists()
    with pytest.raises(SystemExit) as info:
        main([str(log_path), str(tmp_path / "b5"), "--storage", "rosbag1"])
    assert info.value.code == 2


def test_yaw_beyond_pi_kept(tmp_path: Path) -> None:
    """Corrected CARMEN logs hold yaws slightly beyond ±π; they come back unchanged."""
    lines = [f"ODOM 1 2 {yaw!r} 0 0 0 1 h {k}" for k, yaw in enumerate([3.17012, -3.2, math.pi, 6.0])]
    log_path = write_log(tmp_path / "yaw.clf", [*LOG_LINES[:1], *lines])
    assert main([str(log_path), str(tmp_path / "bag")]) == 0
    assert read_run(tmp_path / "bag").odometry.poses[:, 2].tolist() == [3.17012, -3.2, math.pi, 6.0]
