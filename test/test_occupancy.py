"""Occupancy grid: exact ray traversal, the log-odds update, map_server files, the Intel map."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from ptm_ros.errors import ConfigError, DataError
from ptm_ros.maps.occupancy import (
    OccupancyConfig,
    build_grid,
    cells,
    classes_of,
    grid_traversal,
    load_map,
    map_cells,
    probabilities,
    read_pgm,
    save_map,
    save_png,
    to_ros_data,
    trinary,
)

# A rectangular room whose walls lie inside cells (not on cell boundaries) at any resolution used here.
ROOM = (-3.013, 3.021, -2.017, 1.983)  # x_min, x_max, y_min, y_max
ROOM_POSES = np.array(
    [
        [0.0, 0.0, 0.0],
        [-1.5, 0.8, 1.0],
        [1.7, -1.1, -2.0],
        [2.2, 1.0, 0.4],
        [-2.1, -1.2, 2.9],
        [0.3, 1.2, -0.7],
    ]
)


def room_ranges(pose: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Distance from ``pose`` to the first wall along each beam (exact ray / box exit)."""
    x0, x1, y0, y1 = ROOM
    heading = pose[2] + angles
    c, s = np.cos(heading), np.sin(heading)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (x1 - pose[0]) / c, np.where(c < 0, (x0 - pose[0]) / c, np.inf))
        ty = np.where(s > 0, (y1 - pose[1]) / s, np.where(s < 0, (y0 - pose[1]) / s, np.inf))
    return np.minimum(tx, ty)


def room_grid(resolution: float = 0.1) -> tuple[object, OccupancyConfig]:
    cfg = OccupancyConfig(resolution=resolution, max_range=20.0, margin=0.5)
    angles = -math.pi + 0.5 * math.pi / 180.0 * np.arange(720)
    ranges = [room_ranges(p, angles) for p in ROOM_POSES]
    return build_grid(ROOM_POSES, ranges, -math.pi, 0.5 * math.pi / 180.0, 30.0, config=cfg), cfg


