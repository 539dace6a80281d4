"""Keyframe scan matching along revisited passages (ptm_ros.maps.refinement) and the robust pose-graph solver
it shares with the smoothing (ptm_ros.maps.smoothing.robust_optimum)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.factories import cached, make_registrar
from ptm_ros.maps.mapping import scan_points
from ptm_ros.maps.posegraph import RelativeFactors
from ptm_ros.maps.refinement import RefinementConfig, keyframe_scans, refine_trajectory
from ptm_ros.maps.smoothing import RobustGraph, SmoothingConfig, robust_optimum, smooth_topology
from ptm_ros.model.geometry import between
from ptm_ros.scoring.evaluation import absolute_trajectory_error
from ptm_ros.tools.pipeline import map_trajectory


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("enabled", 1),
        ("keyframe_xy", 0.0),
        ("search_radius", float("nan")),
        ("max_shift", -1.0),
        ("submap_travel", True),
        ("rounds", 0),
        ("max_candidates", 2.5),
        ("corridors", "yes"),
        ("corridor_std", 0.0),
    ],
)
def test_config_rejects_bad_values(field, value):
    with pytest.raises(ConfigError, match=f"RefinementConfig.{field}"):
        RefinementConfig(**{field: value})


def test_keyframes_follow_travel_or_turning():
    travel = np.array([0.0, 0.4, 0.9, 1.0, 1.5, 2.1, 2.1, 2.1])
    turned = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.6, 0.7])
    assert keyframe_scans(travel, turned, 1.0, 0.5).tolist() == [0, 3, 5, 6]
    assert keyframe_scans([], [], 1.0, 0.5).tolist() == []


def _chain(n: int, robust_from: int, extra: list[tuple[int, int, tuple[float, float, float], float]]):
    """``n`` poses 1 m apart along x (odometry, σ 0.1 m, 0.01 rad), plus ``extra`` factors ``(a, b, z, σ)``
    that are Cauchy."""
    a = [*range(n - 1), *(e[0] for e in extra)]
    b = [*range(1, n), *(e[1] for e in extra)]
    z = [(1.0, 0.0, 0.0)] * (n - 1) + [e[2] for e in extra]
    sig = [np.array([0.1, 0.1, 0.01])] * (n - 1) + [np.array([e[3], e[3], 0.01]) for e in extra]
    w = np.array([np.diag(1.0 / s) for s in sig])
    factors = RelativeFactors(a=np.array(a), b=np.array(b), z=np.array(z, dtype=float), w=w)
    robust = np.arange(len(a)) >= robust_from
    no_pairs = np.zeros((0, 2), dtype=np.intp)
    return RobustGraph(factors=factors, robust=robust, pairs=no_pairs, scales=np.zeros(0))


def test_robust_optimum_keeps_a_consistent_match_and_lets_a_wrong_one_go():
    x0 = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    # Consistent with the odometry: 0 → 9 is (9, 0.05, 0): kept, the chain bends towards it.
    good = _chain(10, 9, [(0, 9, (9.0, 0.05, 0.0), 0.05)])
    x, w, rounds = robust_optimum(x0, good, SmoothingConfig())
    assert rounds >= 1 and w.factors[-1] > 0.5 and np.all(w.factors[:9] == 1.0)
    assert 0.0 < x[9, 1] <= 0.05 + 1e-9
    # A match claiming that 0 and 9 coincide (9 m off): its weight collapses and the odometry stands.
    bad = _chain(10, 9, [(0, 9, (0.0, 0.0, 0.0), 0.05)])
    x, w, _ = robust_optimum(x0, bad, SmoothingConfig())
    assert w.factors[-1] < 0.01
    assert np.max(np.abs(x[:, :2] - x0[:, :2])) < 0.2
    # Nothing robust (and no place pairs): x0 is taken as the Gaussian optimum, unchanged.
    xg, wg, rounds = robust_optimum(x0, replace(bad, robust=np.zeros(10, dtype=bool)), SmoothingConfig())
    assert rounds == 0 and np.array_equal(xg, x0) and np.all(wg.factors == 1.0)


@pytest.mark.slow
def test_refinement_cuts_the_trajectory_error_of_a_revisited_run(multi_loop_run):
    run, config, visits, odom, labels, true_poses = multi_loop_run
    registrar = cached(make_registrar(visits, config))
    plain_cfg = replace(config, refinement=replace(config.refinement, enabled=False))
    plain = map_trajectory(run, visits, tuple(labels), plain_cfg, registrar, odometry=odom)
    refined = map_trajectory(run, visits, tuple(labels), config, registrar, odometry=odom)
    ate_plain = absolute_trajectory_error(plain[:, :2], true_poses[:, :2])
    ate_refined = absolute_trajectory_error(refined[:, :2], true_poses[:, :2])
    assert ate_refined < 0.6 * ate_plain, (ate_plain, ate_refined)  # measured 0.102 -> 0.021 m

    stamps, points = scan_points(run.scans, config.laser)
    res = refine_trajectory(
        run.odometry.stamps, odom, stamps, points, labels, visits, config.model.odometry, laser=config.laser
    )
    assert res.keyframes > 0 and np.all(np.diff(res.nodes) > 0) and res.tried >= len(res.closures) > 0
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(odom[:, :2], axis=0).T))])
    cfg = RefinementConfig()
    for c in res.closures:
        na, nb = res.nodes[c.a], res.nodes[c.b]
        assert travel[nb] - travel[na] >= cfg.min_travel  # far apart along the path …
        truth = between(true_poses[na], true_poses[nb])
        error = c.mean[:2] - truth[:2]
        if c.slide_axis is not None:  # a corridor match: only the offset across the corridor counts …
            error = error - (error @ c.slide_axis) * c.slide_axis
            spread = np.linalg.eigvalsh(c.cov[:2, :2])[-1]
            assert spread >= cfg.corridor_std**2  # … and its covariance is wide along the corridor
        if c.weight > 0.5:  # … and a match the solution keeps is right (the simulator's truth)
            assert np.hypot(*error) < 0.25
    assert np.mean([c.weight > 0.5 for c in res.closures]) > 0.8
    corridors = [c for c in res.closures if c.slide_axis is not None]
    assert corridors and len(corridors) < len(res.closures)  # measured: both kinds on this run
    sharp = refine_trajectory(
        run.odometry.stamps,
        odom,
        stamps,
        points,
        labels,
        visits,
        config.model.odometry,
        laser=config.laser,
        config=replace(cfg, corridors=False),
    )
    assert all(c.slide_axis is None for c in sharp.closures) and len(sharp.closures) < len(res.closures)


@pytest.mark.slow
def test_without_scan_points_it_is_the_smoothing(multi_loop_run):
    run, config, visits, odom, labels, _ = multi_loop_run
    stamps = run.odometry.stamps
    empty = [np.zeros((0, 2))] * 5
    res = refine_trajectory(stamps, odom, stamps[10:15], empty, labels, visits, config.model.odometry)
    assert res.keyframes == 0 and res.closures == ()
    smooth = smooth_topology(stamps, odom, labels, visits, config.model.odometry)
    np.testing.assert_array_equal(res.trajectory, smooth)


@pytest.mark.slow
def test_inputs_are_checked(multi_loop_run):
    run, config, visits, odom, labels, _ = multi_loop_run
    stamps, odo = run.odometry.stamps, config.model.odometry
    pts = [np.zeros((3, 2))] * 2
    with pytest.raises(ModelError, match="matching"):
        refine_trajectory(stamps, odom[:-1], stamps[:2], pts, labels, visits, odo)
    with pytest.raises(ModelError, match="matching"):
        refine_trajectory(stamps, odom, stamps[:3], pts, labels, visits, odo)
    with pytest.raises(ModelError, match="increasing"):
        refine_trajectory(stamps, odom, stamps[[5, 4]], pts, labels, visits, odo)
    moved = [replace(v, stamp=v.stamp + 1e-4) for v in visits]
    with pytest.raises(ModelError, match="odometry stamps"):
        refine_trajectory(stamps, odom, stamps[:2], pts, labels, moved, odo)


@pytest.mark.slow
def test_worker_processes_refine_exactly_as_one(multi_loop_run):
    """The registrations of a round are independent: a pool of worker processes (ptm-run --jobs) gives the
    same refinement, bit for bit, as one after the other."""
    from ptm_ros.tools.workers import RegistrationPool

    run, config, visits, odom, labels, _ = multi_loop_run
    stamps, points = scan_points(run.scans, config.laser)
    args = (run.odometry.stamps, odom, stamps, points, labels, visits, config.model.odometry)
    alone = refine_trajectory(*args, laser=config.laser)
    with RegistrationPool(2, min_batch=1) as pool:
        pooled = refine_trajectory(*args, laser=config.laser, mapper=pool)
        assert pool._pool is not None  # the workers did the matching
    assert pooled.tried == alone.tried > 0 and len(pooled.closures) == len(alone.closures) > 0
    assert np.array_equal(pooled.trajectory, alone.trajectory)
    for a, b in zip(alone.closures, pooled.closures, strict=True):
        assert (a.a, a.b) == (b.a, b.b) and np.array_equal(a.mean, b.mean) and np.array_equal(a.cov, b.cov)
