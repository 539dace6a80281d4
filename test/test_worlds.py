"""Tests of the simulated worlds: geometry invariants, routes, passages and validation errors."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from ptm_ros.errors import ConfigError
from ptm_ros.io.simulator import MAX_ARC_TURN, CameraConfig, SimConfig, cast_rays, plan_trajectory, simulate
from ptm_ros.io.worlds import (
    CALIBRATION_FAMILIES,
    MIN_PLACE_SEPARATION,
    WORLDS,
    Place,
    Rect,
    World,
    build_world,
    get_world,
    ring_world,
    trace_walls,
)

NO_CAMERA = SimConfig(camera=CameraConfig(enabled=False))


def point_segment_distance(p: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Distance from points ``(N, 2)`` to one segment ``(4,)`` (projection clipped to the segment)."""
    a, b = seg[:2], seg[2:]
    e = b - a
    s = np.clip((p - a) @ e / (e @ e), 0.0, 1.0)
    return np.hypot(*(p - a - s[:, None] * e).T)


def shoelace(segments: np.ndarray) -> float:
    """Signed area enclosed by oriented boundary segments (positive = counter-clockwise)."""
    return float(0.5 * np.sum(segments[:, 0] * segments[:, 3] - segments[:, 2] * segments[:, 1]))


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_places_far_apart_and_route_visits_every_place(name: str) -> None:
    world = get_world(name)
    for p, q in itertools.combinations(world.places, 2):
        assert math.hypot(p.x - q.x, p.y - q.y) >= MIN_PLACE_SEPARATION, (p.id, q.id)
    assert {p.id for p in world.places} == set(world.route)
    corridors = {frozenset(c) for c in world.corridors}
    for a, b in itertools.pairwise((*world.route, world.route[0])):
        assert frozenset((a, b)) in corridors


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_walls_form_closed_oriented_loops(name: str) -> None:
    world = get_world(name)
    starts = sorted(w.start for w in world.walls)
    ends = sorted(w.end for w in world.walls)
    assert starts == ends  # every wall ends where another one starts
    lengths = np.array([w.length for w in world.walls])
    assert np.all(lengths > 0)
    # Axis-aligned walls on the 0.5 m grid.
    seg = world.segments
    assert np.all((seg[:, 0] == seg[:, 2]) | (seg[:, 1] == seg[:, 3]))
    assert np.allclose(seg * 2, np.round(seg * 2), atol=0, rtol=0)


def test_wall_orientation_encloses_the_free_area() -> None:
    # Free space on the left of every wall: outer boundaries counter-clockwise, holes clockwise, so the
    # shoelace sum is the free area. T: 12 x 2 m corridor plus a 2 x 5 m stem.
    assert shoelace(get_world("t-junction").segments) == pytest.approx(24.0 + 10.0, abs=1e-12)
    # Aliased loop: 14 x 14 m outer square minus the 10 x 10 m block, four 1 x 1 m doors and 6 x 5 m rooms.
    assert shoelace(get_world("aliased-loop").segments) == pytest.approx(196 - 100 + 4 * (1 + 30), abs=1e-12)


def test_single_rectangle_gives_four_counter_clockwise_walls() -> None:
    walls = trace_walls([Rect(0.0, 0.0, 3.0, 2.0, 7)])
    assert len(walls) == 4
    assert {w.texture for w in walls} == {7}
    corners = [(0.0, 0.0), (3.0, 0.0), (3.0, 2.0), (0.0, 2.0)]
    assert sorted((w.start, w.end) for w in walls) == sorted(itertools.pairwise([*corners, corners[0]]))


def test_aliased_loop_is_symmetric_under_quarter_turns() -> None:
    world = get_world("aliased-loop")
    seg = world.segments
    rotated = np.stack([12.0 - seg[:, 1], seg[:, 0], 12.0 - seg[:, 3], seg[:, 2]], axis=1)
    assert sorted(map(tuple, rotated.tolist())) == sorted(map(tuple, seg.tolist()))
    assert set(world.wall_textures.tolist()) == {0}


def test_texture_ids_repeat_across_corridors_of_the_larger_worlds() -> None:
    two = get_world("two-loop")
    # The south and north outer corridors share texture 1, and the inner loop is one texture.
    by_texture = {t: int(np.sum(two.wall_textures == t)) for t in set(two.wall_textures.tolist())}
    assert by_texture[1] >= 4
    assert by_texture[5] >= 8


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_passages_detected_equal_the_route(name: str) -> None:
    world = get_world(name)
    n = len(world.route) + 2  # wraps around the cyclic route
    run = simulate(world, NO_CAMERA, np.random.default_rng(1), visits=n)
    assert [p.place for p in run.passages] == list(world.visits(n))
    stamps = np.array([p.stamp for p in run.passages])
    assert np.all(np.diff(stamps) > 0)
    # The true position at each passage is within the passage radius of its place.
    for p in run.passages:
        k = int(np.flatnonzero(run.odom_stamps == p.stamp)[0])
        place = world.place(p.place)
        assert math.hypot(run.true_poses[k, 0] - place.x, run.true_poses[k, 1] - place.y) <= 1.0
    # The robot never comes closer than 0.4 m to a wall (2 m corridors, 1 m turn radius).
    xy = run.true_poses[::5, :2]
    clearance = min(point_segment_distance(xy, s).min() for s in world.segments)
    assert clearance > 0.4


