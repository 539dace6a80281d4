"""config/ptm.rviz against the nodes' own tables of what they publish (no DDS): every topic a display
subscribes is published with the display's message type and a QoS the subscription can match, every
displayable topic is shown, the fixed frame is the nodes' frame, and setup.py installs the file."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
RVIZ = REPO / "config" / "ptm.rviz"
#: rviz_default_plugins display class -> the message type it subscribes.
DISPLAY_TYPES = {
    "rviz_default_plugins/Map": "nav_msgs/msg/OccupancyGrid",
    "rviz_default_plugins/MarkerArray": "visualization_msgs/msg/MarkerArray",
    "rviz_default_plugins/Path": "nav_msgs/msg/Path",
}


def type_name(msg_type: type) -> str:
    """``package/msg/Name`` of a generated ROS 2 message class (``nav_msgs.msg._path.Path``)."""
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def published() -> dict[str, tuple[str, Any]]:
    """Absolute topic (the nodes started without a namespace) -> (message type, QoS) over the nodes
    that publish what RViz shows."""
    pytest.importorskip("rclpy")
    from ptm_ros.nodes import map_publisher, topology_filter

    out: dict[str, tuple[str, Any]] = {}
    for module in (topology_filter, map_publisher):
        for topic, (msg_type, qos) in module.PUBLISHES.items():
            out["/" + topic.lstrip("/")] = (type_name(msg_type), qos)
    return out


def displays(tree: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """Every display of a ``Displays`` list, inside groups too."""
    for d in tree.get("Displays") or ():
        yield d
        yield from displays(d)


@pytest.fixture(scope="module")
def rviz() -> dict[str, Any]:
    return yaml.safe_load(RVIZ.read_text())


def test_every_displayed_topic_is_published_with_its_type(rviz: dict[str, Any]) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    topics = published()
    shown = {}
    for d in displays(rviz["Visualization Manager"]):
        if "Topic" not in d:
            continue
        assert d["Class"] in DISPLAY_TYPES, f"{d['Name']}: a display class this test does not know"
        topic = d["Topic"]["Value"]
        assert topic in topics, f"{d['Name']} shows {topic}, which no node publishes"
        expected, qos = topics[topic]
        assert DISPLAY_TYPES[d["Class"]] == expected, f"{topic} is {expected}, {d['Class']} wants another"
        offered = qos if isinstance(qos, QoSProfile) else QoSProfile(depth=qos)
        if d["Topic"]["Reliability Policy"] == "Reliable":
            assert offered.reliability == ReliabilityPolicy.RELIABLE, f"{topic}: best effort publisher"
        if d["Topic"]["Durability Policy"] == "Transient Local":
            assert offered.durability == DurabilityPolicy.TRANSIENT_LOCAL, f"{topic}: volatile publisher"
        shown[topic] = d["Class"]
    displayable = {t for t, (ty, _) in topics.items() if ty in DISPLAY_TYPES.values()}
    assert set(shown) == displayable == {"/map", "/ptm_markers", "/ptm_path", "/ptm_trajectory"}


def test_fixed_frame_is_the_nodes_frame(rviz: dict[str, Any]) -> None:
    pytest.importorskip("rclpy")
    from ptm_ros.model.ptm import Ptm
    from ptm_ros.nodes.topology_filter import FRAME_ID

    assert rviz["Visualization Manager"]["Global Options"]["Fixed Frame"] == FRAME_ID
    assert Ptm(landmarks=(), topologies=()).frame_id == FRAME_ID  # the map publisher's frame: the ensemble's


def test_setup_installs_the_rviz_config(monkeypatch: pytest.MonkeyPatch) -> None:
    from distutils.core import run_setup  # setuptools' shim

    monkeypatch.chdir(REPO)
    data_files = dict(run_setup("setup.py", stop_after="init").data_files)
    assert "config/ptm.rviz" in data_files["share/ptm_ros/config"]
