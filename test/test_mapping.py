"""The online metric map (ptm_ros.maps.mapping): equal to ptm-run's map from the same samples, bounded, and
robust to sessions restarting."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ptm_ros.config import load_config
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.factories import cached, make_registrar
from ptm_ros.maps.mapping import KeyframeStream, MappingConfig, OnlineMap
from ptm_ros.maps.occupancy import aligned_windows as aligned
from ptm_ros.model.visits import Visit
from ptm_ros.tools.outputs import occupancy_grid
from ptm_ros.tools.pipeline import detect_visits, map_trajectory, merged_messages, run_extractor


@pytest.fixture(scope="module")
def loop_run(multi_loop_run):
    """The simulated multi-loop run of ``conftest.multi_loop_run``: run, config, visits, corrected odometry
    and the true topology."""
    return multi_loop_run[:5]


@pytest.fixture(scope="module")
def registrar(loop_run):
    """The registrar of :func:`loop_run`'s visits, each pair registered once a module."""
    _, config, visits, _, _ = loop_run
    return cached(make_registrar(visits, config))


@pytest.fixture(scope="module")
def full_map(loop_run, registrar):
    """ptm-run's map of :func:`loop_run` along its true topology: the smoothed and refined trajectory at
    every odometry sample and its occupancy grid."""
    run, config, visits, odom, labels = loop_run
    trajectory = map_trajectory(run, visits, tuple(labels), config, registrar, odometry=odom)
    return trajectory, occupancy_grid(run, trajectory, config)


def feed(online: OnlineMap, run, odom) -> None:
    """The odometry samples and scans in stamp order, as the map publisher receives them."""
    sc = run.scans
    for _, topic, k in merged_messages(run):
        if topic == 0:
            online.add_pose(run.odometry.stamps[k], odom[k])
        elif topic == 1:
            ranges = sc.ranges[k]
            online.add_scan(
                sc.stamps[k], ranges, sc.angle_min[k], sc.angle_increment[k], sc.range_min[k], sc.range_max[k]
            )


@pytest.mark.slow
def test_online_map_equals_ptm_run_map_from_the_same_samples(loop_run, registrar, full_map):
    run, config, visits, odom, labels = loop_run
    offline_traj, offline_grid = full_map

    every = MappingConfig(keyframe_xy=0.0, keyframe_yaw=0.0)
    online = OnlineMap(every)
    feed(online, run, odom)
    assert online.counters.resets == 0 and online.counters.poses == len(run.odometry.stamps)
    refine = {"refinement": config.refinement, "laser": config.laser}  # as the map publisher passes them
    res = online.build(visits, labels, config.model, config.occupancy, registration=registrar, **refine)
    np.testing.assert_array_equal(res.stamps, run.odometry.stamps)
    np.testing.assert_allclose(res.trajectory, offline_traj, atol=1e-9)
    assert res.grid is not None and offline_grid is not None
    assert res.grid.scans == offline_grid.scans == online.keyframes
    assert res.grid.origin == offline_grid.origin
    np.testing.assert_array_equal(res.grid.observed, offline_grid.observed)
    np.testing.assert_allclose(res.grid.log_odds, offline_grid.log_odds, atol=1e-9)

    # Without registrations the loops are not refined: a different (worse-constrained) trajectory.
    bare = online.build(visits, labels, config.model, config.occupancy)
    assert np.max(np.abs(bare.trajectory[:, :2] - res.trajectory[:, :2])) > 1e-3


