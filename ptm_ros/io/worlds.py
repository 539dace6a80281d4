"""Simulated indoor worlds: textured walls, named places and a route (the settings of thesis Ch. 5).

A world is built from axis-aligned free-space rectangles: a 2 m wide corridor around every straight
connection between two places, plus rooms and door openings. The walls are the boundary of the union
of those rectangles, traced on a 0.5 m grid and merged into maximal straight segments; every wall is
oriented with free space on its *left* (so a rotation of a symmetric world maps walls onto walls with
the same texture coordinate) and carries the texture id of the free-space rectangle it bounds.
Repeating a texture id in several corridors makes them look alike (perceptual aliasing).

Places are the decision points a landmark detector should fire at (junctions, corners, corridor ends,
doorways, room entrances); the route is a cyclic sequence of place ids the robot drives through, each
consecutive pair (the last to the first included) joined by a corridor. The worlds:

* ``aliased-loop``: a 12 m square loop of identical corridors with a door in the middle of every side;
  the four corners look alike and the four doors look alike (10 visits by default).
* ``two-loop``: a small loop inside a large one joined by two short corridors, like the TSRB floor of
  thesis Figs. 32-33 (18 visits by default).
* ``multi-loop``: a 4 x 3 grid of corridors (six loops) with a dead end, driven through several loops
  like the simulation of thesis Figs. 39-40 (33 visits by default).
* ``t-junction``: a tiny T of three 5 m corridors for fast tests (6 visits per cycle, 3 by default).
* ``twin-junctions``: two T-junctions 5 m apart on one corridor, alike to the laser, the second reached
  from the first only around a 25 x 20 m loop of identical corridors; the first has a wall of another
  texture across from its branch (weak evidence, to the camera only). After the loop the odometry cannot
  tell whether the robot is back at the first junction or at its twin; the drive on to the first tells
  them apart (8 visits by default: ``make demo``'s world).

Calibration families (issue #23): worlds with exact perceptual aliasing, each with a *control* of the same
geometry whose textures all differ (only the laser's view of the geometry can still alias there). Their
routes re-enter rooms and turn back (U-turns on the spot, see ``MAX_ARC_TURN`` in the simulator):

* ``distinct-loop``: ``aliased-loop``'s geometry with a texture of its own per side and per room.
* ``aliased-ring`` / ``distinct-ring``: an 18 m square ring with two doors (and rooms) per side,
  identical sides (or distinct ones); 14 visits by default (the loop closes twice).
* ``twin-rooms`` / ``twin-rooms-distinct``: a 20 m corridor with one room north of its west half and one
  south of its east half; the aliased world is symmetric under a half turn (the rooms, the doors and the
  corridor ends alias); the route enters both rooms, turns back at both ends and re-enters the first
  room (13 visits by default).
* ``room-row`` / ``room-row-distinct``: a 26 m corridor lined on one side with three identical (or
  distinct) rooms, each entered and left with a U-turn, the corridor driven back to close the loop and
  the first room re-entered (17 visits by default).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import ConfigError

#: Kinds of places a world may declare.
PLACE_KINDS = ("junction", "corner", "corridor-end", "doorway", "room-entrance")
#: Minimum distance between two places (m): larger than the evaluation's 4 m "different place" radius.
MIN_PLACE_SEPARATION = 5.0
#: Minimum distance (m) between a corridor centreline and a place that is not one of its two ends.
MIN_CORRIDOR_CLEARANCE = 2.0
#: Grid on which rectangles are laid out and walls traced (m).
GRID = 0.5


@dataclass(frozen=True)
class Place:
    """A named decision point at ``(x, y)`` (m, world frame) of a kind in :data:`PLACE_KINDS`."""

    id: str
    x: float
    y: float
    kind: str


@dataclass(frozen=True)
class Wall:
    """A straight wall from ``start`` to ``end`` (m) with free space on its left and a texture id."""

    start: tuple[float, float]
    end: tuple[float, float]
    texture: int

    @property
    def length(self) -> float:
        """Length of the wall (m)."""
        return math.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1])


@dataclass(frozen=True)
class Rect:
    """An axis-aligned free-space rectangle ``[x0, x1] x [y0, y1]`` (m) whose walls get ``texture``."""

    x0: float
    y0: float
    x1: float
    y1: float
    texture: int

    def __post_init__(self) -> None:
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            msg = f"rectangle {self} must have x1 > x0 and y1 > y0"
            raise ConfigError(msg)
        for v in (self.x0, self.y0, self.x1, self.y1):
            if abs(v / GRID - round(v / GRID)) > 1e-9:
                msg = f"rectangle {self}: coordinates must be multiples of {GRID} m"
                raise ConfigError(msg)


@dataclass(frozen=True)
class World:
    """A 2-D world: walls, places, the corridors joining places and a cyclic route of place ids."""

    name: str
    description: str
    places: tuple[Place, ...]
    corridors: tuple[tuple[str, str], ...]
    walls: tuple[Wall, ...]
    route: tuple[str, ...]
    default_visits: int

    def __post_init__(self) -> None:
        ids = [p.id for p in self.places]
        if len(set(ids)) != len(ids):
            msg = f"world {self.name!r}: duplicate place ids in {ids}"
            raise ConfigError(msg)
        for p in self.places:
            if p.kind not in PLACE_KINDS:
                msg = f"world {self.name!r}: place {p.id!r} has kind {p.kind!r}, not one of {PLACE_KINDS}"
                raise ConfigError(msg)
        xy = np.array([(p.x, p.y) for p in self.places], dtype=float).reshape(-1, 2)
        d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
        d[np.diag_indices(len(xy))] = np.inf
        if len(xy) > 1 and d.min() < MIN_PLACE_SEPARATION:
            i, j = np.unravel_index(np.argmin(d), d.shape)
            msg = (
                f"world {self.name!r}: places {ids[i]!r} and {ids[j]!r} are {d[i, j]:.2f} m apart "
                f"(< {MIN_PLACE_SEPARATION} m)"
            )
            raise ConfigError(msg)
        known = set(ids)
        for a, b in self.corridors:
            if a not in known or b not in known or a == b:
                msg = f"world {self.name!r}: corridor ({a!r}, {b!r}) must join two different known places"
                raise ConfigError(msg)
            self._check_clearance(a, b)
        if not self.route:
            msg = f"world {self.name!r}: empty route"
            raise ConfigError(msg)
        unknown = [r for r in self.route if r not in known]
        if unknown:
            msg = f"world {self.name!r}: route names unknown places {unknown}"
            raise ConfigError(msg)
        missed = sorted(known - set(self.route))
        if missed:
            msg = f"world {self.name!r}: the route never visits {missed}"
            raise ConfigError(msg)
        edges = {frozenset(c) for c in self.corridors}
        for k, a in enumerate(self.route):
            b = self.route[(k + 1) % len(self.route)]
            if frozenset((a, b)) not in edges:
                msg = f"world {self.name!r}: route step {a!r} -> {b!r} is not a corridor"
                raise ConfigError(msg)
        if self.default_visits < 1:
            msg = f"world {self.name!r}: default_visits must be >= 1, got {self.default_visits}"
            raise ConfigError(msg)

    def _check_clearance(self, a: str, b: str) -> None:
        pa, pb = self.place(a), self.place(b)
        if pa.x != pb.x and pa.y != pb.y:
            msg = f"world {self.name!r}: corridor {a!r}-{b!r} is not axis-aligned"
            raise ConfigError(msg)
        ab = np.array([pb.x - pa.x, pb.y - pa.y])
        for p in self.places:
            if p.id in (a, b):
                continue
            ap = np.array([p.x - pa.x, p.y - pa.y])
            s = float(np.clip(ap @ ab / (ab @ ab), 0.0, 1.0))
            dist = float(np.hypot(*(ap - s * ab)))
            if dist < MIN_CORRIDOR_CLEARANCE:
                msg = (
                    f"world {self.name!r}: place {p.id!r} lies {dist:.2f} m from corridor {a!r}-{b!r}; "
                    f"split the corridor at it"
                )
                raise ConfigError(msg)

    def place(self, place_id: str) -> Place:
        """The place with id ``place_id`` (ConfigError if unknown)."""
        for p in self.places:
            if p.id == place_id:
                return p
        msg = f"world {self.name!r} has no place {place_id!r}; places: {[p.id for p in self.places]}"
        raise ConfigError(msg)

    def visits(self, n: int | None = None) -> tuple[str, ...]:
        """The first ``n`` place visits of the cyclic route (``default_visits`` when None)."""
        n = self.default_visits if n is None else n
        if n < 1:
            msg = f"the number of place visits must be >= 1, got {n}"
            raise ConfigError(msg)
        return tuple(self.route[k % len(self.route)] for k in range(n))

    @cached_property
    def segments(self) -> NDArray[np.float64]:
        """Walls as an ``(S, 4)`` array of ``(x0, y0, x1, y1)`` (m)."""
        return np.array([(*w.start, *w.end) for w in self.walls], dtype=float).reshape(-1, 4)

    @cached_property
    def wall_textures(self) -> NDArray[np.int64]:
        """Texture id of each wall, ``(S,)``."""
        return np.array([w.texture for w in self.walls], dtype=np.int64)

    @cached_property
    def place_xy(self) -> NDArray[np.float64]:
        """Place positions ``(P, 2)`` in the order of :attr:`places`."""
        return np.array([(p.x, p.y) for p in self.places], dtype=float).reshape(-1, 2)


def corridor_rect(a: Place, b: Place, texture: int, width: float = 2.0) -> Rect:
    """The free space of a straight corridor from ``a`` to ``b``, extended by half a width at both ends."""
    h = width / 2.0
    return Rect(min(a.x, b.x) - h, min(a.y, b.y) - h, max(a.x, b.x) + h, max(a.y, b.y) + h, texture)


def trace_walls(rects: Sequence[Rect], grid: float = GRID) -> tuple[Wall, ...]:
    """The boundary of the union of ``rects`` as maximal straight walls, free space on their left.

    The plane is rasterised into ``grid`` cells; a cell is free when its centre lies inside a rectangle and
    takes the texture of the first such rectangle. Every edge between a free and a blocked cell becomes a
    unit wall; collinear, contiguous unit walls with the same orientation and texture are merged.
    """
    if not rects:
        msg = "a world needs at least one free-space rectangle"
        raise ConfigError(msg)
    x0 = min(r.x0 for r in rects) - grid
    y0 = min(r.y0 for r in rects) - grid
    nx = round((max(r.x1 for r in rects) + grid - x0) / grid)
    ny = round((max(r.y1 for r in rects) + grid - y0) / grid)
    cx = x0 + (np.arange(nx) + 0.5) * grid
    cy = y0 + (np.arange(ny) + 0.5) * grid
    tex = np.full((nx, ny), -1, dtype=np.int64)
    for r in reversed(rects):  # the first rectangle listed wins where rectangles overlap
        inside = ((cx > r.x0) & (cx < r.x1))[:, None] & ((cy > r.y0) & (cy < r.y1))[None, :]
        tex[inside] = r.texture

    walls: list[Wall] = []

    def emit(runs: list[tuple[int, int, int, int]], make: Callable[[int, int, int], Wall]) -> None:
        # runs: (line, cell, direction, texture) unit walls on one family of grid lines.
        runs.sort()
        k = 0
        while k < len(runs):
            line, start, direction, texture = runs[k]
            end = start
            while k + 1 < len(runs) and runs[k + 1][0] == line and runs[k + 1][1] == end + 1:
                nxt = runs[k + 1]
                if (nxt[2], nxt[3]) != (direction, texture):
                    break
                end += 1
                k += 1
            walls.append(make(line, start, end) if direction > 0 else make(line, end, start))
            k += 1

    # Vertical walls: grid line x = x0 + (i+1)*grid between cells (i, j) and (i+1, j).
    vertical: list[tuple[int, int, int, int]] = []
    for i in range(nx - 1):
        for j in range(ny):
            left, right = tex[i, j], tex[i + 1, j]
            if (left >= 0) != (right >= 0):
                # Free cell to the west: walk north (+1); free to the east: walk south (-1).
                vertical.append((i, j, 1, int(left)) if left >= 0 else (i, j, -1, int(right)))

    def make_vertical(i: int, j_from: int, j_to: int) -> Wall:
        x = x0 + (i + 1) * grid
        texture = int(max(tex[i, j_from], tex[i + 1, j_from]))
        y_from = y0 + j_from * grid if j_from <= j_to else y0 + (j_from + 1) * grid
        y_to = y0 + (j_to + 1) * grid if j_from <= j_to else y0 + j_to * grid
        return Wall((_r(x), _r(y_from)), (_r(x), _r(y_to)), texture)

    # Horizontal walls: grid line y = y0 + (j+1)*grid between cells (i, j) and (i, j+1).
    horizontal: list[tuple[int, int, int, int]] = []
    for j in range(ny - 1):
        for i in range(nx):
            below, above = tex[i, j], tex[i, j + 1]
            if (below >= 0) != (above >= 0):
                # Free cell below: walk west (-1); free above: walk east (+1).
                horizontal.append((j, i, -1, int(below)) if below >= 0 else (j, i, 1, int(above)))

    def make_horizontal(j: int, i_from: int, i_to: int) -> Wall:
        y = y0 + (j + 1) * grid
        texture = int(max(tex[i_from, j], tex[i_from, j + 1]))
        x_from = x0 + i_from * grid if i_from <= i_to else x0 + (i_from + 1) * grid
        x_to = x0 + (i_to + 1) * grid if i_from <= i_to else x0 + i_to * grid
        return Wall((_r(x_from), _r(y)), (_r(x_to), _r(y)), texture)

    emit(vertical, make_vertical)
    emit(horizontal, make_horizontal)
    return tuple(walls)


def _r(v: float) -> float:
    """Round a grid coordinate to kill floating-point dust (grid multiples are exact in binary)."""
    return round(v / GRID) * GRID


def build_world(
    name: str,
    description: str,
    places: Sequence[Place],
    corridors: Sequence[tuple[str, str, int]],
    *,
    route: Sequence[str],
    default_visits: int,
    rooms: Sequence[Rect] = (),
    corridor_width: float = 2.0,
) -> World:
    """Assemble a :class:`World` from places, textured corridors ``(a, b, texture)``, rooms and a route."""
    by_id = {p.id: p for p in places}
    missing = [c for c in corridors if c[0] not in by_id or c[1] not in by_id]
    if missing:
        msg = f"world {name!r}: corridors {missing} name unknown places"
        raise ConfigError(msg)
    rects = [corridor_rect(by_id[a], by_id[b], t, corridor_width) for a, b, t in corridors]
    return World(
        name=name,
        description=description,
        places=tuple(places),
        corridors=tuple((a, b) for a, b, _ in corridors),
        walls=trace_walls([*rects, *rooms]),
        route=tuple(route),
        default_visits=default_visits,
    )


def _rotate_rect(r: Rect, cx: float, cy: float, quarter_turns: int) -> Rect:
    """``r`` rotated by ``quarter_turns`` x 90 degrees counter-clockwise about ``(cx, cy)``."""
    x0, y0, x1, y1 = r.x0, r.y0, r.x1, r.y1
    for _ in range(quarter_turns % 4):
        # (x, y) -> (cx - (y - cy), cy + (x - cx))
        x0, y0, x1, y1 = cx - (y1 - cy), cy + (x0 - cx), cx - (y0 - cy), cy + (x1 - cx)
    return Rect(x0, y0, x1, y1, r.texture)


def aliased_loop() -> World:
    """A 12 m square loop of identical corridors with a door (and a room) in the middle of each side."""
    places = [
        Place("c-sw", 0.0, 0.0, "corner"),
        Place("d-s", 6.0, 0.0, "doorway"),
        Place("c-se", 12.0, 0.0, "corner"),
        Place("d-e", 12.0, 6.0, "doorway"),
        Place("c-ne", 12.0, 12.0, "corner"),
        Place("d-n", 6.0, 12.0, "doorway"),
        Place("c-nw", 0.0, 12.0, "corner"),
        Place("d-w", 0.0, 6.0, "doorway"),
    ]
    ring = [p.id for p in places]
    corridors = [(a, ring[(k + 1) % len(ring)], 0) for k, a in enumerate(ring)]
    door = Rect(5.5, -2.0, 6.5, -1.0, 0)
    room = Rect(3.0, -7.0, 9.0, -2.0, 0)
    rooms = [_rotate_rect(r, 6.0, 6.0, q) for q in range(4) for r in (door, room)]
    return build_world(
        "aliased-loop",
        "12 m square loop of identical corridors, a door to a room mid-side: corners and doors alias",
        places,
        corridors,
        route=ring,
        default_visits=10,
        rooms=rooms,
    )


def two_loop() -> World:
    """A 6 m x 6 m inner loop inside a 24 m x 16 m outer loop, joined by two spokes (TSRB-like)."""
    places = [
        Place("o-sw", 0.0, 0.0, "corner"),
        Place("o-s", 12.0, 0.0, "junction"),
        Place("o-se", 24.0, 0.0, "corner"),
        Place("d-e", 24.0, 8.0, "doorway"),
        Place("o-ne", 24.0, 16.0, "corner"),
        Place("o-n", 12.0, 16.0, "junction"),
        Place("o-nw", 0.0, 16.0, "corner"),
        Place("d-w", 0.0, 8.0, "doorway"),
        Place("i-s", 12.0, 5.0, "junction"),
        Place("i-se", 18.0, 5.0, "corner"),
        Place("i-ne", 18.0, 11.0, "corner"),
        Place("i-n", 12.0, 11.0, "junction"),
        Place("i-nw", 6.0, 11.0, "corner"),
        Place("i-sw", 6.0, 5.0, "corner"),
    ]
    corridors = [
        ("o-sw", "o-s", 1),
        ("o-s", "o-se", 1),
        ("o-se", "d-e", 2),
        ("d-e", "o-ne", 2),
        ("o-ne", "o-n", 1),
        ("o-n", "o-nw", 1),
        ("o-nw", "d-w", 3),
        ("d-w", "o-sw", 3),
        ("o-s", "i-s", 4),
        ("i-n", "o-n", 4),
        ("i-s", "i-se", 5),
        ("i-se", "i-ne", 5),
        ("i-ne", "i-n", 5),
        ("i-n", "i-nw", 5),
        ("i-nw", "i-sw", 5),
        ("i-sw", "i-s", 5),
    ]
    rooms = [
        Rect(-3.0, 7.5, -1.0, 8.5, 6),
        Rect(-9.0, 5.0, -3.0, 11.0, 6),
        Rect(25.0, 7.5, 27.0, 8.5, 7),
        Rect(27.0, 5.0, 33.0, 11.0, 7),
    ]
    route = [
        *("o-sw", "o-s", "o-se", "d-e", "o-ne", "o-n", "o-nw", "d-w"),
        *("o-sw", "o-s", "i-s", "i-se", "i-ne", "i-n", "i-nw", "i-sw", "i-s", "o-s"),
    ]
    return build_world(
        "two-loop",
        "small loop inside a large one joined by two spokes, doors to rooms east and west (thesis TSRB)",
        places,
        corridors,
        route=route,
        default_visits=18,
        rooms=rooms,
    )


def multi_loop() -> World:
    """A 4 x 3 grid of corridors 5 m apart (six loops) with a dead end, several loops driven (Fig. 39)."""
    cols, rows = "abcd", "123"
    degree: dict[str, int] = {}
    corridors: list[tuple[str, str, int]] = []
    row_texture = {0: 1, 1: 2, 2: 1}
    col_texture = {0: 3, 1: 4, 2: 3, 3: 4}
    for r in range(3):
        for c in range(3):
            corridors.append((f"{cols[c]}{rows[r]}", f"{cols[c + 1]}{rows[r]}", row_texture[r]))
    for c in range(4):
        for r in range(2):
            corridors.append((f"{cols[c]}{rows[r]}", f"{cols[c]}{rows[r + 1]}", col_texture[c]))
    corridors.append(("d2", "e2", 5))
    for a, b, _ in corridors:
        degree[a] = degree.get(a, 0) + 1
        degree[b] = degree.get(b, 0) + 1
    names = [(f"{cols[c]}{rows[r]}", 5.0 * c, 5.0 * r) for r in range(3) for c in range(4)]
    places = [Place(n, x, y, "corner" if degree[n] == 2 else "junction") for n, x, y in names]
    places.append(Place("e2", 20.0, 5.0, "corridor-end"))
    route = [
        *("a1", "b1", "c1", "d1", "d2", "c2", "b2", "a2", "a3", "b3", "c3", "d3"),
        *("d2", "d1", "c1", "c2", "c3", "b3", "b2", "b1", "a1", "a2", "b2", "c2"),
        *("d2", "e2", "d2", "d3", "c3", "c2", "b2", "b3", "a3", "a2"),
    ]
    return build_world(
        "multi-loop",
        "4 x 3 grid of corridors 5 m apart (six loops) and a dead end; several loops (thesis Fig. 39-40)",
        places,
        corridors,
        route=route,
        default_visits=33,
    )


def t_junction() -> World:
    """A tiny T of three 5 m corridors ending in dead ends, for fast tests."""
    places = [
        Place("w", 0.0, 0.0, "corridor-end"),
        Place("j", 5.0, 0.0, "junction"),
        Place("e", 10.0, 0.0, "corridor-end"),
        Place("s", 5.0, -5.0, "corridor-end"),
    ]
    corridors = [("w", "j", 0), ("j", "e", 1), ("j", "s", 2)]
    return build_world(
        "t-junction",
        "a tiny T of three 5 m corridors",
        places,
        corridors,
        route=["w", "j", "s", "j", "e", "j"],
        default_visits=3,
    )


def twin_junctions() -> World:
    """Two identical T-junctions 5 m apart on one corridor, the second reached around a 25 x 20 m loop.

    The route enters the first junction ``j1`` heading east (a branch on its left, the corridor on
    ahead), drives the loop through the corners ``c-e``, ``c-ne``, ``c-nw`` and reaches the second
    junction ``j2`` heading south, with the same branch on its left: a dead end ``end-p`` 5 m east, driven
    to and back (a U-turn). It then returns south to ``j1``. The laser sees the same walls at both
    junctions; the camera sees one difference: the corridor west of ``j1`` (to the dead end ``end-w``,
    never reached in the default 8 visits) and ``j1``'s wall across from the branch carry a texture of
    their own, every other wall shares one.
    """
    places = [
        Place("end-w", 0.0, 0.0, "corridor-end"),
        Place("j1", 5.0, 0.0, "junction"),
        Place("c-e", 30.0, 0.0, "corner"),
        Place("c-ne", 30.0, 20.0, "corner"),
        Place("c-nw", 5.0, 20.0, "corner"),
        Place("j2", 5.0, 5.0, "junction"),
        Place("end-p", 10.0, 5.0, "corridor-end"),
    ]
    corridors = [  # listed first, the west corridor's texture also takes j1's wall across from j2
        ("end-w", "j1", 1),
        ("j1", "c-e", 0),
        ("c-e", "c-ne", 0),
        ("c-ne", "c-nw", 0),
        ("c-nw", "j2", 0),
        ("j2", "j1", 0),
        ("j2", "end-p", 0),
    ]
    return build_world(
        "twin-junctions",
        "two identical T-junctions 5 m apart on one corridor, the second reached from the first around a "
        "25 x 20 m loop of identical corridors; the robot then returns to the first",
        places,
        corridors,
        route=["j1", "c-e", "c-ne", "c-nw", "j2", "end-p", "j2", "j1", "end-w"],
        default_visits=8,
    )


def ring_world(
    name: str,
    description: str,
    *,
    side: float,
    doors_per_side: int,
    corridor_texture: Callable[[int], int],
    room_texture: Callable[[int, int], int],
    default_visits: int,
) -> World:
    """A square ring of corridors (corner at the origin, ``side`` m) with ``doors_per_side`` evenly spaced
    doors per side, each a 1 m door opening to a room outside the ring (5 m deep, 6 m wide for one door
    per side, 5 m wide otherwise); the sides are numbered 0..3 counter-clockwise from the south one.

    ``corridor_texture(k)`` is the texture of side ``k``, ``room_texture(k, d)`` that of door ``d``'s door
    opening and room on side ``k``; the route drives the ring counter-clockwise. With one door on a 12 m
    side and every texture 0 this is ``aliased-loop``'s geometry.
    """
    step = side / (doors_per_side + 1)
    width = 6.0 if doors_per_side == 1 else 5.0
    c = side / 2.0
    corners = [(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)]
    directions = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)]
    corner_names = ["c-sw", "c-se", "c-ne", "c-nw"]
    side_names = "senw"
    places: list[Place] = []
    corridors: list[tuple[str, str, int]] = []
    rooms: list[Rect] = []
    for k in range(4):
        (x0, y0), (dx, dy) = corners[k], directions[k]
        ids = [corner_names[k]]
        places.append(Place(corner_names[k], x0, y0, "corner"))
        for d in range(doors_per_side):
            s = step * (d + 1)
            pid = f"d-{side_names[k]}" if doors_per_side == 1 else f"d-{side_names[k]}{d + 1}"
            places.append(Place(pid, x0 + s * dx, y0 + s * dy, "doorway"))
            ids.append(pid)
            # The door and room of the south side at x = s, rotated onto side k about the centre.
            tex = room_texture(k, d)
            door = Rect(s - 0.5, -2.0, s + 0.5, -1.0, tex)
            room = Rect(s - width / 2.0, -7.0, s + width / 2.0, -2.0, tex)
            rooms += [_rotate_rect(door, c, c, k), _rotate_rect(room, c, c, k)]
        nxt = corner_names[(k + 1) % 4]
        corridors += [(a, b, corridor_texture(k)) for a, b in zip(ids, [*ids[1:], nxt], strict=True)]
    return build_world(
        name,
        description,
        places,
        corridors,
        route=[p.id for p in places],
        default_visits=default_visits,
        rooms=rooms,
    )


def distinct_loop() -> World:
    """``aliased-loop``'s geometry with a texture of its own per side and per room (the control)."""
    return ring_world(
        "distinct-loop",
        "aliased-loop's 12 m square with distinct textures per side and per room: geometry aliases only",
        side=12.0,
        doors_per_side=1,
        corridor_texture=lambda k: 10 + k,
        room_texture=lambda k, d: 20 + k,
        default_visits=10,
    )


