"""``landmark_detector``: landmark visits from odometry, laser scans and panoramas.

Subscribes ``odom`` (nav_msgs/Odometry), ``scan`` (sensor_msgs/LaserScan) and ``panorama``
(sensor_msgs/Image, optional) and feeds them to :class:`ptm_ros.perception.landmarks.VisitExtractor`, the
object ``ptm-run`` uses, which re-sequences the three topics by stamp: the visits do not depend on how DDS
interleaves them. Publishes every completed visit on

* ``landmark_visits`` (std_msgs/String, JSON ``ptm_ros.visit/1`` of
:func:`ptm_ros.perception.landmarks.visit_to_json`,
  lossless, plus ``"session"``: the id of the detector session the visit belongs to; reliable, keep all,
  transient local so a late or restarted filter gets every visit);
* ``landmark_poses`` (geometry_msgs/PoseStamped, the visit's odometry pose) for display;
* ``landmark_odom`` (nav_msgs/Odometry, pose only) and ``landmark_scans`` (sensor_msgs/LaserScan; both
  reliable, keep all): for the map publisher's metric map (:mod:`ptm_ros.maps.mapping`), the odometry the
  visits' poses are measured in (corrected by the laser odometry when it is on) every
  ``mapping.pose_xy`` / ``pose_yaw`` of motion or ``pose_interval`` s, and the keyframe scans (every
  ``mapping.keyframe_xy`` / ``keyframe_yaw``), each with an odometry sample at its stamp
  (:class:`ptm_ros.maps.mapping.KeyframeStream`); the end marker (below) counts the keyframes sent;
* ``/diagnostics`` every second and when the input finishes (the final counts): messages received per
  topic, the counters below and the extractor's (``extractor.*``); :func:`input_counts` turns them into
  ``ptm-run``'s ptm.json ``diagnostics`` (``ptm-bringup`` writes them into its ptm.json).

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
"visits": N, "session": ID, "keyframes": K}`` on ``landmark_visits`` (N: the visits of the current
session; K: the keyframe scans sent on ``landmark_scans`` since the node started). Service
``~/flush`` (std_srvs/Trigger) does the same on request.

Service ``~/surprise_trace`` (std_srvs/Trigger): the surprise detector's trace of the current session
(thesis Fig. 62, the report's surprise figure) as JSON (:func:`ptm_ros.perception.surprise.trace_to_dict`,
plus ``session``); ``success: false`` for a detector without one. The node keeps the latest ``trace_rows``
(default 1000) measurements, so its memory stays bounded on a robot; 0 keeps all (``ptm-bringup``
sets it on a bag replay, whose report then shows ``ptm-run``'s figure).

Bad input (issue #9). No message stops the node or reaches the extractor unchecked (the checks of
:mod:`ptm_ros.io.validation`, which ``ptm-run``'s bag reader applies too); each kind of problem is
logged once (a warning; later ones at debug level) and counted in ``/diagnostics`` under its name:

==============================  ===================================================================
``odometry-bad-stamp`` etc.     header stamp with ``sec < 0`` or ``nanosec >= 10⁹`` (any topic): skipped
``odometry-non-finite``         NaN/inf position: skipped
``odometry-out-of-range``       ``|x|`` or ``|y|`` above 10⁷ m: skipped
``odometry-bad-quaternion``     NaN/inf or zero-norm orientation: skipped
``odometry-quaternion-          a quaternion whose norm is off 1 by more than 10⁻³ is normalised
normalized`` (not a skip)       before its yaw is decoded (a unit one is decoded unchanged, bit-exact)
``scan-empty``                  no ranges: skipped
``scan-non-finite``             not one finite range (NaN- or inf-filled): skipped
``scan-malformed``              non-finite angles, ``angle_increment`` 0 with several beams, not
                                ``0 <= range_min < range_max``: skipped (NaN/inf/negative/too long
                                ranges are single beams: the extractor drops them, ``scan_beams_dropped``)
``scan-length-mismatch``        ``angle_min/angle_max/angle_increment`` imply a beam count more than
                                one off the ranges' length: skipped (``intensities`` are not used)
``image-unsupported-encoding``  an encoding outside :data:`ptm_ros.io.bag.IMAGE_ENCODINGS`: skipped
``image-malformed``             ``step`` shorter than a row or ``data`` shorter than ``height·step``
``image-too-small``             narrower than ``2·n_coeffs`` or fewer rows than ``bands``: skipped
``<topic>-duplicate``           same stamp and content as the topic's previous message: skipped
``<topic>-outlier``             a stamp jump or teleport the stream did not confirm (below): skipped
``<topic>-clock-mismatch``      a scan/panorama on another clock than the odometry's (below)
``after-end``                   any message after the end of input: ignored
==============================  ===================================================================

Stamps and odometry jumps (:class:`ptm_ros.nodes.stream_guard.StreamGuard`, parameters ``stamp_jump_s``
default 30 s, ``jump_confirm`` default 3, ``max_speed`` default 5 m/s). Per topic, a stamp more than
``stamp_jump_s`` before the topic's latest, or after it by more than 10 times the topic's median gap
(at least 0.25 s, at most ``stamp_jump_s``), or an odometry step longer than ``max_speed·Δt + 1 m``, is
held until ``jump_confirm`` consistent messages confirm it; one back on the old timeline makes the held
ones outliers (skipped). A topic's first messages are confirmed the same way. Small steps back in time
go to the extractor, which skips them (``extractor.skipped.<topic>-stamp-backwards``). Confirmed:

* a forward jump (a pause, a gap in a log): the held messages are used, nothing else changes
  (``forward_jumps``);
* odometry going back in time (bag looped, clock reset; ``clock_resets``) or teleporting (odometry
  reset or relocalised; ``teleports``): a **new session** (``sessions``): the pending visits of the old
  one are completed and published, the extractor starts afresh and visits are numbered from 0 again
  with a new ``session`` id, so the topology filter starts a new map (odometry cannot relate the two);
* a scan or panorama stream going back in time (``clock_resets``): it joins the new session when its
  new timeline starts within ``stamp_jump_s`` of the odometry's new one, whichever resets first (its
  messages wait, at most 200, for the odometry); after the odometry's reset, messages still on the old
  clock are skipped (``<topic>-clock-mismatch``), as are waiting ones the odometry never matches. A
  topic off the session's clock for 100 messages in a row adopts it (``resyncs``). One going back onto
  the odometry's current timeline (its first messages were stamped ahead of it, and confirmed) is back
  on the session's clock at once: the extractor drops what it still held of the stretch ahead
  (``extractor.skipped.<topic>-off-clock``) and takes the topic's messages from there, as ``ptm-run``'s
  reader keeps the longest increasing run of a topic.

At the end of input, held starts and forward jumps are used and held resets or teleports dropped.
Missing topics: an expected topic silent for ``silence_s`` (default 10 s, wall time; 0 = off) while
another one still delivers is reported once per silence (``silences``; ``silent`` lists them now, and
the status turns WARN). The node's timers run on the steady clock, so a jumping ``/clock``
(``use_sim_time``) changes nothing. A bug reached by some input is caught by the callback's last-resort
guard (:func:`ptm_ros.nodes.common.guarded`, ``internal_errors``).
"""

