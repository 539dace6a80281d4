"""nav2 route graph export of a PTM: hand-computed ensemble edges, brute force, the GeoJSON structure,
edges kept off the walls of a map, stable ids."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ptm_ros.errors import ConfigError, DataError
from ptm_ros.maps.map_quality import ClassGrid
from ptm_ros.maps.occupancy import FREE, OCCUPIED
from ptm_ros.maps.routes import (
    NO_ROUTE,
    PLACE_IN_WALL,
    PLACE_OFF_MAP,
    TOO_WINDING,
    Route,
    RouteConfig,
    crossing_segments,
    occupied_crossings,
    place_medoids,
    plan_route,
    route_block,
    route_graph,
    save_route_graph,
    straight_edge_ids,
)
from ptm_ros.model.partitions import canonical
from ptm_ros.model.ptm import Landmark, Ptm, Topology, make_ptm

POSES = [(0.0, 0.0, 0.0), (4.0, 0.0, 0.1), (4.0, 3.0, 1.0), (4.2, 0.2, 2.0), (0.2, -0.2, 3.0)]
# MAP (0,1,2,1,0); (0,1,1,2,0) puts visit 2 into place 1; (0,0,1,2,1) puts visit 1 into place 0.
ENSEMBLE = [((0, 1, 2, 1, 0), 0.5), ((0, 1, 1, 2, 0), 0.3), ((0, 0, 1, 2, 1), 0.2)]
# Worked by hand from the definition (r_0 = 0, r_1 = 1, r_2 = 2):
#   0-1: T0 yes, T1 yes (places 0,1 adjacent), T2 no (r_0, r_1 share place 0)  -> 0.8
#   1-2: T0 yes, T1 no (r_1, r_2 share place 1), T2 yes (places 0,1 adjacent)  -> 0.7
#   0-2: T0 no, T1 yes (T1 places 0,1), T2 yes (T2 places 0,1)               -> 0.5 (not in the MAP)
PROB = {(0, 1): 0.8, (1, 2): 0.7, (0, 2): 0.5}
# Expected direct passages from the place of r_a to that of r_b:
#   0->1: T0 once, T1 once = 0.8; 1->0: T0 once = 0.5; 1->2: T0 once, T2 (0->1) once = 0.7;
#   2->1: T0 once = 0.5; 0->2: T1 (0->1) once, T2 (0->1) once = 0.5; 2->0: never = 0.
TRAVERSALS = {(0, 1): 0.8, (1, 0): 0.5, (1, 2): 0.7, (2, 1): 0.5, (0, 2): 0.5, (2, 0): 0.0}


def landmarks(poses: list[tuple[float, float, float]]) -> list[Landmark]:
    return [Landmark(k, float(k), p) for k, p in enumerate(poses)]


def nodes_and_edges(doc: dict[str, Any]) -> tuple[dict[int, dict], list[dict]]:
    nodes = {f["properties"]["id"]: f for f in doc["features"] if f["geometry"]["type"] == "Point"}
    edges = [f for f in doc["features"] if f["geometry"]["type"] == "MultiLineString"]
    return nodes, edges


def check_nav2_structure(doc: dict[str, Any]) -> None:
    """The nav2_route GeoJSON conventions (README "File Formats", GeoJsonGraphFileLoader)."""
    assert doc["type"] == "FeatureCollection"
    feats = doc["features"]
    assert all(f["type"] == "Feature" for f in feats)
    assert all(f["geometry"]["type"] in ("Point", "MultiLineString") for f in feats)
    ids = [f["properties"]["id"] for f in feats]
    assert all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in ids)
    assert len(set(ids)) == len(ids), "ids must be unique over nodes and edges"
    nodes, edges = nodes_and_edges(doc)
    assert nodes and edges
    for f in nodes.values():
        xy = f["geometry"]["coordinates"]
        assert len(xy) == 2 and all(math.isfinite(v) for v in xy)
        assert isinstance(f["properties"]["frame"], str)
    pairs = set()
    for e in edges:
        p = e["properties"]
        assert p["startid"] in nodes and p["endid"] in nodes and p["startid"] != p["endid"]
        lines = e["geometry"]["coordinates"]
        assert lines == [
            [nodes[p["startid"]]["geometry"]["coordinates"], nodes[p["endid"]]["geometry"]["coordinates"]]
        ]
        meta = p["metadata"]
        assert 0.0 < meta["probability"] <= 1.0
        assert math.isfinite(meta["length"]) and meta["length"] >= 0.0
        assert meta["traversals"] >= 0.0
        pairs.add((p["startid"], p["endid"]))
    assert len(pairs) == len(edges), "one edge per direction"
    assert all((b, a) in pairs for a, b in pairs), "every connection in both directions"


def test_hand_computed_ensemble(tmp_path: Path) -> None:
    ptm = make_ptm(landmarks(POSES), ENSEMBLE, frame_id="odom")
    assert ptm.map_topology.labels == (0, 1, 2, 1, 0)
    doc = route_graph(ptm, frame_id="map")
    check_nav2_structure(doc)
    nodes, edges = nodes_and_edges(doc)
    assert sorted(nodes) == [0, 1, 2]
    # Positions: mean odometry position of each MAP place's visits.
    xy = {0: (0.1, -0.1), 1: (4.1, 0.1), 2: (4.0, 3.0)}
    for a, f in nodes.items():
        np.testing.assert_allclose(f["geometry"]["coordinates"], xy[a], atol=1e-12)
        assert f["properties"]["frame"] == "map"
    got = {(e["properties"]["startid"], e["properties"]["endid"]): e["properties"]["metadata"] for e in edges}
    assert set(got) == set(TRAVERSALS)
    for (a, b), meta in got.items():
        assert meta["probability"] == pytest.approx(PROB[(min(a, b), max(a, b))], abs=1e-12)
        assert meta["traversals"] == pytest.approx(TRAVERSALS[(a, b)], abs=1e-12)
        assert meta["length"] == pytest.approx(math.dist(xy[a], xy[b]), abs=1e-12)
    assert doc["metadata"]["listed_mass"] == pytest.approx(1.0)
    assert doc["metadata"]["normalised_by_listed_mass"] is False
    assert doc["metadata"]["frame_id"] == "map"
    path = save_route_graph(doc, tmp_path / "out" / "route_graph.geojson")
    assert json.loads(path.read_text()) == doc


def test_truncated_ensemble_is_normalised_and_positions_used() -> None:
    scaled = [(lab, 0.6 * p) for lab, p in ENSEMBLE]  # the listed topologies hold 0.6
    positions = {(0, 1, 2, 1, 0): [(1.0, 2.0), (3.0, 2.0), (3.0, 6.0)]}
    ptm = make_ptm(landmarks(POSES), scaled, positions=positions)
    doc = route_graph(ptm)
    check_nav2_structure(doc)
    assert doc["metadata"]["listed_mass"] == pytest.approx(0.6)
    assert doc["metadata"]["normalised_by_listed_mass"] is True
    assert doc["metadata"]["frame_id"] == "odom"
    nodes, edges = nodes_and_edges(doc)
    assert [nodes[a]["geometry"]["coordinates"] for a in range(3)] == [[1.0, 2.0], [3.0, 2.0], [3.0, 6.0]]
    for e in edges:
        p = e["properties"]
        a, b = p["startid"], p["endid"]
        assert p["metadata"]["probability"] == pytest.approx(PROB[(min(a, b), max(a, b))], abs=1e-12)
        assert p["metadata"]["traversals"] == pytest.approx(TRAVERSALS[(a, b)], abs=1e-12)
    assert {
        (e["properties"]["startid"], e["properties"]["endid"]): e["properties"]["metadata"]["length"]
        for e in edges
    }[(1, 2)] == pytest.approx(4.0)


def brute_force_edges(labels_list: list[tuple[int, ...]], probs: list[float]) -> dict[tuple[int, int], float]:
    """The definition, literally: for each MAP pair and topology, look for a k with the pair of places."""
    map_labels = labels_list[0]
    m = max(map_labels) + 1
    root = [map_labels.index(a) for a in range(m)]
    total = sum(probs)
    out = {}
    for a in range(m):
        for b in range(a + 1, m):
            mass = 0.0
            for lab, p in zip(labels_list, probs, strict=True):
                pa, pb = lab[root[a]], lab[root[b]]
                if pa != pb and any({lab[k], lab[k + 1]} == {pa, pb} for k in range(len(lab) - 1)):
                    mass += p
            if mass > 0:
                out[(a, b)] = mass / total
    return out


def test_random_ensembles_match_the_definition() -> None:
    rng = np.random.default_rng(3)
    for _ in range(25):
        n = int(rng.integers(3, 9))
        tops = {canonical(tuple(int(v) for v in rng.integers(0, 4, size=n))) for _ in range(6)}
        weights = rng.dirichlet(np.ones(len(tops))) * rng.uniform(0.5, 1.0)
        poses = [(float(x), float(y), 0.0) for x, y in rng.normal(size=(n, 2))]
        ptm = make_ptm(landmarks(poses), list(zip(tops, weights, strict=True)))
        ordered = [t.labels for t in ptm.topologies]
        expected = brute_force_edges(ordered, [t.probability for t in ptm.topologies])
        doc = route_graph(ptm)
        _, edges = nodes_and_edges(doc)
        got = {}
        for e in edges:
            p = e["properties"]
            got[(min(p["startid"], p["endid"]), max(p["startid"], p["endid"]))] = p["metadata"]["probability"]
        assert set(got) == set(expected)
        for pair, prob in expected.items():
            assert got[pair] == pytest.approx(prob, rel=1e-12)
        if edges:
            check_nav2_structure(doc)


def test_errors(tmp_path: Path) -> None:
    lms = landmarks(POSES[:3])
    bad_positions = Ptm(landmarks=tuple(lms), topologies=(Topology((0, 1, 0), 1.0, positions=((0.0, 0.0),)),))
    with pytest.raises(DataError, match="2 places but 1 positions"):
        route_graph(bad_positions)
    empty = Ptm(landmarks=tuple(lms), topologies=(Topology((0, 1, 0), 0.0),))
    with pytest.raises(DataError, match="no probability mass"):
        route_graph(empty)
    with pytest.raises(DataError, match="holds no topology"):
        route_graph(Ptm(landmarks=tuple(lms), topologies=()))
    with pytest.raises(DataError, match="not valid JSON"):
        save_route_graph({"x": math.nan}, tmp_path / "g.geojson")


def test_repeated_passages_counted() -> None:
    # One topology, the robot shuttles 0 -> 1 -> 0 -> 1 -> 0 -> 2: two passages each way between 0 and 1.
    ptm = make_ptm(landmarks([*POSES, (9.0, 9.0, 0.0)]), [((0, 1, 0, 1, 0, 2), 1.0)])
    _, edges = nodes_and_edges(route_graph(ptm))
    got = {(e["properties"]["startid"], e["properties"]["endid"]): e["properties"]["metadata"] for e in edges}
    assert {k: v["traversals"] for k, v in got.items()} == {
        (0, 1): 2.0,
        (1, 0): 2.0,
        (0, 2): 1.0,
        (2, 0): 0.0,
    }
    assert all(v["probability"] == 1.0 for v in got.values())


# ------------------------------------------------------------------------------- walls (issue #24)

RES = 0.1
WALL_X = 6.0  # the wall is the column of cells [6.0, 6.1) x [0, wall_top)
PLACES = [(2.0, 2.0), (2.0, 5.0), (9.0, 5.0), (9.0, 2.0)]  # the wall parts 0, 1 from 2, 3


def walled_grid(wall_top: float, *, width: float = 12.0, height: float = 10.0) -> ClassGrid:
    """A free ``width`` x ``height`` m map (origin 0, 0) with a wall at x = 6 from y = 0 to ``wall_top``."""
    classes = np.full((round(height / RES), round(width / RES)), FREE, dtype=np.int8)
    classes[: round(wall_top / RES), round(WALL_X / RES)] = OCCUPIED
    return ClassGrid(classes, (0.0, 0.0, 0.0), RES)


def walled_ptm(ensemble: list[tuple[tuple[int, ...], float]]) -> Ptm:
    """Four visits, one per place of ``PLACES`` (positions of the MAP topology ``(0, 1, 2, 3)``)."""
    poses = [(x, y, 0.0) for x, y in PLACES]
    return make_ptm(landmarks(poses), ensemble, positions={(0, 1, 2, 3): PLACES})


def edge_map(doc: dict[str, Any]) -> dict[int, tuple[int, int, list]]:
    """Edge id -> (startid, endid, geometry)."""
    _, edges = nodes_and_edges(doc)
    return {
        e["properties"]["id"]: (
            e["properties"]["startid"],
            e["properties"]["endid"],
            e["geometry"]["coordinates"],
        )
        for e in edges
    }


def chain(doc: dict[str, Any], a: int, b: int) -> list[int]:
    """The node ids from place ``a`` to place ``b`` along the hops of their rerouted connection."""
    step = {
        e["properties"]["startid"]: e["properties"]["endid"]
        for e in nodes_and_edges(doc)[1]
        if e["properties"]["metadata"].get("places") == [a, b]
    }
    path = [a]
    while path[-1] != b:
        path.append(step[path[-1]])
        assert len(path) <= len(step) + 1, "the hops must lead from a to b"
    return path


def check_hops_are_straight(doc: dict[str, Any]) -> None:
    """Every edge's geometry is the straight segment between its two nodes (what nav2 follows)."""
    nodes, edges = nodes_and_edges(doc)
    for e in edges:
        p = e["properties"]
        xy = [nodes[p["startid"]]["geometry"]["coordinates"], nodes[p["endid"]]["geometry"]["coordinates"]]
        assert e["geometry"]["coordinates"] == [xy]
        assert p["metadata"]["length"] == pytest.approx(math.dist(*xy), abs=1e-12)


