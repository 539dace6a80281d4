"""Laser odometry: the scan-to-map correction removes a heading bias of the wheel odometry."""

from __future__ import annotations

import functools
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.io.simulator import CameraConfig, OdometryNoiseConfig, SimConfig, simulate
from ptm_ros.io.simulator import LaserConfig as SimLaserConfig
from ptm_ros.io.worlds import get_world
from ptm_ros.model.geometry import (
    between,
    compose,
    interpolate_poses,
    inverse,
    path_length,
    transform_points,
    wrap_angle,
)
from ptm_ros.perception.laser_odometry import (
    LaserOdometry,
    LaserOdometryConfig,
    LaserOdometryCounters,
    OffsetEstimate,
    OffsetScore,
    RunInput,
    YawCorrections,
    best_time_offset,
    learn_time_offset,
    offset_slope,
    scan_time_poses,
    time_offset_scores,
)
from ptm_ros.perception.patches import Alignment, scan_to_points


@pytest.fixture(scope="module")
def biased_run():
    """A T-junction run whose wheel odometry turns 0.05 rad too little per metre (like Intel's)."""
    noise = OdometryNoiseConfig(bias_init=0.05, bias_walk=0.0)
    return simulate(get_world("t-junction"), SimConfig(odometry=noise), np.random.default_rng(3), visits=4)


def corrected_scan_poses(run, config=None):
    lo = LaserOdometry(config or LaserOdometryConfig())
    cfg = run.config.laser
    wheel = interpolate_poses(run.odom_stamps, run.odom_poses, run.scan_stamps)
    out = []
    for w, ranges in zip(wheel, run.scan_ranges, strict=True):
        pts = scan_to_points(ranges, cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max).points
        out.append(lo.on_scan(w, pts))
    return wheel, np.array(out), lo


def heading_drift_per_metre(est, true):
    """Accumulated heading error over the run divided by the distance travelled (rad/m)."""
    d_est = np.sum(wrap_angle(np.diff(est[:, 2])))
    d_true = np.sum(wrap_angle(np.diff(true[:, 2])))
    return (d_est - d_true) / path_length(true)


def test_the_heading_bias_is_removed(biased_run):
    wheel, corrected, lo = corrected_scan_poses(biased_run)
    true = interpolate_poses(biased_run.odom_stamps, biased_run.true_poses, biased_run.scan_stamps)
    raw_drift = heading_drift_per_metre(wheel, true)
    lo_drift = heading_drift_per_metre(corrected, true)
    assert abs(raw_drift) > 0.03  # the simulated bias is there
    assert abs(lo_drift) < 0.1 * abs(raw_drift)
    # every scan is matched or inside the motion gate (10 Hz at 0.5 m/s: 5 cm apart, about half gated)
    assert lo.counters.matched + lo.counters.gated > 0.9 * len(wheel)
    assert lo.counters.matched > 0.3 * len(wheel) and lo.counters.gated > 0
    # end-to-end position error (the start pose is shared): far smaller than the wheel odometry's
    start = between(true[0], true[-1])
    err_lo = np.hypot(*(between(corrected[0], corrected[-1])[:2] - start[:2]))
    err_raw = np.hypot(*(between(wheel[0], wheel[-1])[:2] - start[:2]))
    assert err_lo < 0.2 * err_raw


def test_identity_before_any_scan_and_too_few_points():
    lo = LaserOdometry()
    pose = np.array([1.0, 2.0, 0.3])
    assert np.array_equal(lo.correct(pose), pose)
    out = lo.on_scan(pose, np.zeros((3, 2)))  # 3 points: no match, no keyframe
    assert np.allclose(out, pose)
    assert lo.counters.too_few_points == 1 and lo.counters.keyframes == 0
    with pytest.raises(ModelError, match="3 finite numbers"):
        lo.on_scan([0.0, math.nan, 0.0], np.zeros((20, 2)))


def test_a_teleport_is_rejected_not_followed(biased_run):
    """A wheel-odometry jump the scans cannot explain keeps the correction (counted as rejected)."""
    cfg = biased_run.config.laser
    wheel = interpolate_poses(biased_run.odom_stamps, biased_run.odom_poses, biased_run.scan_stamps)
    lo = LaserOdometry()
    for w, ranges in zip(wheel[:40], biased_run.scan_ranges[:40], strict=True):
        pts = scan_to_points(ranges, cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max).points
        lo.on_scan(w, pts)
    before = lo.correction
    rejected = lo.counters.rejected
    jumped = wheel[40] + np.array([0.0, 3.0, 1.2])  # the wheels claim a 3 m, 1.2 rad jump in one step
    pts = scan_to_points(
        biased_run.scan_ranges[40], cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max
    ).points
    lo.on_scan(jumped, pts)
    assert lo.counters.rejected == rejected + 1
    assert np.array_equal(lo.correction, before)