from __future__ import annotations

import array
import json
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import Image, LaserScan
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ptm_ros.config import PtmConfig
from ptm_ros.factories import detector_kind
from ptm_ros.io.validation import ScanPayload
from ptm_ros.nodes.common import (
    DISPLAY_QOS,
    LATCHED_QOS,
    MAP_STREAM_QOS,
    SENSOR_QOS,
    STREAM_QOS,
    check_parameter_names,
    declare_config,
    declare_node_parameter,
    guarded,
    pose_msg,
    publish_diagnostics,
    run_node,
    sensor_qos,
    time_msg,
)
from ptm_ros.nodes.detector_inbox import (
    SKIP_REASONS,
    TRACE_ROWS,
    DetectorInbox,
    MapPose,
    MapScan,
    VisitOut,
)
from ptm_ros.nodes.logs import OnceLogger
from ptm_ros.nodes.messages import visit_message
from ptm_ros.nodes.stream_guard import GuardConfig
from ptm_ros.perception.landmarks import (
    ExtractorConfig,
    ExtractorDiagnostics,
    diagnostics_dict,
    with_input_skips,
)
from ptm_ros.perception.surprise import surprise_trace, trace_to_dict

NODE_NAME = "landmark_detector"
# ------------------------------------------------------------------------------------------ validation