def test_an_edge_through_a_wall_is_rerouted_round_its_end() -> None:
    grid = walled_grid(7.0)
    ptm = walled_ptm([((0, 1, 2, 3), 1.0)])
    plain = route_graph(ptm)
    assert crossing_segments(plain, grid) == 2  # 1 -> 2 and 2 -> 1 through the wall
    doc = route_graph(ptm, grid=grid)
    check_nav2_structure(doc)
    check_hops_are_straight(doc)
    assert crossing_segments(doc, grid) == 0
    meta = doc["metadata"]
    assert meta["rerouted_edges"] == 1 and meta["dropped_edges"] == []
    assert meta["walls"].startswith("checked") and plain["metadata"]["walls"].startswith("not checked")
    nodes, edges = nodes_and_edges(doc)
    forward = chain(doc, 1, 2)
    assert len(forward) > 2 and chain(doc, 2, 1) == forward[::-1]
    assert (
        meta["waypoints"]
        == len(forward) - 2
        == sum("waypoint" in n["properties"]["metadata"] for n in nodes.values())
    )
    # the shortest way passes the wall's end: (2, 5) -> (6.0, 7.0) -> (6.1, 7.0) -> (9, 5), 8.095 m
    xy = np.array([nodes[k]["geometry"]["coordinates"] for k in forward])
    length = float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)))
    shortest = math.dist((2, 5), (6, 7)) + 0.1 + math.dist((6.1, 7), (9, 5))
    assert shortest <= length < shortest + 0.3
    assert np.all(xy[1:-1, 1] > 6.5)  # the waypoints are at the wall's end
    # ids from the formula of the module docstring; hops carry the ensemble's probability
    block = route_block(4, 1, 2, RouteConfig().max_waypoints)
    assert forward[1:-1] == list(range(block, block + len(forward) - 2))
    for e in edges:
        p = e["properties"]
        assert p["metadata"]["probability"] == 1.0
        if "places" in p["metadata"]:
            assert p["id"] >= block + RouteConfig().max_waypoints
    assert {e["properties"]["id"] for e in edges} >= set(
        straight_edge_ids(4, 0, 1) + straight_edge_ids(4, 2, 3)
    )