def aliased_ring() -> World:
    """An 18 m square ring of identical sides, two identical doors and rooms per side (12 places)."""
    return ring_world(
        "aliased-ring",
        "18 m square ring of identical corridors with two doors to identical rooms per side",
        side=18.0,
        doors_per_side=2,
        corridor_texture=lambda k: 0,
        room_texture=lambda k, d: 1,
        default_visits=14,
    )


def distinct_ring() -> World:
    """``aliased-ring``'s geometry with a texture of its own per side and per door and room."""
    return ring_world(
        "distinct-ring",
        "aliased-ring's 18 m square with distinct textures per side and per room: geometry aliases only",
        side=18.0,
        doors_per_side=2,
        corridor_texture=lambda k: 10 + k,
        room_texture=lambda k, d: 20 + 2 * k + d,
        default_visits=14,
    )


def _twin_rooms(name: str, description: str, textures: Sequence[int]) -> World:
    """The ``twin-rooms`` geometry with ``textures`` = (west, middle and east corridor, stub a, room a,
    stub b, room b)."""
    west, middle, east, stub_a, room_a, stub_b, room_b = textures
    places = [
        Place("end-w", 0.0, 0.0, "corridor-end"),
        Place("door-a", 5.0, 0.0, "junction"),
        Place("room-a", 5.0, 5.0, "room-entrance"),
        Place("door-b", 15.0, 0.0, "junction"),
        Place("room-b", 15.0, -5.0, "room-entrance"),
        Place("end-e", 20.0, 0.0, "corridor-end"),
    ]
    corridors = [
        ("end-w", "door-a", west),
        ("door-a", "door-b", middle),
        ("door-b", "end-e", east),
        ("door-a", "room-a", stub_a),
        ("door-b", "room-b", stub_b),
    ]
    # 6 x 6 m rooms whose place lies 1 m past the door, where a laser detector fires on entering; room b
    # is room a turned by a half turn about (10, 0).
    rooms = [Rect(2.0, 4.0, 8.0, 10.0, room_a), Rect(12.0, -10.0, 18.0, -4.0, room_b)]
    route = [
        *("end-w", "door-a", "room-a", "door-a", "door-b", "room-b", "door-b", "end-e"),
        *("door-b", "door-a"),
    ]
    return build_world(name, description, places, corridors, route=route, default_visits=13, rooms=rooms)


