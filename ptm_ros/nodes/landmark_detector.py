"""``landmark_detector``: landmark visits from odometry, laser scans and panoramas.

Subscribes ``odom`` (nav_msgs/Odometry), ``scan`` (sensor_msgs/LaserScan) and ``panorama``
(sensor_msgs/Image, optional) and feeds them to :class:`ptm_ros.landmarks.VisitExtractor`, the object
``ptm-run`` uses, which re-sequences the three topics by stamp: the visits do not depend on how DDS
interleaves them. Publishes every completed visit on

* ``landmark_visits`` (std_msgs/String, JSON ``ptm_ros.visit/1`` of :func:`ptm_ros.landmarks.visit_to_json`,
  lossless, plus ``"session"``: the id of the detector session the visit belongs to; reliable, keep all,
  transient local so a late or restarted filter gets every visit);
* ``landmark_poses`` (geometry_msgs/PoseStamped, the visit's odometry pose) for display;
* ``landmark_odom`` (nav_msgs/Odometry, pose only) and ``landmark_scans`` (sensor_msgs/LaserScan; both
  reliable, keep all): for the map publisher's metric map (:mod:`ptm_ros.mapping`), the odometry the
  visits' poses are measured in (corrected by the laser odometry when it is on) every
  ``mapping.pose_xy`` / ``pose_yaw`` of motion or ``pose_interval`` s, and the keyframe scans (every
  ``mapping.keyframe_xy`` / ``keyframe_yaw``), each with an odometry sample at its stamp
  (:class:`ptm_ros.mapping.KeyframeStream`); the end marker (below) counts the keyframes sent;
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
(thesis Fig. 62, the report's surprise figure) as JSON (:func:`ptm_ros.surprise.trace_to_dict`, plus
``session``); ``success: false`` for a detector without one. The node keeps the latest ``trace_rows``
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

Stamps and odometry jumps (:class:`ptm_ros.nodes.common.StreamGuard`, parameters ``stamp_jump_s``
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
import math
import time
import uuid
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from numpy.typing import NDArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import Image, LaserScan
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ptm_ros.config import PtmConfig
from ptm_ros.errors import PtmError
from ptm_ros.factories import detector_kind, make_extractor
from ptm_ros.io.validation import ScanPayload, image_payload, odometry_pose, scan_payload
from ptm_ros.landmarks import (
    ExtractorConfig,
    ExtractorDiagnostics,
    VisitExtractor,
    diagnostics_dict,
    with_input_skips,
)
from ptm_ros.mapping import KeyframeStream
from ptm_ros.nodes.common import (
    CLOCK_RESET,
    DISPLAY_QOS,
    END_OF_INPUT_SCHEMA,
    FORWARD_JUMP,
    LATCHED_QOS,
    MAP_STREAM_QOS,
    SENSOR_QOS,
    STREAM_QOS,
    TELEPORT,
    Admission,
    GuardConfig,
    StreamGuard,
    check_parameter_names,
    declare_config,
    declare_node_parameter,
    guarded,
    pose_msg,
    publish_diagnostics,
    run_node,
    sensor_qos,
    sum_counters,
    time_msg,
    valid_stamp,
)
from ptm_ros.nodes.logs import OnceLogger
from ptm_ros.nodes.messages import END_SCHEMA, visit_message
from ptm_ros.surprise import limit_surprise_trace, surprise_trace, trace_to_dict
from ptm_ros.visits import Visit

NODE_NAME = "landmark_detector"
STREAMS = ("odometry", "scan", "image")  # the extractor's names of the three inputs
SUBSCRIPTIONS = {"odom": "odometry", "scan": "scan", "panorama": "image"}
MAX_WAITING = 200  # scans/panoramas of a newer clock kept until the odometry's clock resets too
RESYNC_AFTER = 100  # consecutive messages on another clock than the odometry's before adopting its clock
TRACE_ROWS = 1000  # default trace_rows: the latest surprise measurements kept (memory bound)

SKIP_REASONS = (
    "odometry-bad-stamp",
    "odometry-non-finite",
    "odometry-out-of-range",
    "odometry-bad-quaternion",
    "odometry-duplicate",
    "odometry-outlier",
    "scan-bad-stamp",
    "scan-empty",
    "scan-non-finite",
    "scan-malformed",
    "scan-length-mismatch",
    "scan-duplicate",
    "scan-outlier",
    "scan-clock-mismatch",
    "image-bad-stamp",
    "image-unsupported-encoding",
    "image-malformed",
    "image-too-small",
    "image-duplicate",
    "image-outlier",
    "image-clock-mismatch",
    "after-end",
    "end-of-input-invalid",
)
EVENTS = (
    "sessions",
    "forward_jumps",
    "clock_resets",
    "teleports",
    "resyncs",
    "silences",
    "odometry-quaternion-normalized",
    "extractor_errors",
    "internal_errors",
)


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


def _same_pose(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    return bool(np.array_equal(a, b))


def _same_scan(a: ScanPayload, b: ScanPayload) -> bool:
    return a[1:] == b[1:] and a[0].tobytes() == b[0].tobytes()


def _same_image(a: NDArray[Any], b: NDArray[Any]) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


# ----------------------------------------------------------------------------------------------- node


class LandmarkDetectorNode(Node):
    """The ``landmark_detector`` node (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.counters: dict[str, int] = dict.fromkeys(EVENTS, 0)
        self.skipped: dict[str, int] = dict.fromkeys(SKIP_REASONS, 0)
        self._log_once = OnceLogger(self.get_logger())
        check_parameter_names(self)
        self.config: PtmConfig = declare_config(self)
        qos_kind = declare_node_parameter(
            self,
            "sensor_qos",
            "reliable",
            "QoS of odom/scan/panorama: reliable (keep all: replay loses nothing) or sensor_data",
            choices=SENSOR_QOS,
        )
        self._use_scans = declare_node_parameter(self, "use_scans", True, "wait for scans (laser patches)")
        self._use_images = declare_node_parameter(self, "use_images", True, "wait for panoramas (signatures)")
        self.end_timeout = declare_node_parameter(
            self,
            "end_timeout",
            10.0,
            "s without new messages after the end of input was announced before flushing anyway",
            minimum=0.0,
        )
        self._stall = declare_node_parameter(
            self,
            "stall_s",
            ExtractorConfig().stall_s,
            "s of odometry after which a silent expected topic stops holding visits back; 0 = never "
            "(replay: exact whatever the delivery timing)",
            minimum=0.0,
        )
        defaults = GuardConfig()
        self.guard_config = GuardConfig(
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
        self.silence_s = declare_node_parameter(
            self,
            "silence_s",
            10.0,
            "s (wall) an expected topic may stay silent while others deliver before a warning; 0 = off",
            minimum=0.0,
        )
        self.trace_rows = declare_node_parameter(
            self,
            "trace_rows",
            TRACE_ROWS,
            "latest surprise measurements kept for ~/surprise_trace; 0 = all (a bag replay)",
            minimum=0,
        )
        self.kind = detector_kind(self.config, has_scans=self._use_scans, has_images=self._use_images)
        self.extractor = self._make_extractor()
        self.stream_guards = {
            "odometry": StreamGuard(self.guard_config, equal=_same_pose, position=lambda p: (p[0], p[1])),
            "scan": StreamGuard(self.guard_config, equal=_same_scan),
            "image": StreamGuard(self.guard_config, equal=_same_image),
        }
        self.fed = dict.fromkeys(STREAMS, 0)
        # scans and panoramas against the odometry's clock (see _route)
        self._aligned = dict.fromkeys(STREAMS[1:], True)  # on the session's clock
        self._pending_start: dict[str, float | None] = dict.fromkeys(STREAMS[1:])  # own reset, unmatched
        self._waiting: dict[str, deque[tuple[float, Any]]] = {s: deque() for s in STREAMS[1:]}
        self._mismatch = dict.fromkeys(STREAMS[1:], 0)  # consecutive messages not on the session's clock
        self._clock_start: float | None = None  # first stamp after the odometry's latest clock reset
        self._past: dict[str, Any] = {}  # extractor counters of the sessions that ended
        self._nonce = uuid.uuid4().hex[:8]
        self.session = 0
        self.session_visits = 0
        self.counters["sessions"] = 1
        self.frame_id = "odom"
        self.published = 0
        self.finished = False
        self._end_counts: dict[str, int] | None = None
        self._last_progress = time.monotonic()
        self._seen_skips: set[str] = set()
        self._first_rx: float | None = None
        self._last_rx: dict[str, float] = {}
        self._silent: set[str] = set()

        self._visit_pub = self.create_publisher(String, "landmark_visits", STREAM_QOS)
        self._pose_pub = self.create_publisher(PoseStamped, "landmark_poses", DISPLAY_QOS)
        self._odom_pub = self.create_publisher(Odometry, "landmark_odom", MAP_STREAM_QOS)
        self._scan_pub = self.create_publisher(LaserScan, "landmark_scans", MAP_STREAM_QOS)
        self.child_frame_id = "base_link"
        self.scan_frame_id = "laser"
        self.keyframes_published = 0
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
        self.create_service(Trigger, "~/surprise_trace", self._on_surprise_trace)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.create_timer(0.2, self._check_end_timer, clock=steady)
        self.get_logger().info(
            f"detector {self.kind}, sensor QoS {qos_kind}, scans {'on' if self._use_scans else 'off'}, "
            f"panoramas {'on' if self._use_images else 'off'}"
        )

    def _make_extractor(self) -> VisitExtractor:
        self._keyframes = KeyframeStream(self.config.mapping)  # a new session: a new stream
        ext = make_extractor(self.config, self.kind, use_scans=self._use_scans, use_images=self._use_images)
        ext.config = replace(
            ext.config, stall_s=self._stall if self._stall > 0.0 else math.inf, stream_poses=True
        )
        if self.trace_rows > 0:  # the surprise trace is for reports: bounded on a long-running robot
            limit_surprise_trace(ext.detector, self.trace_rows)
        return ext

    @property
    def session_id(self) -> str:
        """The id of the current session (``<node nonce>-<session number>``)."""
        return f"{self._nonce}-{self.session}"

    # ------------------------------------------------------------------------------------- input

    def _count(self, key: str) -> bool:
        """Count a message on subscription ``key``; False when it arrives after the end (ignored)."""
        self.received[self._subs[key].topic_name] += 1
        now = time.monotonic()
        self._last_progress = self._last_rx[key] = now
        if self._first_rx is None:
            self._first_rx = now
        if self.finished:
            self._skip("after-end", f"a {key} message received after the end of input")
            return False
        return True

    def _skip(self, reason: str, detail: str, count: int = 1) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + count
        self._log_once(reason, f"skipped {count} message(s): {reason}: {detail}")

    @guarded
    def _on_odom(self, msg: Odometry) -> None:
        if not self._count("odom"):
            return
        stamp = valid_stamp(msg.header)
        if stamp is None:
            self._skip("odometry-bad-stamp", f"stamp {msg.header.stamp.sec} s {msg.header.stamp.nanosec} ns")
        else:
            pose, rejected, normalised = odometry_pose(msg)
            if rejected is not None:
                self._skip(*rejected)
            else:
                if normalised:
                    self.counters["odometry-quaternion-normalized"] += 1
                    self._log_once("quaternion", "normalised an odometry orientation that was not unit")
                if msg.header.frame_id:
                    self.frame_id = msg.header.frame_id
                if msg.child_frame_id:
                    self.child_frame_id = msg.child_frame_id
                self._admit("odometry", stamp, pose)
        self._check_end()

    @guarded
    def _on_scan(self, msg: LaserScan) -> None:
        if not self._count("scan"):
            return
        stamp = valid_stamp(msg.header)
        if stamp is None:
            self._skip("scan-bad-stamp", f"stamp {msg.header.stamp.sec} s {msg.header.stamp.nanosec} ns")
        else:
            payload, rejected = scan_payload(msg)
            if rejected is not None:
                self._skip(*rejected)
            else:
                if msg.header.frame_id:
                    self.scan_frame_id = msg.header.frame_id
                self._admit("scan", stamp, payload)
        self._check_end()

    @guarded
    def _on_image(self, msg: Image) -> None:
        if not self._count("panorama"):
            return
        stamp = valid_stamp(msg.header)
        if stamp is None:
            self._skip("image-bad-stamp", f"stamp {msg.header.stamp.sec} s {msg.header.stamp.nanosec} ns")
        else:
            image, rejected = image_payload(msg, self.config.model.appearance)
            if rejected is not None:
                self._skip(*rejected)
            else:
                self._admit("image", stamp, image)
        self._check_end()

    # -------------------------------------------------------------------------- stream guards

    def _admit(self, stream: str, stamp: float, payload: Any) -> None:
        adm = self.stream_guards[stream].admit(stamp, payload)
        if adm.duplicate:
            self._skip(f"{stream}-duplicate", f"a repeated {stream} message at {stamp:.9f} s")
        self._apply(stream, adm)

    def _apply(self, stream: str, adm: Admission) -> None:
        if adm.outliers:
            self._skip(f"{stream}-outlier", f"{stream} stamps or poses jumped and came back", adm.outliers)
        if adm.event == FORWARD_JUMP:
            self.counters["forward_jumps"] += 1
            self._log_once(f"{stream}-forward-jump", f"{stream} stamps jumped forward; continuing")
        elif adm.event in (CLOCK_RESET, TELEPORT):
            self.counters["clock_resets" if adm.event == CLOCK_RESET else "teleports"] += 1
        if stream == "odometry":
            if adm.event in (CLOCK_RESET, TELEPORT):
                self._new_session(adm.event)
            for stamp, pose in adm.released:
                self._feed("odometry", stamp, pose)
            if adm.event == CLOCK_RESET:
                self._realign(adm.released[0][0])
            return
        if adm.event == CLOCK_RESET:
            self._sensor_reset(stream, adm.released[0][0])
        for stamp, payload in adm.released:
            self._route(stream, stamp, payload)

    def _matches_clock(self, start: float) -> bool:
        """Whether a timeline starting at ``start`` is the odometry's latest reset clock."""
        return (
            self._clock_start is not None and abs(start - self._clock_start) <= self.guard_config.stamp_jump_s
        )

    def _sensor_reset(self, stream: str, start: float) -> None:
        """A scan/panorama clock went back to ``start``: it joins the session if the odometry already reset
        onto that clock, else its messages wait for the odometry (a timeline still waiting is abandoned).
        A clock that goes back onto the odometry's own timeline (the stream's earlier stretch was stamped
        ahead of it) rejoins at once, and what the extractor queued of that stretch is dropped."""
        self._log_once(f"{stream}-clock-reset", f"{stream} stamps went back in time: a new clock")
        self._drop_waiting(stream, f"{stream} messages of a clock abandoned before the odometry reached it")
        odometry = self.stream_guards["odometry"].last_stamp
        if odometry is not None and abs(start - odometry) <= self.guard_config.stamp_jump_s:
            self.extractor.rewind(stream)
            self._aligned[stream], self._pending_start[stream] = True, None
        elif not self._aligned[stream] and self._matches_clock(start):
            self._aligned[stream], self._pending_start[stream] = True, None
        else:
            self._aligned[stream], self._pending_start[stream] = False, start

    def _realign(self, start: float) -> None:
        """The odometry's clock went back to ``start``: scans/panoramas already waiting on a clock that
        started there join the new session; the others are on the old clock until they reset too."""
        self._clock_start = start
        for stream in self._waiting:
            pending = self._pending_start[stream]
            self._pending_start[stream] = None
            self._aligned[stream] = pending is not None and self._matches_clock(pending)
            if self._aligned[stream]:
                self._mismatch[stream] = 0
                waiting = self._waiting[stream]
                while waiting:
                    self._feed(stream, *waiting.popleft())
            else:
                self._drop_waiting(stream, f"{stream} messages of a clock the odometry did not reset to")

    def _drop_waiting(self, stream: str, detail: str) -> None:
        waiting = self._waiting[stream]
        if waiting:
            self._skip(f"{stream}-clock-mismatch", detail, len(waiting))
            waiting.clear()

    def _route(self, stream: str, stamp: float, payload: Any) -> None:
        """Feed a scan or panorama if its clock is the session's; else keep it waiting for the odometry's
        reset (its own clock reset first) or skip it (the odometry's reset, not yet its own)."""
        if self._aligned[stream]:
            self._mismatch[stream] = 0
            self._feed(stream, stamp, payload)
            return
        self._mismatch[stream] += 1
        if self._pending_start[stream] is not None:
            waiting = self._waiting[stream]
            waiting.append((stamp, payload))
            if len(waiting) > MAX_WAITING:
                waiting.popleft()
                self._skip(f"{stream}-clock-mismatch", f"{stream} messages waited too long for the odometry")
        else:
            self._skip(f"{stream}-clock-mismatch", f"a {stream} message of the odometry's previous clock")
        if self._mismatch[stream] >= RESYNC_AFTER:
            self.counters["resyncs"] += 1
            self._log_once(f"{stream}-resync", f"{stream} adopts the odometry's clock")
            self._aligned[stream], self._pending_start[stream] = True, None
            self._mismatch[stream] = 0
            waiting = self._waiting[stream]
            while waiting:
                self._feed(stream, *waiting.popleft())

    def _new_session(self, cause: str) -> None:
        """Complete the current session's visits and start afresh (odometry went back or teleported)."""
        self._emit(self.extractor.flush())
        self._past = sum_counters(self._past, diagnostics_dict(self.extractor.diagnostics))
        self.extractor = self._make_extractor()
        self.session += 1
        self.session_visits = 0
        self.counters["sessions"] += 1
        what = "went back in time (bag looped or clock reset)" if cause == CLOCK_RESET else "teleported"
        self._log_once(f"session-{cause}", f"odometry {what}: new session {self.session_id}, visits from 0")

    def _feed(self, stream: str, stamp: float, payload: Any) -> None:
        self.fed[stream] += 1
        try:
            if stream == "odometry":
                visits = self.extractor.on_odometry(stamp, payload)
            elif stream == "scan":
                visits = self.extractor.on_scan(stamp, *payload)
            else:
                visits = self.extractor.on_image(stamp, payload)
        except PtmError as err:  # the extractor counts bad input itself; this is a safety net
            self.counters["extractor_errors"] += 1
            self._log_once(f"{stream}-error", f"a {stream} message could not be used: {err}")
            visits = []
        self._note_skips()
        self._emit(visits)

    def _note_skips(self) -> None:
        for reason, count in self.extractor.diagnostics.skipped.items():
            if reason not in self._seen_skips and count > 0:
                self._seen_skips.add(reason)
                self._log_once(reason, f"skipped a message: {reason}")

    def _stream_for_map(self) -> None:
        """Send the map publisher the decimated odometry and the keyframe scans processed since the last
        call (:class:`ptm_ros.mapping.KeyframeStream`)."""
        for stamp, pose, scan in self._keyframes.select(
            self.extractor.take_poses(), self.extractor.take_scans()
        ):
            if scan is None:
                odom = Odometry()
                odom.header.frame_id = self.frame_id
                odom.header.stamp = time_msg(stamp)
                odom.child_frame_id = self.child_frame_id
                odom.pose.pose = pose_msg(*pose)
                self._odom_pub.publish(odom)
            else:
                self._scan_pub.publish(keyframe_scan(stamp, scan, self.scan_frame_id))
                self.keyframes_published += 1

    def _emit(self, visits: Sequence[Visit]) -> None:
        self._stream_for_map()
        for v in visits:
            self._visit_pub.publish(String(data=visit_message(v, self.session_id)))
            ps = PoseStamped()
            ps.header.frame_id = self.frame_id
            ps.header.stamp = time_msg(v.stamp)
            ps.pose = pose_msg(*v.pose)
            self._pose_pub.publish(ps)
            self.published += 1
            self.session_visits += 1

    # ------------------------------------------------------------------------------ end of input

    @guarded
    def _on_end_of_input(self, msg: String) -> None:
        try:
            doc = json.loads(msg.data)
            if not isinstance(doc, dict) or doc.get("schema") != END_OF_INPUT_SCHEMA:
                schema = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
                raise ValueError(f"schema {schema!r}")
            counts = {}
            for topic, n in dict(doc["counts"]).items():
                if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                    raise ValueError(f"count {n!r} of {topic!r}")
                counts[str(topic)] = n
        except (ValueError, TypeError, KeyError, RecursionError) as err:
            self._skip("end-of-input-invalid", f"ignored a malformed end_of_input message: {err}")
            return
        self._end_counts = {t: n for t, n in counts.items() if t in self.received}
        self._last_progress = time.monotonic()
        self.get_logger().info(f"end of input announced: {self._end_counts}")
        self._check_end()

    @guarded
    def _check_end_timer(self) -> None:
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
        """Use what the guards still hold (see the module docstring), complete every pending visit, publish
        them and the end marker; returns the visits published."""
        if not self.finished:
            for stream in STREAMS:
                self._apply(stream, self.stream_guards[stream].settle())
            for stream in self._waiting:
                self._drop_waiting(stream, f"{stream} messages of a clock the odometry never reached")
            self.finished = True
            self._emit(self.extractor.flush())
            end = {
                "schema": END_SCHEMA,
                "visits": self.session_visits,
                "session": self.session_id,
                "keyframes": self.keyframes_published,  # landmark_scans sent, all sessions
            }
            self._visit_pub.publish(String(data=json.dumps(end)))
            self.get_logger().info(f"input finished: {self.published} landmark visits")
            self._publish_diagnostics()  # the final counters at once, not up to a second later
        return self.published

    @guarded
    def _on_flush(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        response.message = json.dumps({"visits": self.finish()})
        return response

    @guarded
    def _on_surprise_trace(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        trace = surprise_trace(self.extractor.detector)
        if trace is None:
            response.success, response.message = False, f"detector {self.kind} keeps no surprise trace"
            return response
        response.success = True
        response.message = json.dumps({**trace_to_dict(trace), "session": self.session_id})
        return response

    # ------------------------------------------------------------------------------ diagnostics

    def check_silence(self, now: float) -> list[str]:
        """Expected topics silent for more than ``silence_s`` at ``now`` (monotonic s) while another topic
        delivered within ``silence_s``; each new silence is counted and logged once."""
        if self.silence_s <= 0.0 or self.finished or self._first_rx is None:
            return []
        expected = ["odom"]
        expected += ["scan"] if self.extractor.config.use_scans else []
        expected += ["panorama"] if self.extractor.config.use_images else []
        newest = max(self._last_rx.values())
        if now - newest > self.silence_s:
            silent = []  # everything stopped (a paused robot or bag): nothing to single out
        else:
            silent = [
                key for key in expected if now - self._last_rx.get(key, self._first_rx) > self.silence_s
            ]
        for key in silent:
            if key not in self._silent:
                self.counters["silences"] += 1
                self._log_once(f"silent-{key}", f"no {key} message for {self.silence_s:g} s, others arrive")
        self._silent = set(silent)
        return silent

    def held(self) -> dict[str, int]:
        """Messages held per stream: by the stream guard (unconfirmed jump) or waiting for the odometry's
        clock."""
        waiting = {s: len(w) for s, w in self._waiting.items()}
        return {s: self.stream_guards[s].held + waiting.get(s, 0) for s in STREAMS}

    def diagnostics(self) -> dict[str, Any]:
        """Counters reported on /diagnostics."""
        return {
            "received": dict(self.received),
            "fed": dict(self.fed),
            "held": self.held(),
            "published_visits": self.published,
            "session": self.session_id,
            "session_visits": self.session_visits,
            "finished": self.finished,
            "silent": ",".join(sorted(self._silent)),
            "extractor": sum_counters(self._past, diagnostics_dict(self.extractor.diagnostics)),
            "time_offset": self.extractor.time_offset,  # the session's (learned once its first scans are in)
            **self.skipped,
            **self.counters,
        }

    @guarded
    def _publish_diagnostics(self) -> None:
        self.check_silence(time.monotonic())
        values = self.diagnostics()
        bad = (
            sum(values["extractor"]["skipped"].values())
            + sum(self.skipped.values())
            + self.counters["internal_errors"]
            + self.counters["extractor_errors"]
        )
        publish_diagnostics(
            self,
            self._diag_pub,
            "landmark visits",
            hardware_id=NODE_NAME,
            message=f"{self.published} visits, {bad} messages skipped",
            values=values,
            warn=bad > 0 or bool(self._silent),
        )


#: Prefix of the extractor's counters among the ``/diagnostics`` values
#: (:meth:`LandmarkDetectorNode.diagnostics`).
EXTRACTOR_PREFIX = "extractor."


def input_counts(values: Mapping[str, str]) -> dict[str, Any]:
    """ptm.json's ``diagnostics`` of the input from the values of the detector's ``/diagnostics`` status
    (:meth:`LandmarkDetectorNode.diagnostics`, flattened into dotted keys by
    :func:`ptm_ros.nodes.common.key_values`), under ``ptm-run``'s keys
    (:func:`ptm_ros.landmarks.with_input_skips`): the extractor's counters (``extractor.*``, summed over the
    detector's sessions) with the messages the node's input checks skipped (:data:`SKIP_REASONS`, the
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
