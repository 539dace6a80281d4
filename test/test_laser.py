"""Tests of ptm_ros.perception.patches (scans to points, patches) and ptm_ros.perception.laser
(registration) (thesis Ch. 3.10.4, Fig. 48).

Synthetic worlds are wall segments; scans are ray-cast against them exactly, so every patch point has a
known wall and every registration a known answer.
"""

from __future__ import annotations

import gzip
import itertools
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from ptm_ros.errors import ConfigError, ModelError, RegistrationError
from ptm_ros.model.geometry import RelativePose, between, compose, inverse, transform_points, wrap_angle
from ptm_ros.perception.laser import (
    FLAT_OPTIMUM,
    LaserConfig,
    register_patches,
    to_relative_pose,
    voxel_downsample,
)
from ptm_ros.perception.patches import (
    PatchBuilder,
    build_patch,
    keyframes,
    passage_patch,
    passage_slice,
    refine_scan_poses,
    scan_to_points,
)

# ------------------------------------------------------------------------------------------ worlds

# A 10 m × 6 m room with a door gap in the top wall and a 1 m × 0.8 m box: no symmetry.
ROOM = np.array(
    [
        [(-5, -3), (5, -3)],
        [(5, -3), (5, 3)],
        [(5, 3), (0.5, 3)],
        [(-0.5, 3), (-5, 3)],
        [(-5, 3), (-5, -3)],
        [(1, -1), (2, -1)],
        [(2, -1), (2, -0.2)],
        [(2, -0.2), (1, -0.2)],
        [(1, -0.2), (1, -1)],
    ],
    dtype=float,
)
# A plain rectangle: symmetric under a half turn.
RECTANGLE = np.array([*ROOM[[0, 1]].tolist(), [(5, 3), (-5, 3)], [(-5, 3), (-5, -3)]], dtype=float)
# A T-junction of 2 m wide corridors with a niche, and a plain straight corridor.
JUNCTION = np.array(
    [
        [(-8, -1), (8, -1)],
        [(-8, 1), (-1, 1)],
        [(1, 1), (3, 1)],
        [(3, 1), (3, 1.6)],
        [(3, 1.6), (4, 1.6)],
        [(4, 1.6), (4, 1)],
        [(4, 1), (8, 1)],
        [(-1, 1), (-1, 8)],
        [(1, 1), (1, 8)],
    ],
    dtype=float,
)
CORRIDOR = np.array([[(-15, -1), (15, -1)], [(-15, 1), (15, 1)]], dtype=float)


def sample_walls(segments: np.ndarray, step: float = 0.02) -> np.ndarray:
    """Points every ``step`` along every segment."""
    parts = []
    for a, b in segments:
        n = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
        parts.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    return np.vstack(parts)


