"""Ground-truth loaders (CARMEN gt text, simulator JSON) and pose interpolation."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from ptm_ros.errors import ConfigError, DataError
from ptm_ros.io.groundtruth import (
    GroundTruthTrajectory,
    Passage,
    Place,
    interpolate_pose,
    load_carmen_gt,
    load_ground_truth,
    load_sim_gt,
    run_ground_truth_problem,
)
from ptm_ros.scoring.evaluation import ODOMETRY_FIT_LIMIT, path_samples

GT_FILES = {
    "mit-csail/mit-csail-gt-406.txt": 406,
    "intel/intel-gt-910.txt": 910,
    "aces/aces-gt-440.txt": 440,
}


@pytest.mark.parametrize("name", sorted(GT_FILES))
def test_real_gt_rows_and_knots(datasets_dir: Path, name: str) -> None:
    gt = load_ground_truth(datasets_dir / name)
    n = GT_FILES[name]
    assert gt.stamps.shape == (n,)
    assert gt.poses_corrected.shape == (n, 3)
    assert gt.poses_raw is not None
    assert gt.poses_raw.shape == (n, 3)
    assert gt.raw_scan_index is not None
    assert np.all(np.diff(gt.raw_scan_index) >= 0)  # README: indices never decrease
    # exact at the knots (Intel has four stamps that step backwards; still exact)
    assert np.array_equal(interpolate_pose(gt, gt.stamps), gt.poses_corrected)
    assert np.array_equal(interpolate_pose(gt, gt.stamps, which="raw"), gt.poses_raw)


def test_real_gt_layouts(datasets_dir: Path) -> None:
    mit = load_carmen_gt(datasets_dir / "mit-csail/mit-csail-gt-406.txt")
    # first row: 0 61 1134864642.914187 13.121886 0.154000 0.068000 0.562729 576.480680 -0.103068 -1.487635
    assert mit.stamps[0] == 13.121886  # logger_timestamp, not the ipc one
    assert mit.poses_corrected[0].tolist() == [0.154, 0.068, 0.562729]
    assert mit.poses_raw[0].tolist() == [576.48068, -0.103068, -1.487635]
    assert mit.raw_scan_index[:3].tolist() == [61, 64, 67]
    aces = load_carmen_gt(datasets_dir / "aces/aces-gt-440.txt")
    # first row: 0 136 21.0199 0.897060 -0.180771 -0.454003 -0.136518 -0.896861 -2.046650
    assert aces.stamps[0] == 21.0199
    assert aces.poses_corrected[0].tolist() == [0.89706, -0.180771, -0.454003]
    assert aces.poses_raw[0].tolist() == [-0.136518, -0.896861, -2.04665]


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_layout_by_column_count_and_by_header(tmp_path: Path) -> None:
    nine = write(tmp_path / "a.txt", "0 5 1.5 1 2 3 4 5 6\n1 7 2.5 1.5 2.5 3.5 4.5 5.5 6.5\n")
    gt = load_carmen_gt(nine)
    assert gt.stamps.tolist() == [1.5, 2.5]
    assert gt.poses_corrected.tolist() == [[1, 2, 3], [1.5, 2.5, 3.5]]
    assert gt.poses_raw.tolist() == [[4, 5, 6], [4.5, 5.5, 6.5]]
    assert gt.raw_scan_index.tolist() == [5, 7]
    ten = write(tmp_path / "b.txt", "0 5 99.0 1.5 1 2 3 4 5 6\n")
    assert load_carmen_gt(ten).stamps.tolist() == [1.5]
    # a header naming the columns wins over the count
    shuffled = write(
        tmp_path / "c.txt",
        "# x_raw y_raw theta_raw logger_timestamp x_corr y_corr theta_corr\n4 5 6 1.5 1 2 3\n",
    )
    gt = load_carmen_gt(shuffled)
    assert (gt.stamps.tolist(), gt.poses_corrected.tolist(), gt.poses_raw.tolist()) == (
        [1.5],
        [[1, 2, 3]],
        [[4, 5, 6]],
    )
    assert gt.raw_scan_index is None


def test_carmen_gt_errors(tmp_path: Path) -> None:
    with pytest.raises(DataError, match=r"bad\.txt:2: expected 9 columns like the first row, got 8"):
        load_carmen_gt(write(tmp_path / "bad.txt", "0 5 1.5 1 2 3 4 5 6\n0 5 1.5 1 2 3 4 5\n"))
    with pytest.raises(DataError, match="cannot tell the column layout"):
        load_carmen_gt(write(tmp_path / "w.txt", "1 2 3 4 5 6 7\n"))
    with pytest.raises(DataError, match=r"n\.txt:1: non-numeric"):
        load_carmen_gt(write(tmp_path / "n.txt", "0 5 1.5 1 2 x 4 5 6\n"))
    with pytest.raises(DataError, match="no data rows"):
        load_carmen_gt(write(tmp_path / "e.txt", "# nothing\n"))


def brute_interpolate(t: np.ndarray, poses: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Reference: unwrap the yaw sequence, np.interp every coordinate, wrap the yaw."""
    yaw = np.unwrap(poses[:, 2])
    out = np.column_stack([np.interp(q, t, poses[:, 0]), np.interp(q, t, poses[:, 1]), np.interp(q, t, yaw)])
    out[:, 2] = np.angle(np.exp(1j * out[:, 2]))
    return out


