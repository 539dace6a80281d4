"""Issue #6: the node suite replaying the bundled bag at 10× real time over DDS loses no landmark visit.

``ptm-bringup --bag bags/demo --rate 10 --params config/demo.yaml`` (separate processes, real DDS): the
visits the detector publishes, the visits the filter maps and the landmarks of the final ptm.json all
equal ``ptm-run``'s on the same bag, and so does the ensemble; every message of the bag reaches the
detector, and no node reports a skipped or dropped message (log, ``/diagnostics``, ptm.json counters).
"""

from __future__ import annotations

import ast
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from ros_helpers import BRINGUP, REPO, Inbox, assert_no_orphans, dds_env, ros_context

from ptm_ros.model.ptm import load_ptm
from ptm_ros.nodes.bag_player import bag_topics

# the node suite over DDS at ten times real time (about 20 s)
pytestmark = [pytest.mark.dds, pytest.mark.slow]

RATE = 10.0
NODES = ("landmark_detector", "topology_filter", "map_publisher")
#: the filter's counters of visit messages it could not use (ptm.json ``diagnostics``; all must stay 0)
FILTER_DROPS = ("invalid", "rejected", "duplicates", "gaps", "resets")


@pytest.fixture(scope="module")
def demo_bag(tmp_path_factory):
    """A private copy of ``bags/demo`` (its path marks every process of this test, and no other)."""
    bag = tmp_path_factory.mktemp("replay") / "demo"
    shutil.copytree(REPO / "bags" / "demo", bag)
    return bag


def logged_dict(log: str, pattern: str) -> dict[str, int]:
    """The ``{...}`` literal at the end of the first log line matching ``pattern``."""
    m = re.search(pattern + r"[^{\n]*(\{[^}\n]*\})", log)
    assert m is not None, f"no {pattern!r} in the log:\n{log[-3000:]}"
    return ast.literal_eval(m.group(1))


def test_ten_times_real_time_loses_no_visit(demo_bag, demo_run, tmp_path, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from std_msgs.msg import String

    from ptm_ros.nodes.common import STREAM_QOS
    from ptm_ros.nodes.messages import parse_visit_message

    params = REPO / "config" / "demo.yaml"
    out = tmp_path / "bringup"
    sent = {name: t.count for name, t in bag_topics(demo_bag).items()}
    cmd = [*BRINGUP, "--bag", str(demo_bag), "--rate", f"{RATE:g}", "--params", str(params)]
    cmd += ["--out", str(out), "--no-report"]
    with ros_context(monkeypatch) as ros:  # a probe on the suite's domain: what went over DDS
        probe = ros.node("replay_probe")
        visits_seen = Inbox(probe, String, "/landmark_visits", STREAM_QOS)
        diagnostics = Inbox(probe, DiagnosticArray, "/diagnostics", 200)
        ros.spin(probe)
        try:
            proc = subprocess.run(
                cmd, env=dds_env(ros.domain_id), capture_output=True, text=True, timeout=240, check=False
            )
        finally:
            assert_no_orphans(str(out), str(demo_bag))
        published = [parse_visit_message(m.data) for m in visits_seen.items]
        statuses = [s for m in diagnostics.items for s in m.status]
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    offline = load_ptm(demo_run[1] / "ptm.json")  # ptm-run on another copy of the bag, same parameters
    n = len(offline.landmarks)
    assert n >= 8

    # every message of the bag was published at 10x and received by the detector before it finished
    assert f"at rate {RATE:g}" in log
    assert logged_dict(log, r"\[ptm_bag_player\]: published \d+ messages") == sent
    assert logged_dict(log, r"\[landmark_detector\]: end of input announced") == sent
    assert "never arrived" not in log
    skips = re.findall(r"^\[landmark_detector\] \[WARN\].*skipped.*$", log, re.MULTILINE)
    assert not skips  # the detector logs the first message it skips of every kind

    # the detector's visits as published over DDS, then its end marker: ptm-run's visits
    assert published[-1] == n
    assert [(v.index, v.stamp, v.input_pose, v.pose) for v in published[:-1]] == [
        (lm.index, lm.stamp, lm.pose, lm.map_pose) for lm in offline.landmarks
    ]
    assert f"[landmark_detector]: input finished: {n} landmark visits" in log
    assert f"[topology_filter]: end of visits reported ({n}); {n} in the map" in log

    # the map publisher's ptm.json: the filter took every visit; the same landmarks and ensemble as ptm-run
    online = load_ptm(out / "ptm.json")
    assert online.landmarks == offline.landmarks
    assert [t.labels for t in online.topologies] == [t.labels for t in offline.topologies]
    p_on = np.array([t.probability for t in online.topologies])
    p_off = np.array([t.probability for t in offline.topologies])
    assert np.max(np.abs(p_on - p_off)) <= 1e-9
    doc = json.loads((out / "ptm.json").read_text())
    assert doc["stream"] == {"visits": n, "complete": True}
    assert doc["diagnostics"]["visits"] == n and doc["diagnostics"]["messages"] == n + 1  # + end marker
    assert {k: doc["diagnostics"][k] for k in FILTER_DROPS} == dict.fromkeys(FILTER_DROPS, 0)

    # /diagnostics during the replay: every node reported, none skipped or dropped a message
    by_node = {node: [s for s in statuses if s.name.startswith(f"{node}:")] for node in NODES}
    assert all(by_node.values()), {k: len(v) for k, v in by_node.items()}
    for status in by_node["landmark_detector"]:
        values = {kv.key: kv.value for kv in status.values}
        assert re.search(r"\b0 messages skipped", status.message), (status.message, values)
        assert all(int(values[f"received.{t}"]) <= c for t, c in sent.items()), values
    for status in by_node["topology_filter"] + by_node["map_publisher"]:  # WARN = a dropped message
        values = {kv.key: kv.value for kv in status.values}
        assert status.level == DiagnosticStatus.OK, (status.name, status.message, values)