def test_edges_in_free_space_are_unchanged() -> None:
    ptm = walled_ptm([((0, 1, 2, 3), 1.0)])
    plain, walled = route_graph(ptm), route_graph(ptm, grid=walled_grid(7.0))
    for pair in ((0, 1), (2, 3)):
        ids = straight_edge_ids(4, *pair)
        old = [f for f in plain["features"] if f["properties"]["id"] in ids]
        assert len(old) == 2 and old == [f for f in walled["features"] if f["properties"]["id"] in ids]
    # a map without walls changes nothing but the metadata's note
    free = ClassGrid(np.full((100, 120), FREE, dtype=np.int8), (0.0, 0.0, 0.0), RES)
    assert route_graph(ptm, grid=free)["features"] == plain["features"]


def test_an_edge_with_no_way_round_is_dropped_and_counted() -> None:
    ptm = walled_ptm([((0, 1, 2, 3), 1.0)])
    grid = walled_grid(10.0)  # the wall closes the whole map; routes stay on it
    doc = route_graph(ptm, grid=grid, config=RouteConfig(corridor=20.0))
    check_nav2_structure(doc)
    assert crossing_segments(doc, grid) == 0
    assert doc["metadata"]["dropped_edges"] == [{"places": [1, 2], "probability": 1.0, "reason": NO_ROUTE}]
    _, edges = nodes_and_edges(doc)
    assert {(e["properties"]["startid"], e["properties"]["endid"]) for e in edges} == {
        (0, 1),
        (1, 0),
        (2, 3),
        (3, 2),
    }
    # a place inside a wall cell: no edge of it can avoid the wall
    assert plan_route(grid, (WALL_X + 0.05, 5.0), (9.0, 5.0)) == Route(None, PLACE_IN_WALL)
    assert plan_route(grid, (2.0, 5.0), (13.0, 5.0)) == Route(None, PLACE_OFF_MAP)
    assert plan_route(grid, (2.0, 5.0), (9.0, 5.0), RouteConfig(corridor=3.0)).reason == NO_ROUTE
    # a second wall from above at x = 4: under the first, over the second, two waypoints at least
    zigzag = walled_grid(7.0)
    zigzag.classes[round(3.0 / RES) :, round(4.0 / RES)] = OCCUPIED
    way = plan_route(zigzag, (2.0, 5.0), (9.0, 5.0))
    assert way.points is not None and len(way.points) >= 4
    assert np.all(occupied_crossings(zigzag, way.points[:-1], way.points[1:]) == 0)
    assert way.points[1:-1, 1].min() < 3.0 and way.points[1:-1, 1].max() > 7.0
    # a route needing more waypoints than allowed is dropped, not cut short
    assert plan_route(zigzag, (2.0, 5.0), (9.0, 5.0), RouteConfig(max_waypoints=1)) == Route(
        None, TOO_WINDING
    )


