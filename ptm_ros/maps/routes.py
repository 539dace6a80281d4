"""A PTM's ensemble as a nav2 route server graph (GeoJSON), its edges kept off the walls of the run's map.

Format (nav2 ``nav2_route`` README, "File Formats", https://github.com/ros-navigation/navigation2/tree/main/nav2_route,
read by ``GeoJsonGraphFileLoader``, docs: https://docs.nav2.org/configuration/packages/configuring-route-server.html):
a GeoJSON ``FeatureCollection`` whose ``features`` are nodes (``geometry.type = "Point"``,
``coordinates [x, y]``, ``properties.id`` and the recommended ``properties.frame``) and edges
(``geometry.type = "MultiLineString"``, ``properties.id``, ``startid``, ``endid``); ids are unsigned
integers unique over nodes *and* edges; any application data goes under ``properties.metadata``. Edges
are directional ("All edges are directional"), so every connection is written once per direction. The
loader rejects a file without nodes or without edges, so a MAP topology with a single place gives a
graph nav2 cannot load. The loader reads an edge's ``startid`` and ``endid`` only, never its geometry: a
route runs straight from node to node, so a detour must be made of nodes. As nav2's own saver, the
collection carries ``"name": "graph"`` and its ``crs`` member; a foreign ``metadata`` member describes how
the graph was made.

Nodes are the places of the MAP (most probable) topology, at ``Topology.positions`` when present, else
at the mean odometry position of their visits; given the trajectory a map was drawn along, at their
medoid visit on it, so that they lie in the map's frame, off its walls (:func:`node_positions`). Edge
probabilities are the thesis' ensemble rule (Ch. 0.3.1: "the transition probabilities of edges are the
sum of the probabilities of the topologies in the PTM containing that edge"), made meaningful across
topologies whose place labels differ by naming places through visits: with ``r_a`` the first visit of
MAP place ``a`` and ``T(k)`` the place of visit ``k`` in topology ``T``,

.. math::
    P(a \\leftrightarrow b) = \\frac{1}{S} \\sum_{T} p_T \\,
        \\mathbb{1}\\bigl[T(r_a) \\ne T(r_b) \\wedge
        \\exists k:\\ \\{T(k), T(k+1)\\} = \\{T(r_a), T(r_b)\\}\\bigr],
    \\qquad S = \\sum_T p_T,

the mass of the topologies in which the robot travelled directly between the place of ``r_a`` and the
place of ``r_b``. Every pair with ``P > 0`` is exported, also when only non-MAP topologies hold it. ``S``
normalises when the listed topologies hold less than all the mass (recorded in the metadata). Each
directed edge ``a → b`` carries ``metadata: {probability, length, traversals}``: the undirected
probability above, the Euclidean length between its two nodes (m), and the posterior expected number of
direct passages from the place of ``r_a`` to the place of ``r_b`` (same normalisation).

Walls (issue #24). Given the run's occupancy map (:class:`~ptm_ros.maps.map_quality.ClassGrid`, the trinary
classes of ``map.pgm``), a connection whose straight segment meets an occupied cell (a cell whose
interior the segment crosses, :func:`ptm_ros.maps.occupancy.grid_traversal`) is rerouted (:func:`plan_route`)
over the *passable* cells: on the map, not occupied, centre within ``corridor`` of the segment. The
cheapest 8-connected path of passable cells (no corner cut between two cells that are not both
passable), a metre through a free cell costing 1 and through an unknown one ``unknown_cost``, is
shortened by string pulling: from each kept vertex to the farthest later one whose segment meets only
passable cells. The inner vertices become *waypoint* nodes (``metadata: {waypoint: true, places: [a,
b], index: j}``), joined in both directions by *hop* edges that carry the connection's probability and
traversals, their own length and ``places`` (the connection's direction). A connection that cannot be
rerouted (a place in an occupied cell or off the map, no path within the corridor, more than
``max_waypoints`` waypoints) is dropped and listed in the collection's ``metadata.dropped_edges`` with
its reason. Without a map the edges are the straight segments, walls unchecked. Either way no written
segment meets an occupied cell of the map it was checked against (:func:`crossing_segments` counts them).

Ids depend only on the place indices, the number ``M`` of MAP places and ``max_waypoints`` ``K``, never on
which other connections exist, so a route server can reload a graph rewritten from a grown ensemble:
place ``a`` is node ``a``; the pair ``a < b`` has index ``q = b (b - 1) / 2 + a`` (:func:`pair_index`);
its straight edges are ``a → b = M + 2q`` and ``b → a = M + 2q + 1``; a rerouted pair owns the block
``B = M² + q (3K + 2)``: waypoint ``j`` (counted from ``a``) is node ``B + j``, the hop from vertex ``i`` to
``i + 1`` (vertex 0 = ``a``) is edge ``B + K + 2i`` and its reverse ``B + K + 2i + 1``.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import dijkstra

from ptm_ros.errors import DataError
from ptm_ros.maps.map_quality import ClassGrid
from ptm_ros.maps.occupancy import FREE, OCCUPIED, UNKNOWN, grid_traversal
from ptm_ros.model.geometry import FloatArray, interpolate_poses
from ptm_ros.model.partitions import num_places
from ptm_ros.model.ptm import Ptm, Topology
from ptm_ros.settings import Settings, setting

IntArray = NDArray[np.int64]

SCHEMA = "ptm_ros.route_graph/2"
_MASS_TOL = 1e-9  # listed masses this close to 1 are taken as the whole posterior
#: Coordinate reference member written by nav2's ``GeoJsonGraphFileSaver`` (ignored by its loader).
NAV2_CRS = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::3857"}}
MAX_ID = 2**32 - 1  # nav2 reads ids as unsigned int
#: Why a connection was dropped (``metadata.dropped_edges[].reason``).
PLACE_IN_WALL = "a place lies in an occupied cell"
PLACE_OFF_MAP = "a place lies off the map"
NO_ROUTE = "no path around the walls within the corridor"
TOO_WINDING = "the path needs more than max_waypoints waypoints"
SIGHT_CHUNK = 64  # later vertices string pulling tests at once
# 8-connected steps (row, column) taken once each: right, up and the two upward diagonals.
_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))


@dataclass(frozen=True)
class RouteConfig(Settings):
    """How the route graph's edges keep off the walls of the run's map (module docstring; lengths in m)."""

    corridor: float = setting(
        6.0, gt=0, doc="a rerouted edge keeps within this distance [m] of its straight segment."
    )
    unknown_cost: float = setting(
        4.0,
        ge=1,
        doc=(
            "cost of a metre through an unknown cell (never observed, or between the map's thresholds) "
            "relative to a free one: detours keep to space the scans saw free."
        ),
    )
    max_waypoints: int = setting(
        16,
        ge=1,
        doc=(
            "most waypoints of one rerouted connection; it sizes the block of ids each pair owns, so "
            "changing it renumbers the waypoints and hops."
        ),
    )


@dataclass(frozen=True)
class Route:
    """How a connection runs: ``points (P, 2)`` from its first place to its second (``P = 2``: the
    straight segment), or None and the ``reason`` it is dropped."""

    points: FloatArray | None
    reason: str | None = None

    @property
    def rerouted(self) -> bool:
        return self.points is not None and len(self.points) > 2


def place_means(labels: Sequence[int], xy: ArrayLike) -> FloatArray:
    """``(M, 2)`` mean of the visit positions ``xy (N, 2)`` of each place of the labels ``(N,)``."""
    lab = np.asarray(labels, dtype=np.intp)
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(pts) != len(lab):
        msg = f"{len(lab)} labels for {len(pts)} landmarks"
        raise DataError(msg)
    m = num_places(tuple(int(v) for v in lab))
    counts = np.bincount(lab, minlength=m).astype(float)
    return np.stack([np.bincount(lab, pts[:, c], minlength=m) / counts for c in (0, 1)], axis=1)


def place_medoids(labels: Sequence[int], xy: ArrayLike) -> FloatArray:
    """``(M, 2)``: for each place of the labels ``(N,)``, the position among its visits' ``xy (N, 2)``
    with the least summed distance to the others (the first such visit on ties)."""
    lab = np.asarray(labels, dtype=np.intp)
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(pts) != len(lab):
        msg = f"{len(lab)} labels for {len(pts)} landmarks"
        raise DataError(msg)
    out = np.empty((num_places(tuple(int(v) for v in lab)), 2))
    for a in range(len(out)):
        own = pts[lab == a]
        out[a] = own[np.argmin(np.linalg.norm(own[:, None] - own[None], axis=2).sum(axis=1))]
    return out


def node_positions(ptm: Ptm, trajectory: tuple[ArrayLike, ArrayLike] | None = None) -> FloatArray:
    """``(M, 2)`` positions of the MAP topology's places. With ``trajectory`` = ``(stamps (T,), poses
    (T, 3))``, the path a map was drawn along, each place's medoid visit on it (:func:`place_medoids` of
    :func:`ptm_ros.model.geometry.interpolate_poses` at the visits' stamps): in the map's frame, and a spot
    the robot stood on, so off the walls even where the smoothing left a place's visits apart; else the
    topology's ``positions`` if given, else the mean odometry position of each place's visits."""
    top = ptm.map_topology
    m = num_places(top.labels)
    if trajectory is not None:
        stamps = [lm.stamp for lm in ptm.landmarks]
        try:
            xy = interpolate_poses(trajectory[0], trajectory[1], stamps)[:, :2]
        except ValueError as err:
            msg = f"cannot place the visits on the trajectory: {err}"
            raise DataError(msg) from err
        pos = place_medoids(top.labels, xy)
    elif top.positions is not None:
        if len(top.positions) != m:
            msg = f"the MAP topology has {m} places but {len(top.positions)} positions"
            raise DataError(msg)
        pos = np.asarray(top.positions, dtype=float).reshape(m, 2)
    else:
        pos = place_means(top.labels, [lm.map_pose[:2] for lm in ptm.landmarks])
    if not np.all(np.isfinite(pos)):
        msg = "place positions must be finite"
        raise DataError(msg)
    return pos


def first_visits(labels: tuple[int, ...]) -> list[int]:
    """Index of the first visit of each place of a canonical label sequence (``r_a`` for place ``a``)."""
    first: dict[int, int] = {}
    for k, lab in enumerate(labels):
        first.setdefault(lab, k)
    return [first[a] for a in range(len(first))]


def edge_statistics(ptm: Ptm) -> tuple[dict[tuple[int, int], float], dict[tuple[int, int], float], float]:
    """Unnormalised ensemble sums over the listed topologies, keyed by MAP places.

    Returns ``(mass, passages, S)``: ``mass[(a, b)]`` (``a < b``) is the summed probability of the
    topologies with a direct passage between the places of ``r_a`` and ``r_b``; ``passages[(a, b)]``
    (ordered) the probability-weighted count of passages from the place of ``r_a`` to that of ``r_b``;
    ``S`` the listed mass.
    """
    roots = first_visits(ptm.map_topology.labels)
    n = len(ptm.map_topology.labels)
    mass: dict[tuple[int, int], float] = defaultdict(float)
    passages: dict[tuple[int, int], float] = defaultdict(float)
    listed = 0.0
    for top in ptm.topologies:
        if len(top.labels) != n:
            msg = f"a topology has {len(top.labels)} labels, the MAP topology {n}"
            raise DataError(msg)
        p = float(top.probability)
        listed += p
        # MAP places named by their first visit's place in this topology.
        named: dict[int, list[int]] = defaultdict(list)
        for a, r in enumerate(roots):
            named[top.labels[r]].append(a)
        moves: dict[tuple[int, int], int] = defaultdict(int)
        for u, v in zip(top.labels[:-1], top.labels[1:], strict=True):
            if u != v:
                moves[(u, v)] += 1
        linked: set[tuple[int, int]] = set()
        for (u, v), count in moves.items():
            for a in named.get(u, ()):
                for b in named.get(v, ()):
                    passages[(a, b)] += p * count
                    linked.add((min(a, b), max(a, b)))
        for pair in linked:
            mass[pair] += p
    return dict(mass), dict(passages), listed


# ------------------------------------------------------------------------------------------ ids


def pair_index(a: int, b: int) -> int:
    """Index ``b (b - 1) / 2 + a`` of the place pair ``a < b`` in the order (0, 1), (0, 2), (1, 2), (0, 3), …,
    whatever the number of places."""
    if not 0 <= a < b:
        msg = f"a place pair needs 0 <= a < b, got ({a}, {b})"
        raise DataError(msg)
    return b * (b - 1) // 2 + a


def straight_edge_ids(m: int, a: int, b: int) -> tuple[int, int]:
    """Ids of the straight edges ``a → b`` and ``b → a`` of a graph with ``m`` place nodes (``a < b``)."""
    q = pair_index(a, b)
    return m + 2 * q, m + 2 * q + 1


def route_block(m: int, a: int, b: int, max_waypoints: int) -> int:
    """First id of the block of the rerouted pair ``a < b``: its waypoints from there, then its hops."""
    return m * m + pair_index(a, b) * (3 * max_waypoints + 2)


# ------------------------------------------------------------------------------------------ walls


def _cells(grid: ClassGrid, points: ArrayLike) -> FloatArray:
    """World points in grid cell units (cell ``(i, j)`` = ``[i, i+1) × [j, j+1)``, column first)."""
    return (np.asarray(points, dtype=float) - np.asarray(grid.origin[:2])) / grid.resolution


def _class_at(
    classes: NDArray[np.int8], ix: IntArray, iy: IntArray, lo: tuple[int, int] = (0, 0)
) -> NDArray[np.int8]:
    """Classes of the cells ``(ix, iy)`` of a window whose cell (0, 0) is ``lo``; unknown outside it."""
    c, r = ix - lo[0], iy - lo[1]
    inside = (c >= 0) & (c < classes.shape[1]) & (r >= 0) & (r < classes.shape[0])
    out = np.full(len(c), UNKNOWN, dtype=np.int8)
    out[inside] = classes[r[inside], c[inside]]
    return out


def occupied_crossings(grid: ClassGrid, starts: ArrayLike, ends: ArrayLike) -> IntArray:
    """Number of occupied cells each segment ``starts → ends`` (world ``(B, 2)`` or ``(2,)``, broadcast)
    meets (:func:`ptm_ros.maps.occupancy.grid_traversal`); cells off the grid are unknown, not occupied."""
    s, e = np.broadcast_arrays(_cells(grid, starts).reshape(-1, 2), _cells(grid, ends).reshape(-1, 2))
    ix, iy, ray = grid_traversal(s, e)
    hit = _class_at(np.asarray(grid.classes), ix, iy) == OCCUPIED
    return np.bincount(ray[hit], minlength=len(s)).astype(np.int64)


def crossing_segments(doc: dict[str, Any], grid: ClassGrid) -> int:
    """Number of the written edge segments of a route graph document that meet an occupied cell of
    ``grid`` (every line of every edge's ``MultiLineString``, point to point)."""
    starts, ends = [], []
    for f in doc["features"]:
        if f["geometry"]["type"] != "MultiLineString":
            continue
        for line in f["geometry"]["coordinates"]:
            xy = np.asarray(line, dtype=float).reshape(-1, 2)
            starts.append(xy[:-1])
            ends.append(xy[1:])
    if not starts:
        return 0
    return int(np.count_nonzero(occupied_crossings(grid, np.concatenate(starts), np.concatenate(ends))))


def _segment_distance(x: FloatArray, y: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """``(H, W)`` distances of the points ``(x[j], y[i])`` to the segment ``a b``."""
    ab = b - a
    l2 = float(ab @ ab)
    dx, dy = x[None, :] - a[0], y[:, None] - a[1]
    t = np.clip((dx * ab[0] + dy * ab[1]) / l2, 0.0, 1.0) if l2 > 0 else np.zeros(1)
    return np.asarray(np.hypot(dx - t * ab[0], dy - t * ab[1]), dtype=float)


def cell_graph(passable: NDArray[np.bool_], cost: FloatArray, resolution: float) -> csr_matrix:
    """Undirected 8-connected graph of the ``passable`` cells of an ``(H, W)`` window, numbered row-major
    among them: a step's weight is its length (m) times the mean ``cost`` of its two cells; a diagonal
    step only where both cells beside it are passable (no corner cut)."""
    h, w = passable.shape
    index = np.full((h, w), -1, dtype=np.int64)
    n = int(np.count_nonzero(passable))
    index[passable] = np.arange(n)
    rows, cols, weights = [], [], []
    for dr, dc in _STEPS:
        c0, c1 = max(0, -dc), w - max(0, dc)
        u = (slice(0, h - dr), slice(c0, c1))
        v = (slice(dr, h), slice(c0 + dc, c1 + dc))
        ok = passable[u] & passable[v]
        if dr and dc:
            ok &= passable[dr:h, c0:c1] & passable[0 : h - dr, c0 + dc : c1 + dc]
        rows.append(index[u][ok])
        cols.append(index[v][ok])
        weights.append(math.hypot(dr, dc) * resolution * 0.5 * (cost[u][ok] + cost[v][ok]))
    data = (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols)))
    return coo_matrix(data, shape=(n, n)).tocsr()


