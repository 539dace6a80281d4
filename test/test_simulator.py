"""Tests of the simulator: ray casting, odometry noise statistics, panoramas, determinism, bag output."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ptm_ros.errors import BagError, ConfigError
from ptm_ros.io.groundtruth import SIM_SCHEMA
from ptm_ros.io.simulator import (
    CameraConfig,
    LaserConfig,
    OdometryNoiseConfig,
    PanoramaRenderer,
    SimConfig,
    cast_rays,
    odometry_from_truth,
    plan_trajectory,
    simulate,
    simulate_scans,
    write_run,
)
from ptm_ros.io.worlds import get_world
from ptm_ros.model.geometry import between, compose

try:
    from ptm_ros.model.appearance import fourier_signature as _fourier_signature

    def signature(image: np.ndarray) -> np.ndarray:
        return _fourier_signature(image, 16)

except ImportError:  # pragma: no cover - appearance.py absent

    def signature(image: np.ndarray) -> np.ndarray:
        """Row-mean |FFT| (thesis Ch. 2.5), coefficients 1..16."""
        return np.abs(np.fft.rfft(image.astype(float).mean(axis=0)))[1:17] / image.shape[1]


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(a))


# ------------------------------------------------------------------------------------------ ray casting

RECT = np.array([[0, 0, 7, 0], [7, 0, 7, 4], [7, 4, 0, 4], [0, 4, 0, 0]], dtype=float)


def rectangle_range(x: float, y: float, angle: np.ndarray, w: float = 7.0, h: float = 4.0) -> np.ndarray:
    """Distance from (x, y) inside [0, w] x [0, h] to the boundary along ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (w - x) / c, np.where(c < 0, -x / c, np.inf))
        ty = np.where(s > 0, (h - y) / s, np.where(s < 0, -y / s, np.inf))
    return np.minimum(tx, ty)


def test_ray_casting_matches_analytic_distances_in_a_rectangle() -> None:
    rng = np.random.default_rng(3)
    origins = np.column_stack([rng.uniform(0.1, 6.9, 20), rng.uniform(0.1, 3.9, 20)])
    angles = rng.uniform(-np.pi, np.pi, (20, 50))
    hits = cast_rays(RECT, origins, angles)
    expected = np.stack([rectangle_range(x, y, a) for (x, y), a in zip(origins, angles, strict=True)])
    np.testing.assert_allclose(hits.range, expected, rtol=0, atol=1e-9)
    # The hit point from the wall side agrees with the one from the ray side.
    seg = RECT[hits.wall]
    unit = (seg[..., 2:] - seg[..., :2]) / np.linalg.norm(seg[..., 2:] - seg[..., :2], axis=-1, keepdims=True)
    from_wall = seg[..., :2] + hits.along[..., None] * unit
    from_ray = origins[:, None, :] + hits.range[..., None] * np.stack([np.cos(angles), np.sin(angles)], -1)
    np.testing.assert_allclose(from_wall, from_ray, rtol=0, atol=1e-9)


def test_rays_through_corners_and_misses() -> None:
    hits = cast_rays(RECT, np.array([[3.5, 2.0]]), np.array([[math.atan2(2.0, 3.5), math.pi / 2]]))
    np.testing.assert_allclose(hits.range[0], [math.hypot(3.5, 2.0), 2.0], rtol=0, atol=1e-12)
    # Outside the rectangle looking away: no hit.
    miss = cast_rays(RECT, np.array([[10.0, 2.0]]), np.array([[0.0]]))
    assert miss.range[0, 0] == np.inf and miss.wall[0, 0] == -1


def test_scans_have_the_analytic_ranges_and_inf_beyond_range_max() -> None:
    laser = LaserConfig(beams=361, fov=2 * math.pi, range_max=5.0, noise=0.0)
    pose = np.array([2.0, 1.0, 0.3])
    ranges = simulate_scans(RECT, pose[None], laser)[0]
    exact = rectangle_range(2.0, 1.0, 0.3 + laser.angles)
    beyond = exact > 5.0
    assert np.any(beyond) and np.all(np.isinf(ranges[beyond]))
    np.testing.assert_allclose(ranges[~beyond], exact[~beyond].astype(np.float32), rtol=0, atol=0)


def test_laser_angles() -> None:
    half = LaserConfig()
    assert half.angle_min == -math.pi / 2
    assert half.angle_increment == pytest.approx(math.pi / 180, abs=1e-15)
    assert half.angles[-1] == pytest.approx(math.pi / 2, abs=1e-12)
    full = LaserConfig(beams=360, fov=2 * math.pi)
    assert full.angle_min == -math.pi
    assert full.angles[-1] == pytest.approx(math.pi - 2 * math.pi / 360, abs=1e-12)