def keyframe_scan(stamp: float, scan: ScanPayload, frame_id: str) -> LaserScan:
    """The ``landmark_scans`` message of a keyframe: the scan as received (its ranges as float32)."""
    ranges, amin, ainc, rmin, rmax = scan
    msg = LaserScan()
    msg.header.stamp = time_msg(stamp)
    msg.header.frame_id = frame_id
    msg.angle_min, msg.angle_increment = float(amin), float(ainc)
    msg.angle_max = float(amin) + (len(ranges) - 1) * float(ainc)
    msg.range_min, msg.range_max = float(rmin), float(rmax)
    msg.ranges = array.array("f", np.asarray(ranges, dtype=np.float32).tobytes())
    return msg


# ----------------------------------------------------------------------------------------------- node


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
        end_timeout = declare_node_parameter(
            self,
            "end_timeout",
            10.0,
            "s without new messages after the end of input was announced before flushing anyway",
            minimum=0.0,
        )
        stall_s = declare_node_parameter(
            self,
            "stall_s",
            ExtractorConfig().stall_s,
            "s of odometry after which a silent expected topic stops holding visits back; 0 = never "
            "(replay: exact whatever the delivery timing)",
            minimum=0.0,
        )
        defaults = GuardConfig()
        guard = GuardConfig(
            stamp_jump_s=declare_node_parameter(
                self,
                "stamp_jump_s",
                defaults.stamp_jump_s,
                "s: a stamp this far from its topic's latest is a jump (held until confirmed)",
                minimum=1e-9,
            ),
            confirm=declare_node_parameter(
                self,
                "jump_confirm",
                defaults.confirm,
                "consistent messages that confirm a stamp jump, an odometry teleport or a topic's start",
                minimum=1,
            ),
            max_speed=declare_node_parameter(
                self,
                "max_speed",
                defaults.max_speed,
                "m/s: odometry steps longer than max_speed * dt + 1 m are teleports",
                minimum=1e-9,
            ),
        )
        silence_s = declare_node_parameter(
            self,
            "silence_s",
            10.0,
            "s (wall) an expected topic may stay silent while others deliver before a warning; 0 = off",
            minimum=0.0,
        )
        trace_rows = declare_node_parameter(
            self,
            "trace_rows",
            TRACE_ROWS,
            "latest surprise measurements kept for ~/surprise_trace; 0 = all (a bag replay)",
            minimum=0,
        )
        kind = detector_kind(self.config, has_scans=use_scans, has_images=use_images)
        qos = sensor_qos(qos_kind)
        self._visit_pub = self.create_publisher(String, "landmark_visits", STREAM_QOS)
        self._pose_pub = self.create_publisher(PoseStamped, "landmark_poses", DISPLAY_QOS)
        self._odom_pub = self.create_publisher(Odometry, "landmark_odom", MAP_STREAM_QOS)
        self._scan_pub = self.create_publisher(LaserScan, "landmark_scans", MAP_STREAM_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        subs = {
            "odom": self.create_subscription(Odometry, "odom", self._on_odom, qos),
            "scan": self.create_subscription(LaserScan, "scan", self._on_scan, qos),
            "panorama": self.create_subscription(Image, "panorama", self._on_image, qos),
        }
        self.inbox = DetectorInbox(
            self.config,
            self.get_logger(),
            kind=kind,
            topics={key: sub.topic_name for key, sub in subs.items()},
            use_scans=use_scans,
            use_images=use_images,
            stall_s=stall_s,
            guard=guard,
            silence_s=silence_s,
            end_timeout=end_timeout,
            trace_rows=trace_rows,
        )
        self._log_once = OnceLogger(self.get_logger())
        self._final_diagnostics = False
        self.create_subscription(String, "end_of_input", self._on_end_of_input, LATCHED_QOS)
        self.create_service(Trigger, "~/flush", self._on_flush)
        self.create_service(Trigger, "~/surprise_trace", self._on_surprise_trace)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.create_timer(0.2, self._check_end_timer, clock=steady)
        self.get_logger().info(
            f"detector {kind}, sensor QoS {qos_kind}, scans {'on' if use_scans else 'off'}, "
            f"panoramas {'on' if use_images else 'off'}"
        )

    @property
    def counters(self) -> dict[str, int]:
        """The inbox's event counters (the guard of :func:`ptm_ros.nodes.common.guarded` adds to them)."""
        return self.inbox.counters

    # ------------------------------------------------------------------------------------- input

    @guarded
    def _on_odom(self, msg: Odometry) -> None:
        self.inbox.odometry(msg)
        self._publish()

    @guarded
    def _on_scan(self, msg: LaserScan) -> None:
        self.inbox.scan(msg)
        self._publish()

    @guarded
    def _on_image(self, msg: Image) -> None:
        self.inbox.image(msg)
        self._publish()

    @guarded
    def _on_end_of_input(self, msg: String) -> None:
        self.inbox.end_of_input(msg.data)
        self._publish()

    @guarded
    def _check_end_timer(self) -> None:
        self.inbox.check_end()
        self._publish()

    def _publish(self) -> None:
        """Publish what the inbox queued; once the input is finished, the final counters at once."""
        for out in self.inbox.take():
            if isinstance(out, VisitOut):
                self._visit_pub.publish(String(data=visit_message(out.visit, out.session)))
                ps = PoseStamped()
                ps.header.frame_id = out.frame_id
                ps.header.stamp = time_msg(out.visit.stamp)
                ps.pose = pose_msg(*out.visit.pose)
                self._pose_pub.publish(ps)
            elif isinstance(out, MapPose):
                odom = Odometry()
                odom.header.frame_id = out.frame_id
                odom.header.stamp = time_msg(out.stamp)
                odom.child_frame_id = out.child_frame_id
                odom.pose.pose = pose_msg(*out.pose)
                self._odom_pub.publish(odom)
            elif isinstance(out, MapScan):
                self._scan_pub.publish(keyframe_scan(out.stamp, out.scan, out.frame_id))
            else:
                self._visit_pub.publish(String(data=out.text))
        if self.inbox.finished and not self._final_diagnostics:
            self._final_diagnostics = True
            self._publish_diagnostics()

    def finish(self) -> int:
        """:meth:`DetectorInbox.finish <ptm_ros.nodes.detector_inbox.DetectorInbox.finish>`, published;
        returns the visits published."""
        n = self.inbox.finish()
        self._publish()
        return n

    @guarded
    def _on_flush(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        response.message = json.dumps({"visits": self.finish()})
        return response

    @guarded
    def _on_surprise_trace(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        inbox = self.inbox
        trace = surprise_trace(inbox.extractor.detector)
        if trace is None:
            response.success, response.message = False, f"detector {inbox.kind} keeps no surprise trace"
            return response
        response.success = True
        response.message = json.dumps({**trace_to_dict(trace), "session": inbox.session_id})
        return response

    # ------------------------------------------------------------------------------ diagnostics

    @guarded
    def _publish_diagnostics(self) -> None:
        inbox = self.inbox
        inbox.check_silence(time.monotonic())
        values = inbox.diagnostics()
        bad = inbox.problems()
        publish_diagnostics(
            self,
            self._diag_pub,
            "landmark visits",
            hardware_id=NODE_NAME,
            message=f"{inbox.published} visits, {bad} messages skipped",
            values=values,
            warn=inbox.warns(),
        )


#: Prefix of the extractor's counters among the ``/diagnostics`` values
#: (:meth:`LandmarkDetectorNode.diagnostics`).
EXTRACTOR_PREFIX = "extractor."


def input_counts(values: Mapping[str, str]) -> dict[str, Any]:
    """ptm.json's ``diagnostics`` of the input from the values of the detector's ``/diagnostics`` status
    (:meth:`LandmarkDetectorNode.diagnostics`, flattened into dotted keys by
    :func:`ptm_ros.nodes.common.key_values`), under ``ptm-run``'s keys
    (:func:`ptm_ros.perception.landmarks.with_input_skips`): the extractor's counters (``extractor.*``, summed
    over the detector's sessions) with the messages the node's input checks skipped (:data:`SKIP_REASONS`, the
    names of ``ptm-run``'s bag reader) added to ``skipped`` and kept apart under ``read_skipped``. A value
    that is not an integer count is left out (the extractor's defaults stand)."""

    def count(text: str) -> int | None:
        try:
            n = int(text)
        except (TypeError, ValueError):
            return None
        return n if n >= 0 else None

    extractor = diagnostics_dict(ExtractorDiagnostics())
    for key, text in values.items():
        if not key.startswith(EXTRACTOR_PREFIX) or (n := count(text)) is None:
            continue
        name, _, sub = key[len(EXTRACTOR_PREFIX) :].partition(".")
        if sub and isinstance(extractor.get(name), dict):
            extractor[name][sub] = n
        elif not sub and isinstance(extractor.get(name), int):
            extractor[name] = n
    skipped = {reason: n for reason in SKIP_REASONS if (n := count(values.get(reason, ""))) is not None}
    return with_input_skips(extractor, skipped)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``landmark_detector``."""
    return run_node(LandmarkDetectorNode, args, NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