def shortcut(points: FloatArray, open_cells: NDArray[np.bool_], lo: tuple[int, int]) -> FloatArray:
    """String pulling of a polyline ``(P, 2)`` in grid cell units: from each kept vertex to the farthest
    later vertex whose segment meets only ``open_cells`` (a window whose cell (0, 0) is ``lo``; outside
    it nothing is open); a vertex that sees no later one keeps the next. Later vertices are tried
    :data:`SIGHT_CHUNK` at a time from the far end (memory bounded on long paths)."""
    opened = open_cells.astype(np.int8)
    keep, i, n = [0], 0, len(points)
    while i < n - 1:
        nxt = i + 1
        for top in range(n, i + 1, -SIGHT_CHUNK):
            later = np.arange(max(i + 1, top - SIGHT_CHUNK), top)
            ix, iy, ray = grid_traversal(points[i], points[later])
            shut = np.bincount(ray[_class_at(opened, ix, iy, lo) != 1], minlength=len(later))
            seen = later[shut == 0]
            if len(seen):
                nxt = int(seen[-1])
                break
        i = nxt
        keep.append(i)
    return points[keep]


def plan_route(grid: ClassGrid, start: ArrayLike, end: ArrayLike, config: RouteConfig | None = None) -> Route:
    """The way between two places (world ``(2,)``) that meets no occupied cell of ``grid``: the straight
    segment when it meets none, else the path of the module docstring over the map's cells (not beyond
    its edge); a dropped :class:`Route` when the start or end cell is occupied or off the map, no path
    lies within ``config.corridor`` of the segment, or it needs more than ``config.max_waypoints``
    waypoints."""
    cfg = config if config is not None else RouteConfig()
    p0, p1 = np.asarray(start, dtype=float).reshape(2), np.asarray(end, dtype=float).reshape(2)
    if occupied_crossings(grid, p0, p1)[0] == 0:
        return Route(np.array([p0, p1]))
    g0, g1 = _cells(grid, p0), _cells(grid, p1)
    s_cell, t_cell = np.floor(g0).astype(np.int64), np.floor(g1).astype(np.int64)
    classes = np.asarray(grid.classes)
    h, w = classes.shape
    if not all(0 <= c[0] < w and 0 <= c[1] < h for c in (s_cell, t_cell)):
        return Route(None, PLACE_OFF_MAP)
    if OCCUPIED in (classes[s_cell[1], s_cell[0]], classes[t_cell[1], t_cell[0]]):
        return Route(None, PLACE_IN_WALL)
    # the window: the corridor's bounding box on the map
    reach = cfg.corridor / grid.resolution
    c0, r0 = np.maximum(np.floor(np.minimum(g0, g1) - reach).astype(np.int64), 0)
    c1, r1 = np.minimum(np.floor(np.maximum(g0, g1) + reach).astype(np.int64), (w - 1, h - 1))
    cls = classes[r0 : r1 + 1, c0 : c1 + 1]
    near = _segment_distance(np.arange(c0, c1 + 1) + 0.5, np.arange(r0, r1 + 1) + 0.5, g0, g1) <= reach
    passable = near & (cls != OCCUPIED)
    ends = [int((c[1] - r0) * cls.shape[1] + c[0] - c0) for c in (s_cell, t_cell)]  # flat in the window
    passable.reshape(-1)[ends] = True  # on the map and not occupied: in the corridor however narrow
    s, t = (int(np.count_nonzero(passable.reshape(-1)[:k])) for k in ends)  # their numbers in cell_graph
    cost = np.where(cls == FREE, 1.0, cfg.unknown_cost)
    dist, pred = dijkstra(
        cell_graph(passable, cost, grid.resolution), directed=False, indices=s, return_predecessors=True
    )
    if not np.isfinite(dist[t]):
        return Route(None, NO_ROUTE)
    chain = [t]
    while chain[-1] != s:
        chain.append(int(pred[chain[-1]]))
    row, col = np.divmod(np.flatnonzero(passable.reshape(-1))[chain[::-1]], cls.shape[1])
    path = np.column_stack([col + c0 + 0.5, row + r0 + 0.5])  # cell centres, grid cell units
    # consecutive vertices see each other: a step's segment stays in its cells and, diagonally, the two
    # passable cells beside it (the end points lie in their cells)
    pulled = shortcut(np.vstack([g0, path[1:-1], g1]), passable, (int(c0), int(r0)))
    if len(pulled) - 2 > cfg.max_waypoints:
        return Route(None, TOO_WINDING)
    world = np.asarray(grid.origin[:2]) + pulled * grid.resolution
    world[0], world[-1] = p0, p1
    if np.any(occupied_crossings(grid, world[:-1], world[1:])):
        return Route(None, NO_ROUTE)  # not expected: every pulled segment meets passable cells only
    return Route(world)


