"""``map_publisher``: the most probable topology as a path, and the ensemble written to ptm.json on request.

Subscribes ``ptm_graph`` (std_msgs/String, the topology filter's JSON document, reliable + transient
local), validates each document (:func:`ptm_ros.ptm.from_json_dict`) and keeps the latest. Publishes
``ptm_path`` (nav_msgs/Path, reliable + transient local) of the MAP topology: **one pose per visit, in
visit order**, at the estimated position of the place the MAP topology assigns the visit to (the
odometry position of the visit when the document carries no place positions), with the visit's odometry
heading and header stamp; so revisits of a place coincide and the path draws the topological map.

Service ``~/save_ptm`` (std_srvs/Trigger) writes the latest document to ``<out_dir>/ptm.json`` (it
refuses, ``success: false``, while it has no document or one without visits, as ``ptm-run`` does); its
response message is JSON ``{"path", "visits", "topologies", "complete"}`` (``complete``: the filter had
every visit of a finished input), which ``ptm-bringup`` uses to know the run is fully mapped.
``/diagnostics`` every second: documents received, invalid ones, visits of the latest.

Bad input (issue #9): a document that is not JSON (also nested too deep, or numbers beyond float range),
not a valid ptm.json, or has non-finite stamps, poses or place positions, positions of the wrong shape
or a ``stream`` section that is not a mapping with a boolean ``complete`` is dropped (``invalid``); a
repetition of the latest document is dropped (``duplicates``); the previous document stays in force.
Each is logged once and counted; a bug reached by some input is caught by the callback's last-resort
guard (``internal_errors``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ptm_ros.errors import DataError
from ptm_ros.nodes.common import (
    LATCHED_QOS,
    OnceLogger,
    check_parameter_names,
    declare_node_parameter,
    diagnostic_status,
    guarded,
    pose_msg,
    run_node,
    time_msg,
)
from ptm_ros.ptm import Ptm, from_json_dict

NODE_NAME = "map_publisher"


def map_path(ptm: Ptm) -> PathMsg:
    """The ``nav_msgs/Path`` of the MAP topology (see the module docstring); empty without topologies."""
    path = PathMsg()
    path.header.frame_id = ptm.frame_id
    if not ptm.topologies or not ptm.landmarks:
        return path
    top = ptm.topologies[0]
    places = None
    if top.positions is not None and len(top.positions) == max(top.labels) + 1:
        places = np.asarray(top.positions, dtype=float)
    for lm, label in zip(ptm.landmarks, top.labels, strict=True):
        x, y = places[label] if places is not None else lm.map_pose[:2]
        ps = PoseStamped()
        ps.header.frame_id = ptm.frame_id
        ps.header.stamp = time_msg(lm.stamp)
        ps.pose = pose_msg(float(x), float(y), lm.map_pose[2])
        path.poses.append(ps)
    path.header.stamp = time_msg(ptm.landmarks[-1].stamp)
    return path


def check_graph(doc: dict[str, Any], ptm: Ptm) -> None:
    """What :func:`ptm_ros.ptm.from_json_dict` does not check: finite stamps and (x, y, yaw) poses of the
    landmarks, finite ``(M, 2)`` place positions of every topology (M its number of places), and the
    ``stream`` section of a graph document.

    Raises:
        DataError: naming the offending item.
    """
    for lm in ptm.landmarks:
        if not (math.isfinite(lm.stamp) and len(lm.pose) == 3 and all(map(math.isfinite, lm.pose))):
            msg = f"landmark {lm.index}: stamp {lm.stamp} and pose {lm.pose} must be finite (x, y, yaw)"
            raise DataError(msg)
    for rank, t in enumerate(ptm.topologies):
        if t.positions is None:
            continue
        if len(t.positions) != max(t.labels, default=-1) + 1 or not all(
            math.isfinite(c) for xy in t.positions for c in xy
        ):
            msg = f"topology {rank}: positions must be finite, one (x, y) per place"
            raise DataError(msg)
    stream = doc.get("stream", {})
    if not isinstance(stream, dict) or not isinstance(stream.get("complete", False), bool):
        msg = f"stream must be a mapping with a boolean 'complete', got {stream!r:.80}"
        raise DataError(msg)


def parse_graph(text: str) -> tuple[dict[str, Any], Ptm]:
    """The JSON document of a ``ptm_graph`` message and its validated :class:`Ptm`.

    Raises:
        DataError: not JSON, or not a valid ptm.json document (:func:`check_graph`).
    """
    try:
        doc = json.loads(text)
    except (ValueError, OverflowError, RecursionError) as err:
        msg = f"ptm_graph message is not JSON: {type(err).__name__}: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict):
        msg = f"ptm_graph message must be a JSON object, got {type(doc).__name__}"
        raise DataError(msg)
    try:
        ptm = from_json_dict(doc)
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as err:  # beside DataError
        msg = f"invalid ptm.json document: {type(err).__name__}: {err}"
        raise DataError(msg) from err
    check_graph(doc, ptm)
    return doc, ptm


class MapPublisherNode(Node):
    """The ``map_publisher`` node (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        check_parameter_names(self)
        self.out_dir = declare_node_parameter(
            self, "out_dir", "out/map_publisher", "directory ~/save_ptm writes ptm.json to", read_only=False
        )
        self.doc: dict[str, Any] | None = None
        self.ptm: Ptm | None = None
        self.counters = {"messages": 0, "invalid": 0, "duplicates": 0, "internal_errors": 0}
        self._text: str | None = None  # the latest document as received
        self._log_once = OnceLogger(self.get_logger())
        self._path_pub = self.create_publisher(PathMsg, "ptm_path", LATCHED_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(String, "ptm_graph", self._on_graph, LATCHED_QOS)
        self.create_service(Trigger, "~/save_ptm", self._on_save)
        self.create_timer(1.0, self._publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME))

    @property
    def complete(self) -> bool:
        """Whether the latest document says the filter had every visit of a finished input."""
        return bool(self.doc is not None and self.doc.get("stream", {}).get("complete", False))

    @guarded
    def _on_graph(self, msg: String) -> None:
        self.counters["messages"] += 1
        if msg.data == self._text:
            self.counters["duplicates"] += 1
            self._log_once("duplicate-graph", "dropped a repeated ptm_graph message")
            return
        try:
            doc, ptm = parse_graph(msg.data)
        except DataError as err:
            self.counters["invalid"] += 1
            self._log_once("invalid-graph", f"dropped an invalid ptm_graph message: {err}")
            return
        path = map_path(ptm)
        self.doc, self.ptm, self._text = doc, ptm, msg.data
        self._path_pub.publish(path)

    @guarded
    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.doc is None or self.ptm is None:
            response.success, response.message = False, "no ensemble received yet: nothing to save"
            return response
        if not self.ptm.landmarks:
            response.success, response.message = (
                False,
                "the ensemble holds no landmark visit: nothing to save",
            )
            return response
        out = Path(self.get_parameter("out_dir").value)
        path = out / "ptm.json"
        try:
            out.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(self.doc, indent=1) + "\n")
        except OSError as err:
            response.success, response.message = False, f"cannot write {path}: {err}"
            return response
        response.success = True
        response.message = json.dumps(
            {
                "path": str(path),
                "visits": len(self.ptm.landmarks),
                "topologies": len(self.ptm.topologies),
                "complete": self.complete,
            }
        )
        self.get_logger().info(f"wrote {path} ({len(self.ptm.landmarks)} visits)")
        return response

    @guarded
    def _publish_diagnostics(self) -> None:
        values = {
            **self.counters,
            "visits": 0 if self.ptm is None else len(self.ptm.landmarks),
            "topologies": 0 if self.ptm is None else len(self.ptm.topologies),
            "complete": self.complete,
        }
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [
            diagnostic_status(
                f"{self.get_name()}: ensemble",
                NODE_NAME,
                f"{values['visits']} visits, {values['topologies']} topologies",
                values,
                warn=self.counters["invalid"] + self.counters["internal_errors"] > 0,
            )
        ]
        self._diag_pub.publish(msg)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``map_publisher``."""
    return run_node(MapPublisherNode, args, NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