def twin_rooms() -> World:
    """Two identical rooms off a 20 m corridor, symmetric under a half turn: rooms, doors and ends alias."""
    return _twin_rooms(
        "twin-rooms",
        "two identical rooms off a 20 m corridor (north-west, south-east), symmetric under a half turn; "
        "both rooms entered with U-turns, U-turns at both ends, the first room re-entered",
        (1, 1, 1, 2, 3, 2, 3),
    )


def twin_rooms_distinct() -> World:
    """``twin-rooms``' geometry with distinct textures (the control)."""
    return _twin_rooms(
        "twin-rooms-distinct",
        "twin-rooms' geometry with a texture of its own per corridor and room: geometry aliases only",
        (1, 4, 7, 2, 3, 5, 6),
    )


def _room_row(name: str, description: str, textures: Sequence[tuple[int, int]], corridor: int) -> World:
    """The ``room-row`` geometry: ``textures`` = (stub, room) texture per room, ``corridor`` the main one."""
    doors = (6.0, 13.0, 20.0)
    places = [Place("end-w", 0.0, 0.0, "corridor-end")]
    corridors: list[tuple[str, str, int]] = []
    rooms: list[Rect] = []
    prev = "end-w"
    for k, x in enumerate(doors, start=1):
        places += [Place(f"d{k}", x, 0.0, "junction"), Place(f"r{k}", x, 5.0, "room-entrance")]
        stub, room = textures[k - 1]
        corridors += [(prev, f"d{k}", corridor), (f"d{k}", f"r{k}", stub)]
        # 6 x 6 m, the place 1 m past the door, 1 m of wall between rooms.
        rooms.append(Rect(x - 3.0, 4.0, x + 3.0, 10.0, room))
        prev = f"d{k}"
    places.append(Place("end-e", 26.0, 0.0, "corridor-end"))
    corridors.append((prev, "end-e", corridor))
    route = [
        *("end-w", "d1", "r1", "d1", "d2", "r2", "d2", "d3", "r3", "d3"),
        *("end-e", "d3", "d2", "d1"),
    ]
    return build_world(name, description, places, corridors, route=route, default_visits=17, rooms=rooms)