def raycast(segments: np.ndarray, sensor: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Exact ranges from ``sensor`` (x, y, yaw) along beam ``angles`` (sensor frame); inf = no hit."""
    d = np.stack([np.cos(sensor[2] + angles), np.sin(sensor[2] + angles)], axis=1)  # (B, 2)
    a, b = segments[:, 0], segments[:, 1]  # (W, 2)
    e = b - a
    # sensor + t d = a + u e  ->  t d - u e = a - sensor
    denom = d[:, None, 0] * (-e[None, :, 1]) - d[:, None, 1] * (-e[None, :, 0])
    rhs = a - sensor[:2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (rhs[None, :, 0] * (-e[None, :, 1]) - rhs[None, :, 1] * (-e[None, :, 0])) / denom
        u = (d[:, None, 0] * rhs[None, :, 1] - d[:, None, 1] * rhs[None, :, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (u >= 0.0) & (u <= 1.0)
    return np.where(hit, t, np.inf).min(axis=1)


def wall_distance(segments: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance of every point to the nearest wall segment (brute force over all segments)."""
    a, b = segments[:, 0], segments[:, 1]
    e = b - a
    rel = points[:, None, :] - a[None]
    u = np.clip(np.einsum("pwi,wi->pw", rel, e) / np.einsum("wi,wi->w", e, e), 0.0, 1.0)
    closest = a[None] + u[..., None] * e[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2).min(axis=1)


BEAMS = np.deg2rad(np.arange(-90.0, 90.5, 0.5))  # 361 beams, 180° field of view like a SICK LMS


def scan(segments, sensor, rng=None, sigma=0.0, max_range=30.0):
    ranges = raycast(segments, np.asarray(sensor, float), BEAMS)
    if rng is not None and sigma > 0.0:
        ranges = ranges + rng.normal(0.0, sigma, ranges.shape)
    return scan_to_points(ranges, BEAMS[0], BEAMS[1] - BEAMS[0], 0.05, max_range).points


def brute_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """First point of every voxel, via a dictionary, sorted by cell (reference for voxel_downsample)."""
    first: dict[tuple[int, int], np.ndarray] = {}
    for p in points:
        cell = (math.floor(p[0] / voxel), math.floor(p[1] / voxel))
        first.setdefault(cell, p)
    return np.array([first[c] for c in sorted(first)]).reshape(-1, 2)


def trajectory(waypoints: np.ndarray, step: float) -> np.ndarray:
    """Poses every ``step`` m along a polyline, heading along the segment."""
    poses = []
    for a, b in itertools.pairwise(waypoints):
        n = max(int(np.linalg.norm(b - a) / step), 1)
        yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        poses.extend([(*(a + k / n * (b - a)), yaw) for k in range(n)])
    return np.array(poses)


# ------------------------------------------------------------------------------------------- scans


def test_scan_to_points_exact_coordinates_and_drop_count():
    ranges = [1.0, np.nan, np.inf, 50.0, 0.05, 2.0, -np.inf, 30.0]
    out = scan_to_points(ranges, -np.pi / 2, np.pi / 4, 0.1, 30.0, angle_max=-np.pi / 2 + 7 * np.pi / 4)
    # kept: beam 0 at -90°, beam 5 at +135°, beam 7 at +225° (range == range_max is kept)
    expected = np.array(
        [[0.0, -1.0], [-math.sqrt(2.0), math.sqrt(2.0)], [-30.0 / math.sqrt(2.0), -30.0 / math.sqrt(2.0)]]
    )
    np.testing.assert_allclose(out.points, expected, atol=1e-12)
    assert out.dropped == 5


def test_scan_to_points_empty_and_errors():
    empty = scan_to_points([], 0.0, 0.01, 0.1, 10.0, angle_max=1.0)
    assert empty.points.shape == (0, 2)
    assert empty.dropped == 0
    with pytest.raises(ModelError, match="negative beam count"):
        scan_to_points([1.0, 1.0], 0.0, 0.1, 0.1, 10.0, angle_max=-1.0)
    with pytest.raises(ModelError, match=r"imply 11\.0 beams, got 3"):
        scan_to_points([1.0, 1.0, 1.0], 0.0, 0.1, 0.1, 10.0, angle_max=1.0)
    with pytest.raises(ModelError, match="angle_increment is 0"):
        scan_to_points([1.0, 1.0], 0.0, 0.0, 0.1, 10.0)
    with pytest.raises(ModelError, match="range_min < range_max"):
        scan_to_points([1.0], 0.0, 0.1, 5.0, 1.0)
    with pytest.raises(ModelError, match="1-D"):
        scan_to_points([[1.0, 2.0]], 0.0, 0.1, 0.1, 10.0)
    with pytest.raises(ModelError, match="angle_min must be finite"):
        scan_to_points([1.0], np.nan, 0.1, 0.1, 10.0)


# ----------------------------------------------------------------------------------------- patches


def test_voxel_downsample_matches_brute_force_and_is_incremental():
    rng = np.random.default_rng(3)
    a = rng.uniform(-2.0, 2.0, (400, 2))
    b = rng.uniform(-2.0, 2.0, (300, 2))
    np.testing.assert_array_equal(voxel_downsample(a, 0.3), brute_downsample(a, 0.3))
    both = np.vstack([a, b])
    np.testing.assert_array_equal(
        voxel_downsample(np.vstack([voxel_downsample(a, 0.3), b]), 0.3), voxel_downsample(both, 0.3)
    )
    with pytest.raises(ModelError, match="voxel must be finite"):
        voxel_downsample(a, 0.0)


def test_voxel_downsample_far_and_spread_out_points_match_brute_force():
    """Negative, far-away and astronomically spread coordinates (the sort falls back from one integer
    key per cell to the cell pairs) give the brute-force result too."""
    rng = np.random.default_rng(4)
    far = rng.uniform(-3.0, 3.0, (500, 2)) + np.array([-1e6, 2e6])
    spread = np.vstack([rng.uniform(-1.0, 1.0, (50, 2)), [[1e15, -1e15], [-1e15, 1e15], [0.01, 0.02]]])
    for pts, voxel in ((far, 0.25), (spread, 0.3), (spread, 1e-3)):
        np.testing.assert_array_equal(voxel_downsample(pts, voxel), brute_downsample(pts, voxel))


def test_build_patch_points_lie_on_walls_in_visit_frame():
    rng = np.random.default_rng(0)
    sigma, voxel, radius = 0.01, 0.05, 2.0
    offset = np.array([0.2, 0.0, 0.0])  # laser 20 cm ahead of the robot centre
    robot = np.array([[-1.0, -0.5, 0.3], [0.0, 0.0, 1.2], [-0.8, 0.8, 2.5], [4.0, 2.0, 0.0]])  # last: far
    scans = [scan(ROOM, compose(p, offset), rng, sigma) for p in robot]
    visit = np.array([-0.5, 0.2, -0.7])
    patch = build_patch(scans, robot, visit, radius, voxel, sensor_offset=offset)

    # reference: world points of the three scans within the radius, then into the visit frame
    world = np.vstack(
        [transform_points(compose(p, offset), s) for p, s in zip(robot[:3], scans[:3], strict=True)]
    )
    reference = brute_downsample(transform_points(inverse(visit), world), voxel)
    np.testing.assert_allclose(patch, reference, atol=1e-9)

    # every point is on a wall (ranges are exact up to the noise), and every room wall is seen
    dist = wall_distance(ROOM, transform_points(visit, patch))
    assert dist.max() < voxel / 2 + 5 * sigma
    assert len(patch) > 300
    room_walls = wall_distance(ROOM[:5], transform_points(visit, patch)) < 5 * sigma
    assert room_walls.mean() > 0.8


def test_build_patch_errors():
    with pytest.raises(ModelError, match="2 scans but 1 scan poses"):
        build_patch([np.zeros((3, 2)), np.zeros((3, 2))], [[0.0, 0.0, 0.0]], [0.0, 0.0, 0.0], 1.0, 0.1)
    with pytest.raises(ModelError, match="radius must be finite"):
        build_patch([np.zeros((3, 2))], [[0.0, 0.0, 0.0]], [0.0, 0.0, 0.0], -1.0, 0.1)
    with pytest.raises(ModelError, match=r"shape \(P, 2\)"):
        build_patch([np.zeros((3, 3))], [[0.0, 0.0, 0.0]], [0.0, 0.0, 0.0], 1.0, 0.1)
    empty = build_patch([np.ones((3, 2))], [[5.0, 0.0, 0.0]], [0.0, 0.0, 0.0], 1.0, 0.1)
    assert empty.shape == (0, 2)


def test_passage_slice_separates_passages():
    # out along x, back along x: the place at x = 2 is passed twice
    xs = np.r_[np.arange(0.0, 6.0, 0.5), np.arange(6.0, -0.1, -0.5)]
    poses = np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)])
    stamps = np.arange(len(xs), dtype=float)
    first = passage_slice(stamps, poses, 4.0, [2.0, 0.0, 0.0], 1.0)
    second = passage_slice(stamps, poses, 20.0, [2.0, 0.0, 0.0], 1.0)
    assert (first.start, first.stop) == (2, 7)  # x = 1.0 … 3.0 outbound
    assert (second.start, second.stop) == (18, 23)  # x = 3.0 … 1.0 inbound
    away = passage_slice(stamps, poses, 11.0, [2.0, 0.0, 0.0], 1.0)  # at time 11 the robot is at x = 5.5
    assert away.start == away.stop