def room_scan(pose, step=0.02):
    """Points (robot frame) of a 6 m x 4 m room with a pillar, seen from ``pose`` (no occlusion needed:
    the matcher only needs consistent geometry)."""
    t = np.arange(0.0, 1.0, step / 6.0)[:, None]
    walls = [
        ((0.0, 0.0), (6.0, 0.0)),
        ((6.0, 0.0), (6.0, 4.0)),
        ((6.0, 4.0), (0.0, 4.0)),
        ((0.0, 4.0), (0.0, 0.0)),
    ]
    walls += [((2.0, 1.0), (2.5, 1.0)), ((2.5, 1.0), (2.5, 1.6))]  # a pillar's corner breaks the symmetry
    world = np.vstack([np.asarray(a) + t * (np.asarray(b) - np.asarray(a)) for a, b in walls])
    return transform_points(inverse(np.asarray(pose, dtype=float)), world)


def test_motion_gate_matches_only_after_enough_motion():
    """A scan closer than ``match_xy`` (and turned less than ``match_yaw``) to the last matched one is not
    matched and keeps the correction; one beyond either threshold is matched."""
    cfg = LaserOdometryConfig(match_xy=0.1, match_yaw=0.05)
    lo = LaserOdometry(cfg)
    start = np.array([3.0, 2.0, 0.2])
    lo.on_scan(start, room_scan(start))  # the first scan starts the map (no match)
    # the wheels under-report a 0.15 m step by 4 cm: the scan match corrects it
    true1 = compose(start, [0.15, 0.0, 0.0])
    wheel1 = compose(start, [0.11, 0.0, 0.0])
    pose1 = lo.on_scan(wheel1, room_scan(true1))
    assert lo.counters.matched == 1 and lo.counters.gated == 0
    assert np.hypot(*(pose1[:2] - true1[:2])) < 0.01
    correction = lo.correction
    assert np.hypot(*correction[:2]) > 0.02  # the correction moved off the identity
    # 5 cm further (below match_xy): gated, the pose is the kept correction applied to the wheels
    wheel2 = compose(wheel1, [0.05, 0.0, 0.0])
    pose2 = lo.on_scan(wheel2, room_scan(compose(true1, [0.05, 0.0, 0.0])))
    assert lo.counters.gated == 1 and lo.counters.matched == 1
    assert np.array_equal(lo.correction, correction)
    assert np.array_equal(pose2, compose(correction, wheel2))
    # 12 cm from the last matched scan (the gate measures from there, not from the gated scan): matched
    wheel3 = compose(wheel1, [0.12, 0.0, 0.0])
    lo.on_scan(wheel3, room_scan(compose(true1, [0.12, 0.0, 0.0])))
    assert lo.counters.matched == 2 and lo.counters.gated == 1
    # turning in place: 0.03 rad is gated, 0.06 rad (beyond match_yaw) is matched
    lo.on_scan(compose(wheel3, [0.0, 0.0, 0.03]), room_scan(compose(true1, [0.12, 0.0, 0.03])))
    assert lo.counters.matched == 2 and lo.counters.gated == 2
    pose5 = lo.on_scan(compose(wheel3, [0.0, 0.0, 0.06]), room_scan(compose(true1, [0.12, 0.0, 0.06])))
    assert lo.counters.matched == 3 and lo.counters.gated == 2
    assert np.hypot(*(pose5[:2] - compose(true1, [0.12, 0.0, 0.06])[:2])) < 0.01


def test_the_correction_limits_grow_with_the_travel_since_the_last_accepted_match():
    """The wheels' heading error grows with the travel it accrued over: after 0.5 m a 0.3 rad correction
    is beyond ``max_correction_yaw`` (0.2) and rejected; after 2 m (a laser logged at a low rate, or
    steps rejected in a row) the limit is twice that and the same error is corrected."""
    start = np.array([1.5, 2.0, 0.0])
    for travel, matched in ((0.5, False), (2.0, True)):
        lo = LaserOdometry()
        lo.on_scan(start, room_scan(start))  # the first map
        true = compose(start, [travel, 0.0, 0.0])
        wheel = compose(true, [0.0, 0.0, 0.3])  # the wheels turned 0.3 rad that the robot did not
        pose = lo.on_scan(wheel, room_scan(true))
        assert (lo.counters.matched, lo.counters.rejected) == ((1, 0) if matched else (0, 1))
        if matched:
            assert np.hypot(*(pose[:2] - true[:2])) < 0.02 and abs(wrap_angle(pose[2] - true[2])) < 0.01
        else:
            assert np.array_equal(pose, wheel)


def test_a_rejected_match_is_retried_from_turned_headings():
    """After 3 m without a match the heading limit is 0.6 rad, but ICP from a guess 0.45 rad off does not
    reach the true pose and the match was rejected; started again from the guess turned by ±0.3 and
    ±0.6 rad, one start lands in the right basin and the wheels' error is taken out."""
    start = np.array([1.0, 2.0, 0.0])
    lo = LaserOdometry()
    lo.on_scan(start, room_scan(start))  # the first map
    true = compose(start, [3.0, 0.0, 0.0])
    pose = lo.on_scan(compose(true, [0.0, 0.0, 0.45]), room_scan(true))
    assert (lo.counters.matched, lo.counters.rejected) == (1, 0)
    assert np.hypot(*(pose[:2] - true[:2])) < 0.02 and abs(wrap_angle(pose[2] - true[2])) < 0.01
    # beyond the limit nothing is accepted, from any start: 0.7 rad after 3 m keeps the wheel pose
    lo = LaserOdometry()
    lo.on_scan(start, room_scan(start))
    wheel = compose(true, [0.0, 0.0, 0.7])
    assert np.array_equal(lo.on_scan(wheel, room_scan(true)), wheel)
    assert (lo.counters.matched, lo.counters.rejected) == (0, 1)


