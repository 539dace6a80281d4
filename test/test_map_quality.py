"""Map quality against a reference: hand-built grids whose leak, walls and areas are known exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptm_ros.errors import DataError
from ptm_ros.maps.map_quality import ClassGrid, leaked_cells, map_quality

RES = 0.05
UNK, FREE, OCC = -1, 0, 100


def room(height: int = 40, width: int = 60) -> np.ndarray:
    """Classes of a walled room: a one-cell wall ring, free inside, unknown beyond (row 0 = lowest y)."""
    c = np.full((height, width), UNK, dtype=np.int8)
    c[5:-5, 5:-5] = OCC
    c[6:-6, 6:-6] = FREE
    return c


def test_identical_maps_score_perfectly() -> None:
    ref = ClassGrid(room(), (1.0, -2.0, 0.0), RES)
    q = map_quality(ref, ref)
    assert (q.leak, q.wall_precision, q.wall_recall, q.free_area_ratio) == (0.0, 1.0, 1.0, 1.0)
    assert q.free_cells == 28 * 48 and q.wall_cells == q.reference_wall_cells == 30 * 50 - 28 * 48
    assert q.free_area_m2 == pytest.approx(28 * 48 * RES**2)


def corridor_out(grid: np.ndarray, width: int = 80) -> np.ndarray:
    """``grid`` widened to ``width`` columns (unknown) with a free corridor, rows 18..20, from the east wall
    (column 54) to the new edge."""
    out = np.full((grid.shape[0], width), UNK, dtype=np.int8)
    out[:, : grid.shape[1]] = grid
    out[18:21, 54:] = FREE
    return out


def test_a_constructed_leak_is_measured_exactly() -> None:
    """A free corridor out through the wall: its cells farther than 0.3 m from every seen reference cell
    leak, the nearer ones do not."""
    res = 0.04  # 0.3 m falls between two columns (7 × 0.04 = 0.28, 8 × 0.04 = 0.32)
    reference = ClassGrid(room(), (0.0, 0.0, 0.0), res)
    q = map_quality(ClassGrid(corridor_out(room()), (0.0, 0.0, 0.0), res), reference)
    # Seen reference cells end at column 54 (the wall): columns 55..61 lie within 0.28 m of it, columns
    # 62..79 (18 columns of 3 rows) leak.
    assert q.leaked_cells == 18 * 3
    assert q.free_cells == 28 * 48 + 3 * (80 - 54)
    assert q.leak == pytest.approx(54 / q.free_cells)
    assert q.free_area_ratio == pytest.approx(q.free_cells / (28 * 48))
    assert q.wall_cells == 30 * 50 - 28 * 48 - 3  # the corridor opened three wall cells
    assert q.wall_precision == 1.0 and q.wall_recall == 1.0  # their neighbours lie within 0.2 m


def test_leaked_cells_are_the_corridor_beyond_the_radius() -> None:
    """The mask the report draws in red: exactly the 18 x 3 corridor cells of the measure above."""
    res = 0.04
    reference = ClassGrid(room(), (0.0, 0.0, 0.0), res)
    product = ClassGrid(corridor_out(room()), (0.0, 0.0, 0.0), res)
    mask = leaked_cells(product, reference)
    expected = np.zeros(product.classes.shape, dtype=bool)
    expected[18:21, 62:] = True
    np.testing.assert_array_equal(mask, expected)
    assert int(mask.sum()) == map_quality(product, reference).leaked_cells
    assert not leaked_cells(reference, reference).any()
    with pytest.raises(DataError, match="leak_radius"):
        leaked_cells(product, reference, leak_radius=-1.0)


def test_seen_cells_count_even_when_unknown() -> None:
    """A reference cell passed and hit alike is seen though neither free nor occupied: no leak there."""
    classes = room(width=80)
    classes[:, 60:] = UNK
    seen = classes != UNK
    seen[18:21, 55:] = True  # seen beyond the wall, class unknown
    product = ClassGrid(corridor_out(room()), (0.0, 0.0, 0.0), RES)
    assert map_quality(product, ClassGrid(classes, (0.0, 0.0, 0.0), RES, seen=seen)).leaked_cells == 0
    assert map_quality(product, ClassGrid(classes, (0.0, 0.0, 0.0), RES)).leaked_cells > 0


def test_walls_shifted_beyond_the_radius_are_missed_and_imprecise() -> None:
    """A map whose bottom wall sits 5 rows (0.25 m > 0.2 m) above the reference's: its cells are neither
    precise nor recalled but near the side walls; 3 rows (0.15 m) off it still matches."""
    ref = ClassGrid(room(), (0.0, 0.0, 0.0), RES)
    for shift in (3, 5):
        product = room()
        product[5, 5:-5] = FREE  # the bottom wall (row 5, columns 5..54) moved up by `shift` rows
        product[5 + shift, 6:-6] = OCC
        q = map_quality(ClassGrid(product, (0.0, 0.0, 0.0), RES), ref)
        if shift == 3:
            assert q.wall_precision == 1.0 and q.wall_recall == 1.0
            continue
        # The moved wall's 48 cells: the 4 at each end lie within 0.2 m of a side wall (columns 5, 54).
        assert q.wall_precision == pytest.approx(1.0 - 40 / q.wall_cells)
        # The reference's 50 bottom cells: the 4 at each end lie within 0.2 m of the side walls' row 6.
        assert q.wall_recall == pytest.approx(1.0 - 42 / q.reference_wall_cells)


def test_the_map_is_carried_into_the_reference_frame() -> None:
    """The product in a frame rotated by 90° and shifted: with the right motion it scores perfectly."""
    classes = room()
    reference = ClassGrid(classes, (0.0, 0.0, 0.0), RES)
    # The product frame: x_p = R(-90°) x_ref + d, i.e. x_ref = R(90°) (x_p - d) = R(90°) x_p + t.
    rotated = np.rot90(classes, k=-1)  # the same room, rotated by -90° about the grid's corner
    w = classes.shape[1]
    d = np.array([3.0, 7.0])
    product = ClassGrid(np.ascontiguousarray(rotated), (d[0], d[1] - w * RES, 0.0), RES)
    t = -np.array([[0.0, -1.0], [1.0, 0.0]]) @ d
    q = map_quality(product, reference, theta=math.pi / 2, t=t)
    assert (q.leak, q.wall_precision, q.wall_recall) == (0.0, 1.0, 1.0)
    wrong = map_quality(product, reference)
    assert wrong.leak == 1.0 and wrong.wall_precision == 0.0


def test_empty_sets_and_errors() -> None:
    empty = ClassGrid(np.full((4, 4), UNK, dtype=np.int8), (0.0, 0.0, 0.0), RES)
    q = map_quality(empty, empty)
    assert all(math.isnan(v) for v in (q.leak, q.wall_precision, q.wall_recall, q.free_area_ratio))
    assert q.as_dict()["leak"] is None
    with pytest.raises(DataError, match="yaw 0"):
        ClassGrid(room(), (0.0, 0.0, 0.1), RES)
    with pytest.raises(DataError, match="seen has shape"):
        ClassGrid(room(), (0.0, 0.0, 0.0), RES, seen=np.ones((2, 2), dtype=bool))
    with pytest.raises(DataError, match="radii"):
        map_quality(empty, empty, leak_radius=-1.0)