@pytest.mark.slow
def test_default_online_map_keeps_keyframes_and_matches_the_full_map(loop_run, registrar, full_map):
    run, config, visits, odom, labels = loop_run
    full_traj, full = full_map
    online = OnlineMap(MappingConfig())
    feed(online, run, odom)
    c = online.counters
    assert c.poses == len(run.odometry.stamps) and c.scans == len(run.scans.stamps)
    assert 0 < c.keyframes < c.scans / 2
    assert c.scans_unposed == 0
    refine = {"refinement": config.refinement, "laser": config.laser}  # as the map publisher passes them
    res = online.build(visits, labels, config.model, config.occupancy, registration=registrar, **refine)
    # Keyframe poses are spaced by the configured motion (in the odometry the visits are measured in).
    kf = online.keyframe_scans()
    assert len(kf.stamps) == c.keyframes and np.all(np.diff(kf.stamps) > 0)
    # The smoothed trajectory at the visits passes through the same poses as the full-rate one …
    at = np.searchsorted(run.odometry.stamps, [v.stamp for v in visits])
    on = np.searchsorted(res.stamps, [v.stamp for v in visits])
    plain = replace(config, refinement=replace(config.refinement, enabled=False))
    full_plain = map_trajectory(run, visits, tuple(labels), plain, registrar, odometry=odom)
    res_plain = online.build(visits, labels, config.model, config.occupancy, registration=registrar)
    np.testing.assert_allclose(res_plain.trajectory[on], full_plain[at], atol=1e-6)
    # … and, refined by the keyframes' scan matches (fewer scans online than offline), nearly so.
    np.testing.assert_allclose(res.trajectory[on, :2], full_traj[at, :2], atol=0.05)
    # Same classes on nearly every cell both maps know (keyframes: fewer passes over each cell).
    assert res.grid is not None and full is not None
    a, b = aligned(res.grid.log_odds, res.grid.origin, full.log_odds, full.origin, full.resolution)
    ka, kb = aligned(res.grid.observed, res.grid.origin, full.observed, full.origin, full.resolution)
    known = ka & kb
    assert known.sum() > 1000
    assert np.mean((a > 0)[known] == (b > 0)[known]) > 0.95


def visit(k: int, t: float, x: float) -> Visit:
    return Visit(index=k, stamp=t, pose=(x, 0.0, 0.0), travel=1.0 if k else 0.0)


def test_clock_reset_and_teleport_start_a_new_session():
    m = OnlineMap(MappingConfig(keyframe_xy=0.0, keyframe_yaw=0.0))
    for k in range(20):
        m.add_pose(10.0 + 0.1 * k, (0.05 * k, 0.0, 0.0))
        m.add_scan(10.0 + 0.1 * k + 0.05, np.full(5, 2.0), -0.5, 0.25, 0.1, 10.0)
    assert m.keyframes == 19 and m.span == (10.0, 11.9)
    assert not m.add_pose(12.0, (1.0, 0.0, 0.0))
    assert m.add_pose(3.0, (0.0, 0.0, 0.0))  # the clock went back: a new session
    assert m.counters.resets == 1 and m.keyframes == 0 and m.span == (3.0, 3.0)
    m.add_pose(3.1, (0.05, 0.0, 0.0))
    assert m.add_pose(3.2, (50.0, 0.0, 0.0))  # 50 m in 0.1 s: a teleport
    assert m.counters.resets == 2 and m.span == (3.2, 3.2)
    m.add_scan(3.0, np.full(5, 2.0), -0.5, 0.25, 0.1, 10.0)  # before the session: never posed
    assert m.counters.scans_unposed == 1
    # Visits of the session ended by the reset lie before the kept odometry: refused.
    with pytest.raises(DataError, match="precedes"):
        m.build([visit(0, 1.0, 0.0)], [0], load_config().model)
    with pytest.raises(DataError, match="at least one visit"):
        m.build([], [], load_config().model)