def test_interpolation_matches_reference() -> None:
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.1, 2.0, 60))
    yaw = np.angle(np.exp(1j * np.cumsum(rng.uniform(-1.5, 1.5, 60))))  # steps < π, crossing ±π often
    poses = np.column_stack([rng.normal(0, 10, 60), rng.normal(0, 10, 60), yaw])
    order = rng.permutation(60)  # knots given out of order are sorted
    traj = GroundTruthTrajectory(stamps=t[order], poses_corrected=poses[order])
    q = rng.uniform(t[0], t[-1], 5000)
    got = interpolate_pose(traj, q)
    ref = brute_interpolate(t, poses, q)
    np.testing.assert_allclose(got[:, :2], ref[:, :2], rtol=0, atol=1e-10)
    dyaw = np.angle(np.exp(1j * (got[:, 2] - ref[:, 2])))
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-10)
    assert np.all((got[:, 2] >= -math.pi) & (got[:, 2] < math.pi))
    assert np.array_equal(interpolate_pose(traj, t), poses)  # exact at knots
    assert interpolate_pose(traj, q.reshape(50, 100)).shape == (50, 100, 3)


def test_yaw_wrap_takes_the_short_arc() -> None:
    traj = GroundTruthTrajectory(
        stamps=np.array([0.0, 1.0]), poses_corrected=np.array([[0.0, 0.0, 3.0], [2.0, 4.0, -3.0]])
    )
    mid = interpolate_pose(traj, [0.5])[0]
    assert mid[:2].tolist() == [1.0, 2.0]
    assert abs(mid[2]) == pytest.approx(math.pi, abs=1e-12)  # through ±π, not through 0
    quarter = interpolate_pose(traj, [0.25])[0]
    assert quarter[2] == pytest.approx(3.0 + 0.25 * (2 * math.pi - 6.0), abs=1e-12)


def test_interpolation_range_and_errors() -> None:
    traj = GroundTruthTrajectory(
        stamps=np.array([1.0, 2.0, 3.0]), poses_corrected=np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    )
    assert interpolate_pose(traj, [0.9999999, 3.0000005]).tolist() == [[0, 0, 0], [2, 0, 0]]
    with pytest.raises(DataError, match=r"1 stamp\(s\) outside the ground truth's range \[1.0, 3.0\]"):
        interpolate_pose(traj, [2.0, 3.01])
    with pytest.raises(DataError, match="outside"):
        interpolate_pose(traj, [0.5], tolerance=0.1)
    assert interpolate_pose(traj, [0.5], tolerance=0.6).tolist() == [[0, 0, 0]]
    with pytest.raises(DataError, match="no 'raw' poses"):
        interpolate_pose(traj, [2.0], which="raw")
    with pytest.raises(DataError, match="must be finite"):
        interpolate_pose(traj, [math.nan])
    twice = GroundTruthTrajectory(stamps=np.array([1.0, 1.0]), poses_corrected=np.zeros((2, 3)))
    with pytest.raises(DataError, match="repeats"):
        interpolate_pose(twice, [1.0])