# ------------------------------------------------------------------------------------------ GeoJSON


def _node_feature(node_id: int, xy: ArrayLike, frame_id: str, metadata: dict[str, Any]) -> dict[str, Any]:
    x, y = np.asarray(xy, dtype=float).reshape(2)
    return {
        "type": "Feature",
        "properties": {"id": node_id, "frame": frame_id, "metadata": metadata},
        "geometry": {"type": "Point", "coordinates": [float(x), float(y)]},
    }


def _place_metadata(place: int, top: Topology, root: int) -> dict[str, Any]:
    visits = [k for k, lab in enumerate(top.labels) if lab == place]
    return {"place": place, "first_visit": root, "visits": visits}


def _edge_feature(
    edge_id: int, ends: tuple[int, int], line: FloatArray, metadata: dict[str, Any]
) -> dict[str, Any]:
    (x0, y0), (x1, y1) = np.asarray(line, dtype=float)
    return {
        "type": "Feature",
        "properties": {"id": edge_id, "startid": ends[0], "endid": ends[1], "metadata": metadata},
        "geometry": {
            "type": "MultiLineString",
            "coordinates": [[[float(x0), float(y0)], [float(x1), float(y1)]]],
        },
    }


def _connection_features(
    pair: tuple[int, int],
    route: FloatArray,
    stats: tuple[float, float, float],
    *,
    m: int,
    frame: str,
    max_waypoints: int,
) -> list[dict[str, Any]]:
    """Features of one kept connection ``a < b`` along ``route (P, 2)`` (module docstring): the straight
    edges, or the waypoints and hops of a detour. ``stats``: probability, traversals ``a → b``, ``b → a``."""
    a, b = pair
    prob, forward, backward = stats
    if len(route) == 2:
        length = float(np.hypot(*(route[1] - route[0])))
        ab, ba = straight_edge_ids(m, a, b)
        return [
            _edge_feature(ab, (a, b), route, {"probability": prob, "length": length, "traversals": forward}),
            _edge_feature(
                ba, (b, a), route[::-1], {"probability": prob, "length": length, "traversals": backward}
            ),
        ]
    block = route_block(m, a, b, max_waypoints)
    inner = len(route) - 2
    ids = [a, *range(block, block + inner), b]
    feats = [
        _node_feature(ids[j + 1], route[j + 1], frame, {"waypoint": True, "places": [a, b], "index": j})
        for j in range(inner)
    ]
    for i in range(len(route) - 1):
        seg = route[i : i + 2]
        length = float(np.hypot(*(seg[1] - seg[0])))
        hop = block + max_waypoints + 2 * i
        for eid, ends, line, places, count in (
            (hop, (ids[i], ids[i + 1]), seg, [a, b], forward),
            (hop + 1, (ids[i + 1], ids[i]), seg[::-1], [b, a], backward),
        ):
            meta = {"probability": prob, "length": length, "traversals": count, "places": places}
            feats.append(_edge_feature(eid, ends, line, meta))
    return feats