class _ScriptedMap:
    """A local map whose alignment from each start heading (relative to the guess) is scripted:
    ``{turn: (pose, inlier fraction)}``; records the starts tried."""

    def __init__(self, guess, script):
        self.guess, self.script, self.turns = np.asarray(guess, dtype=float), script, []
        self.fractions = {}

    def align(self, points, start, **_):
        turn = round(float(wrap_angle(start[2] - self.guess[2])), 6)
        self.turns.append(turn)
        pose, fraction = self.script[turn]
        self.fractions[tuple(np.round(pose, 9))] = fraction
        return Alignment(np.asarray(pose, dtype=float), 0)

    def inlier_fraction(self, points, pose):
        return self.fractions[tuple(np.round(pose, 9))]


@pytest.mark.parametrize(
    ("from_guess", "from_turned", "kept"),
    [
        # from the guess: beyond the 0.2 rad limit but the best fit; a worse fit inside the limit is
        # not taken in its place
        (([0.0, 0.0, 0.25], 0.9), ([0.0, 0.0, 0.1], 0.5), None),
        # from the guess: too little of the scan on the map; a better fit from a turned start is kept
        (([0.0, 0.0, 0.05], 0.2), ([0.0, 0.0, 0.15], 0.8), [0.0, 0.0, 0.15]),
    ],
)
def test_the_best_fit_of_all_starts_decides_a_retried_match(from_guess, from_turned, kept):
    """A match rejected from the guess is retried from the guess turned by ±0.1 and ±0.2 rad (the limit
    after 0.5 m); the alignment with the largest inlier fraction is kept if it passes the tests."""
    start = np.array([1.5, 2.0, 0.0])
    lo = LaserOdometry()
    lo.on_scan(start, room_scan(start))
    wheel = compose(start, [0.5, 0.0, 0.0])
    script = {0.0: from_guess} | dict.fromkeys((-0.1, 0.1, -0.2, 0.2), from_turned)
    script = {t: (compose(wheel, pose), f) for t, (pose, f) in script.items()}
    lo._map = scripted = _ScriptedMap(wheel, script)
    pose = lo.on_scan(wheel, room_scan(wheel))
    assert scripted.turns == [0.0, -0.1, 0.1, -0.2, 0.2]
    if kept is None:
        assert np.array_equal(pose, wheel) and lo.counters.rejected == 1
    else:
        assert np.allclose(pose, compose(wheel, kept)) and lo.counters.matched == 1


def _turn_in_place(lo, slip, transient):
    """Turn in place in the room by 0.1 rad a scan, 12 scans after the first; at the first turn the wheels
    report ``slip`` rad that the robot did not turn, for good or (``transient``) for that scan alone.
    Returns each scan's returned pose and true pose."""
    start = np.array([3.0, 2.0, 0.0])
    lo.on_scan(start, room_scan(start))  # the first map
    out = []
    for k in range(1, 13):
        true = compose(start, [0.0, 0.0, 0.1 * k])
        wheel = compose(true, [0.0, 0.0, slip]) if k == 1 or not transient else true
        out.append((lo.on_scan(wheel, room_scan(true)), true))
    return out


def heading_error(pose, true):
    return abs(float(wrap_angle(pose[2] - true[2])))


def test_a_slip_beyond_the_limits_is_taken_out_once_the_next_scans_confirm_it():
    """Turning in place the travel does not grow the limits, and a 0.3 rad slip at one scan is rejected
    (``max_correction_yaw`` 0.2) though the scan fits the map at the true heading. Without a second look
    (``defer_scans`` 0) the odometry keeps the slip for good. With it, the alternative that accepted the
    fit places the next 10 scans on the branch's map better, replaces the rejection, and the odometry is
    right again; the poses returned meanwhile are the rejection's."""
    kept = _turn_in_place(LaserOdometry(LaserOdometryConfig(defer_scans=0)), 0.3, transient=False)
    assert all(heading_error(pose, true) > 0.25 for pose, true in kept)
    lo = LaserOdometry()
    revised = _turn_in_place(lo, 0.3, transient=False)
    assert (lo.counters.deferred, lo.counters.revised) == (1, 1)
    assert heading_error(*revised[0]) > 0.25  # the first hypothesis, meanwhile
    pose, true = revised[-1]  # the scan after the ten that judged the branch
    assert heading_error(pose, true) < 0.01 and np.hypot(*(pose[:2] - true[:2])) < 0.02
    assert lo.counters.rejected == 0 and lo.counters.matched == 12  # the counts of the hypothesis kept


def test_a_rejection_that_the_next_scans_heal_is_not_overruled():
    """When the wheels disagree with the scan for that one scan only (a scan taken off its stamp while
    turning), the rejection keeps the wheels, which are right from the next scan on; the alternative
    that took the scan's fit would carry a 0.3 rad error, places the next scans worse and is dropped."""
    lo = LaserOdometry()
    healed = _turn_in_place(lo, 0.3, transient=True)
    assert (lo.counters.deferred, lo.counters.revised) == (1, 0)
    assert all(heading_error(pose, true) < 0.01 for pose, true in healed[1:])