def test_keyframes_skip_standing_still():
    poses = np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.06, 0, 0], [0.06, 0, 0.06], [0.07, 0, 0.07]])
    np.testing.assert_array_equal(keyframes(poses, 0.05, 0.05), [0, 3, 4])


def drifting_run(rng, segments, waypoints, step=0.25, yaw_drift=0.02, scale=1.03, sigma=0.01):
    """True poses along ``waypoints``, their scans, and odometry with a heading drift and scale error."""
    truth = trajectory(waypoints, step)
    scans = [scan(segments, p, rng, sigma) for p in truth]
    odo = [truth[0]]
    for k in range(1, len(truth)):
        inc = between(truth[k - 1], truth[k])
        odo.append(compose(odo[-1], [scale * inc[0], scale * inc[1], inc[2] + yaw_drift]))
    return truth, scans, np.array(odo)


def test_refine_scan_poses_removes_odometry_drift():
    rng = np.random.default_rng(1)
    truth, scans, odo = drifting_run(rng, ROOM, np.array([[-3.5, -1.5], [3.5, -1.8], [3.8, 1.8]]))
    refined = refine_scan_poses(scans, odo)
    err_odo = np.array([between(truth[0], t) - between(odo[0], o) for t, o in zip(truth, odo, strict=True)])
    err_ref = np.array(
        [between(truth[0], t) - between(refined[0], r) for t, r in zip(truth, refined, strict=True)]
    )
    err_odo[:, 2] = wrap_angle(err_odo[:, 2])
    err_ref[:, 2] = wrap_angle(err_ref[:, 2])
    assert np.abs(err_odo[:, 2]).max() > 0.5  # the odometry has drifted by more than 30°
    assert np.hypot(err_ref[:, 0], err_ref[:, 1]).max() < 0.05
    assert np.abs(err_ref[:, 2]).max() < np.deg2rad(1.0)
    np.testing.assert_allclose(refined[0], odo[0], atol=1e-12)


def test_passage_patch_refined_is_sharp_and_plain_equals_build_patch():
    rng = np.random.default_rng(2)
    truth, scans, odo = drifting_run(
        rng, ROOM, np.array([[-3.5, -1.5], [3.5, -1.8], [3.8, 1.8]]), yaw_drift=0.01
    )
    stamps = np.arange(len(truth)) * 0.1
    k = len(truth) // 2
    plain_cfg = LaserConfig(patch_radius=2.5, refine=False, keyframe_xy=0.0, keyframe_yaw=0.0)
    plain = passage_patch(scans, stamps, odo, stamps[k], odo[k], config=plain_cfg)
    sl = passage_slice(stamps, odo, stamps[k], odo[k], 2.5)
    np.testing.assert_array_equal(plain, build_patch(scans[sl], odo[sl], odo[k], 2.5, 0.05))

    sharp = passage_patch(scans, stamps, odo, stamps[k], odo[k], config=LaserConfig(patch_radius=2.5))
    # the visit frame is the true pose of scan k: patch points map onto the walls through truth[k]
    d_sharp = wall_distance(ROOM, transform_points(truth[k], sharp))
    d_plain = wall_distance(ROOM, transform_points(truth[k], plain))
    assert np.quantile(d_sharp, 0.95) < 0.05
    assert np.quantile(d_plain, 0.95) > 0.1


def test_patch_builder_online_equals_offline_and_is_bounded():
    rng = np.random.default_rng(4)
    truth, scans, odo = drifting_run(
        rng, ROOM, np.array([[-4.0, -2.0], [4.0, -2.0], [4.0, 2.0], [-4.0, 2.2]])
    )
    stamps = np.arange(len(truth)) * 0.1
    cfg = LaserConfig(patch_radius=2.0)
    visits = {0: 8, 1: 30, 2: 55, 4: len(truth) - 1}  # visit key -> scan index at which the detector fires
    late = {3: 12}  # declared 10 scans after the robot passed (robot already out of the radius)
    builder = PatchBuilder(cfg, max_scans=30)
    for k in range(len(truth)):
        builder.add_scan(stamps[k], odo[k], scans[k])
        # the robot stands still for a while at scan 20: no new keyframes, bounded buffer
        if k == 20:
            for j in range(100):
                builder.add_scan(stamps[k] + 1e-4 * (j + 1), odo[k], scans[k])
        for key, idx in visits.items():
            if idx == k:
                builder.add_visit(key, stamps[k], odo[k])
        for key, idx in late.items():
            if idx + 10 == k:
                builder.add_visit(key, stamps[idx], odo[idx])
        assert builder.n_buffered <= 30
    assert builder.n_buffered == 30  # full, oldest scans dropped; the 100 standing-still scans were skipped
    done = dict(builder.pop_ready())
    assert sorted(done) == [0, 1, 2, 3]  # the robot has left their neighbourhoods
    assert builder.n_open == 1  # the run ends inside visit 4's neighbourhood
    done.update(builder.flush())
    assert builder.n_open == 0
    for key, idx in {**visits, **late}.items():
        offline = passage_patch(scans, stamps, odo, stamps[idx], odo[idx], config=cfg)
        np.testing.assert_array_equal(done[key], offline)
        assert len(offline) > 200
    with pytest.raises(ModelError, match="already declared"):
        builder.add_visit(1, 0.0, odo[0])
    with pytest.raises(ModelError, match="must not decrease"):
        builder.add_scan(0.0, odo[0], scans[0])


# ------------------------------------------------------------------------------------ registration

TRUE = np.array([0.4, -0.3, np.deg2rad(100.0)])  # between(x_target, x_source)


