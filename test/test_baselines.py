"""Tests of the baselines (ptm_ros.scoring.baselines): greedy association and robust pose-graph loop
closure."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest
from scipy import optimize, stats

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.io.synthetic import odometry_visits, visits_at
from ptm_ros.model.geometry import RelativePose, between, inverse, transform_points, wrap_angle
from ptm_ros.model.odometry import OdometryConfig, odometry_covariances
from ptm_ros.model.posterior import ModelConfig, PosteriorModel, exact_posterior, normalize_log
from ptm_ros.model.visits import Visit
from ptm_ros.perception.laser import LaserConfig
from ptm_ros.scoring.baselines import (
    GreedyAssociation,
    GreedyConfig,
    LoopClosureConfig,
    greedy_association,
    loop_candidates,
    patch_registrar,
    place_innovations,
    robust_loop_closure,
    robust_pose_graph,
)

ODOMETRY = OdometryConfig()
LASER_COV = np.diag([0.05**2, 0.05**2, 0.02**2])

# ---------------------------------------------------------------------------------------------------------
# helpers


def headings_along(points: Sequence[Sequence[float]], last: Sequence[float]) -> np.ndarray:
    """Poses at ``points``, each facing the next point (the last one facing ``last``)."""
    pts = np.asarray(points, dtype=float)
    nxt = np.vstack([pts[1:], np.asarray(last, dtype=float)])
    yaw = np.arctan2(nxt[:, 1] - pts[:, 1], nxt[:, 0] - pts[:, 0])
    return np.column_stack([pts, yaw])


SQUARE = [(0.0, 0.0), (8.0, 0.0), (8.0, 8.0), (0.0, 8.0)]

# ---------------------------------------------------------------------------------------------------------
# greedy association


def test_gate_is_the_chi_square_quantile_with_two_degrees_of_freedom():
    for p in (0.5, 0.9, 0.99, 0.999):
        assert GreedyConfig(gate_probability=p).gate == pytest.approx(stats.chi2.ppf(p, 2), rel=1e-10)


@pytest.mark.parametrize("p", [0.0, 1.0, -0.1, float("nan")])
def test_greedy_config_rejects_bad_gate(p):
    with pytest.raises(ConfigError, match="gate_probability"):
        GreedyConfig(gate_probability=p)


@pytest.mark.parametrize("sd_heading", [1e-5, 0.02])
def test_place_innovations_match_importance_sampling(sd_heading):
    """Mean and covariance of x_n - x̄_s against weighted samples of the model.

    Samples of the odometry chain (headings included), weighted by the coincidence factor of the places
    (without the visit offset, as in the filter), are draws from the posterior given the labels. With
    (nearly) fixed headings the model is linear, the posterior mean is the optimum and its covariance
    H^{-1} exactly; with 0.02 rad of heading noise per segment, the linearisation is within the tolerances.
    """
    cfg = OdometryConfig(a_th=0.0, c_th=0.0, b_th=sd_heading**2, a_xy=0.1**2, b_xy=0.05**2, sigma_offset=0.0)
    u = [
        (0.0, 0.0, 0.0),
        (4.0, 0.0, 0.5 * math.pi),
        (4.0, 4.0, math.pi),
        (0.3, 0.4, -0.5 * math.pi),
        (3.6, 0.3, 0.0),
    ]
    visits = visits_at(u)
    labels = (0, 1, 2, 0)  # visit 3 revisits place 0; visit 4 is the new one
    inn = place_innovations(labels, visits, cfg)

    rng = np.random.default_rng(3)
    S = 400_000
    U = np.asarray(u)
    X = np.zeros((S, 5, 2))
    X[:, 0] = U[0, :2]
    theta = np.full(S, U[0, 2])
    for k in range(4):
        o = between(U[k], U[k + 1])
        var = cfg.a_xy * visits[k + 1].travel + cfg.b_xy
        step = o[:2] + rng.normal(0.0, math.sqrt(var), (S, 2))
        c, s = np.cos(theta), np.sin(theta)
        X[:, k + 1, 0] = X[:, k, 0] + c * step[:, 0] - s * step[:, 1]
        X[:, k + 1, 1] = X[:, k, 1] + s * step[:, 0] + c * step[:, 1]
        theta = theta + o[2] + rng.normal(0.0, sd_heading, S)
    centre = 0.5 * (X[:, 0] + X[:, 3])
    log_w = -np.sum((X[:, [0, 3]] - centre[:, None]) ** 2, axis=(1, 2)) / (2.0 * cfg.sigma_topology**2)
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    assert 1.0 / np.sum(w**2) > 0.3 * S  # the weights are well behaved
    means = [centre, X[:, 1], X[:, 2]]
    for place, mean_s in enumerate(means):
        nu = X[:, 4] - mean_s
        m = w @ nu
        cov = (nu - m).T @ (w[:, None] * (nu - m))
        size = 2 if place == 0 else 1
        spread = cfg.sigma_topology**2 * (1.0 + 1.0 / size) * np.eye(2)
        np.testing.assert_allclose(inn.mean[place], m, atol=3e-3)
        np.testing.assert_allclose(inn.cov[place] - spread, cov, rtol=0.02, atol=5e-4)
        assert inn.d2[place] == pytest.approx(m @ np.linalg.solve(cov + spread, m), rel=0.02)
    # the new visit is nearest (in Mahalanobis distance) to place 1
    assert int(np.argmin(inn.d2)) == 1


def test_place_innovations_rejects_mismatched_labels():
    visits = visits_at([(0, 0, 0), (1, 0, 0), (2, 0, 0)])
    with pytest.raises(ModelError, match="N - 1 labels"):
        place_innovations((0, 1, 2), visits, ODOMETRY)
    with pytest.raises(ModelError, match="N >= 2"):
        place_innovations((), visits[:1], ODOMETRY)


def test_greedy_recovers_square_driven_twice_with_small_noise():
    true = headings_along(SQUARE * 2 + SQUARE[:1], (8.0, 0.0))
    for seed in range(3):
        visits = odometry_visits(true, ODOMETRY, np.random.default_rng(seed))
        assert greedy_association(visits, ODOMETRY, GreedyConfig()) == (0, 1, 2, 3, 0, 1, 2, 3, 0)


def test_greedy_trivial_inputs():
    assert greedy_association([], ODOMETRY, GreedyConfig()) == ()
    assert greedy_association(visits_at([(1, 2, 3)]), ODOMETRY, GreedyConfig()) == (0,)


def test_greedy_one_visit_at_a_time_decides_as_the_batch_and_never_revisits():
    """Fed one visit at a time (as the filter session runs it), the decisions are the batch function's,
    and the labels after visit k are the batch answer on the first k + 1 visits (decisions are final)."""
    true = headings_along([*SQUARE, (0.0, 4.0), *SQUARE], (8.0, 0.0))
    visits = odometry_visits(true, ODOMETRY, np.random.default_rng(4))
    greedy = GreedyAssociation(ODOMETRY)
    for k in range(len(visits)):
        assert greedy.add(visits[: k + 1]) == greedy.labels[-1]
        assert greedy.labels == greedy_association(visits[: k + 1], ODOMETRY, GreedyConfig())
    assert len(set(greedy.labels)) < len(greedy.labels)  # it closed loops
    n = len(visits)
    with pytest.raises(ModelError, match=f"decided {n} visits: expected {n + 1}, got {n}"):
        greedy.add(visits)
    assert len(greedy.labels) == len(visits)


def test_greedy_commits_to_a_wrong_merge_the_ptm_keeps_uncertain():
    """After a lap of the square the robot stops at a *new* place 4 m from the start: greedy merges it
    with the start, while the exact posterior keeps a fifth of its mass on the true topology."""
    true = headings_along([*SQUARE, (0.0, 4.0)], (0.0, -5.0))
    visits = odometry_visits(true, ODOMETRY, np.random.default_rng(0))
    labels = greedy_association(visits, ODOMETRY, GreedyConfig())
    assert labels == (0, 1, 2, 3, 0)
    inn = place_innovations(labels[:4], visits, ODOMETRY)
    assert inn.d2[0] < GreedyConfig().gate < min(inn.d2[1:])

    post = normalize_log(exact_posterior(PosteriorModel(visits, ModelConfig(odometry=ODOMETRY))))
    assert post[(0, 1, 2, 3, 4)] > 0.15  # truth: kept with real mass
    assert post[(0, 1, 2, 3, 0)] < 0.85  # greedy's choice: far from certain
    assert post[(0, 1, 2, 3, 4)] + post[(0, 1, 2, 3, 0)] > 0.99


def test_greedy_misses_a_revisit_under_drift_beyond_the_model():
    """A heading bias of 0.025 rad/m (0.2 rad per side, beyond the model's 0.09) puts the return to the
    start outside the gate: greedy opens a new place and never revisits that decision, although the next
    visit is matched to corner 1 again (a topology no single lap of a square can have)."""
    true = headings_along([*SQUARE, SQUARE[0], SQUARE[1]], (8.0, 8.0))
    visits = odometry_visits(true, ODOMETRY, np.random.default_rng(0), yaw_bias=0.025)
    labels = greedy_association(visits, ODOMETRY, GreedyConfig())
    assert labels == (0, 1, 2, 3, 4, 1)
    inn = place_innovations(labels[:4], visits[:5], ODOMETRY)
    assert inn.d2[0] > 1.3 * GreedyConfig().gate


# ---------------------------------------------------------------------------------------------------------
# robust pose graph on synthetic loops (no laser)


def graph_scene(seed: int = 0):
    """A hexagon driven once and a bit: true poses, odometry visits, true loops and one outlier."""
    ang = np.arange(8) * (2.0 * math.pi / 6.0)
    true = headings_along(np.column_stack([5.0 * np.cos(ang), 5.0 * np.sin(ang)]), (0.0, 0.0))
    visits = odometry_visits(true, ODOMETRY, np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 100)

    def measured(i: int, j: int) -> RelativePose:
        z = between(true[i], true[j]) + rng.normal(0.0, np.sqrt(np.diag(LASER_COV)))
        return RelativePose(i, j, z, LASER_COV)

    good = [measured(0, 6), measured(1, 7)]
    outlier = RelativePose(2, 5, np.array([0.3, -0.2, 0.4]), LASER_COV)
    return true, visits, good, outlier


def own_residuals(x_free: np.ndarray, u: np.ndarray, covs, loops) -> tuple[np.ndarray, np.ndarray]:
    """Whitened odometry residuals (K, 3) and loop residuals (L, 3), written from the model."""
    x = np.vstack([u[:1], x_free.reshape(-1, 3)])
    odo = []
    for k in range(len(u) - 1):
        e = between(x[k], x[k + 1]) - between(u[k], u[k + 1])
        e[2] = wrap_angle(e[2])
        odo.append(e / np.sqrt(np.diag(covs[k])))
    lps = []
    for lp in loops:
        e = between(x[lp.i], x[lp.j]) - lp.mean
        e[2] = wrap_angle(e[2])
        lps.append(np.linalg.solve(np.linalg.cholesky(lp.cov), e))
    return np.array(odo), np.array(lps).reshape(-1, 3)


def test_robust_pose_graph_without_kernel_is_least_squares():
    _, visits, good, outlier = graph_scene()
    u = np.array([v.pose for v in visits])
    covs = odometry_covariances(visits, ODOMETRY)
    loops = [*good, outlier]
    res = robust_pose_graph(u, covs, loops, LoopClosureConfig(kernel_scale=1e8))
    ref = optimize.least_squares(
        lambda xf: np.concatenate([a.ravel() for a in own_residuals(xf, u, covs, loops)]),
        u[1:].ravel(),
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    X = np.vstack([u[:1], ref.x.reshape(-1, 3)])
    np.testing.assert_allclose(res.poses[:, :2], X[:, :2], atol=1e-6)
    np.testing.assert_allclose(wrap_angle(res.poses[:, 2] - X[:, 2]), 0.0, atol=1e-7)
    np.testing.assert_allclose(res.weights, 1.0, atol=1e-6)
    _, r_loops = own_residuals(ref.x, u, covs, loops)
    np.testing.assert_allclose(res.residuals2, np.sum(r_loops**2, axis=1), rtol=1e-5)


def test_robust_pose_graph_rejects_outlier_at_a_geman_mcclure_minimum():
    true, visits, good, outlier = graph_scene()
    u = np.array([v.pose for v in visits])
    covs = odometry_covariances(visits, ODOMETRY)
    loops = [*good, outlier]
    cfg = LoopClosureConfig()
    res = robust_pose_graph(u, covs, loops, cfg)
    assert res.weights[:2].min() > 0.9
    assert res.weights[2] < 1e-3
    assert res.gnc_steps > 5  # the outlier forced a graduated schedule
    # the estimate is the true geometry up to the odometry/laser noise, far better than odometry
    inliers_only = robust_pose_graph(u, covs, good, LoopClosureConfig(kernel_scale=1e8))
    np.testing.assert_allclose(res.poses[:, :2], inliers_only.poses[:, :2], atol=5e-3)
    # the closed loops pull the second lap onto the first: errors of visits 6, 7 drop from the drift
    assert np.min(np.hypot(*(u[6:, :2] - true[6:, :2]).T)) > 0.5
    assert np.max(np.hypot(*(res.poses[6:, :2] - true[6:, :2]).T)) < 0.15

    c2 = cfg.kernel_scale**2

    def gm_cost(xf: np.ndarray) -> float:
        r_odo, r_lp = own_residuals(xf, u, covs, loops)
        s = np.sum(r_lp**2, axis=1)
        return 0.5 * float(np.sum(r_odo**2)) + 0.5 * float(np.sum(c2 * s / (c2 + s)))

    # a stationary point: a generic optimizer started nearby returns to it, no lower
    x_star = res.poses[1:].copy()
    x_star[:, 2] = np.unwrap(np.concatenate([u[:1, 2], x_star[:, 2]]))[1:]
    start = x_star + np.random.default_rng(5).normal(0.0, 0.02, x_star.shape)
    ref = optimize.minimize(gm_cost, start.ravel(), method="BFGS", options={"gtol": 1e-9, "maxiter": 5000})
    np.testing.assert_allclose(ref.x.reshape(-1, 3), x_star, atol=2e-4)
    assert gm_cost(x_star.ravel()) <= ref.fun + 1e-8
    # and its weights are the kernel's at the final residuals
    np.testing.assert_allclose(res.weights, (c2 / (c2 + res.residuals2)) ** 2, rtol=1e-12)


def test_robust_pose_graph_without_loops_returns_odometry():
    _, visits, _, _ = graph_scene()
    u = np.array([v.pose for v in visits])
    res = robust_pose_graph(u, odometry_covariances(visits, ODOMETRY), [], LoopClosureConfig())
    np.testing.assert_allclose(res.poses, u, atol=1e-12)
    assert res.weights.shape == (0,)
    assert res.gnc_steps == 0


def test_robust_pose_graph_input_errors():
    _, visits, good, _ = graph_scene()
    u = np.array([v.pose for v in visits])
    covs = odometry_covariances(visits, ODOMETRY)
    with pytest.raises(ModelError, match="odometry_cov must have shape"):
        robust_pose_graph(u, covs[:-1], good, LoopClosureConfig())
    bad = RelativePose(0, 3, np.zeros(3), np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(ModelError, match="not positive definite"):
        robust_pose_graph(u, covs, [bad], LoopClosureConfig())
    backwards = RelativePose(3, 1, np.zeros(3), LASER_COV)
    with pytest.raises(ModelError, match="need 0 <= i < j"):
        robust_pose_graph(u, covs, [backwards], LoopClosureConfig())


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("search_radius", 0.0),
        ("kernel_scale", -1.0),
        ("max_offset", float("inf")),
        ("inlier_threshold", 1.0),
        ("gnc_factor", 1.0),
        ("max_candidates", 0),
        ("all_pairs_below", -1),
        ("max_iterations", 2.5),
    ],
)
def test_loop_closure_config_validation(field, value):
    with pytest.raises(ConfigError, match=f"LoopClosureConfig.{field}"):
        LoopClosureConfig(**{field: value})


def test_loop_candidates_against_brute_force():
    rng = np.random.default_rng(2)
    poses = np.column_stack([rng.uniform(0, 20, (30, 2)), rng.uniform(-3, 3, 30)])
    cfg = LoopClosureConfig(search_radius=4.0, all_pairs_below=0, max_candidates=25)
    pairs = []
    for i in range(30):
        for j in range(i + 1, 30):
            d = math.dist(poses[i, :2], poses[j, :2])
            if d <= 4.0:
                pairs.append((d, i, j))
    pairs.sort()
    assert len(pairs) > 25  # the cap matters
    assert loop_candidates(poses, cfg) == [(i, j) for _, i, j in pairs[:25]]
    everything = loop_candidates(poses[:6], LoopClosureConfig(search_radius=0.1, all_pairs_below=6))
    assert sorted(everything) == [(i, j) for i in range(6) for j in range(i + 1, 6)]


def test_inlier_with_large_offset_is_a_constraint_not_a_revisit():
    """A consistent registration of two visits 5 m apart (> max_offset) is an inlier but joins no places."""
    true, visits, good, _ = graph_scene()
    far = RelativePose(0, 1, between(true[0], true[1]), LASER_COV)  # 5 m apart on the hexagon
    loops = {(lp.i, lp.j): lp for lp in [*good, far]}
    cfg = LoopClosureConfig(all_pairs_below=20)
    labels, details = robust_loop_closure(
        visits, ODOMETRY, LaserConfig(), cfg, registrar=lambda i, j: loops.get((i, j))
    )
    assert labels == (0, 1, 2, 3, 4, 5, 0, 1)
    assert bool(details.inliers.all())
    assert details.joined == ((0, 6), (1, 7))
    assert len(details.candidates) == 28


def test_registrar_answering_another_pair_is_an_error():
    _, visits, _, _ = graph_scene()
    wrong = RelativePose(0, 2, np.zeros(3), LASER_COV)
    with pytest.raises(ModelError, match=r"answered pair \(0, 2\) when asked for \(0, 6\)"):
        robust_loop_closure(
            visits, ODOMETRY, LaserConfig(), LoopClosureConfig(), registrar=lambda i, j: wrong
        )


# ---------------------------------------------------------------------------------------------------------
# robust loop closure with laser patches of synthetic rooms


def wall_points(segments, step: float = 0.03) -> np.ndarray:
    parts = []
    for start, end in segments:
        a, b = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
        n = max(2, int(np.linalg.norm(b - a) / step) + 1)
        parts.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    return np.vstack(parts)


def make_room(rng: np.random.Generator, corners: int = 9) -> list:
    """An irregular polygon (radius 1.8-2.8 m) with two pieces of furniture: no symmetry to alias."""
    ang = np.sort(rng.uniform(0.0, 2.0 * math.pi, corners))
    rad = rng.uniform(1.8, 2.8, corners)
    v = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    segments = [(v[i], v[(i + 1) % corners]) for i in range(corners)]
    for _ in range(2):
        c, a, half = rng.uniform(-1.0, 1.0, 2), rng.uniform(0.0, math.pi), rng.uniform(0.2, 0.4)
        d = half * np.array([math.cos(a), math.sin(a)])
        segments.append((c - d, c + d))
    return segments


ROOM_CENTRES = np.array([(0.0, 0.0), (10.0, 0.0), (5.0, 9.0)])


def rooms_scene():
    """Three rooms visited twice (A B C A B C) with drifting odometry; patches see only their room."""
    gen = np.random.default_rng(0)
    rooms = [wall_points(make_room(gen)) + c for c in ROOM_CENTRES]
    rng = np.random.default_rng(1)
    route = [0, 1, 2, 0, 1, 2]
    true = np.array(
        [[*ROOM_CENTRES[r] + rng.uniform(-0.3, 0.3, 2), rng.uniform(-math.pi, math.pi)] for r in route]
    )
    patches = []
    for r, pose in zip(route, true, strict=True):
        local = transform_points(inverse(pose), rooms[r])
        local = local[np.hypot(local[:, 0], local[:, 1]) <= 3.0]
        patches.append(local + rng.normal(0.0, 0.01, local.shape))
    visits = odometry_visits(true, ODOMETRY, rng, yaw_bias=0.01, patches=patches)
    return true, visits


def test_robust_loop_closure_keeps_true_loops_and_rejects_injected_false_one():
    true, visits = rooms_scene()
    u = np.array([v.pose for v in visits])
    assert np.max(np.hypot(*(u[:, :2] - true[:, :2]).T)) > 2.0  # the second lap has drifted
    laser = LaserConfig()
    real = patch_registrar(visits, laser)
    fake = RelativePose(0, 4, np.array([0.2, -0.1, 0.3]), LASER_COV)  # "room A is room B"
    asked = []

    def registrar(i: int, j: int) -> RelativePose | None:
        asked.append((i, j))
        return fake if (i, j) == (0, 4) else real(i, j)

    labels, details = robust_loop_closure(visits, ODOMETRY, laser, LoopClosureConfig(), registrar=registrar)
    assert labels == (0, 1, 2, 0, 1, 2)
    assert sorted(asked) == [(i, j) for i in range(6) for j in range(i + 1, 6)]  # N <= all_pairs_below
    found = {(lp.i, lp.j): w for lp, w in zip(details.loops, details.weights, strict=True)}
    assert set(found) == {(0, 3), (1, 4), (2, 5), (0, 4)}  # distinct rooms never registered validly
    assert min(found[(0, 3)], found[(1, 4)], found[(2, 5)]) > 0.9
    assert found[(0, 4)] < 1e-3
    assert (0, 4) not in details.joined
    # the true registrations are accurate, and the robust estimate undoes the drift
    for lp in details.loops:
        if (lp.i, lp.j) != (0, 4):
            err = between(true[lp.i], true[lp.j]) - lp.mean
            assert math.hypot(err[0], err[1]) < 0.05
    real_loops = [lp for lp in details.loops if (lp.i, lp.j) != (0, 4)]
    covs = odometry_covariances(visits, ODOMETRY)
    clean = robust_pose_graph(u, covs, real_loops, LoopClosureConfig(kernel_scale=1e8))
    np.testing.assert_allclose(details.poses[:, :2], clean.poses[:, :2], atol=1e-3)
    assert np.max(np.hypot(*(details.poses[:, :2] - true[:, :2]).T)) < 0.25
    doc = details.to_dict()
    assert sorted(doc["joined"]) == [[0, 3], [1, 4], [2, 5]]


def test_pure_odometry_run_gives_all_distinct_places():
    _, visits = rooms_scene()
    bare = [Visit(v.index, v.stamp, v.pose, v.travel, v.rotation) for v in visits]  # no patches
    labels, details = robust_loop_closure(bare, ODOMETRY, LaserConfig(), LoopClosureConfig())
    assert labels == (0, 1, 2, 3, 4, 5)
    assert details.loops == ()
    assert details.joined == ()
    np.testing.assert_allclose(details.poses, np.array([v.pose for v in bare]), atol=1e-12)
    labels, _ = robust_loop_closure(
        visits, ODOMETRY, LaserConfig(), LoopClosureConfig(), registrar=lambda i, j: None
    )
    assert labels == (0, 1, 2, 3, 4, 5)