def test_a_dropped_second_hypothesis_leaves_no_trace():
    """Driving along the room, the wheels' heading is 0.3 rad off at one scan only: the rejection starts a
    second hypothesis, which is dropped; the poses, the correction and the learned wheel scale are those of
    the odometry that never looked again (``defer_scans`` 0), bit for bit."""
    start = np.array([1.0, 2.0, 0.0])
    runs = []
    for defer in (0, 10):
        lo = LaserOdometry(LaserOdometryConfig(defer_scans=defer))
        lo.on_scan(start, room_scan(start))
        poses = []
        for k in range(1, 14):
            true = compose(start, [0.15 * k, 0.0, 0.0])
            wheel = compose(true, [0.0, 0.0, 0.3]) if k == 1 else true
            poses.append(lo.on_scan(wheel, room_scan(true)))
        runs.append((lo, np.array(poses)))
    (never, poses0), (looked, poses1) = runs
    assert (looked.counters.deferred, looked.counters.revised) == (1, 0)
    assert np.array_equal(poses0, poses1) and np.array_equal(never.correction, looked.correction)
    assert never.wheel_scale == looked.wheel_scale != 1.0


def test_motion_gate_off_matches_every_scan():
    lo = LaserOdometry(LaserOdometryConfig(match_xy=0.0, match_yaw=0.0))
    pose = np.array([3.0, 2.0, 0.0])
    for _ in range(3):  # a robot standing still: every scan is matched without the gate
        lo.on_scan(pose, room_scan(pose))
    assert lo.counters.matched == 2 and lo.counters.gated == 0


def test_match_interval_matches_a_standing_robot_every_interval():
    """With stamps, a scan inside the motion gate is still matched once ``match_interval`` has passed since
    the last match: a robot standing still at 40 Hz is matched every 4th scan (0.1 s >= 0.09 s), and
    scans 0.1 s apart (10 Hz, the real logs and the simulator's default) are never gated."""
    pose = np.array([3.0, 2.0, 0.0])
    lo = LaserOdometry(LaserOdometryConfig(match_interval=0.09))
    for k in range(9):  # 0.000, 0.025, ..., 0.200 s
        lo.on_scan(pose, room_scan(pose), stamp=100.0 + 0.025 * k)
    assert lo.counters.matched == 2 and lo.counters.gated == 6  # first scan starts the map; 0.1, 0.2 s
    slow = LaserOdometry(LaserOdometryConfig(match_interval=0.09))
    for k in range(4):
        slow.on_scan(pose, room_scan(pose), stamp=100.0 + 0.1 * k)
    assert slow.counters.matched == 3 and slow.counters.gated == 0
    motion_only = LaserOdometry(LaserOdometryConfig(match_interval=0.0))  # 0: the motion gate alone
    for k in range(4):
        motion_only.on_scan(pose, room_scan(pose), stamp=100.0 + 0.1 * k)
    assert motion_only.counters.matched == 0 and motion_only.counters.gated == 3


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("window", 0, "window"),
        ("match_interval", -0.1, "match_interval"),
        ("match_interval", math.inf, "match_interval"),
        ("voxel", 0.1, "voxel"),
        ("max_correction_yaw", -1.0, "max_correction_yaw"),
        ("enabled", 1, "enabled"),
        ("match_xy", -0.1, "match_xy"),
        ("match_xy", 0.3, "keyframe_xy"),  # beyond the keyframe spacing (0.25)
        ("match_yaw", math.nan, "match_yaw"),
        ("match_yaw", True, "match_yaw"),
    ],
)
def test_bad_config(field, value, match):
    with pytest.raises(ConfigError, match=match):
        LaserOdometryConfig(**{field: value})


@pytest.mark.slow
def test_apply_corrections_reproduces_the_extractor_poses():
    """Carrying the wheel odometry by the recorded corrections gives back, at every visit stamp, exactly the
    pose the extractor gave the visit (the latest scan strictly before; identity before the first)."""
    from ptm_ros.perception.landmarks import ExtractorConfig, VisitExtractor
    from ptm_ros.perception.laser_odometry import apply_corrections

    run = simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(5), visits=3)
    cfg = run.config.laser
    ext = VisitExtractor(config=ExtractorConfig(use_images=False, record_corrections=True))
    visits = []
    for t, topic, k in run.events(images=False):
        if topic == 0:
            visits += ext.on_odometry(t, run.odom_poses[k])
        else:
            visits += ext.on_scan(
                t, run.scan_ranges[k], cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max
            )
    visits += ext.flush()
    assert len(visits) >= 3 and len(ext.corrections) == len(run.scan_stamps)
    stamps = [t for t, _ in ext.corrections]
    corrected = apply_corrections(run.odom_stamps, run.odom_poses, stamps, [c for _, c in ext.corrections])
    for v in visits:
        k = int(np.flatnonzero(run.odom_stamps == v.stamp)[0])
        assert tuple(corrected[k]) == v.pose
        assert v.odom_pose == tuple(run.odom_poses[k])
    before = run.odom_stamps <= stamps[0]
    assert np.array_equal(corrected[before], run.odom_poses[before])
    with pytest.raises(ModelError, match="matching"):
        apply_corrections(run.odom_stamps, run.odom_poses[:-1], stamps, [c for _, c in ext.corrections])