def patch_pair(segments, pose, rng, sigma=0.01, source_segments=None):
    """Target patch in the world frame; source patch in the frame of ``pose``; independent noise."""
    world = sample_walls(segments)
    target = voxel_downsample(world + rng.normal(0.0, sigma, world.shape), 0.05)
    src_world = world if source_segments is None else sample_walls(source_segments)
    source = transform_points(inverse(pose), src_world)
    source = voxel_downsample(source + rng.normal(0.0, sigma, source.shape), 0.05)
    return source, target


@pytest.mark.parametrize("segments", [ROOM, JUNCTION], ids=["room", "junction"])
def test_register_patches_recovers_known_pose(segments):
    rng = np.random.default_rng(5)
    source, target = patch_pair(segments, TRUE, rng)
    reg = register_patches(source, target, (0.0, 0.0, 0.0))
    assert reg.valid, reg.reason
    assert np.hypot(*(reg.mean[:2] - TRUE[:2])) < 0.05
    assert abs(wrap_angle(reg.mean[2] - TRUE[2])) < np.deg2rad(1.0)
    assert reg.inlier_fraction > 0.9
    assert reg.rmse < 0.03
    np.testing.assert_allclose(reg.cov, reg.cov.T)
    assert np.linalg.eigvalsh(reg.cov).min() > 0.0
    # floored: cov - diag(floor²) is positive semi-definite
    floor = np.diag([0.05, 0.05, 0.02]) ** 2
    assert np.linalg.eigvalsh(reg.cov - floor).min() > -1e-12
    # direction: the estimate carries source points onto the target
    moved = transform_points(reg.mean, source)
    assert np.median(wall_distance(segments, moved)) < 0.02
    rel = to_relative_pose(reg, i=7, j=3)
    assert isinstance(rel, RelativePose)
    assert (rel.i, rel.j) == (7, 3)
    np.testing.assert_array_equal(rel.mean, reg.mean)


def test_register_patches_swapped_gives_inverse():
    rng = np.random.default_rng(6)
    source, target = patch_pair(ROOM, TRUE, rng)
    forward = register_patches(source, target)
    backward = register_patches(target, source)
    np.testing.assert_allclose(compose(forward.mean, backward.mean), np.zeros(3), atol=0.02)


def test_register_patches_covariance_matches_monte_carlo():
    # small noise: the estimator is then unbiased and its spread is what the covariance predicts
    rng = np.random.default_rng(7)
    cfg = LaserConfig(n_rotations=1, min_std_xy=1e-6, min_std_yaw=1e-6)
    errors, covs = [], []
    for _ in range(80):
        source, target = patch_pair(ROOM, TRUE, rng, sigma=0.004)
        reg = register_patches(source, target, TRUE + np.array([0.05, -0.05, 0.03]), cfg)
        err = reg.mean - TRUE
        err[2] = wrap_angle(err[2])
        errors.append(err)
        covs.append(reg.cov)
    empirical = np.sqrt(np.diag(np.cov(np.array(errors).T)))
    predicted = np.sqrt(np.diag(np.mean(covs, axis=0)))
    ratio = empirical / predicted
    assert np.all((ratio > 0.6) & (ratio < 1.7)), (empirical, predicted)


def test_unrelated_structures_are_no_match():
    rng = np.random.default_rng(8)
    source, target = patch_pair(ROOM, TRUE, rng, source_segments=JUNCTION)
    reg = register_patches(source, target)
    assert not reg.valid
    assert reg.reason
    assert to_relative_pose(reg, 0, 1) is None


def test_symmetric_room_is_ambiguous():
    rng = np.random.default_rng(9)
    source, target = patch_pair(RECTANGLE, TRUE, rng)
    reg = register_patches(source, target)
    assert not reg.valid
    assert reg.reason.startswith("ambiguous")
    # both the true pose and its half-turn image are among the solutions, with equal fitness
    half = compose(TRUE, [0.0, 0.0, 0.0])
    flipped = compose([0.0, 0.0, np.pi], TRUE)
    sols = np.array(reg.candidates)
    for pose in (half, flipped):
        d = np.hypot(sols[:, 0] - pose[0], sols[:, 1] - pose[1]) + np.abs(wrap_angle(sols[:, 2] - pose[2]))
        assert d.min() < 0.05
        assert sols[d.argmin(), 3] > 0.9


def test_corridor_is_a_flat_optimum():
    rng = np.random.default_rng(10)
    source, target = patch_pair(CORRIDOR, np.array([0.0, 0.0, 0.0]), rng)
    reg = register_patches(source, target, slide_axis=True)
    assert not reg.valid
    assert reg.reason.startswith(FLAT_OPTIMUM)
    # from 8 headings the half-turned corridor fits as well: no slide axis (the heading is ambiguous)
    assert reg.slide_axis is None


def test_corridor_match_from_a_guess_reports_its_axis_and_fixes_the_lateral_offset():
    """From one initial heading a corridor match slides only along the corridor: its axis is the
    corridor's direction (in the target frame), and the offset across it and the heading are right."""
    rng = np.random.default_rng(11)
    turn = np.array([0.0, 0.0, 0.7])  # the corridor runs at 0.7 rad in the target frame
    walls = np.array([[transform_points(turn, seg) for seg in CORRIDOR]]).reshape(-1, 2, 2)
    truth = np.array([1.5 * np.cos(0.7) - 0.3 * np.sin(0.7), 1.5 * np.sin(0.7) + 0.3 * np.cos(0.7), 0.05])
    source, target = patch_pair(walls, truth, rng)
    cfg = LaserConfig(n_rotations=1)
    reg = register_patches(source, target, truth + np.array([0.2, -0.25, -0.04]), cfg, slide_axis=True)
    assert not reg.valid and reg.reason.startswith(FLAT_OPTIMUM)
    plain = register_patches(source, target, truth + np.array([0.2, -0.25, -0.04]), cfg)
    assert plain.slide_axis is None and plain.reason == reg.reason  # not asked for: not computed
    axis = np.array([np.cos(0.7), np.sin(0.7)])
    assert reg.slide_axis is not None and abs(reg.slide_axis @ axis) > 0.999
    across = np.array([-axis[1], axis[0]])
    assert abs((reg.mean[:2] - truth[:2]) @ across) < 0.03
    assert abs(wrap_angle(reg.mean[2] - truth[2])) < 0.01
    # sharp matches have no axis; nor has a flat optimum that turns (a circle about the origin)
    room = register_patches(*patch_pair(ROOM, TRUE, rng), slide_axis=True)
    assert room.valid and room.slide_axis is None
    angles = np.linspace(-np.pi, np.pi, 2000, endpoint=False)
    circle = np.column_stack([3.0 * np.cos(angles), 3.0 * np.sin(angles)])
    spin = register_patches(circle, circle, (0.0, 0.0, 0.1), cfg, slide_axis=True)
    assert spin.reason.startswith(FLAT_OPTIMUM) and spin.slide_axis is None