# ------------------------------------------------------------------------------------------- odometry


def straight_line(n: int, step: float) -> np.ndarray:
    return np.column_stack([step * np.arange(n + 1), np.zeros(n + 1), np.zeros(n + 1)])


def test_odometry_without_noise_is_the_truth_in_the_odometry_frame() -> None:
    world = get_world("t-junction")
    cfg = SimConfig()
    traj = plan_trajectory(world, cfg, 6)
    true = traj.pose_at(np.arange(0.0, traj.total_time, 0.05))
    zero = OdometryNoiseConfig(trans=0, rot=0, turn=0, bias_init=0, bias_walk=0)
    odom, inc = odometry_from_truth(true, zero, np.random.default_rng(0))
    np.testing.assert_allclose(odom, between(true[0], true), rtol=0, atol=1e-9)
    np.testing.assert_allclose(compose(true[0], odom)[:, :2], true[:, :2], rtol=0, atol=1e-9)
    assert inc.shape == (len(true) - 1, 3)


def test_odometry_error_statistics_on_a_straight_segment() -> None:
    n, delta, runs = 200, 0.05, 3000  # 10 m in 5 cm steps
    noise = OdometryNoiseConfig(trans=0.05, rot=0.01, turn=0.0, bias_init=0.003, bias_walk=0.002)
    true = straight_line(n, delta)
    err = np.empty((runs, 3))
    for seed in range(runs):
        odom, _ = odometry_from_truth(true, noise, np.random.default_rng(seed))
        err[seed] = odom[-1] - true[-1]

    # Independent prediction: propagate the unit normals through the (linearised) model explicitly.
    # Sources: zeta_1..n (heading), eta_1..n (drift walk), b0; theta_m = sum_{i<=m} dyaw_i.
    zeta = noise.rot * math.sqrt(delta) * np.tril(np.ones((n, n)))  # theta_m from zeta_i, i <= m
    walk = noise.bias_walk * math.sqrt(delta) * np.tril(np.ones((n, n)))  # b_i from eta_l, l <= i
    eta = delta * np.tril(np.ones((n, n))) @ walk  # theta_m from eta
    b0 = delta * noise.bias_init * np.arange(1, n + 1)[:, None]  # theta_m from b0
    theta = np.hstack([zeta, eta, b0])  # rows m = 1..n
    var_theta = np.sum(theta**2, axis=1)
    lateral = delta * np.vstack([np.zeros(2 * n + 1), theta[:-1]]).sum(axis=0)  # y_n = delta sum theta_{j-1}
    pred = {
        "x_mean": -0.5 * delta * np.sum(np.concatenate([[0.0], var_theta[:-1]])),
        "x_var": noise.trans**2 * delta * n,
        "y_var": float(lateral @ lateral),
        "yaw_var": var_theta[-1],
    }
    # Closed form of the heading variance (module docstring) agrees with the propagation.
    closed = n * noise.rot**2 * delta + delta**2 * (
        n**2 * noise.bias_init**2 + noise.bias_walk**2 * delta * n * (n + 1) * (2 * n + 1) / 6
    )
    assert pred["yaw_var"] == pytest.approx(closed, rel=1e-12)

    def check_var(sample: np.ndarray, var: float) -> None:
        se = var * math.sqrt(2.0 / (len(sample) - 1))
        assert abs(sample.var(ddof=1) - var) < 4 * se

    def check_mean(sample: np.ndarray, mean: float, var: float) -> None:
        assert abs(sample.mean() - mean) < 4 * math.sqrt(var / len(sample))

    check_var(err[:, 2], pred["yaw_var"])
    check_mean(err[:, 2], 0.0, pred["yaw_var"])
    check_var(err[:, 1], pred["y_var"])
    check_mean(err[:, 1], 0.0, pred["y_var"])
    check_var(err[:, 0], pred["x_var"])
    check_mean(err[:, 0], pred["x_mean"], pred["x_var"])
    # The drift matters: the lateral spread is dominated by the heading drift, not by per-step noise.
    assert pred["y_var"] > 2 * np.sum((delta * zeta[:-1].sum(axis=0)) ** 2)