@pytest.mark.parametrize("value", [0.05, -1.5, True, float("nan")])
def test_time_offset_must_be_a_past_offset_of_at_most_a_second(value):
    with pytest.raises(ConfigError, match=r"time_offset must be a finite number in \[-1, 0\]"):
        LaserOdometryConfig(time_offset=value)


def test_scan_time_poses_interpolate_the_odometry_at_the_offset():
    stamps = np.array([0.0, 1.0, 2.0, 3.0])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [2.0, 1.0, 1.0], [2.0, 2.0, 3.0]])
    np.testing.assert_array_equal(scan_time_poses(stamps, poses, 0.0), poses)
    moved = scan_time_poses(stamps, poses, -0.25)
    np.testing.assert_array_equal(moved[0], poses[0])  # before the input began: its first pose
    np.testing.assert_allclose(moved[1], [0.75, 0.0, 0.375])
    np.testing.assert_allclose(moved[3], [2.0, 1.75, 1.0 + 0.75 * wrap_angle(2.0)])


@pytest.mark.slow
@pytest.mark.parametrize("laser_odometry", [True, False])
def test_extractor_works_in_the_scans_time_frame(sim_bag, laser_odometry):
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.tools.pipeline import corrected_odometry, detect_visits, run_extractor

    run = read_run(sim_bag)  # t-junction, 5 visits
    over = {"laser_odometry": {"time_offset": -0.15, "enabled": laser_odometry}}
    config = load_config(None, {**over, "detector": {"kind": "equidistant"}})
    extractor = run_extractor(run, config)
    visits = detect_visits(run, config, extractor=extractor)
    base = corrected_odometry(run, extractor)  # what the offline smoothing starts from
    stamps, raw = run.odometry.stamps, run.odometry.poses
    shifted = scan_time_poses(stamps, raw, -0.15)
    assert len(visits) >= 3
    for v in visits:
        k = int(np.flatnonzero(stamps == v.stamp)[0])
        assert v.odom_pose == tuple(raw[k])  # ptm.json keeps the input odometry at the visit's stamp
        assert v.pose == tuple(base[k])  # the extractor and the offline trajectory agree bit for bit
        if not laser_odometry:
            assert v.pose == tuple(shifted[k])
    plain = load_config(
        None, {"laser_odometry": {"enabled": laser_odometry}, "detector": {"kind": "equidistant"}}
    )
    assert [v.pose for v in detect_visits(run, plain)] != [v.pose for v in visits]


def _delayed_run(delay: float):
    """An aliased-loop run whose laser driver stamps each scan ``delay`` s after taking it."""
    cfg = SimConfig(laser=SimLaserConfig(stamp_delay=delay), camera=CameraConfig(enabled=False))
    return simulate(get_world("aliased-loop"), cfg, np.random.default_rng(3), visits=4)


def _points(run):
    cfg = run.config.laser
    return [
        scan_to_points(r, cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max).points
        for r in run.scan_ranges
    ]


def test_the_simulated_stamp_delay_shifts_only_the_scan_stamps():
    plain, late = _delayed_run(0.0), _delayed_run(0.15)
    np.testing.assert_allclose(late.scan_stamps - plain.scan_stamps, 0.15, atol=1e-9)
    np.testing.assert_array_equal(late.scan_ranges, plain.scan_ranges)
    np.testing.assert_array_equal(late.odom_poses, plain.odom_poses)


@pytest.mark.parametrize("delay", [0.0, 0.15])
@pytest.mark.slow
def test_the_time_offset_is_recovered_from_the_heading_corrections(delay):
    """The laser odometry's heading corrections are smallest (RMS) at the offset that undoes the delay;
    measured on the run's 463 scans: 2.4 mrad at the right offset, 5.5-5.8 mrad 0.15 s off."""
    run = _delayed_run(delay)
    n = len(run.scan_stamps)
    scores = time_offset_scores(
        run.odom_stamps, run.odom_poses, run.scan_stamps, _points(run), [0, -0.15, -0.3]
    )
    assert [s.offset for s in scores] == [0.0, -0.15, -0.3]
    assert all(s.matched > 0.95 * n for s in scores)
    assert best_time_offset(scores) == -delay
    right = next(s for s in scores if s.offset == -delay)
    assert all(s.rms_yaw_correction > 1.5 * right.rms_yaw_correction for s in scores if s is not right)
    # the median does not tell: most scan steps do not turn
    assert max(s.median_yaw_correction for s in scores) < 1.5 * min(s.median_yaw_correction for s in scores)


