"""``landmark_detector``: landmark visits from odometry, laser scans and panoramas.

Subscribes ``odom`` (nav_msgs/Odometry), ``scan`` (sensor_msgs/LaserScan) and ``panorama``
(sensor_msgs/Image, optional) and feeds them to :class:`ptm_ros.landmarks.VisitExtractor`, the object
``ptm-run`` uses, which re-sequences the three topics by stamp: the visits do not depend on how DDS
interleaves them. Publishes every completed visit on

* ``landmark_visits`` (std_msgs/String, JSON ``ptm_ros.visit/1`` of :func:`ptm_ros.landmarks.visit_to_json`,
  lossless; reliable, keep all, transient local so a late or restarted filter gets every visit);
* ``landmark_poses`` (geometry_msgs/PoseStamped, the visit's odometry pose) for display;
* ``/diagnostics`` every second: messages received per topic and the extractor's counters (skipped
  messages by reason: non-finite odometry, stamps going backwards, malformed scans, undecodable images).

Bad messages are counted and the first of each kind is logged; none stops the node.

QoS of the sensor subscriptions: parameter ``sensor_qos`` — ``reliable`` (default; keep all, so a
replayed bag loses nothing and the visits equal ``ptm-run``'s) or ``sensor_data`` (best effort, for a
live robot; a dropped message changes the visits).

End of input. ``use_scans`` / ``use_images`` (default true) tell the extractor which streams to wait
for; ``ptm-bringup`` sets them from the bag's topics, as ``ptm-run`` does. ``stall_s`` (default 5 s of
odometry) is how long a silent stream may hold visits back before the extractor goes on without it (a
live robot whose camera died); a message older than what was already processed is then dropped, so a
replay sets ``stall_s: 0`` (never give up: the visits then never depend on delivery timing; ``ptm-bringup``
does). When the bag player announces
its end on ``end_of_input`` (messages per topic), the detector waits until it has received that many on
each of its topics (or ``end_timeout`` s without progress), completes the pending visits
(:meth:`VisitExtractor.flush`) and publishes the end marker ``{"schema": "ptm_ros.visits_end/1",
"visits": N}`` on ``landmark_visits``. Service ``~/flush`` (std_srvs/Trigger) does the same on request.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import Image, LaserScan
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ptm_ros.config import PtmConfig
from ptm_ros.errors import PtmError
from ptm_ros.landmarks import ExtractorConfig, diagnostics_dict, visit_to_json
from ptm_ros.nodes.common import (
    DISPLAY_QOS,
    END_OF_INPUT_SCHEMA,
    END_SCHEMA,
    LATCHED_QOS,
    SENSOR_QOS,
    STREAM_QOS,
    OnceLogger,
    check_parameter_names,
    declare_config,
    declare_node_parameter,
    header_stamp,
    image_array,
    odometry_sample,
    pose_msg,
    publish_diagnostics,
    run_node,
    scan_fields,
    sensor_qos,
    time_msg,
)
from ptm_ros.tools.pipeline import detector_kind, make_extractor
from ptm_ros.visits import Visit

NODE_NAME = "landmark_detector"


class LandmarkDetectorNode(Node):
    """The ``landmark_detector`` node (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        check_parameter_names(self)
        self.config: PtmConfig = declare_config(self)
        qos_kind = declare_node_parameter(
            self,
            "sensor_qos",
            "reliable",
            "QoS of odom/scan/panorama: reliable (keep all: replay loses nothing) or sensor_data",
            choices=SENSOR_QOS,
        )
        use_scans = declare_node_parameter(self, "use_scans", True, "wait for scans (laser patches)")
        use_images = declare_node_parameter(self, "use_images", True, "wait for panoramas (signatures)")
        self.end_timeout = declare_node_parameter(
            self,
            "end_timeout",
            10.0,
            "s without new messages after the end of input was announced before flushing anyway",
            minimum=0.0,
        )
        stall = declare_node_parameter(
            self,
            "stall_s",
            ExtractorConfig().stall_s,
            "s of odometry after which a silent expected topic stops holding visits back; 0 = never "
            "(replay: exact whatever the delivery timing)",
            minimum=0.0,
        )
        kind = detector_kind(self.config, has_scans=use_scans, has_images=use_images)
        self.extractor = make_extractor(self.config, kind, use_scans=use_scans, use_images=use_images)
        self.extractor.config = replace(self.extractor.config, stall_s=stall if stall > 0.0 else math.inf)
        self.frame_id = "odom"
        self.published = 0
        self.finished = False
        self.counters: dict[str, int] = {
            "image-unsupported-encoding": 0,
            "image-malformed": 0,
            "after-end": 0,
        }
        self._end_counts: dict[str, int] | None = None
        self._last_progress = time.monotonic()
        self._seen_skips: set[str] = set()
        self._log_once = OnceLogger(self.get_logger())

        self._visit_pub = self.create_publisher(String, "landmark_visits", STREAM_QOS)
        self._pose_pub = self.create_publisher(PoseStamped, "landmark_poses", DISPLAY_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        qos = sensor_qos(qos_kind)
        self._subs = {
            "odom": self.create_subscription(Odometry, "odom", self._on_odom, qos),
            "scan": self.create_subscription(LaserScan, "scan", self._on_scan, qos),
            "panorama": self.create_subscription(Image, "panorama", self._on_image, qos),
        }
        self.received = {sub.topic_name: 0 for sub in self._subs.values()}
        self.create_subscription(String, "end_of_input", self._on_end_of_input, LATCHED_QOS)
        self.create_service(Trigger, "~/flush", self._on_flush)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.create_timer(0.2, self._check_end, clock=steady)
        self.get_logger().info(
            f"detector {kind}, sensor QoS {qos_kind}, scans {'on' if use_scans else 'off'}, "
            f"panoramas {'on' if use_images else 'off'}"
        )

    # ---------------------------------------------------------------------------------- input

    def _count(self, key: str) -> bool:
        """Count a message on subscription ``key``; False when it arrives after the end (ignored)."""
        self.received[self._subs[key].topic_name] += 1
        self._last_progress = time.monotonic()
        if self.finished:
            self.counters["after-end"] += 1
            self._log_once("after-end", f"ignored a {key} message received after the end of input")
            return False
        return True

    def _on_odom(self, msg: Odometry) -> None:
        if not self._count("odom"):
            return
        if msg.header.frame_id:
            self.frame_id = msg.header.frame_id
        stamp, pose = odometry_sample(msg)
        self._feed("odometry", lambda: self.extractor.on_odometry(stamp, pose))

    def _on_scan(self, msg: LaserScan) -> None:
        if not self._count("scan"):
            return
        fields = scan_fields(msg)
        self._feed("scan", lambda: self.extractor.on_scan(*fields))

    def _on_image(self, msg: Image) -> None:
        if not self._count("panorama"):
            return
        try:
            image = image_array(msg)
        except PtmError as err:
            self.counters["image-malformed"] += 1
            self._log_once("image-malformed", f"skipped a malformed panorama: {err}")
            self._check_end()
            return
        if image is None:
            self.counters["image-unsupported-encoding"] += 1
            self._log_once("image-encoding", f"skipped a panorama with unsupported encoding {msg.encoding!r}")
            self._check_end()
            return
        stamp = header_stamp(msg.header)
        self._feed("image", lambda: self.extractor.on_image(stamp, image))

    def _feed(self, topic: str, call: Any) -> None:
        try:
            visits = call()
        except PtmError as err:  # the extractor counts bad input itself; this is a safety net
            self.counters[f"{topic}-error"] = self.counters.get(f"{topic}-error", 0) + 1
            self._log_once(f"{topic}-error", f"a {topic} message could not be used: {err}")
            visits = []
        self._note_skips()
        self._emit(visits)
        self._check_end()

    def _note_skips(self) -> None:
        for reason, count in self.extractor.diagnostics.skipped.items():
            if reason not in self._seen_skips and count > 0:
                self._seen_skips.add(reason)
                self._log_once(reason, f"skipped a message: {reason}")

    def _emit(self, visits: Sequence[Visit]) -> None:
        for v in visits:
            self._visit_pub.publish(String(data=visit_to_json(v)))
            ps = PoseStamped()
            ps.header.frame_id = self.frame_id
            ps.header.stamp = time_msg(v.stamp)
            ps.pose = pose_msg(*v.pose)
            self._pose_pub.publish(ps)
            self.published += 1

    # ------------------------------------------------------------------------------ end of input

    def _on_end_of_input(self, msg: String) -> None:
        try:
            doc = json.loads(msg.data)
            if doc.get("schema") != END_OF_INPUT_SCHEMA:
                raise ValueError(f"schema {doc.get('schema')!r}")
            counts = {str(k): int(v) for k, v in doc["counts"].items()}
        except (ValueError, TypeError, KeyError, AttributeError) as err:
            self._log_once("end-of-input", f"ignored a malformed end_of_input message: {err}")
            return
        self._end_counts = {t: n for t, n in counts.items() if t in self.received}
        self._last_progress = time.monotonic()
        self.get_logger().info(f"end of input announced: {self._end_counts}")
        self._check_end()

    def _check_end(self) -> None:
        if self._end_counts is None or self.finished:
            return
        done = all(self.received[t] >= n for t, n in self._end_counts.items())
        if not done and time.monotonic() - self._last_progress < self.end_timeout:
            return
        if not done:
            missing = {t: n - self.received[t] for t, n in self._end_counts.items() if self.received[t] < n}
            self.get_logger().warning(f"end of input: messages never arrived {missing}; finishing anyway")
        self.finish()

    def finish(self) -> int:
        """Complete every pending visit, publish them and the end marker; returns the visits published."""
        if not self.finished:
            self.finished = True
            self._emit(self.extractor.flush())
            self._visit_pub.publish(String(data=json.dumps({"schema": END_SCHEMA, "visits": self.published})))
            self.get_logger().info(f"input finished: {self.published} landmark visits")
        return self.published

    def _on_flush(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        response.message = json.dumps({"visits": self.finish()})
        return response

    # ------------------------------------------------------------------------------ diagnostics

    def diagnostics(self) -> dict[str, Any]:
        """Counters reported on /diagnostics."""
        return {
            "received": dict(self.received),
            "published_visits": self.published,
            "finished": self.finished,
            "extractor": diagnostics_dict(self.extractor.diagnostics),
            **self.counters,
        }

    def _publish_diagnostics(self) -> None:
        values = self.diagnostics()
        bad = sum(self.extractor.diagnostics.skipped.values()) + sum(self.counters.values())
        publish_diagnostics(
            self,
            self._diag_pub,
            "landmark visits",
            hardware_id=NODE_NAME,
            message=f"{self.published} visits, {bad} messages skipped",
            values=values,
            warn=bad > 0,
        )


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``landmark_detector``."""
    return run_node(LandmarkDetectorNode, args, NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