def test_ids_are_stable_across_writes_and_unrelated_topologies(tmp_path: Path) -> None:
    grid, cfg = walled_grid(7.0), RouteConfig(corridor=4.0)
    before = walled_ptm([((0, 1, 2, 3), 0.6)])
    first = save_route_graph(route_graph(before, grid=grid, config=cfg), tmp_path / "a.geojson").read_text()
    second = save_route_graph(route_graph(before, grid=grid, config=cfg), tmp_path / "b.geojson").read_text()
    assert first == second
    # (0, 1, 1, 2) puts visit 2 into place 1: it adds the connections 0-2 and 1-3 (through the wall too),
    # which sort between the others (0-1, 0-2, 1-2, 1-3, 2-3)
    grown = walled_ptm([((0, 1, 2, 3), 0.6), ((0, 1, 1, 2), 0.1)])
    after = route_graph(grown, grid=grid, config=cfg)
    assert after["metadata"]["rerouted_edges"] == 3 and after["metadata"]["dropped_edges"] == []
    assert crossing_segments(after, grid) == 0
    old, new = edge_map(json.loads(first)), edge_map(after)
    assert set(new) > set(old)
    assert all(new[k] == v for k, v in old.items())
    old_nodes, new_nodes = nodes_and_edges(json.loads(first))[0], nodes_and_edges(after)[0]
    assert set(new_nodes) > set(old_nodes)
    assert all(new_nodes[k] == f for k, f in old_nodes.items())