def brute_fit(source, target, pose, cfg):
    """Fitness of one pose by brute force over all point distances: (source fraction, target fraction,
    source inliers, rmse), as documented for :class:`ptm_ros.perception.laser.Registration`."""
    from scipy.spatial.distance import cdist

    src = voxel_downsample(source, 0.5 * cfg.voxel)
    tgt = voxel_downsample(target, 0.5 * cfg.voxel)
    d_src = cdist(transform_points(pose, src), target).min(axis=1)
    d_tgt = cdist(transform_points(inverse(pose), tgt), source).min(axis=1)
    inl = d_src <= cfg.inlier_distance
    rmse = math.sqrt(np.mean(d_src[inl] ** 2)) if inl.any() else math.nan
    return inl.mean(), np.mean(d_tgt <= cfg.inlier_distance), int(inl.sum()), rmse


def brute_peak(source, target, pose, cfg):
    """Best symmetric fraction after moving ``pose`` by ``distinct_xy`` in 8 directions or turning it by
    ``±distinct_yaw`` (the sharpness test), by brute force."""
    moves = [pose + cfg.distinct_xy * np.array([np.cos(a), np.sin(a), 0.0]) for a in np.arange(8) * np.pi / 4]
    moves += [compose(pose, [0.0, 0.0, s * cfg.distinct_yaw]) for s in (-1.0, 1.0)]
    return max(min(brute_fit(source, target, m, cfg)[:2]) for m in moves)


@pytest.mark.parametrize("world", ["room", "rectangle", "corridor", "unrelated"])
def test_registration_fitness_and_decision_match_brute_force(world):
    """The pruned KD-tree searches and the lazy sharpness test of the registration give what exhaustive
    distances give: the reported fitness of the solution and of every heading's candidate, the sharpness
    decision (and the fraction a flat optimum reports), and an ambiguous match really has a distinct
    candidate within the margin."""
    cfg = LaserConfig()
    rng = np.random.default_rng(21)
    segments, pose, other = {
        "room": (ROOM, TRUE, None),
        "rectangle": (RECTANGLE, TRUE, None),
        "corridor": (CORRIDOR, np.zeros(3), None),
        "unrelated": (ROOM, TRUE, JUNCTION),
    }[world]
    source, target = patch_pair(segments, pose, rng, source_segments=other)
    reg = register_patches(source, target, (0.0, 0.0, 0.0), cfg)
    src_frac, tgt_frac, n_inliers, rmse = brute_fit(source, target, reg.mean, cfg)
    assert (reg.source_fraction, reg.target_fraction, reg.n_inliers) == (src_frac, tgt_frac, n_inliers)
    assert reg.inlier_fraction == min(src_frac, tgt_frac)
    assert math.isclose(reg.rmse, rmse, rel_tol=1e-9)
    assert reg.n_points == len(voxel_downsample(source, 0.5 * cfg.voxel))
    assert len(reg.candidates) == cfg.n_rotations
    np.testing.assert_array_equal(reg.candidates[0][:3], reg.mean)
    for x, y, yaw, fraction in reg.candidates[1:]:
        assert fraction == min(brute_fit(source, target, np.array([x, y, yaw]), cfg)[:2])
    fractions = [c[3] for c in reg.candidates]
    assert fractions[1:] == sorted(fractions[1:], reverse=True)
    if reg.inlier_fraction < cfg.min_inlier_fraction:
        assert not reg.valid and reg.reason.startswith("inlier fraction")
        assert world == "unrelated"
        return
    nearby = brute_peak(source, target, reg.mean, cfg)
    flat = reg.inlier_fraction - nearby < cfg.min_peak_drop
    assert flat == reg.reason.startswith("flat optimum") == (world == "corridor")
    if flat:
        assert f"keeps inlier fraction {nearby:.3f} of {reg.inlier_fraction:.3f}" in reg.reason
    distinct = [
        c[3] >= reg.inlier_fraction - cfg.ambiguity_margin
        and (
            math.hypot(*between(reg.mean, c[:3])[:2]) >= cfg.distinct_xy
            or abs(between(reg.mean, c[:3])[2]) >= cfg.distinct_yaw
        )
        for c in reg.candidates[1:]
    ]
    assert (not flat and any(distinct)) == reg.reason.startswith("ambiguous") == (world == "rectangle")
    assert reg.valid == (world == "room")