def room_row() -> World:
    """A 26 m corridor lined with three identical rooms on its north side."""
    return _room_row(
        "room-row",
        "a 26 m corridor lined with three identical 6 x 6 m rooms, each entered with a U-turn; "
        "the corridor driven back and the first room re-entered",
        [(2, 3)] * 3,
        1,
    )


def room_row_distinct() -> World:
    """``room-row``'s geometry with a texture of its own per room (the control)."""
    return _room_row(
        "room-row-distinct",
        "room-row's geometry with a texture of its own per room and door: geometry aliases only",
        [(2, 3), (4, 5), (6, 7)],
        1,
    )


#: The named worlds, built on demand by :func:`get_world`.
WORLDS: Mapping[str, Callable[[], World]] = {
    "aliased-loop": aliased_loop,
    "two-loop": two_loop,
    "multi-loop": multi_loop,
    "t-junction": t_junction,
    "twin-junctions": twin_junctions,
    "distinct-loop": distinct_loop,
    "aliased-ring": aliased_ring,
    "distinct-ring": distinct_ring,
    "twin-rooms": twin_rooms,
    "twin-rooms-distinct": twin_rooms_distinct,
    "room-row": room_row,
    "room-row-distinct": room_row_distinct,
}

#: Calibration families (issue #23): family -> (aliased world, control world of the same geometry).
CALIBRATION_FAMILIES: Mapping[str, tuple[str, str]] = {
    "loop": ("aliased-loop", "distinct-loop"),
    "ring": ("aliased-ring", "distinct-ring"),
    "twin-rooms": ("twin-rooms", "twin-rooms-distinct"),
    "room-row": ("room-row", "room-row-distinct"),
}


def get_world(name: str) -> World:
    """The world called ``name`` (ConfigError listing the known names otherwise)."""
    try:
        factory = WORLDS[name]
    except KeyError as err:
        msg = f"unknown world {name!r}; known worlds: {', '.join(sorted(WORLDS))}"
        raise ConfigError(msg) from err
    return factory()