def test_route_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="corridor"):
        RouteConfig(corridor=0.0)
    with pytest.raises(ConfigError, match="unknown_cost"):
        RouteConfig(unknown_cost=0.5)
    with pytest.raises(ConfigError, match="max_waypoints"):
        RouteConfig(max_waypoints=0)


def test_nodes_on_the_trajectory_the_map_was_drawn_along() -> None:
    # the map's trajectory: the visits' odometry moved by (1, -2), sampled between the visits too
    positions = {(0, 1, 2, 1, 0): [(1.0, 2.0), (3.0, 2.0), (3.0, 6.0)]}
    ptm = make_ptm(landmarks(POSES), ENSEMBLE, positions=positions)
    stamps = np.arange(0.0, 4.01, 0.5)
    xy = np.array([p[:2] for p in POSES])
    along = np.column_stack([np.interp(stamps, np.arange(5.0), xy[:, c]) + (1.0, -2.0)[c] for c in (0, 1)])
    doc = route_graph(ptm, trajectory=(stamps, np.column_stack([along, np.zeros(len(stamps))])))
    check_nav2_structure(doc)
    nodes, _ = nodes_and_edges(doc)
    # MAP (0, 1, 2, 1, 0): two visits each for places 0 and 1, a tie: their first visit
    for a, k in enumerate((0, 1, 2)):
        np.testing.assert_allclose(nodes[a]["geometry"]["coordinates"], xy[k] + (1.0, -2.0), atol=1e-12)
    assert doc["metadata"]["node_positions"] == (
        "medoid of the places' visits on the trajectory the map was drawn along"
    )
    assert route_graph(ptm)["metadata"]["node_positions"] == "the MAP topology's place positions"
    with pytest.raises(DataError, match="cannot place the visits on the trajectory"):
        route_graph(ptm, trajectory=(stamps[:3], np.zeros((2, 3))))


def test_place_medoids_are_visits_nearest_the_others() -> None:
    xy = [(0.0, 0.0), (10.0, 0.0), (1.0, 0.0), (5.0, 5.0)]
    # place 0: summed distances 11, 19, 10 -> (1, 0), not the mean (3.67, 0); place 1: its one visit
    np.testing.assert_array_equal(place_medoids((0, 0, 0, 1), xy), [(1.0, 0.0), (5.0, 5.0)])
    with pytest.raises(DataError, match="3 labels for 4 landmarks"):
        place_medoids((0, 0, 1), xy)