def route_graph(
    ptm: Ptm,
    *,
    frame_id: str | None = None,
    grid: ClassGrid | None = None,
    trajectory: tuple[ArrayLike, ArrayLike] | None = None,
    config: RouteConfig | None = None,
) -> dict[str, Any]:
    """The nav2 route graph GeoJSON document of ``ptm`` (see the module docstring for the edges, the walls
    and the ids).

    ``grid``: the run's occupancy map; each connection whose straight segment meets its walls is
    rerouted or dropped (:func:`plan_route` with ``config``). Without it the edges are straight, walls
    unchecked. ``trajectory``: ``(stamps, poses)`` of the path the map was drawn along; the nodes are
    then the places' medoid visits on it, in the map's frame (:func:`node_positions`), rather than the
    topology's place positions, which the inference estimated from the visits' odometry and which may lie
    metres off the map's corridors after a smoothing that moved the path. ``frame_id`` defaults to the
    PTM's frame.
    """
    cfg = config if config is not None else RouteConfig()
    frame = ptm.frame_id if frame_id is None else frame_id
    top = ptm.map_topology
    pos = node_positions(ptm, trajectory)
    roots = first_visits(top.labels)
    mass, passages, listed = edge_statistics(ptm)
    if not (listed > 0.0 and math.isfinite(listed)):
        msg = f"the listed topologies hold no probability mass (sum {listed})"
        raise DataError(msg)
    normalised = listed < 1.0 - _MASS_TOL
    scale = 1.0 / listed if normalised else 1.0
    m = len(pos)
    if m * m + m * (m - 1) // 2 * (3 * cfg.max_waypoints + 2) - 1 > MAX_ID:
        msg = f"{m} places need edge ids beyond nav2's unsigned 32-bit range"
        raise DataError(msg)
    features = [_node_feature(a, pos[a], frame, _place_metadata(a, top, roots[a])) for a in range(m)]
    dropped: list[dict[str, Any]] = []
    rerouted = waypoints = 0
    for a, b in sorted(mass):
        prob = min(1.0, mass[(a, b)] * scale)
        if prob <= 0.0:
            continue
        way = Route(np.array([pos[a], pos[b]])) if grid is None else plan_route(grid, pos[a], pos[b], cfg)
        if way.points is None:
            dropped.append({"places": [a, b], "probability": prob, "reason": way.reason})
            continue
        rerouted += int(way.rerouted)
        waypoints += len(way.points) - 2
        stats = (prob, passages.get((a, b), 0.0) * scale, passages.get((b, a), 0.0) * scale)
        features += _connection_features(
            (a, b), way.points, stats, m=m, frame=frame, max_waypoints=cfg.max_waypoints
        )
    return {
        "type": "FeatureCollection",
        "name": "graph",
        "crs": NAV2_CRS,
        "metadata": {
            "schema": SCHEMA,
            "frame_id": frame,
            "nodes": "places of the MAP topology, and waypoints of the edges rerouted around walls",
            "node_positions": "medoid of the places' visits on the trajectory the map was drawn along"
            if trajectory is not None
            else "the MAP topology's place positions"
            if top.positions is not None
            else "mean odometry position of the places' visits",
            "edge_probability": "posterior mass of the listed topologies in which the robot travelled "
            "directly between the places of the two nodes' first visits",
            "topologies": len(ptm.topologies),
            "map_probability": float(top.probability),
            "listed_mass": listed,
            "normalised_by_listed_mass": normalised,
            "walls": "checked against the run's occupancy map" if grid is not None else "not checked: no map",
            "routing": asdict(cfg),
            "rerouted_edges": rerouted,
            "waypoints": waypoints,
            "dropped_edges": dropped,
        },
        "features": features,
    }


def save_route_graph(doc: dict[str, Any], path: str | Path) -> Path:
    """Write a route graph document as GeoJSON (parent directories created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        text = json.dumps(doc, indent=1, allow_nan=False)
    except (TypeError, ValueError) as err:
        msg = f"route graph is not valid JSON: {err}"
        raise DataError(msg) from err
    path.write_text(text + "\n")
    return path