def cell_of(grid, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    col = np.floor((np.asarray(x) - grid.origin[0]) / grid.resolution).astype(int)
    row = np.floor((np.asarray(y) - grid.origin[1]) / grid.resolution).astype(int)
    return row, col


# --- exact traversal -------------------------------------------------------------------------------


def cells_by_clipping(p0: np.ndarray, p1: np.ndarray) -> set[tuple[int, int]]:
    """Cells in the segment's bounding box whose box it crosses with a chord of positive length
    (Liang–Barsky clipping against each cell, by enumeration)."""
    out = set()
    d = p1 - p0
    for i in range(int(np.floor(min(p0[0], p1[0]))), int(np.floor(max(p0[0], p1[0]))) + 1):
        for j in range(int(np.floor(min(p0[1], p1[1]))), int(np.floor(max(p0[1], p1[1]))) + 1):
            t_lo, t_hi = 0.0, 1.0
            for a, da, lo in ((p0[0], d[0], i), (p0[1], d[1], j)):
                if da == 0.0:
                    if not (lo <= a < lo + 1):
                        t_lo, t_hi = 1.0, 0.0
                    continue
                ta, tb = sorted(((lo - a) / da, (lo + 1 - a) / da))
                t_lo, t_hi = max(t_lo, ta), min(t_hi, tb)
            length = (t_hi - t_lo) * float(np.hypot(*d))
            if length > 1e-9 or (np.all(d == 0) and t_hi >= t_lo):
                out.add((i, j))
    return out


def cells_by_sampling(p0: np.ndarray, p1: np.ndarray, n: int = 200_001) -> set[tuple[int, int]]:
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = np.floor(p0 + t * (p1 - p0)).astype(np.int64)
    key = np.unique((pts[:, 0] + 1000) * 4096 + (pts[:, 1] + 1000))
    return set(zip((key // 4096 - 1000).tolist(), (key % 4096 - 1000).tolist(), strict=True))


def test_traversal_equals_brute_force_for_random_segments() -> None:
    rng = np.random.default_rng(7)
    starts = rng.uniform(-6.0, 6.0, size=(60, 2))
    ends = starts + rng.normal(scale=4.0, size=(60, 2))
    ix, iy, ray = grid_traversal(starts, ends)
    for b in range(len(starts)):
        got = set(zip(ix[ray == b].tolist(), iy[ray == b].tolist(), strict=True))
        assert len(got) == int(np.sum(ray == b)), "a cell listed twice for one segment"
        assert got == cells_by_clipping(starts[b], ends[b])
        assert got == cells_by_sampling(starts[b], ends[b])
        assert (int(np.floor(ends[b, 0])), int(np.floor(ends[b, 1]))) in got


@pytest.mark.parametrize(
    ("p0", "p1"),
    [
        ((0.5, 0.5), (0.7, 0.2)),  # inside one cell
        ((0.5, 0.5), (0.5, 0.5)),  # zero length
        ((2.3, -1.5), (2.3, 4.6)),  # vertical
        ((-3.2, 1.4), (5.9, 1.4)),  # horizontal
        ((4.9, 3.1), (-2.2, -0.4)),  # both directions negative
        ((0.25, 0.1), (0.26, 7.9)),  # nearly vertical, one column crossing
    ],
)
def test_traversal_special_segments(p0: tuple[float, float], p1: tuple[float, float]) -> None:
    a, b = np.array(p0), np.array(p1)
    ix, iy, _ = grid_traversal(a, b)
    got = set(zip(ix.tolist(), iy.tolist(), strict=True))
    assert len(got) == len(ix)
    assert got == cells_by_sampling(a, b)


def test_traversal_rejects_non_finite() -> None:
    with pytest.raises(DataError, match="finite"):
        grid_traversal([0.0, 0.0], [[np.nan, 1.0]])


# --- the log-odds update ---------------------------------------------------------------------------


def test_square_room_walls_occupied_interior_free_outside_unknown() -> None:
    grid, cfg = room_grid()
    cls = trinary(grid, cfg)
    x0, x1, y0, y1 = ROOM
    res = grid.resolution
    # Wall cells: cells holding wall points (sampled densely, corners excluded by one cell).
    s = np.linspace(0.0, 1.0, 4001)
    xs = x0 + res + s * (x1 - x0 - 2 * res)
    ys = y0 + res + s * (y1 - y0 - 2 * res)
    walls = [
        cell_of(grid, xs, np.full_like(xs, y0)),
        cell_of(grid, xs, np.full_like(xs, y1)),
        cell_of(grid, np.full_like(ys, x0), ys),
        cell_of(grid, np.full_like(ys, x1), ys),
    ]
    for rows, cols in walls:
        assert np.all(cls[rows, cols] == 100)
    # Cell centres: interior (two cells from any wall) free; beyond the wall cells never observed.
    cx = grid.origin[0] + (np.arange(grid.width) + 0.5) * res
    cy = grid.origin[1] + (np.arange(grid.height) + 0.5) * res
    gx, gy = np.meshgrid(cx, cy)
    inside = (gx > x0 + 2 * res) & (gx < x1 - 2 * res) & (gy > y0 + 2 * res) & (gy < y1 - 2 * res)
    outside = (gx < x0 - res) | (gx > x1 + res) | (gy < y0 - res) | (gy > y1 + res)
    assert inside.sum() > 1500 and outside.sum() > 500
    assert np.all(cls[inside] == 0)
    assert np.all(cls[outside] == -1)
    assert not np.any(grid.observed[outside])
    # The grid covers the data plus the margin, origin on the resolution lattice.
    assert grid.origin[0] <= x0 - cfg.margin + 1e-9 and grid.origin[1] <= y0 - cfg.margin + 1e-9
    assert grid.origin[0] + grid.width * res >= x1 + cfg.margin
    assert abs(grid.origin[0] / res - round(grid.origin[0] / res)) < 1e-9
    assert grid.skipped == 0 and grid.beams == 720 * len(ROOM_POSES)


def test_one_update_per_cell_and_scan_and_hit_wins() -> None:
    cfg = OccupancyConfig(resolution=0.1, margin=0.2, clamp=10.0)
    # 50 beams fan out of the sensor cell: it receives l_free once. Two beams along +x, one ending at
    # x = 1.02 and one passing through that cell to 2.04: the cell takes l_occ only.
    fan = build_grid([[0.05, 0.05, 0.0]], [np.full(50, 1.0)], 0.0, 2 * math.pi / 50, 30.0, config=cfg)
    r, c = cell_of(fan, 0.05, 0.05)
    assert fan.log_odds[r, c] == pytest.approx(cfg.l_free)
    pair = build_grid([[0.05, 0.05, 0.0]], [np.array([1.02, 2.04])], 0.0, 0.0, 30.0, config=cfg)
    r, c = cell_of(pair, 1.02, 0.05)
    assert pair.log_odds[r, c] == pytest.approx(cfg.l_occ)
    r, c = cell_of(pair, 0.55, 0.05)
    assert pair.log_odds[r, c] == pytest.approx(cfg.l_free)
    r, c = cell_of(pair, 2.04, 0.05)
    assert pair.log_odds[r, c] == pytest.approx(cfg.l_occ)


def test_clamping_after_every_scan() -> None:
    cfg = OccupancyConfig(resolution=0.1, margin=0.2, clamp=2.0, l_occ=0.9, l_free=-0.7)
    n = 8
    grid = build_grid(np.tile([0.05, 0.05, 0.0], (n, 1)), [np.array([1.02])] * n, 0.0, 0.0, 30.0, config=cfg)
    r, c = cell_of(grid, 1.02, 0.05)
    assert grid.log_odds[r, c] == pytest.approx(2.0)
    r, c = cell_of(grid, 0.55, 0.05)
    assert grid.log_odds[r, c] == pytest.approx(-2.0)
    # Clamped per scan, not at the end: after 8 hits the cell sits at the clamp; 2 passes bring it to
    # 2.0 - 1.4 (an end-of-run clamp would give min(2, 7.2 - 1.4) = 2.0).
    poses = np.tile([0.05, 0.05, 0.0], (n + 2, 1))
    grid = build_grid(poses, [np.array([1.02])] * n + [np.array([3.0])] * 2, 0.0, 0.0, 30.0, config=cfg)
    r, c = cell_of(grid, 1.02, 0.05)
    assert grid.log_odds[r, c] == pytest.approx(2.0 - 1.4)


def test_max_range_and_no_return() -> None:
    cfg = OccupancyConfig(resolution=0.1, margin=0.2, max_range=3.0, missing_ray_length=1.0)
    # Beam 0: return at 2.02 (hit). Beam 1: 5.02 > max_range: free to 3.0, no hit. Beam 2: at range_max
    # (10): no return, free to missing_ray_length = 1.0 only.
    grid = build_grid([[0.05, 0.05, 0.0]], [np.array([2.02, 5.02, 10.0])], 0.0, math.pi / 2, 10.0, config=cfg)
    assert grid.log_odds[cell_of(grid, 2.02, 0.05)] == pytest.approx(cfg.l_occ)
    assert grid.log_odds[cell_of(grid, 0.05, 2.95)] == pytest.approx(cfg.l_free)
    assert not grid.observed[cell_of(grid, 0.05, 3.15)]
    assert grid.log_odds[cell_of(grid, -0.95, 0.05)] == pytest.approx(cfg.l_free)
    assert not grid.observed[cell_of(grid, -1.15, 0.05)]
    assert np.sum(grid.log_odds > 0) == 1
    # missing_ray_length 0: a no-return beam clears nothing; one longer than max_range is cut there.
    zero = build_grid(
        [[0.05, 0.05, 0.0]], [np.array([10.0])], 0.0, 0.0, 10.0, config=replace(cfg, missing_ray_length=0)
    )
    assert not np.any(zero.observed) and zero.beams == 0
    far = build_grid(
        [[0.05, 0.05, 0.0]], [np.array([10.0])], 0.0, 0.0, 10.0, config=replace(cfg, missing_ray_length=50)
    )
    assert far.observed[cell_of(far, 2.95, 0.05)] and not far.observed[cell_of(far, 3.15, 0.05)]


def test_a_wall_survives_the_beams_that_pass_through_its_cells() -> None:
    """Hits outweigh misses (module docstring): a wall cell hit by one beam per scan stays occupied while
    up to four beams per scan graze through it; five passes per hit erase it."""
    cfg = OccupancyConfig(resolution=0.1, margin=0.2)
    wall_x = 2.05  # the wall cell: column [2.0, 2.1)
    for passes, occupied in ((4, True), (5, False)):
        # one scan: the hit, then `passes` scans whose only beam crosses the wall cell to a farther return
        poses = np.tile([0.05, 0.05, 0.0], (1 + passes, 1))
        ranges = [np.array([wall_x - 0.05])] + [np.array([4.02])] * passes
        scans = 30
        grid = build_grid(np.tile(poses, (scans, 1)), ranges * scans, 0.0, 0.0, 30.0, config=cfg)
        assert bool(trinary(grid, cfg)[cell_of(grid, wall_x, 0.05)] == 100) is occupied
    assert cfg.l_occ == pytest.approx(math.log(0.7 / 0.3), abs=0.01)
    assert cfg.l_free == pytest.approx(math.log(0.45 / 0.55), abs=0.01)


def test_invalid_ranges_counted_and_skipped() -> None:
    cfg = OccupancyConfig(resolution=0.1, margin=0.3)
    good = np.array([1.0, 1.5, 2.0, 2.5])
    bad = np.array([np.nan, np.inf, -np.inf, -1.0, 0.0, 0.05])  # 0.05 < range_min = 0.1
    pose = [[0.3, -0.2, 0.4]]
    with_bad = build_grid(pose, [np.concatenate([good, bad])], -0.5, 0.1, 30.0, config=cfg, range_min=0.1)
    clean = build_grid(pose, [good], -0.5, 0.1, 30.0, config=cfg, range_min=0.1)
    assert with_bad.skipped == len(bad) and clean.skipped == 0
    assert with_bad.beams == clean.beams == len(good)
    assert with_bad.origin == clean.origin
    np.testing.assert_array_equal(with_bad.log_odds, clean.log_odds)


def test_ros_data_is_the_trinary_map_in_ros_layout() -> None:
    cfg = OccupancyConfig(resolution=0.1, margin=0.2)
    # 8 scans from one spot: a return straight up, free space along the beam, unknown around.
    grid = build_grid(
        np.tile([0.05, 0.05, 0.0], (8, 1)), [np.array([1.02])] * 8, math.pi / 2, 0.0, 30.0, config=cfg
    )
    p = probabilities(grid)
    np.testing.assert_allclose(p, 1.0 / (1.0 + np.exp(-grid.log_odds)))
    data = to_ros_data(grid, cfg)
    assert data.dtype == np.int8 and data.shape == (grid.width * grid.height,)
    assert set(np.unique(data).tolist()) == {-1, 0, 100}  # map_server's trinary values, nothing between
    np.testing.assert_array_equal(data, trinary(grid, cfg).reshape(-1))
    r, c = cell_of(grid, 0.05, 1.02)  # the hit straight up: row r counted from the lowest y
    assert r > grid.height // 2 and data[r * grid.width + c] == 100
    r, c = cell_of(grid, 0.05, 0.55)
    assert data[r * grid.width + c] == 0
    assert data[0] == -1  # lower-left corner of the margin
    # A cell passed a few times only, or hit and passed as often, is neither free nor occupied: unknown.
    once = build_grid([[0.05, 0.05, 0.0]], [np.array([1.02])], math.pi / 2, 0.0, 30.0, config=cfg)
    assert np.all(to_ros_data(once, cfg)[once.observed.reshape(-1)] != 0)
    # The thresholds are the ones the YAML carries: a stricter occupied_thresh leaves the wall unknown.
    strict = OccupancyConfig(resolution=0.1, margin=0.2, occupied_thresh=0.999)
    r, c = cell_of(grid, 0.05, 1.02)
    assert to_ros_data(grid, strict)[r * grid.width + c] == -1


def test_build_grid_errors() -> None:
    cfg = OccupancyConfig(resolution=0.1, max_cells=10_000)
    with pytest.raises(DataError, match=r"poses must be \(T, 3\)"):
        build_grid(np.zeros((2, 2)), [[1.0], [1.0]], 0.0, 0.1, 10.0, config=cfg)
    with pytest.raises(DataError, match="2 range arrays for 3 poses"):
        build_grid(np.zeros((3, 3)), [[1.0], [1.0]], 0.0, 0.1, 10.0, config=cfg)
    with pytest.raises(DataError, match="one value per scan"):
        build_grid(np.zeros((2, 3)), [[1.0], [1.0]], [0.0, 0.1, 0.2], 0.1, 10.0, config=cfg)
    with pytest.raises(DataError, match="finite"):
        build_grid([[np.nan, 0.0, 0.0]], [[1.0]], 0.0, 0.1, 10.0, config=cfg)
    with pytest.raises(DataError, match="max_cells"):
        build_grid([[0.0, 0.0, 0.0], [500.0, 0.0, 0.0]], [[1.0], [1.0]], 0.0, 0.1, 10.0, config=cfg)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"resolution": 0.0}, "resolution must be a finite number > 0"),
        ({"max_range": -1.0}, "max_range must be a finite number > 0"),
        ({"clamp": math.inf}, "clamp must be a finite number > 0"),
        ({"l_occ": -0.2}, "l_occ must be a finite number > 0"),
        ({"l_free": 0.3}, "l_free must be a finite number < 0"),
        ({"margin": -0.1}, "margin must be a finite number >= 0"),
        ({"free_thresh": 0.7}, "free_thresh < occupied_thresh"),
        (
            {"occupied_thresh": 1.0},
            r"occupied_thresh must be a finite number in \(0\.00392157, 1\), got 1\.0",
        ),
        ({"free_thresh": 0.001}, r"free_thresh must be a finite number in \(0\.00392157, 1\), got 0\.001"),
        ({"free_thresh": 0.5, "occupied_thresh": 0.501}, "no 8-bit grey level"),
        ({"max_cells": 0}, "max_cells must be an integer >= 1"),
        ({"mode": "raw"}, "mode must be one of"),
    ],
)
def test_config_errors(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        OccupancyConfig(**kwargs)


# --- map_server files ------------------------------------------------------------------------------


def test_map_files_round_trip(tmp_path: Path) -> None:
    # Beams into the upper half plane only: the lower wall stays unknown, so the map is not symmetric
    # under a vertical flip.
    cfg = OccupancyConfig(resolution=0.1, margin=0.5)
    poses = ROOM_POSES * [1.0, 1.0, 0.0]
    angles = np.deg2rad(np.arange(0.0, 180.0, 0.5))
    grid = build_grid(poses, [room_ranges(p, angles) for p in poses], 0.0, np.deg2rad(0.5), 30.0, config=cfg)
    expected = trinary(grid, cfg)
    assert not np.array_equal(expected, expected[::-1])
    assert {-1, 0, 100} <= set(np.unique(expected).tolist())
    pgm, yml = save_map(grid, tmp_path / "maps" / "room", cfg)
    assert pgm.name == "room.pgm" and yml.name == "room.yaml"
    doc = yaml.safe_load(yml.read_text())
    assert doc == {
        "image": "room.pgm",
        "mode": "trinary",
        "resolution": grid.resolution,
        "origin": list(grid.origin),
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.25,
    }
    # map_server's rule applied here by hand: p = (255 - v) / 255, image row 0 = highest y.
    pix = read_pgm(pgm).astype(float)
    assert pix.shape == (grid.height, grid.width)
    p = (255.0 - pix) / 255.0
    by_hand = np.where(p > 0.65, 100, np.where(p < 0.25, 0, -1))[::-1]
    np.testing.assert_array_equal(by_hand, expected)
    loaded = load_map(yml)
    np.testing.assert_array_equal(loaded.data, expected)
    assert loaded.origin == grid.origin and loaded.resolution == grid.resolution
    # The top wall (highest y) is in the first image rows.
    top_row = int(np.max(np.nonzero(np.any(expected == 100, axis=1))[0]))
    assert np.any(pix[grid.height - 1 - top_row] == 0)


def test_load_map_errors(tmp_path: Path) -> None:
    (tmp_path / "bad.pgm").write_bytes(b"P2\n2 2\n255\n0 0 0 0\n")
    base = "image: bad.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 0\noccupied_thresh: 0.65\n"
    (tmp_path / "a.yaml").write_text(base + "free_thresh: 0.25\n")
    with pytest.raises(DataError, match="not a binary"):
        load_map(tmp_path / "a.yaml")
    (tmp_path / "b.yaml").write_text(base)
    with pytest.raises(DataError, match="free_thresh"):
        load_map(tmp_path / "b.yaml")
    (tmp_path / "c.yaml").write_text(base + "free_thresh: 0.25\nmode: raw\n")
    with pytest.raises(DataError, match="only modes"):
        load_map(tmp_path / "c.yaml")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nnot a png")
    (tmp_path / "d.yaml").write_text(base.replace("bad.pgm", "bad.png") + "free_thresh: 0.25\nmode: scale\n")
    with pytest.raises(DataError, match="cannot read the PNG"):
        load_map(tmp_path / "d.yaml")


def half_plane_room(cfg: OccupancyConfig):
    """The room seen by beams into the upper half plane only (the lower wall stays unknown)."""
    poses = ROOM_POSES * [1.0, 1.0, 0.0]
    angles = np.deg2rad(np.arange(0.0, 180.0, 0.5))
    return build_grid(poses, [room_ranges(p, angles) for p in poses], 0.0, np.deg2rad(0.5), 30.0, config=cfg)


def test_map_cells_read_pixels_as_nav2_map_server_does() -> None:
    # nav2 map_io.cpp loadMapFromFile, worked by hand for occupied_thresh 0.65, free_thresh 0.25:
    # occ = (255 - v) / 255; v = 89: occ 0.651 > 0.65; v = 90: occ 0.647, scale rint(99.26) = 99;
    # v = 140: 0.451 -> rint(50.2) = 50; v = 150: 0.412 -> 40; v = 191: 0.2510 -> rint(0.245) = 0 (between);
    # v = 192: 0.247 < 0.25 (free); v = 254: free.
    grey = np.array([[0, 89, 90, 140, 150, 191, 192, 254]])
    th = {"occupied_thresh": 0.65, "free_thresh": 0.25}
    np.testing.assert_array_equal(map_cells(grey, mode="trinary", **th), [[100, 100, -1, -1, -1, -1, 0, 0]])
    np.testing.assert_array_equal(map_cells(grey, mode="scale", **th), [[100, 100, 99, 50, 40, 0, 0, 0]])
    # scale mode: a pixel that is not opaque is unknown, whatever its grey level
    alpha = np.array([[255, 0, 255, 254, 255, 255, 255, 0]])
    np.testing.assert_array_equal(
        map_cells(grey, alpha, mode="scale", **th), [[100, -1, 99, -1, 40, 0, 0, -1]]
    )
    # trinary mode averages the alpha in as a fourth channel: v = 254 transparent reads (3*254 + 0) / 4
    # = 190.5, occ 0.253 (unknown); v = 0 transparent stays 0 (occupied)
    np.testing.assert_array_equal(
        map_cells(np.array([[254, 0]]), np.array([[0, 0]]), mode="trinary", **th), [[-1, 100]]
    )
    # negate: black is free, white occupied
    np.testing.assert_array_equal(
        map_cells(np.array([[0, 255]]), mode="trinary", negate=True, **th), [[0, 100]]
    )
    with pytest.raises(DataError, match="not supported"):
        map_cells(grey, mode="raw", **th)


def test_scale_map_files_round_trip(tmp_path: Path) -> None:
    from PIL import Image  # an independent PNG decoder (matplotlib's own dependency)

    cfg = OccupancyConfig(resolution=0.1, margin=0.5, mode="scale")
    grid = half_plane_room(cfg)
    expected = cells(grid, cfg)
    image, yml = save_map(grid, tmp_path / "maps" / "room", cfg)
    assert image.name == "room_scale.png" and yml.name == "room.yaml"
    assert yaml.safe_load(yml.read_text()) == {
        "image": "room_scale.png",
        "mode": "scale",
        "resolution": grid.resolution,
        "origin": list(grid.origin),
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.25,
    }
    with Image.open(image) as im:
        assert im.mode == "RGBA" and im.size == (grid.width, grid.height)  # nav2's saver: true colour + alpha
        rgba = np.asarray(im).astype(float)
    # map_server's scale rule applied here by hand (image row 0 = highest y)
    occ = 1.0 - rgba[..., :3].mean(axis=2) / 255.0
    level = np.rint((occ - 0.25) / 0.4 * 100.0)
    by_hand = np.where(occ > 0.65, 100, np.where(occ < 0.25, 0, level))
    by_hand = np.where(rgba[..., 3] != 255, -1, by_hand)[::-1]
    np.testing.assert_array_equal(by_hand, expected)
    # never observed cells are transparent (unknown); the others keep their occupancy to half a grey level
    np.testing.assert_array_equal(expected == -1, ~grid.observed)
    p = probabilities(grid)
    np.testing.assert_allclose(occ[::-1][grid.observed], p[grid.observed], atol=0.5 / 255 + 1e-12)
    # walls, free space and cells in between (passed by a few beams only) as 1..99
    assert {-1, 0, 100} <= set(np.unique(expected).tolist())
    between = (expected > 0) & (expected < 100)
    assert np.count_nonzero(between) > 10
    loaded = load_map(yml)
    assert loaded.mode == "scale" and loaded.image == image
    np.testing.assert_array_equal(loaded.data, expected)
    # its classes are the trinary map's, but where the 8-bit grey level rounds p across a threshold
    near = (np.abs(p - 0.65) <= 0.5 / 255) | (np.abs(p - 0.25) <= 0.5 / 255)
    np.testing.assert_array_equal(loaded.classes()[~near], trinary(grid, cfg)[~near])
    np.testing.assert_array_equal(loaded.classes(), classes_of(expected))


def test_ros_data_in_scale_mode_is_what_map_server_publishes_of_the_saved_map(tmp_path: Path) -> None:
    cfg = OccupancyConfig(resolution=0.1, margin=0.5, mode="scale")
    grid = half_plane_room(cfg)
    data = to_ros_data(grid, cfg)
    assert data.dtype == np.int8 and data.shape == (grid.width * grid.height,)
    _, yml = save_map(grid, tmp_path / "room", cfg)
    np.testing.assert_array_equal(data, load_map(yml).data.reshape(-1))
    assert data.min() == -1 and data.max() == 100 and np.any((data > 0) & (data < 100))
    # the same grid in trinary mode: 100 / 0 / -1 only
    assert set(np.unique(to_ros_data(grid, replace(cfg, mode="trinary"))).tolist()) == {-1, 0, 100}


def test_save_png(tmp_path: Path) -> None:
    grid, _ = room_grid(resolution=0.2)
    out = save_png(grid, tmp_path / "room.png", trajectory=ROOM_POSES)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- the Intel Research Lab map --------------------------------------------------------------------


def test_intel_map_from_corrected_poses_is_sharper_than_raw(datasets_dir: Path) -> None:
    from ptm_ros.io.carmen import read_log
    from ptm_ros.io.groundtruth import load_carmen_gt

    log = read_log(datasets_dir / "intel" / "intel-raw-910.clf.gz")
    gt = load_carmen_gt(datasets_dir / "intel" / "intel-gt-910.txt")
    assert len(log.lasers) == len(gt.poses_corrected) == 910
    ranges = [rec.ranges for rec in log.lasers]
    range_max = max(float(r.max()) for r in ranges)  # "no return" reading (81.83 m)
    a0, da = log.lasers[0].angle_min, log.lasers[0].angle_increment
    cfg = OccupancyConfig()
    maps = {}
    for name, poses in (("corrected", gt.poses_corrected), ("raw", gt.poses_raw)):
        grid = build_grid(poses, ranges, a0, da, range_max, config=cfg)
        cls = trinary(grid, cfg)
        maps[name] = (int(np.sum(cls == 100)), int(np.sum(cls >= 0)), int(np.sum(grid.observed)))
    occ_c, known_c, seen_c = maps["corrected"]
    occ_r, known_r, seen_r = maps["raw"]
    # Corrected: walls a few percent of the known area (measured 16691 of 200931 = 8.3 %), the known area
    # of a ~30 m x 30 m building. Raw odometry smears the same scans over a larger area (measured 594063
    # cells reached against 228284) where returns disagree: walls 12967 of 272910 known cells = 4.8 %.
    assert 0.01 < occ_c / known_c < 0.15
    assert 150_000 < known_c < 450_000
    assert seen_r > 2.0 * seen_c
    assert occ_c / known_c > 1.4 * (occ_r / known_r)


def test_aligned_windows_pair_the_cells_of_one_place():
    from ptm_ros.maps.occupancy import aligned_windows

    a = np.arange(4 * 5).reshape(4, 5)  # origin (0, 0): cell [r, c] at (c, r) * 0.5 m
    b = np.arange(3 * 3).reshape(3, 3) + 100  # origin (1.0, 0.5): b[0, 0] is a[1, 2]
    wa, wb = aligned_windows(a, (0.0, 0.0, 0.0), b, (1.0, 0.5, 0.0), 0.5)
    assert wa.tolist() == [[7, 8, 9], [12, 13, 14], [17, 18, 19]]
    assert wb.tolist() == [[100, 101, 102], [103, 104, 105], [106, 107, 108]]
    wb2, wa2 = aligned_windows(b, (1.0, 0.5, 0.0), a, (0.0, 0.0, 0.0), 0.5)  # either order
    assert wa2.tolist() == wa.tolist() and wb2.tolist() == wb.tolist()
    with pytest.raises(DataError, match="overlap"):
        aligned_windows(a, (0.0, 0.0, 0.0), b, (10.0, 0.0, 0.0), 0.5)