SIM_DOC = {
    "schema": "ptm_ros.ground_truth/1",
    "frame_id": "map",
    "poses": {"stamp": [0.0, 0.5, 1.0], "x": [0.0, 1.0, 2.0], "y": [0, 0, 1], "yaw": [0.0, 0.1, 3.1]},
    "places": [
        {"id": 0, "x": 0.0, "y": 0.0, "kind": "junction"},
        {"id": 1, "x": 2.0, "y": 1.0, "kind": "room"},
    ],
    "passages": [{"stamp": 0.0, "place": 0}, {"stamp": 1.0, "place": 1}],
    "extra": "ignored",
}


def test_sim_json(tmp_path: Path) -> None:
    bag = tmp_path / "sim_bag"
    bag.mkdir()
    (bag / "ground_truth.json").write_text(json.dumps(SIM_DOC))
    for path in (bag, bag / "ground_truth.json"):
        gt = load_ground_truth(path)
        assert gt.frame_id == "map"
        assert gt.stamps.tolist() == [0.0, 0.5, 1.0]
        assert gt.poses_corrected.tolist() == [[0, 0, 0], [1, 0, 0.1], [2, 1, 3.1]]
        assert gt.poses_raw is None
        assert gt.places == (Place(0, 0.0, 0.0, "junction"), Place(1, 2.0, 1.0, "room"))
        assert gt.passages == (Passage(0.0, 0), Passage(1.0, 1))
    assert interpolate_pose(gt, [0.25])[0].tolist() == pytest.approx([0.5, 0.0, 0.05])


def sim_error(tmp_path: Path, doc: object, match: str) -> None:
    path = tmp_path / "gt.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(DataError, match=match):
        load_sim_gt(path)


def test_sim_json_errors(tmp_path: Path) -> None:
    sim_error(tmp_path, "{not json", "is not valid JSON")
    sim_error(
        tmp_path, {**SIM_DOC, "schema": "other/2"}, "expected schema 'ptm_ros.ground_truth/1', got 'other/2'"
    )
    sim_error(tmp_path, {**SIM_DOC, "frame_id": 3}, "'frame_id' must be a non-empty string")
    bad_len = {**SIM_DOC, "poses": {**SIM_DOC["poses"], "yaw": [0.0]}}
    sim_error(tmp_path, bad_len, "equal length")
    bad_num = {**SIM_DOC, "poses": {**SIM_DOC["poses"], "x": [0, "1", 2]}}
    sim_error(tmp_path, bad_num, r"poses\.x must be a list of numbers")
    sim_error(tmp_path, {**SIM_DOC, "passages": [{"stamp": 1.0, "place": 7}]}, "unknown places 7")
    sim_error(
        tmp_path, {**SIM_DOC, "places": [{"id": 0, "x": "a", "y": 0}]}, r"places\[0\]\.x must be a finite"
    )
    dup = {**SIM_DOC, "places": [SIM_DOC["places"][0], SIM_DOC["places"][0]]}
    sim_error(tmp_path, dup, "not unique")
    sim_error(tmp_path, {**SIM_DOC, "raw_poses": [1, 2]}, "'raw_poses' must be an object")
    short = {"x": [0.0], "y": [0.0], "yaw": [0.0]}
    sim_error(tmp_path, {**SIM_DOC, "raw_poses": short}, "raw_poses lists must be as long as the poses'")
    sim_error(tmp_path, {**SIM_DOC, "raw_poses": {**short, "x": None}}, r"raw_poses\.x must be a list")