def test_odometry_rotation_noise_on_the_spot() -> None:
    n, runs = 400, 3000
    true = np.column_stack([np.zeros(n + 1), np.zeros(n + 1), np.unwrap(np.linspace(0, 2 * np.pi, n + 1))])
    true[:, 2] = (true[:, 2] + np.pi) % (2 * np.pi) - np.pi
    noise = OdometryNoiseConfig(trans=0.05, rot=0.01, turn=0.03, bias_init=0.01, bias_walk=0.01)
    err = np.empty((runs, 3))
    for seed in range(runs):
        odom, _ = odometry_from_truth(true, noise, np.random.default_rng(seed))
        err[seed] = odom[-1] - between(true[0], true[-1])
    err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.all(err[:, :2] == 0.0)  # no translation, no drift: the position stays exact
    var = noise.turn**2 * 2 * np.pi
    assert abs(err[:, 2].var(ddof=1) - var) < 4 * var * math.sqrt(2 / (runs - 1))


def test_systematic_odometry_errors_scale_distances_and_drift_heading() -> None:
    true = straight_line(200, 0.05)
    base = OdometryNoiseConfig()
    ref_odom, ref_inc = odometry_from_truth(true, base, np.random.default_rng(3))
    # Off by default, bit for bit: the explicit zeros give the very same odometry.
    odom, _ = odometry_from_truth(
        true, dataclasses.replace(base, scale=0.0, bias_mean=0.0), np.random.default_rng(3)
    )
    assert np.array_equal(odom, ref_odom)
    # A scale error stretches every increment's translation, the headings untouched.
    _, inc = odometry_from_truth(true, dataclasses.replace(base, scale=0.04), np.random.default_rng(3))
    np.testing.assert_allclose(inc[:, :2], 1.04 * ref_inc[:, :2], rtol=1e-12, atol=0)
    np.testing.assert_array_equal(inc[:, 2], ref_inc[:, 2])
    # A mean drift alone turns the heading by bias_mean per metre: 10 m at 0.01 rad/m = 0.1 rad.
    drift = OdometryNoiseConfig(trans=0, rot=0, turn=0, bias_init=0, bias_walk=0, bias_mean=0.01)
    odom, _ = odometry_from_truth(true, drift, np.random.default_rng(0))
    assert odom[-1, 2] == pytest.approx(0.1, abs=1e-12)
    with pytest.raises(ConfigError, match="scale must be finite and > -1"):
        OdometryNoiseConfig(scale=-1.0)
    with pytest.raises(ConfigError, match="bias_mean must be finite"):
        OdometryNoiseConfig(bias_mean=math.nan)


# ------------------------------------------------------------------------------------------ trajectory


