"""The map publisher's inputs without rclpy (:class:`ptm_ros.nodes.map_inbox.MapInbox`): which visits and
ensembles the map is drawn from, what is dropped and counted. The drawing and the topics are tested
through the node in ``test_nodes.py`` and ``test_fuzz.py``."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace

import numpy as np

from ptm_ros.config import load_config
from ptm_ros.model.ptm import Landmark, make_ptm
from ptm_ros.nodes.map_inbox import MapInbox
from ptm_ros.nodes.messages import END_SCHEMA, graph_document, visit_message


def inbox() -> MapInbox:
    return MapInbox(load_config(), logging.getLogger("map_inbox"))


def graph(visits, complete=False) -> str:
    """An ensemble of the visits (each its own place, or the first and last one place)."""
    n = len(visits)
    ptm = make_ptm([Landmark.from_visit(v) for v in visits], {tuple(range(n)): 0.4, (*range(n - 1), 0): 0.6})
    return json.dumps(graph_document(ptm, complete=complete))


def test_the_map_is_drawn_from_the_ensembles_visits_of_the_current_session(sim_visits):
    box = inbox()
    v = list(sim_visits[:4])
    for k in range(3):
        box.visit(visit_message(v[k], "a"))
    assert box.dirty and box.map_inputs() is None  # no ensemble yet
    assert box.graph(graph(v[:3])) is not None and box.counters["messages"] == 1
    visits, labels = box.map_inputs()
    assert [u.stamp for u in visits] == [u.stamp for u in v[:3]] and labels == (0, 1, 0)
    assert box.graph(graph(v[:4])) is not None and box.map_inputs() is None  # visit 3 not here yet
    box.visit(visit_message(v[3], "a"))
    assert len(box.map_inputs()[0]) == 4 and not box.complete
    # out of sequence, another session not from its start, malformed: ignored and counted
    box.visit(visit_message(replace(v[0], index=6), "a"))
    box.visit(visit_message(replace(v[1], index=1), "b"))
    box.visit("{")
    assert box.counters["visits_ignored"] == 3 and len(box.map_inputs()[0]) == 4
    # a new session from its visit 0: its own visits; the old ensemble no longer matches them
    box.visit(visit_message(replace(v[2], index=0), "b"))
    assert box.map_inputs() is None and box.counters["visits_ignored"] == 3
    # the end marker's keyframe count
    assert box.scans_expected is None and not box.scans_complete
    box.visit(json.dumps({"schema": END_SCHEMA, "visits": 1, "session": "b", "keyframes": 0}))
    assert box.scans_expected == 0 and box.scans_complete


def test_repeated_and_invalid_ensembles_leave_the_latest_in_force(sim_visits):
    box = inbox()
    v = list(sim_visits[:3])
    text = graph(v, complete=True)
    assert box.graph(text) is not None and box.complete
    assert box.graph(text) is None and box.counters["duplicates"] == 1
    bad = json.loads(text)
    bad["stream"] = {"complete": "yes"}
    assert box.graph(json.dumps(bad)) is None and box.graph("[") is None
    assert box.counters["invalid"] == 2 and box.doc == json.loads(text) and box.counters["messages"] == 4


def test_bad_odometry_and_scans_are_counted_not_mapped():
    box = inbox()
    box.odometry(None, (0.0, 0.0, 0.0))
    box.odometry(1.0, (math.nan, 0.0, 0.0))
    box.odometry(1.0, (0.0, 0.0, 0.0))
    box.scan(None, (np.ones(5, np.float32), -1.0, 0.5, 0.1, 10.0))
    box.scan(2.0, None, ("scan-empty", "no ranges"))
    assert box.counters["odometry_invalid"] == 2 and box.counters["scans_invalid"] == 2
    assert box.online.counters.poses == 1 and box.online.counters.scans == 0 and box.scans_received == 2


def test_scans_that_wait_for_the_odometry_mark_the_map_changed_when_it_reaches_them():
    """Over DDS the scans may arrive before the odometry of their stamps (two topics): they wait, and the
    odometry sample that reaches them makes them keyframes. That must mark the inputs changed as a new
    keyframe scan does, or ``~/save_map`` returns the map drawn before them (a stale map under load)."""
    box = inbox()
    scan = (np.full(90, 3.0, np.float32), -math.pi / 2, math.pi / 90, 0.1, 10.0)
    box.odometry(0.0, (0.0, 0.0, 0.0))
    box.scan(0.0, scan)  # reached at once: a keyframe
    assert box.online.keyframes == 1 and box.dirty
    box.dirty = False  # the map publisher took a snapshot and draws it
    for k in range(1, 4):  # scans ahead of the odometry: held
        box.scan(float(k), scan)
    assert box.online.keyframes == 1 and not box.dirty
    box.odometry(0.5, (0.5, 0.0, 0.0))  # reaches none of them
    assert not box.dirty
    box.odometry(3.0, (3.0, 0.0, 0.0))  # reaches all three
    assert box.online.keyframes == 4 and box.dirty