def test_offset_slope_is_the_offset_error_under_a_slow_drift():
    """The running sum of the corrections is (δ - o)·ω plus a slow drift: the slope recovers δ - o."""
    t = np.arange(0.0, 60.0, 0.02)
    heading = 0.8 * np.sin(0.5 * t) + 0.3 * np.sin(1.3 * t)  # a robot turning left and right
    poses = np.stack([np.zeros_like(t), np.zeros_like(t), wrap_angle(heading)], axis=1)
    run = RunInput.of(t, poses, t[::5], [np.zeros((0, 2))] * len(t[::5]))
    stamps = t[10:-10:5]
    rate = 0.4 * np.cos(0.5 * stamps) + 0.39 * np.cos(1.3 * stamps)  # d heading / dt
    for offset, delta in ((0.0, -0.15), (-0.1, -0.25), (-0.2, -0.2)):
        total = (delta - offset) * rate + 0.002 * stamps  # plus a heading bias the matches remove
        yaw = np.diff(total, prepend=0.0)
        yc = YawCorrections(offset, stamps, yaw, LaserOdometryCounters())
        slope, energy = offset_slope(run, yc)
        assert slope == pytest.approx(delta - offset, abs=0.01) and energy > 0.0
    standing = RunInput.of(t, np.zeros_like(poses), t[::5], [np.zeros((0, 2))] * len(t[::5]))
    still = YawCorrections(0.0, stamps, np.full(len(stamps), 1e-3), LaserOdometryCounters())
    assert offset_slope(standing, still) == (0.0, 0.0)  # never turned: nothing to learn from


@functools.cache
def learned(delay: float) -> tuple[RunInput, OffsetEstimate]:
    """The odometry and the first 300 scans of :func:`_delayed_run` and what learn_time_offset learns from
    them (once a test process)."""
    run = _delayed_run(delay)
    data = RunInput.of(run.odom_stamps, run.odom_poses, run.scan_stamps[:300], _points(run)[:300])
    return data, learn_time_offset(data)


@pytest.mark.parametrize("delay", [0.0, 0.15])
@pytest.mark.slow
def test_the_time_offset_is_learned_from_the_run(delay):
    """learn_time_offset on the first 300 scans finds the delay of a simulated laser (the regression's
    estimate picks the candidates, their heading corrections choose), and 0 for one on time after a
    single pass."""
    est = learned(delay)[1]
    assert est.scans == 300 and est.scores[0].offset == 0.0 and est.scores[0].matched > 280
    assert est.offset == -delay
    if delay:
        tried = [s.offset for s in est.scores]
        assert tried == [0.0, -0.1, -0.15, -0.2]  # the regression said about -0.14: -0.15 and its neighbours
        assert est.first == pytest.approx(-delay, abs=0.03)
    else:
        assert len(est.scores) == 1 and abs(est.first) < LaserOdometryConfig().learn_step / 2


@pytest.mark.slow
def test_the_candidate_passes_run_in_the_workers_with_the_same_estimate():
    """With workers, the candidates after the first run there (``ptm-run``'s worker processes): the same
    passes, so the same estimate, scores and all."""
    data, alone = learned(0.15)
    sent: list[float] = []

    class Recording(ThreadPoolExecutor):
        def submit(self, fn, /, *args, **kwargs):
            sent.append(args[1])
            return super().submit(fn, *args, **kwargs)

    with Recording(max_workers=2) as pool:
        assert learn_time_offset(data, workers=pool) == alone
    assert sent == [-0.15, -0.2]  # the first candidate, -0.1, ran here


def test_best_time_offset_keeps_the_stamps_unless_an_offset_is_clearly_better():
    def score(offset, rms):
        return OffsetScore(
            offset=offset, median_yaw_correction=0.0, rms_yaw_correction=rms, matched=9, rejected=0
        )

    assert best_time_offset([score(0.0, 1.0), score(-0.1, 0.97)]) == 0.0  # 3 % better: not enough
    assert best_time_offset([score(0.0, 1.0), score(-0.1, 0.9), score(-0.2, 0.8)]) == -0.2
    assert best_time_offset([score(0.0, 1.0), score(-0.1, 0.97)], min_gain=0.0) == -0.1
    assert best_time_offset([score(0.0, 1.0), score(-0.1, math.nan)]) == 0.0  # no matched scan there
    with pytest.raises(ModelError, match="include 0"):
        best_time_offset([score(-0.1, 0.5)])
    with pytest.raises(ModelError, match="min_gain"):
        best_time_offset([score(0.0, 1.0)], min_gain=1.0)
    with pytest.raises(ModelError, match=r"\[-1, 0\]"):
        time_offset_scores([0.0, 1.0], np.zeros((2, 3)), [0.5], [np.zeros((0, 2))], [0.1])
    with pytest.raises(ModelError, match="matching"):
        time_offset_scores([0.0, 1.0], np.zeros((2, 3)), [0.5, 0.6], [np.zeros((0, 2))], [0.0])