def test_trajectory_length_and_duration_in_the_t_junction() -> None:
    cfg = SimConfig()
    traj = plan_trajectory(get_world("t-junction"), cfg, 3)
    # Start half-way j->w, U-turn at w, 5 m to j, a 90 degree arc of radius 1 into the stem, 5 m to s,
    # U-turn, 2.5 m back: straight legs 15 m minus what the arc cuts (2 r - r pi / 2).
    length = 15.0 - (2.0 - math.pi / 2)
    assert traj.total_time == pytest.approx(length / 0.5 + 2 * math.pi / 0.5, abs=1e-9)
    t, dt = np.linspace(0.0, traj.total_time, 10001, retstep=True)
    p = traj.pose_at(t)
    step = np.hypot(*np.diff(p[:, :2], axis=0).T)
    assert step.sum() == pytest.approx(length, abs=1e-6)
    assert step.max() <= 0.5 * dt + 1e-9  # never faster than the speed
    dyaw = np.abs((np.diff(p[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
    assert dyaw.max() <= 0.5 * dt + 1e-9  # continuous heading, at most 0.5 rad/s
    np.testing.assert_allclose(p[0], [2.5, 0.0, -math.pi], atol=1e-12)
    np.testing.assert_allclose(p[-1, :2], [5.0, -2.5], atol=1e-9)


# ------------------------------------------------------------------------------------------- panoramas


@pytest.fixture(scope="module")
def two_loop_renderer() -> PanoramaRenderer:
    return PanoramaRenderer.build(get_world("two-loop"), CameraConfig(noise=0.0))


def test_panorama_rotation_by_whole_columns_is_exact(two_loop_renderer: PanoramaRenderer) -> None:
    w = two_loop_renderer.camera.width
    pose = np.array([6.3, 0.2, 0.4])
    turns = [37, 128, 300]
    images = two_loop_renderer.render(
        np.array([pose, *[pose + np.array([0, 0, 2 * np.pi * k / w]) for k in turns]])
    )
    for k, img in zip(turns, images[1:], strict=True):
        assert np.array_equal(np.roll(images[0], -k, axis=1), img)
        assert rel(signature(images[0]), signature(img)) < 1e-12


def test_panorama_signature_nearly_invariant_to_any_rotation(two_loop_renderer: PanoramaRenderer) -> None:
    w = two_loop_renderer.camera.width
    yaws = 0.4 + np.array([0.0, 2 * np.pi * 37.5 / w, 1.234, -2.0])
    images = two_loop_renderer.render(np.column_stack([np.full(4, 6.3), np.full(4, 0.2), yaws]))
    s0 = signature(images[0])
    errors = [rel(s0, signature(img)) for img in images[1:]]
    assert max(errors) < 0.08  # measured 0.028-0.035: column quantisation of the textures
    assert not np.array_equal(images[0], images[2])


def test_aliased_places_look_alike_and_different_textures_do_not() -> None:
    world = get_world("aliased-loop")
    pl = {p.id: p for p in world.places}
    corners, doors = ["c-sw", "c-se", "c-ne", "c-nw"], ["d-s", "d-e", "d-n", "d-w"]
    poses = np.array([[pl[k].x, pl[k].y, (q % 4) * np.pi / 2 + 0.1] for q, k in enumerate(corners + doors)])
    # Perfect aliasing: a quarter turn of the world maps a corner onto the next corner, pixel for pixel.
    exact = PanoramaRenderer.build(world, CameraConfig(noise=0.0, texture_aliasing=1.0)).render(poses[:4])
    assert all(np.array_equal(exact[0], img) for img in exact[1:])
    # Default aliasing (0.9): alike, not identical; corners vs doors clearly different.
    sig = [signature(img) for img in PanoramaRenderer.build(world, CameraConfig(noise=0.0)).render(poses)]
    alike = [rel(sig[i], sig[j]) for group in (range(4), range(4, 8)) for i in group for j in group if i < j]
    apart = [rel(sig[i], sig[j]) for i in range(4) for j in range(4, 8)]
    assert min(alike) > 0.0 and max(alike) < 0.6 * min(apart)
    # Two-loop: the outer corridors (textures 1-3) do not look like the inner loop (texture 5).
    two = get_world("two-loop")
    r2 = PanoramaRenderer.build(two, CameraConfig(noise=0.0))
    outer = [two.place(k) for k in ("o-sw", "o-se", "o-ne", "o-nw")]
    inner = [two.place(k) for k in ("i-se", "i-ne", "i-nw", "i-sw")]
    s_out = [signature(i) for i in r2.render(np.array([[p.x, p.y, 0.0] for p in outer]))]
    s_in = [signature(i) for i in r2.render(np.array([[p.x, p.y, 0.0] for p in inner]))]
    assert min(rel(a, b) for a in s_out for b in s_in) > 1.5 * max(alike)


def test_panorama_geometry_heading_column_and_wall_rows() -> None:
    cam = CameraConfig(noise=0.0)
    renderer = PanoramaRenderer.build(get_world("t-junction"), cam)
    h, w = cam.height, cam.width
    slope = (h / 2 - np.arange(h) - 0.5) * (2 * math.tan(cam.vfov / 2) / h)

    def background_rows(d: float) -> tuple[np.ndarray, np.ndarray]:
        return slope * d >= cam.wall_height - cam.camera_height, slope * d < -cam.camera_height

    # At (2.5, 0.5) heading east: column 0 looks east 8.5 m to the far end, column W/4 (left, north) at
    # the wall 0.5 m away, column 3W/4 (right, south) at the wall 1.5 m away.
    img = renderer.render(np.array([[2.5, 0.5, 0.0]]))[0]
    for col, d in ((0, 8.5), (w // 4, 0.5), (3 * w // 4, 1.5)):
        ceiling, floor = background_rows(d)
        assert np.all(img[ceiling, col] == 215) and np.all(img[floor, col] == 70)
        assert ceiling.sum() + floor.sum() < h
    counts = [sum(m.sum() for m in background_rows(d)) for d in (0.5, 1.5, 8.5)]
    assert counts[0] < counts[1] < counts[2]
    rgb = PanoramaRenderer.build(get_world("t-junction"), dataclasses.replace(cam, encoding="rgb8"))
    assert rgb.render(np.array([[2.5, 0.5, 0.0]])).shape == (1, h, w, 3)


# --------------------------------------------------------------------------------------- whole runs


def test_simulation_is_deterministic_under_the_seed() -> None:
    world = get_world("t-junction")
    a, b, c = (simulate(world, SimConfig(), np.random.default_rng(s), visits=3) for s in (7, 7, 8))
    for name in ("odom_poses", "odom_twist", "scan_ranges", "images", "true_poses", "odom_stamps"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.passages == b.passages and a.seed == 7
    assert np.array_equal(a.true_poses, c.true_poses)  # the truth does not depend on the seed
    assert not np.array_equal(a.odom_poses, c.odom_poses)
    assert not np.array_equal(a.scan_ranges, c.scan_ranges)
    assert not np.array_equal(a.images, c.images)
    # Rates: odometry 20 Hz, scans 10 Hz, one panorama per metre.
    assert np.allclose(np.diff(a.odom_stamps), 0.05) and np.allclose(np.diff(a.scan_stamps), 0.1)
    assert len(a.images) == math.floor(a.path_length / 1.0 + 1e-6) + 1


def test_ground_truth_document_and_bag_round_trip(tmp_path: Path) -> None:
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth

    run = simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(5), visits=3)
    doc = run.ground_truth()
    assert doc["schema"] == SIM_SCHEMA and doc["world"] == "t-junction" and doc["seed"] == 5
    assert [p["place"] for p in doc["passages"]] == ["w", "j", "s"]
    assert doc["odometry_frame_offset"] == [2.5, 0.0, -math.pi]
    out = write_run(run, tmp_path / "bag", storage="sqlite3")
    data = read_run(out)
    assert np.array_equal(data.odometry.stamps, run.odom_stamps)
    np.testing.assert_allclose(data.odometry.poses, run.odom_poses, rtol=0, atol=1e-12)
    assert np.array_equal(data.scans.ranges, run.scan_ranges)
    assert np.array_equal(np.stack(data.images.images), run.images)
    gt = load_ground_truth(out)
    assert np.array_equal(gt.stamps, run.odom_stamps)
    assert [(p.stamp, p.place) for p in gt.passages] == [(p.stamp, p.place) for p in run.passages]
    with pytest.raises(BagError, match="already exists"):
        write_run(run, out)


def test_ptm_sim_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from ptm_ros.io.bag import read_run
    from ptm_ros.tools.sim import main

    out = tmp_path / "sim"
    assert main([str(out), "--world", "t-junction", "--landmarks", "4", "--seed", "3", "--no-images"]) == 0
    text = capsys.readouterr().out
    assert "Simulated 4 place visits" in text and "0 /panorama" in text
    data = read_run(out)
    assert data.images is None and data.odometry is not None and data.scans is not None
    gt = json.loads((out / "ground_truth.json").read_text())
    assert gt["seed"] == 3 and [p["place"] for p in gt["passages"]] == ["w", "j", "s", "j"]
    assert main([str(out), "--world", "t-junction"]) == 2
    assert "exists already" in capsys.readouterr().err


@pytest.mark.slow
def test_a_thirty_three_visit_bag_with_panoramas_stays_small(tmp_path: Path) -> None:
    from ptm_ros.tools.sim import main

    out = tmp_path / "multi"
    assert main([str(out), "--world", "multi-loop", "--landmarks", "33"]) == 0
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    assert size < 16e6  # measured 13.1 MB (mcap, 157 panoramas of 64 x 512 mono8)


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match=r"at least 64 x 512"):
        CameraConfig(height=32)
    with pytest.raises(ConfigError, match="encoding must be"):
        CameraConfig(encoding="bgr8")
    with pytest.raises(ConfigError, match=r"texture_aliasing must be in \[0, 1\]"):
        CameraConfig(texture_aliasing=1.5)
    with pytest.raises(ConfigError, match=r"OdometryNoiseConfig.turn must be finite and >= 0"):
        OdometryNoiseConfig(turn=-0.1)
    with pytest.raises(ConfigError, match=r"range_min \(30.0\) must be < range_max"):
        LaserConfig(range_min=30.0)
    with pytest.raises(ConfigError, match="fov must be <= 2π"):
        LaserConfig(fov=7.0)
    with pytest.raises(ConfigError, match=r"SimConfig.speed must be finite and > 0"):
        SimConfig(speed=0.0)
    with pytest.raises(ConfigError, match="exceeds the odometry rate"):
        SimConfig(laser=LaserConfig(rate=50.0))
    with pytest.raises(ConfigError, match=r"true_poses must have shape \(K, 3\)"):
        odometry_from_truth(np.zeros((4, 2)), OdometryNoiseConfig(), np.random.default_rng(0))