def test_default_visits_match_the_brief() -> None:
    assert get_world("aliased-loop").default_visits == 10
    assert get_world("multi-loop").default_visits == 33
    assert len(get_world("multi-loop").visits()) == 33
    assert get_world("t-junction").visits(8) == ("w", "j", "s", "j", "e", "j", "w", "j")


def test_twin_junctions_look_alike_within_the_laser_patch_as_the_route_enters_them() -> None:
    """``j1`` entered heading east and ``j2`` heading south: the same walls at the same ranges in every
    direction up to 3.9 m (beyond, j2 sees j1's cross corridor ahead); one texture at ``j2``, and at ``j1``
    the same but for the walls behind and on the right (the corridor west and the wall across from the
    branch). The two are 5 m apart, 49 m along the route."""
    world = get_world("twin-junctions")
    j1, j2 = world.place("j1"), world.place("j2")
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    origins = np.array([[j1.x, j1.y], [j2.x, j2.y]])
    hits = cast_rays(world.segments, origins, np.stack([angles, angles - math.pi / 2]))
    np.testing.assert_allclose(np.minimum(hits.range[0], 3.9), np.minimum(hits.range[1], 3.9), atol=1e-9)
    seen = hits.range[0] < 3.9
    at_j1, at_j2 = world.wall_textures[hits.wall[0][seen]], world.wall_textures[hits.wall[1][seen]]
    assert set(at_j2.tolist()) == {0} and set(at_j1.tolist()) == {0, 1}
    own = angles[seen][at_j1 == 1]
    assert np.all((own <= -math.pi / 4 + 1e-9) | (own >= 3 * math.pi / 4 - 1e-9))
    assert math.hypot(j1.x - j2.x, j1.y - j2.y) == 5.0
    assert world.visits() == ("j1", "c-e", "c-ne", "c-nw", "j2", "end-p", "j2", "j1")


def test_get_world_lists_names_on_error() -> None:
    with pytest.raises(
        ConfigError, match=r"unknown world 'nowhere'; known worlds: aliased-loop, aliased-ring, distinct-loop"
    ):
        get_world("nowhere")


def test_visits_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="must be >= 1, got 0"):
        get_world("t-junction").visits(0)


PLACES = [Place("a", 0.0, 0.0, "corridor-end"), Place("b", 6.0, 0.0, "corridor-end")]


def test_validation_errors() -> None:
    with pytest.raises(ConfigError, match=r"places 'a' and 'b' are 4.00 m apart"):
        build_world(
            "x",
            "",
            [PLACES[0], Place("b", 4.0, 0.0, "junction")],
            [("a", "b", 0)],
            route=["a", "b"],
            default_visits=2,
        )
    with pytest.raises(ConfigError, match="has kind 'plaza'"):
        build_world(
            "x",
            "",
            [PLACES[0], Place("b", 6.0, 0.0, "plaza")],
            [("a", "b", 0)],
            route=["a", "b"],
            default_visits=2,
        )
    with pytest.raises(ConfigError, match="never visits"):
        build_world("x", "", PLACES, [("a", "b", 0)], route=["a"], default_visits=2)
    with pytest.raises(ConfigError, match="unknown places"):
        build_world("x", "", PLACES, [("a", "c", 0)], route=["a", "b"], default_visits=2)
    with pytest.raises(ConfigError, match=r"route step 'a' -> 'c' is not a corridor"):
        build_world(
            "x",
            "",
            [*PLACES, Place("c", 6.0, 6.0, "corner")],
            [("a", "b", 0), ("b", "c", 0)],
            route=["a", "c", "b"],
            default_visits=2,
        )
    with pytest.raises(ConfigError, match="not axis-aligned"):
        build_world(
            "x",
            "",
            [PLACES[0], Place("b", 6.0, 6.0, "corner")],
            [("a", "b", 0)],
            route=["a", "b"],
            default_visits=2,
        )
    with pytest.raises(ConfigError, match=r"place 'c' lies 0.50 m from corridor 'a'-'b'"):
        build_world(
            "x",
            "",
            [Place("a", 0, 0, "corner"), Place("b", 12, 0, "corner"), Place("c", 6, 0.5, "doorway")],
            [("a", "b", 0), ("b", "c", 0)],
            route=["a", "b", "c"],
            default_visits=2,
        )
    with pytest.raises(ConfigError, match=r"multiples of 0\.5 m"):
        Rect(0.0, 0.0, 1.2, 1.0, 0)
    with pytest.raises(ConfigError, match="x1 > x0"):
        Rect(1.0, 0.0, 1.0, 1.0, 0)


# --------------------------------------------------------------------------------------------------
# Calibration families (issue #23)