def test_bad_samples_and_bounded_queue():
    m = OnlineMap(MappingConfig(max_pending_scans=3))
    m.add_pose(1.0, (0.0, 0.0, 0.0))
    m.add_pose(1.0, (0.0, 0.0, 0.0))  # duplicate stamp
    m.add_pose(1.1, (np.nan, 0.0, 0.0))
    m.add_pose(np.inf, (0.0, 0.0, 0.0))
    assert m.counters.poses_invalid == 3 and m.counters.resets == 0
    for k in range(5):  # ahead of the odometry: they wait, at most 3
        m.add_scan(2.0 + k, np.ones(3), 0.0, 0.1, 0.0, 5.0)
    assert m.counters.scans_unposed == 2 and m.keyframes == 0
    m.add_pose(10.0, (9.0, 0.0, 0.0))
    assert m.keyframes == 3  # 1 m apart each: all keyframes


def test_map_before_the_first_scan_and_single_visit():
    m = OnlineMap()
    for k in range(10):
        m.add_pose(float(k), (0.5 * k, 0.0, 0.0))
    res = m.build([visit(0, 4.0, 2.0)], [0], load_config().model)
    assert res.grid is None and len(res.keyframe_stamps) == 0
    np.testing.assert_allclose(res.trajectory[:, 0], 0.5 * res.stamps, atol=1e-12)


@pytest.mark.parametrize(
    ("field", "value"),
    [("period", -1.0), ("keyframe_xy", float("nan")), ("max_pending_scans", 0), ("max_speed", 0.0)],
)
def test_config_is_checked(field, value):
    with pytest.raises(ConfigError, match=field):
        MappingConfig(**{field: value})


@pytest.mark.slow
def test_the_detector_stream_draws_the_map_of_every_sample(loop_run, registrar):
    """The detector sends a few odometry samples per metre and the keyframe scans (KeyframeStream); the
    map publisher's map from them is the map of the full-rate streams."""
    run, config, visits, odom, labels = loop_run
    extractor = run_extractor(run, config)
    extractor.config = replace(extractor.config, stream_poses=True)
    assert detect_visits(run, config, extractor=extractor) == visits
    poses, scans = extractor.take_poses(), extractor.take_scans()
    assert len(poses) == len(run.odometry.stamps) and len(scans) == len(run.scans.stamps)
    np.testing.assert_allclose([p for _, p in poses], odom, atol=1e-12)  # the corrected odometry
    sent = KeyframeStream(config.mapping).select(poses, scans)
    stamps = [t for t, _, _ in sent]
    assert stamps == sorted(stamps)
    n_scans = sum(scan is not None for _, _, scan in sent)
    assert 0 < n_scans < len(scans) / 3 and 0 < len(sent) - n_scans < len(poses) / 2  # 20 Hz at 0.5 m/s

    streamed, full = OnlineMap(config.mapping), OnlineMap(config.mapping)
    for t, pose, scan in sent:
        if scan is None:
            streamed.add_pose(t, pose)
        else:
            streamed.add_scan(t, *scan)
    feed(full, run, odom)
    assert streamed.counters.resets == streamed.counters.poses_invalid == streamed.counters.scans_unposed == 0
    np.testing.assert_array_equal(streamed.keyframe_scans().stamps, full.keyframe_scans().stamps)
    a = streamed.build(visits, labels, config.model, config.occupancy, registration=registrar)
    b = full.build(visits, labels, config.model, config.occupancy, registration=registrar)
    at_a = np.searchsorted(a.stamps, [v.stamp for v in visits])
    at_b = np.searchsorted(b.stamps, [v.stamp for v in visits])
    np.testing.assert_allclose(a.trajectory[at_a], b.trajectory[at_b], atol=1e-9)  # same visit poses
    np.testing.assert_allclose(a.keyframe_poses, b.keyframe_poses, atol=0.02)  # 5 cm samples vs all
    la, lb = aligned(a.grid.log_odds, a.grid.origin, b.grid.log_odds, b.grid.origin, b.grid.resolution)
    oa, ob = aligned(a.grid.observed, a.grid.origin, b.grid.observed, b.grid.origin, b.grid.resolution)
    known = oa & ob
    assert np.mean((la > 0)[known] == (lb > 0)[known]) > 0.99