@pytest.mark.slow
def test_ptm_calibrate_writes_the_offset_into_the_parameters(tmp_path, capsys):
    import json

    from ptm_ros.config import load_config
    from ptm_ros.io.bag import BagWriter
    from ptm_ros.io.simulator import write_run
    from ptm_ros.tools import calibrate

    bag = write_run(_delayed_run(0.15), tmp_path / "late")
    out = tmp_path / "params.yaml"
    args = [str(bag), "--max-scans", "400", "--offsets", "-0.15", "-0.3", "--out", str(out)]
    assert calibrate.main(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["schema"] == "ptm_ros.calibration/1" and report["scans"] == 400
    assert [s["offset"] for s in report["offsets"]] == [0.0, -0.15, -0.3]
    assert report["time_offset"] == -0.15
    written = load_config(out).laser_odometry
    assert written.time_offset == -0.15 and not written.learn_time_offset  # fixed, not learned again
    assert calibrate.main([str(bag), "--offsets", "0.2"]) == 2
    assert "[-1, 0]" in capsys.readouterr().err
    assert calibrate.main([str(tmp_path / "missing")]) == 2
    assert calibrate.main([str(bag), "--max-scans", "1"]) == 2
    capsys.readouterr()
    odom_only = tmp_path / "odom-only"
    with BagWriter(odom_only) as w:
        for k in range(5):
            w.write_odometry(float(k), (0.1 * k, 0.0, 0.0))
    assert calibrate.main([str(odom_only)]) == 2
    assert "lacks required topic /scan" in capsys.readouterr().err


def corridor_travel(degenerate_ratio: float, seed: int) -> tuple[float, float]:
    """(wheel, corrected) travel of 8 m along a 2 m wide, 60 m long corridor (1 cm range noise, 5 cm of
    travel per scan): only the walls' normals, estimated from noisy points, see the along-track axis."""
    from ptm_ros.io.simulator import simulate_scans

    walls = np.array([[-30.0, -1.0, 30.0, -1.0], [30.0, 1.0, -30.0, 1.0]])
    laser = SimLaserConfig()
    rng = np.random.default_rng(seed)
    true = np.column_stack([np.arange(-4.0, 4.0, 0.05), np.zeros(160), np.zeros(160)])
    ranges = simulate_scans(walls, true, laser, rng)
    lo = LaserOdometry(LaserOdometryConfig(degenerate_ratio=degenerate_ratio))
    poses = [
        lo.on_scan(pose, scan_to_points(r, -laser.fov / 2, laser.fov / (laser.beams - 1), 0.05, 20.0).points)
        for pose, r in zip(true, ranges, strict=True)  # a perfect wheel odometry: the truth
    ]
    return path_length(true), float(poses[-1][0] - poses[0][0])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.slow
def test_the_correction_keeps_the_wheel_travel_along_a_corridor(seed):
    """Issue #23: scan matching does not erase travel along a corridor (the direction its walls do not
    constrain keeps the wheel odometry, :func:`ptm_ros.perception.laser.keep_unobserved`), while it still
    corrects across it."""
    wheel, corrected = corridor_travel(0.05, seed)
    assert corrected == pytest.approx(wheel, rel=0.02)
    assert corridor_travel(0.0, seed)[1] < 0.95 * wheel  # off: the travel is eroded


def room_then_corridor(
    wheel_scale: float, degenerate_ratio: float, seed: int = 0
) -> tuple[LaserOdometry, list]:
    """A 6 x 6 m room (its far wall, with a 2 m wide corridor mouth, constrains every direction) opening
    into a 40 m corridor; the robot drives 5 m through the room and 8 m down the corridor, 5 cm per scan,
    with wheel odometry that reads ``wheel_scale`` times the true travel."""
    from ptm_ros.io.simulator import simulate_scans

    walls = np.array(
        [
            [-6.0, -3.0, 0.0, -3.0],
            [0.0, -3.0, 0.0, -1.0],
            [0.0, -1.0, 40.0, -1.0],
            [40.0, 1.0, 0.0, 1.0],
            [0.0, 1.0, 0.0, 3.0],
            [0.0, 3.0, -6.0, 3.0],
            [-6.0, 3.0, -6.0, -3.0],
        ]
    )
    laser = SimLaserConfig()
    x = np.arange(-5.0, 8.0, 0.05)
    true = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    ranges = simulate_scans(walls, true, laser, np.random.default_rng(0))
    wheel = true.copy()
    wheel[:, 0] = -5.0 + wheel_scale * (x + 5.0)
    lo = LaserOdometry(LaserOdometryConfig(degenerate_ratio=degenerate_ratio, scale_prior_m=0.5))
    poses = [
        lo.on_scan(pose, scan_to_points(r, -laser.fov / 2, laser.fov / (laser.beams - 1), 0.05, 20.0).points)
        for pose, r in zip(wheel, ranges, strict=True)
    ]
    return lo, poses


@pytest.mark.slow
def test_the_wheel_scale_is_learned_where_the_scans_constrain_every_direction():
    """Issue #23: a wheel odometry that under-reads travel by 5 % (MIT-CSAIL's reads 2.3 % short) is
    scaled along the corridor by what the constrained matches in the room showed, not kept as it reads."""
    lo, poses = room_then_corridor(0.95, 0.05)
    assert lo.wheel_scale == pytest.approx(1.0 / 0.95, rel=0.01)
    in_corridor = [p for p in poses if p[0] > 1.0]
    travel = in_corridor[-1][0] - in_corridor[0][0]
    true_travel = 0.05 * (len(in_corridor) - 1)
    assert travel == pytest.approx(true_travel, rel=0.02)  # the wheel's own reading is 5 % short
    off, _ = room_then_corridor(0.95, 0.0)
    assert off.wheel_scale == 1.0  # learned only where wheel motion is kept (degenerate_ratio > 0)
    lo_exact, _ = room_then_corridor(1.0, 0.05)
    assert lo_exact.wheel_scale == pytest.approx(1.0, abs=0.01)


@pytest.mark.slow
def test_a_corridor_alone_teaches_no_wheel_scale():
    """Matches that leave a direction to the wheel odometry measure no travel: the scale stays the prior."""
    walls = np.array([[-30.0, -1.0, 30.0, -1.0], [30.0, 1.0, -30.0, 1.0]])
    from ptm_ros.io.simulator import simulate_scans

    laser = SimLaserConfig()
    true = np.column_stack([np.arange(-4.0, 4.0, 0.05), np.zeros(160), np.zeros(160)])
    ranges = simulate_scans(walls, true, laser, np.random.default_rng(0))
    lo = LaserOdometry(LaserOdometryConfig(degenerate_ratio=0.05))
    for pose, r in zip(true * [0.9, 1.0, 1.0], ranges, strict=True):
        lo.on_scan(pose, scan_to_points(r, -laser.fov / 2, laser.fov / (laser.beams - 1), 0.05, 20.0).points)
    assert lo.wheel_scale == 1.0


def test_keep_unobserved_reverts_only_the_weak_directions():
    from ptm_ros.perception.laser import keep_unobserved

    guess = np.array([1.0, 2.0, 0.3])
    pose = np.array([1.5, 2.2, 0.35])
    info = np.diag([2.0, 1000.0, 50.0])  # x hardly seen, y well
    assert np.allclose(keep_unobserved(pose, guess, info, 0.05), [1.0, 2.2, 0.35])
    assert np.array_equal(keep_unobserved(pose, guess, info, 0.0), pose)
    assert np.allclose(keep_unobserved(pose, guess, np.diag([900.0, 1000.0, 5.0]), 0.05), pose)
    assert np.array_equal(keep_unobserved(pose, guess, np.zeros((3, 3)), 0.05), pose)
    c, s = math.cos(0.7), math.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    turned = keep_unobserved(pose, guess, rot @ info @ rot.T, 0.05)  # the weak axis turned by 0.7 rad
    weak = rot[:2, 0]
    assert abs(weak @ (turned[:2] - guess[:2])) < 1e-12
    assert np.allclose(rot[:2, 1] @ (turned[:2] - guess[:2]), rot[:2, 1] @ (pose[:2] - guess[:2]))


@pytest.mark.slow
def test_the_extractor_learns_the_offset_then_processes_every_message_with_it(tmp_path):
    """With learn_time_offset (the default) the extractor holds the messages until learn_scans scans are
    in, learns the offset, and then gives exactly the visits of an extractor told that offset; with fewer
    scans than learn_scans it learns at the end of the data."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.simulator import write_run
    from ptm_ros.perception.landmarks import ODOM, SCAN
    from ptm_ros.tools.pipeline import detect_visits, merged_messages, run_extractor

    run = read_run(write_run(_delayed_run(0.15), tmp_path / "late"))
    detector = {"detector": {"kind": "equidistant"}}
    learned = run_extractor(run, load_config(None, {**detector, "laser_odometry": {"learn_scans": 200}}))
    scans_before_first_visit, visits = 0, []
    for stamp, topic, k in merged_messages(run):  # as detect_visits feeds them, counting the scans
        if topic == SCAN:
            sc = run.scans
            fields = (sc.ranges[k], sc.angle_min[k], sc.angle_increment[k], sc.range_min[k], sc.range_max[k])
            visits += learned.on_scan(stamp, *fields)
            scans_before_first_visit += not visits
        elif topic == ODOM:
            visits += learned.on_odometry(stamp, run.odometry.poses[k])
    visits += learned.flush()
    assert scans_before_first_visit >= 199  # nothing comes out while the offset is learned
    offset = learned.time_offset
    assert offset == pytest.approx(-0.15, abs=0.04)
    assert learned.time_offset_estimate is not None
    assert learned.time_offset_estimate.offset == offset and learned.time_offset_estimate.scans == 200
    fixed = load_config(
        None, {**detector, "laser_odometry": {"time_offset": offset, "learn_time_offset": False}}
    )
    told = detect_visits(run, fixed)
    assert len(visits) >= 3
    assert [(v.stamp, v.pose) for v in visits] == [(v.stamp, v.pose) for v in told]
    # fewer scans than learn_scans: learned from all of them when the data ends
    everything = load_config(None, {**detector, "laser_odometry": {"learn_scans": 100_000}})
    at_end = run_extractor(run, everything)
    assert len(detect_visits(run, everything, extractor=at_end)) == len(told)
    assert at_end.time_offset_estimate is not None
    assert at_end.time_offset_estimate.scans == len(run.scans.stamps)
    assert at_end.time_offset == pytest.approx(-0.15, abs=0.04)


def test_a_silent_laser_does_not_hold_the_visits_back():
    """With learn_time_offset on and no scan ever received, the learning ends after stall_s of odometry
    (with nothing learned): the visits come out while the odometry streams, not at the end of the data."""
    from ptm_ros.perception.landmarks import ExtractorConfig, VisitExtractor

    extractor = VisitExtractor(config=ExtractorConfig(use_images=False))
    online = []
    for k in range(600):  # 60 s at 10 Hz, 0.5 m/s along x
        online += extractor.on_odometry(0.1 * k, (0.05 * k, 0.0, 0.0))
    assert online and extractor.time_offset_estimate is None and extractor.time_offset == 0.0
    assert len(online + extractor.flush()) >= 10