def rotated_walls(world: World, cx: float, cy: float, quarter_turns: int) -> list[tuple]:
    """The world's walls ``(x0, y0, x1, y1, texture)`` turned by quarter turns about ``(cx, cy)``, sorted."""
    seg = world.segments.copy()
    for _ in range(quarter_turns % 4):
        seg = np.stack(
            [cx - (seg[:, 1] - cy), cy + (seg[:, 0] - cx), cx - (seg[:, 3] - cy), cy + (seg[:, 2] - cx)], 1
        )
    return sorted(zip(*seg.T.tolist(), world.wall_textures.tolist(), strict=True))


def walls_of(world: World) -> list[tuple]:
    return rotated_walls(world, 0.0, 0.0, 0)


def free_cells(world: World) -> set[tuple[int, int]]:
    """The 0.5 m cells inside the walls (ray parity along +x from each cell centre): the geometry alone."""
    seg = world.segments
    lo, hi = seg[:, [0, 2]].min() - 1, seg[:, [0, 2]].max() + 1
    blo, bhi = seg[:, [1, 3]].min() - 1, seg[:, [1, 3]].max() + 1
    vertical = seg[seg[:, 0] == seg[:, 2]]
    ymin, ymax = np.minimum(vertical[:, 1], vertical[:, 3]), np.maximum(vertical[:, 1], vertical[:, 3])
    cells = set()
    for x in np.arange(lo, hi, 0.5) + 0.25:
        for y in np.arange(blo, bhi, 0.5) + 0.25:
            crossings = np.count_nonzero((vertical[:, 0] > x) & (ymin < y) & (ymax > y))
            if crossings % 2:
                cells.add((round(x * 4), round(y * 4)))
    return cells


def test_calibration_families_are_known_worlds_with_same_geometry_controls() -> None:
    assert set(CALIBRATION_FAMILIES) == {"loop", "ring", "twin-rooms", "room-row"}
    for aliased, control in CALIBRATION_FAMILIES.values():
        a, c = get_world(aliased), get_world(control)
        assert a.places == c.places and a.route == c.route and a.corridors == c.corridors
        assert a.default_visits == c.default_visits
        assert free_cells(a) == free_cells(c)  # the same free space ...
        assert shoelace(a.segments) == pytest.approx(shoelace(c.segments), abs=1e-12)
        # ... and the control's textures distinguish more walls than the aliased world's.
        assert len(set(c.wall_textures.tolist())) > len(set(a.wall_textures.tolist()))


def test_ring_world_reproduces_the_aliased_loop() -> None:
    ring = ring_world(
        "aliased-loop",
        "",
        side=12.0,
        doors_per_side=1,
        corridor_texture=lambda k: 0,
        room_texture=lambda k, d: 0,
        default_visits=10,
    )
    reference = get_world("aliased-loop")
    assert ring.walls == reference.walls and ring.places == reference.places and ring.route == reference.route


def test_aliased_worlds_map_onto_themselves_textures_included() -> None:
    ring = get_world("aliased-ring")
    assert rotated_walls(ring, 9.0, 9.0, 1) == walls_of(ring)
    assert len(ring.places) == 12 and len(ring.route) == 12
    twins = get_world("twin-rooms")
    assert rotated_walls(twins, 10.0, 0.0, 2) == walls_of(twins)
    # The control breaks the symmetry through its textures only.
    control = get_world("twin-rooms-distinct")
    assert rotated_walls(control, 10.0, 0.0, 2) != walls_of(control)
    row = get_world("room-row")
    rooms = [r for r in row.places if r.kind == "room-entrance"]
    assert len(rooms) == 3

    # Every room (with its door) is the first one translated, textures included.
    def near(world: World, x: float) -> list[tuple]:
        return sorted(
            (round(w.start[0] - x, 6), w.start[1], round(w.end[0] - x, 6), w.end[1], w.texture)
            for w in world.walls
            if min(w.start[1], w.end[1]) >= 1.0 and abs((w.start[0] + w.end[0]) / 2 - x) <= 3.0
        )

    assert near(row, rooms[0].x) == near(row, rooms[1].x) == near(row, rooms[2].x)
    distinct = get_world("room-row-distinct")
    assert near(distinct, rooms[0].x) != near(distinct, rooms[1].x)


@pytest.mark.parametrize("name", ["twin-rooms", "room-row"])
def test_room_routes_re_enter_rooms_with_u_turns(name: str) -> None:
    world = get_world(name)
    visits = world.visits()
    rooms = {p.id for p in world.places if p.kind == "room-entrance"}
    entered = [v for v in visits if v in rooms]
    assert set(entered) == rooms and len(entered) == len(rooms) + 1  # the first room entered twice
    assert entered[0] == entered[-1]
    traj = plan_trajectory(world, NO_CAMERA)
    spins = np.flatnonzero(traj.kind == 2)
    # A U-turn on the spot at every visit of a room or a corridor end (and nowhere else).
    ends = {p.id for p in world.places if p.kind == "corridor-end"}
    assert len(spins) == len(entered) + sum(v in ends for v in visits)
    assert np.all(np.abs(traj.turn[spins]) > MAX_ARC_TURN)
    run = simulate(world, NO_CAMERA, np.random.default_rng(0))
    assert [p.place for p in run.passages] == list(visits)
