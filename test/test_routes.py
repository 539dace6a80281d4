"""nav2 route graph export of a PTM: hand-computed ensemble edges, brute force, the GeoJSON structure."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ptm_ros.errors import DataError
from ptm_ros.partitions import canonical
from ptm_ros.ptm import Landmark, Ptm, Topology, make_ptm
from ptm_ros.routes import route_graph, save_route_graph

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