def plain_gauss_newton(start, source, target, cfg, prior_std):
    """The point-to-plane Gauss–Newton polish as documented, iteration by iteration (full KD-tree
    searches, every iteration computed, normals computed afresh): (pose, covariance, poses visited)."""
    from scipy.linalg import cho_factor, cho_solve
    from scipy.spatial import cKDTree

    from ptm_ros.perception.laser import _normals

    src, tree = voxel_downsample(source, 0.5 * cfg.voxel), cKDTree(target)
    prior = np.diag(prior_std**-2.0)
    current, info, visited = start.copy(), prior, []
    for _ in range(30):
        visited.append(current.tobytes())
        moved = transform_points(current, src)
        dist, idx = tree.query(moved)
        close = np.flatnonzero(dist <= cfg.inlier_distance)
        which = np.unique(idx[close])
        normals, flat = _normals(target, tree, which)
        at = np.searchsorted(which, idx[close])
        inl, n = close[flat[at]], normals[at][flat[at]]
        assert len(inl) > 3
        q = moved[inl]
        e = np.einsum("ij,ij->i", n, q - target[idx[inl]])
        arm = q - current[:2]
        g = np.column_stack([n, arm[:, 0] * n[:, 1] - arm[:, 1] * n[:, 0]])
        sigma2 = max(float(e @ e) / (len(e) - 3), 1e-12)
        info = prior + g.T @ g / sigma2
        offset = current - start
        offset[2] = wrap_angle(offset[2])
        step = -cho_solve(cho_factor(info), g.T @ e / sigma2 + prior @ offset)
        current = np.array(
            [current[0] + step[0], current[1] + step[1], float(wrap_angle(current[2] + step[2]))]
        )
        if np.max(np.abs(step)) < 1e-7:
            break
    between_ = between(start, current)
    if math.hypot(between_[0], between_[1]) >= cfg.distinct_xy or abs(between_[2]) >= cfg.distinct_yaw:
        current = start
    cov = cho_solve(cho_factor(info), np.eye(3))
    return current, 0.5 * (cov + cov.T), visited


