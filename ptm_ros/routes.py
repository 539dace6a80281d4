"""A PTM's ensemble as a nav2 route server graph (GeoJSON).

Format (nav2 ``nav2_route`` README, "File Formats", https://github.com/ros-navigation/navigation2/tree/main/nav2_route,
read by ``GeoJsonGraphFileLoader``, docs: https://docs.nav2.org/configuration/packages/configuring-route-server.html):
a GeoJSON ``FeatureCollection`` whose ``features`` are nodes (``geometry.type = "Point"``,
``coordinates [x, y]``, ``properties.id`` and the recommended ``properties.frame``) and edges
(``geometry.type = "MultiLineString"``, ``properties.id``, ``startid``, ``endid``); ids are unsigned
integers unique over nodes *and* edges; any application data goes under ``properties.metadata``. Edges
are directional ("All edges are directional"), so every connection is written once per direction. The
loader rejects a file without nodes or without edges, so a MAP topology with a single place gives a
graph nav2 cannot load. As nav2's own saver, the collection carries ``"name": "graph"`` and its
``crs`` member; a foreign ``metadata`` member describes how the graph was made.

Nodes are the places of the MAP (most probable) topology, at ``Topology.positions`` when present, else
at the mean odometry position of their visits. Edge probabilities are the thesis' ensemble rule
(Ch. 0.3.1: "the transition probabilities of edges are the sum of the probabilities of the topologies in
the PTM containing that edge"), made meaningful across topologies whose place labels differ by naming
places through visits: with ``r_a`` the first visit of MAP place ``a`` and ``T(k)`` the place of visit
``k`` in topology ``T``,

.. math::
    P(a \\leftrightarrow b) = \\frac{1}{S} \\sum_{T} p_T \\,
        \\mathbb{1}\\bigl[T(r_a) \\ne T(r_b) \\wedge
        \\exists k:\\ \\{T(k), T(k+1)\\} = \\{T(r_a), T(r_b)\\}\\bigr],
    \\qquad S = \\sum_T p_T,

the mass of the topologies in which the robot travelled directly between the place of ``r_a`` and the
place of ``r_b``. Every pair with ``P > 0`` is exported, also when only non-MAP topologies hold it. ``S``
normalises when the listed topologies hold less than all the mass (recorded in the metadata). Each
directed edge ``a → b`` carries ``metadata: {probability, length, traversals}``: the undirected
probability above, the Euclidean length between the node positions (m), and the posterior expected
number of direct passages from the place of ``r_a`` to the place of ``r_b`` (same normalisation).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from ptm_ros.errors import DataError
from ptm_ros.partitions import num_places
from ptm_ros.ptm import Ptm, Topology

SCHEMA = "ptm_ros.route_graph/1"
_MASS_TOL = 1e-9  # listed masses this close to 1 are taken as the whole posterior
#: Coordinate reference member written by nav2's ``GeoJsonGraphFileSaver`` (ignored by its loader).
NAV2_CRS = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::3857"}}


def node_positions(ptm: Ptm) -> np.ndarray:
    """``(M, 2)`` positions of the MAP topology's places: its ``positions`` if given, else the mean
    odometry position of each place's visits."""
    top = ptm.map_topology
    m = num_places(top.labels)
    if top.positions is not None:
        if len(top.positions) != m:
            msg = f"the MAP topology has {m} places but {len(top.positions)} positions"
            raise DataError(msg)
        pos = np.asarray(top.positions, dtype=float).reshape(m, 2)
    else:
        labels = np.asarray(top.labels, dtype=np.intp)
        xy = np.array([lm.map_pose[:2] for lm in ptm.landmarks], dtype=float).reshape(-1, 2)
        if len(xy) != len(labels):
            msg = f"{len(labels)} labels for {len(xy)} landmarks"
            raise DataError(msg)
        counts = np.bincount(labels, minlength=m).astype(float)
        pos = np.stack([np.bincount(labels, xy[:, c], minlength=m) / counts for c in (0, 1)], axis=1)
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


def _node_feature(node_id: int, xy: np.ndarray, frame_id: str, top: Topology, root: int) -> dict[str, Any]:
    visits = [k for k, lab in enumerate(top.labels) if lab == node_id]
    return {
        "type": "Feature",
        "properties": {
            "id": node_id,
            "frame": frame_id,
            "metadata": {"place": node_id, "first_visit": root, "visits": visits},
        },
        "geometry": {"type": "Point", "coordinates": [float(xy[0]), float(xy[1])]},
    }


def route_graph(ptm: Ptm, *, frame_id: str | None = None) -> dict[str, Any]:
    """The nav2 route graph GeoJSON document of ``ptm`` (see the module docstring).

    Node ids are the MAP place labels ``0..M-1``; edge ids follow from ``M`` on, ``a → b`` before
    ``b → a``, pairs in ascending order. ``frame_id`` defaults to the PTM's frame.
    """
    frame = ptm.frame_id if frame_id is None else frame_id
    top = ptm.map_topology
    pos = node_positions(ptm)
    roots = first_visits(top.labels)
    mass, passages, listed = edge_statistics(ptm)
    if not (listed > 0.0 and math.isfinite(listed)):
        msg = f"the listed topologies hold no probability mass (sum {listed})"
        raise DataError(msg)
    normalised = listed < 1.0 - _MASS_TOL
    scale = 1.0 / listed if normalised else 1.0
    m = len(pos)
    features = [_node_feature(a, pos[a], frame, top, roots[a]) for a in range(m)]
    next_id = m
    for a, b in sorted(mass):
        prob = min(1.0, mass[(a, b)] * scale)
        if prob <= 0.0:
            continue
        length = float(np.hypot(*(pos[b] - pos[a])))
        for s, e in ((a, b), (b, a)):
            features.append(
                {
                    "type": "Feature",
                    "properties": {
                        "id": next_id,
                        "startid": s,
                        "endid": e,
                        "metadata": {
                            "probability": prob,
                            "length": length,
                            "traversals": passages.get((s, e), 0.0) * scale,
                        },
                    },
                    "geometry": {
                        "type": "MultiLineString",
                        "coordinates": [
                            [[float(pos[s][0]), float(pos[s][1])], [float(pos[e][0]), float(pos[e][1])]]
                        ],
                    },
                }
            )
            next_id += 1
    return {
        "type": "FeatureCollection",
        "name": "graph",
        "crs": NAV2_CRS,
        "metadata": {
            "schema": SCHEMA,
            "frame_id": frame,
            "nodes": "places of the MAP topology",
            "edge_probability": "posterior mass of the listed topologies in which the robot travelled "
            "directly between the places of the two nodes' first visits",
            "topologies": len(ptm.topologies),
            "map_probability": float(top.probability),
            "listed_mass": listed,
            "normalised_by_listed_mass": normalised,
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