def test_load_ground_truth_dispatch_errors(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="does not exist"):
        load_ground_truth(tmp_path / "missing.txt")
    with pytest.raises(DataError, match=r"unknown file type '\.csv'"):
        load_ground_truth(write(tmp_path / "gt.csv", "1,2"))
    empty_dir = tmp_path / "bag"
    empty_dir.mkdir()
    with pytest.raises(DataError, match=r"bag/ground_truth\.json does not exist"):
        load_ground_truth(empty_dir)


# ------------------------------------------------------------------ is it this run's ground truth? (#25)


def test_path_samples_are_one_per_spacing_of_travel_whatever_the_rate() -> None:
    """The points at which ptm-run judges a bag's odometry: one per metre of travel, none added while the
    robot stands still or by a faster odometry rate."""
    line = np.column_stack([np.linspace(0.0, 10.0, 101), np.zeros(101)])  # 0.1 m steps
    assert path_samples(line, 1.0).tolist() == list(range(0, 101, 10))
    dense = np.column_stack([np.linspace(0.0, 10.0, 1001), np.zeros(1001)])
    assert len(path_samples(dense, 1.0)) == 11
    still = np.vstack([line[:51], np.repeat(line[50:51], 200, axis=0), line[51:]])  # 200 samples standing
    k = path_samples(still, 1.0)
    assert len(k) == 11 and np.allclose(still[k, 0], np.arange(11.0))
    assert path_samples(np.zeros((5, 2)), 1.0).tolist() == [0]
    assert path_samples(np.zeros((0, 2)), 1.0).tolist() == []
    with pytest.raises(ConfigError, match="spacing"):
        path_samples(line, 0.0)


def _square(side: float, stamps: np.ndarray) -> np.ndarray:
    """Poses round a square of ``side`` m at 0.5 m/s, at ``stamps`` (s from the first)."""
    s = (0.5 * (stamps - stamps[0])) % (4 * side)
    k = (s // side).astype(int)
    corners = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    heading = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    xy = corners[k] + (s - k * side)[:, None] * heading[k]
    return np.column_stack([xy, np.arctan2(heading[k, 1], heading[k, 0])])


def test_run_ground_truth_problem_refuses_another_runs_and_passes_the_runs_own() -> None:
    """ptm-eval's rule on a bag's whole odometry (ptm-run, before any visit): the run's own ground truth
    (the odometry moved rigidly: another frame) passes; another route on the same clock is refused with
    the figures; one covering less than half of the run's path is refused as such."""
    stamps = 100.0 + 0.05 * np.arange(4000)  # 20 Hz, 200 s, 100 m
    truth = _square(12.0, stamps)
    c, s = np.cos(0.7), np.sin(0.7)
    odom = np.column_stack([truth[:, :2] @ np.array([[c, s], [-s, c]]) + [3.0, -2.0], truth[:, 2] + 0.7])
    own = GroundTruthTrajectory(stamps, truth)
    fit, problem = run_ground_truth_problem(own, stamps, odom)
    assert problem is None and fit.statistic is not None and fit.statistic < 1e-6
    assert fit.windows > 80 and fit.visits == len(path_samples(odom[:, :2], 1.0))

    other = GroundTruthTrajectory(stamps, _square(18.0, stamps))
    fit, problem = run_ground_truth_problem(other, stamps, odom)
    assert fit.statistic is not None and fit.statistic > ODOMETRY_FIT_LIMIT
    assert problem is not None and problem.startswith(
        "the bag's odometry does not move as the ground truth's"
    )
    assert f"relative residual {fit.statistic:.2f}" in problem and f"below {ODOMETRY_FIT_LIMIT:g}" in problem

    part = GroundTruthTrajectory(stamps[:1500], truth[:1500])  # its first 75 s (+ 0.5 s): 38 of 100 points
    _, problem = run_ground_truth_problem(part, stamps, odom)
    assert problem is not None
    assert problem.startswith("62 of 100 points of the bag's odometry (1 m of travel apart) lie outside")
    _, problem = run_ground_truth_problem(GroundTruthTrajectory(stamps[:2100], truth[:2100]), stamps, odom)
    assert problem is None  # 53 of 100 points inside: judged on them, and they fit