def test_spd_solve_is_scipys_cholesky_solve_bit_for_bit_and_refuses_an_indefinite_matrix():
    """The Gauss–Newton step's direct LAPACK solve gives scipy's ``cho_solve(cho_factor(...))`` exactly
    (information matrices of 3 × 3, right-hand sides of one and of three columns)."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve

    from ptm_ros.perception.laser import _spd_solve

    rng = np.random.default_rng(5)
    for _ in range(50):
        a = rng.normal(size=(3, 7))
        info = a @ a.T + np.diag(rng.uniform(1e-6, 1e3, size=3))
        for rhs in (rng.normal(size=3), np.eye(3)):
            assert np.array_equal(_spd_solve(info, rhs), cho_solve(cho_factor(info), rhs))
    with pytest.raises(LinAlgError, match="not positive definite"):
        _spd_solve(np.diag([1.0, -1.0, 1.0]), np.ones(3))


@pytest.mark.parametrize(
    ("world", "seed", "spread"),
    [("junction", 0, 0.05), ("junction", 10, 0.05), ("corridor", 10, 0.2), ("room", 3, 0.2)],
)
def test_point_to_plane_equals_the_plain_iteration(world, seed, spread):
    """The polish (pruned searches, cached normals, a pose that repeats ends the loop with the result the
    cycle reaches at the last iteration) is bit for bit the plain iteration, on cases that converge
    and cases that cycle until the iteration limit (junction seed 10, corridor)."""
    from ptm_ros.perception.laser import _Overlap, _point_to_plane, _Target

    cfg = LaserConfig()
    segments = {"junction": JUNCTION, "corridor": CORRIDOR, "room": ROOM}[world]
    rng = np.random.default_rng(seed)
    source, target = patch_pair(segments, TRUE, rng, sigma=0.03)
    start = TRUE + rng.normal(0.0, [spread, spread, spread / 2])
    prior_std = np.array([3.0, 3.0, np.pi])
    want, want_cov, visited = plain_gauss_newton(start, source, target, cfg, prior_std)
    cycles = len(set(visited)) < len(visited)
    assert cycles == (seed == 10)  # both kinds are exercised
    overlap = _Overlap(
        _Target(source, 0.5 * cfg.voxel), _Target(target, 0.5 * cfg.voxel), cfg.inlier_distance
    )
    got, got_cov, _ = _point_to_plane(start, overlap, cfg, prior_std)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_cov, want_cov)


def test_patch_registrar_prepares_each_patch_once_and_equals_register_patches(monkeypatch):
    """The registrar keeps every visit's patch prepared across pairs and roles (source of one pair,
    target of another); its outcomes equal fresh :func:`register_patches` calls, also after the prepared
    patches are evicted (a cache of 2), when a visit's patch object is replaced and when the pairs are
    registered elsewhere (``many``)."""
    from dataclasses import replace as dc_replace

    import ptm_ros.perception.laser as laser
    from ptm_ros.model.geometry import NoMatch
    from ptm_ros.model.visits import Visit
    from ptm_ros.perception.laser import laser_outcome, patch_registrar

    rng = np.random.default_rng(22)
    cfg = LaserConfig()
    room_a, room_b = patch_pair(ROOM, TRUE, rng)
    rect, _ = patch_pair(RECTANGLE, TRUE, rng)
    corridor, _ = patch_pair(CORRIDOR, np.zeros(3), rng)
    patches = [room_b, rect, room_a, corridor, None]
    visits = [Visit(index=k, stamp=float(k), pose=(0.0, 0.0, 0.0), patch=p) for k, p in enumerate(patches)]
    counters: dict[str, int] = {}
    registrar = patch_registrar(visits, cfg, counters)

    def expected(i, j):
        if visits[i].patch is None or visits[j].patch is None:
            return None
        return laser_outcome(
            register_patches(visits[j].patch, visits[i].patch, (0.0, 0.0, 0.0), cfg), i, j, cfg
        )

    def same(got, want):
        assert type(got) is type(want)
        if isinstance(want, RelativePose):
            np.testing.assert_array_equal(got.mean, want.mean)
            np.testing.assert_array_equal(got.cov, want.cov)
        if want is not None:
            assert (got.i, got.j, got.log_bayes) == (want.i, want.j, want.log_bayes)

    def check(i, j):
        got = registrar(i, j)
        same(got, expected(i, j))
        return got

    pairs = [(0, 2), (2, 3), (0, 1), (1, 2), (0, 3), (1, 3), (3, 4)]
    outcomes = {pair: check(*pair) for pair in pairs}
    assert isinstance(outcomes[(0, 2)], RelativePose)  # the room seen twice
    assert isinstance(outcomes[(0, 1)], NoMatch)
    assert outcomes[(3, 4)] is None  # no patch
    assert counters == {"registrations": 6, "registrations_valid": 1}
    visits[2] = dc_replace(visits[2], patch=patch_pair(ROOM, TRUE, rng)[0])  # a new patch object for visit 2
    assert isinstance(check(0, 2), RelativePose)
    check(1, 2)
    monkeypatch.setattr(laser, "_PREPARED_PATCHES", 2)
    for pair in [(0, 1), (2, 3), (0, 3), (1, 2)]:
        check(*pair)

    # many(): the same outcomes and counters, registered elsewhere (a worker pool's submit)
    from concurrent.futures import ThreadPoolExecutor

    counted: dict[str, int] = {}
    with ThreadPoolExecutor(max_workers=2) as pool:
        pooled = patch_registrar(visits, cfg, counted).many(pairs, pool)
    assert list(pooled) == pairs
    for (i, j), got in pooled.items():
        same(got, registrar(i, j))
    assert counted == {"registrations": 6, "registrations_valid": 1}


def test_tiny_or_empty_patches_raise():
    rng = np.random.default_rng(11)
    source, target = patch_pair(ROOM, TRUE, rng)
    with pytest.raises(RegistrationError, match="too small"):
        register_patches(np.empty((0, 2)), target)
    with pytest.raises(RegistrationError, match="too small"):
        register_patches(source, target[:5])
    with pytest.raises(ModelError, match="initial"):
        register_patches(source, target, (0.0, 0.0))
    with pytest.raises(ModelError, match="non-finite"):
        register_patches(np.full((40, 2), np.nan), target)


def test_to_relative_pose_rejects_self_pairs():
    rng = np.random.default_rng(12)
    reg = register_patches(*patch_pair(ROOM, TRUE, rng))
    with pytest.raises(ModelError, match="two different visits"):
        to_relative_pose(reg, 2, 2)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("voxel", 0.1, "voxel must be a finite number >= 0.25"),
        ("n_rotations", 0, "n_rotations must be an integer >= 1"),
        ("min_inlier_fraction", 0.0, r"min_inlier_fraction must be a finite number in \(0, 1\]"),
        ("patch_radius", -1.0, "patch_radius must be a finite number > 0"),
        ("min_points", 2.5, "min_points must be an integer"),
        ("refine", 1, "refine must be true or false"),
        ("min_peak_drop", 1.0, r"min_peak_drop must be a finite number in \[0, 1\)"),
    ],
)
def test_config_validation(field, value, match):
    with pytest.raises(ConfigError, match=match):
        LaserConfig(**{field: value})


# ---------------------------------------------------------------------------------------- real data


def _load_clf(path: Path) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """FLASER ranges, odometry poses and logger stamps of a CARMEN log (all the test needs)."""
    ranges, poses, stamps = [], [], []
    with gzip.open(path, "rt") as f:
        for line in f:
            fields = line.split()
            if not fields or fields[0] != "FLASER":
                continue
            n = int(fields[1])
            ranges.append(np.array(fields[2 : 2 + n], dtype=float))
            poses.append([float(v) for v in fields[2 + n : 5 + n]])
            stamps.append(float(fields[-1]))
    return ranges, np.array(poses), np.array(stamps)


DATASETS = {  # name: (raw log, ground truth, ground-truth columns: raw scan index or None, x y yaw)
    "intel": ("intel/intel-raw-910.clf.gz", "intel/intel-gt-910.txt", None, slice(3, 6)),
    "aces": ("aces/aces-raw-440.clf.gz", "aces/aces-gt-440.txt", None, slice(3, 6)),
    "mit-csail": ("mit-csail/mit-csail.clf.gz", "mit-csail/mit-csail-gt-406.txt", 1, slice(4, 7)),
}


def evaluate_dataset(
    root: Path, name: str, cfg: LaserConfig, *, until: float = np.inf, n_different: int = 300
):
    """Visits every 5 m of raw odometry travel (among scans with ground truth, up to ``until`` m); pairs
    of separate passages < 1.5 m apart (corrected poses) are 'same', > 4 m 'different' (a random sample).
    A valid registration is right when within 0.3 m / 5° of the corrected relative pose."""
    log, gt_file, index_col, cols = DATASETS[name]
    ranges, odo, stamps = _load_clf(root / log)
    table = np.loadtxt(root / gt_file)
    gt = np.full((len(ranges), 3), np.nan)
    rows = np.arange(len(table)) if index_col is None else table[:, index_col].astype(int)
    gt[rows] = table[:, cols]
    n = len(ranges[0])
    step = np.pi / (n - 1) if n % 2 else np.pi / n  # 361 beams at 0.5°, or 180 at 1° (CARMEN FLASER)
    pts = [scan_to_points(r, -np.pi / 2, step, 0.0, cfg.max_range).points for r in ranges]
    travelled = np.r_[0.0, np.cumsum(np.hypot(*np.diff(odo[:, :2], axis=0).T))]
    visits, next_at = [], 0.0
    for k in np.flatnonzero(np.isfinite(gt[:, 0]) & (travelled <= until)):
        if travelled[k] >= next_at:
            visits.append(k)
            next_at = travelled[k] + 5.0
    patches = [passage_patch(pts, stamps, odo, stamps[k], odo[k], config=cfg) for k in visits]
    slices = [passage_slice(stamps, odo, stamps[k], odo[k], cfg.patch_radius) for k in visits]
    same, different = [], []
    for a, b in itertools.combinations(range(len(visits)), 2):
        if slices[a].stop <= slices[b].start:
            d = np.hypot(*(gt[visits[a], :2] - gt[visits[b], :2]))
            (same if d < 1.5 else different if d > 4.0 else []).append((a, b))
    rng = np.random.default_rng(0)
    if len(different) > n_different:
        different = [different[i] for i in rng.choice(len(different), n_different, replace=False)]
    counts = {"same": len(same), "different": len(different)}
    errors = []
    for label, pairs in (("same", same), ("different", different)):
        for a, b in pairs:
            reg = register_patches(patches[b], patches[a], (0.0, 0.0, 0.0), cfg)
            if not reg.valid:
                continue
            err = reg.mean - between(gt[visits[a]], gt[visits[b]])
            err[2] = wrap_angle(err[2])
            ok = np.hypot(err[0], err[1]) < 0.3 and abs(err[2]) < np.deg2rad(5.0)
            key = f"{label}_{'right' if ok else 'wrong'}"
            counts[key] = counts.get(key, 0) + 1
            if ok:
                errors.append(np.r_[err, err @ np.linalg.solve(reg.cov, err)])
    return counts, np.array(errors).reshape(-1, 4)


@pytest.mark.slow
def test_intel_registrations_are_right_or_invalid(datasets_dir):
    """Intel lab, raw odometry, first 180 m: same-place pairs register to the corrected relative pose
    or are invalid; different places never give a valid match."""
    counts, errors = evaluate_dataset(datasets_dir, "intel", LaserConfig(), until=180.0, n_different=25)
    assert counts["same"] >= 15
    assert counts.get("same_wrong", 0) == 0
    assert counts.get("different_wrong", 0) == 0
    assert counts.get("same_right", 0) >= counts["same"] // 2
    # the floored covariance is consistent with the errors: median squared Mahalanobis near chi2_3's 2.37
    assert 0.5 < np.median(errors[:, 3]) < 5.0


if __name__ == "__main__":  # figures for the report: python test/test_laser.py [DATASETS_DIR]
    root = (
        Path(sys.argv[1])
        if len(sys.argv) > 1
        else Path(__file__).resolve().parents[2] / "shared" / "datasets"
    )
    for name in DATASETS:
        counts, errors = evaluate_dataset(root, name, LaserConfig())
        rms = np.sqrt(np.mean(errors[:, :3] ** 2, axis=0)) if len(errors) else np.full(3, np.nan)
        print(
            name,
            counts,
            "rms err (x, y, yaw)",
            np.round(rms, 3),
            "median d2",
            np.round(np.median(errors[:, 3]), 2),
        )


# ------------------------------------------------------------------------------- fitness evidence


def test_fitness_densities_are_normalised_and_the_ratio_matches_them():
    """Both mixture densities integrate to 1 over [0, 1] (quadrature), and the log ratio is theirs."""
    from scipy.integrate import quad
    from scipy.stats import beta

    from ptm_ros.perception.laser import fitness_log_bayes

    cfg = LaserConfig()
    eps = cfg.fitness_outlier

    def same(f):
        return (1 - eps) * beta.pdf(f, cfg.fitness_same_a, cfg.fitness_same_b) + eps

    def diff(f):
        return (1 - eps) * beta.pdf(f, cfg.fitness_different_a, cfg.fitness_different_b) + eps

    assert abs(quad(same, 0, 1)[0] - 1) < 1e-8
    assert abs(quad(diff, 0, 1, points=[0.1, 0.2, 0.3])[0] - 1) < 1e-8
    for f in (0.0, 0.1, 0.15, 0.28, 0.5, 0.9, 1.0):
        expected = math.log(same(f) / diff(f))
        assert math.isclose(fitness_log_bayes(f, cfg), expected, rel_tol=1e-12, abs_tol=1e-12)
    assert fitness_log_bayes(0.15) < -1.5 and fitness_log_bayes(0.5) > 2.5  # the fitted shape
    assert fitness_log_bayes(math.nan) == fitness_log_bayes(0.0)  # nothing overlapped


@pytest.mark.parametrize("a", [0.5, 1.0, 1.6, 6.5])
@pytest.mark.parametrize("b", [0.5, 1.0, 1.6, 31.3])
def test_the_beta_density_is_scipys_at_the_ends_and_between(a, b):
    """``beta_pdf`` equals ``scipy.stats.beta.pdf`` (infinite or zero at the ends as it is, 0^0 = 1)."""
    from scipy.stats import beta

    from ptm_ros.perception.laser import beta_pdf

    for f in (0.0, 1e-12, 0.01, 0.15, 0.5, 0.99, 1.0 - 1e-12, 1.0):
        expected = float(beta.pdf(f, a, b))
        got = beta_pdf(f, a, b)
        if math.isinf(expected) or expected == 0.0:
            assert got == expected
        else:
            assert math.isclose(got, expected, rel_tol=1e-11)


def test_the_laser_module_and_its_fitness_evidence_leave_scipy_stats_unimported():
    """The fitness evidence comes from scipy.special: scipy.stats (about 0.3 s to import) stays out of a
    visit's update."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from ptm_ros.perception.laser import fitness_log_bayes, register_patch_pair, LaserConfig\n"
        "fitness_log_bayes(0.5)\n"
        "print('scipy.stats' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_laser_outcome_kinds():
    """A valid registration gives a RelativePose with the fitness evidence, an invalid one a NoMatch (or
    None when the fitness model is off)."""
    from dataclasses import replace as dc_replace

    from ptm_ros.model.geometry import NoMatch, RelativePose
    from ptm_ros.perception.laser import fitness_log_bayes, laser_outcome

    source, target = patch_pair(JUNCTION, TRUE, np.random.default_rng(5))
    good = register_patches(source, target)
    assert good.valid, good.reason
    z = laser_outcome(good, 2, 5, LaserConfig())
    assert isinstance(z, RelativePose) and (z.i, z.j) == (2, 5)
    assert z.log_bayes == fitness_log_bayes(good.inlier_fraction)
    bad = dc_replace(good, valid=False, reason="forced", inlier_fraction=0.12)
    nm = laser_outcome(bad, 2, 5, LaserConfig())
    assert isinstance(nm, NoMatch) and nm.log_bayes == fitness_log_bayes(0.12) < 0
    assert laser_outcome(bad, 2, 5, LaserConfig(use_fitness=False)) is None
    assert laser_outcome(good, 2, 5, LaserConfig(use_fitness=False)).log_bayes == 0.0
