"""The ``landmark_detector`` node's logic without rclpy: guarded input streams, sessions, the extractor.

:class:`DetectorInbox` takes the ``odom``, ``scan`` and ``panorama`` messages (the ROS message objects,
read by the checks of :mod:`ptm_ros.io.validation`, as ``ptm-run``'s bag reader reads them) and the bag
player's ``end_of_input``; it guards each stream (:class:`~ptm_ros.nodes.stream_guard.StreamGuard`),
keeps scans and panoramas on the odometry's clock, starts a new session when the odometry goes back in
time or teleports, feeds the :class:`~ptm_ros.perception.landmarks.VisitExtractor` and queues what the node
publishes in :attr:`DetectorInbox.outbox`: visits (with their session id), the map's odometry samples
and keyframe scans, and the end marker. :mod:`ptm_ros.nodes.landmark_detector` documents the rules and
counters; the node declares the parameters, converts the queue into messages and publishes them. Nothing
here imports rclpy (a contract of ``.importlinter``).
"""

from __future__ import annotations

import json
import math
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.config import PtmConfig
from ptm_ros.errors import PtmError
from ptm_ros.factories import make_extractor
from ptm_ros.io.validation import (
    Rejection,
    ScanPayload,
    image_payload,
    odometry_pose,
    scan_payload,
    valid_stamp,
)
from ptm_ros.maps.mapping import KeyframeStream
from ptm_ros.model.visits import Visit
from ptm_ros.nodes.logs import Logger, OnceLogger
from ptm_ros.nodes.messages import END_OF_INPUT_SCHEMA, END_SCHEMA
from ptm_ros.nodes.stream_guard import (
    CLOCK_RESET,
    FORWARD_JUMP,
    TELEPORT,
    Admission,
    GuardConfig,
    StreamGuard,
    sum_counters,
)
from ptm_ros.perception.landmarks import VisitExtractor, diagnostics_dict
from ptm_ros.perception.surprise import limit_surprise_trace

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


@dataclass(frozen=True)
class VisitOut:
    """A landmark visit to publish, with the detector session it belongs to and the odometry frame."""

    visit: Visit
    session: str
    frame_id: str


@dataclass(frozen=True)
class MapPose:
    """An odometry sample for the map publisher (``landmark_odom``)."""

    stamp: float
    pose: NDArray[np.float64]  # (x, y, yaw)
    frame_id: str
    child_frame_id: str


@dataclass(frozen=True)
class MapScan:
    """A keyframe scan for the map publisher (``landmark_scans``)."""

    stamp: float
    scan: ScanPayload
    frame_id: str


@dataclass(frozen=True)
class EndOut:
    """The end marker on ``landmark_visits`` (its JSON text)."""

    text: str


Output = VisitOut | MapPose | MapScan | EndOut


def _same_pose(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    return bool(np.array_equal(a, b))


def _same_scan(a: ScanPayload, b: ScanPayload) -> bool:
    return a[1:] == b[1:] and a[0].tobytes() == b[0].tobytes()


def _same_image(a: NDArray[Any], b: NDArray[Any]) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


class DetectorInbox:
    """The landmark detector's input handling (see the module docstring).

    Args:
        config: the configuration (``ptm-run``'s); ``kind`` the detector made from it.
        logger: where problems and progress are logged.
        topics: the topic name of each subscription key (``odom``, ``scan``, ``panorama``), for the
            counts of ``end_of_input``.
        use_scans, use_images: whether visits wait for scans (laser patches) and panoramas (signatures).
        stall_s: s of odometry after which a silent expected topic stops holding visits back; 0 = never.
        guard: the stream guards' settings.
        silence_s: s (wall) an expected topic may stay silent while others deliver; 0 = off.
        end_timeout: s without new messages after the end of input was announced before finishing.
        trace_rows: latest surprise measurements kept; 0 = all.
    """

    def __init__(
        self,
        config: PtmConfig,
        logger: Logger,
        *,
        kind: str,
        topics: Mapping[str, str],
        use_scans: bool = True,
        use_images: bool = True,
        stall_s: float = 0.0,
        guard: GuardConfig | None = None,
        silence_s: float = 10.0,
        end_timeout: float = 10.0,
        trace_rows: int = TRACE_ROWS,
    ) -> None:
        self.config = config
        self.kind = kind
        self._logger = logger
        self._log_once = OnceLogger(logger)
        self._use_scans, self._use_images, self._stall = use_scans, use_images, stall_s
        self.guard_config = guard or GuardConfig()
        self.silence_s, self.end_timeout, self.trace_rows = silence_s, end_timeout, trace_rows
        self.counters: dict[str, int] = dict.fromkeys(EVENTS, 0)
        self.skipped: dict[str, int] = dict.fromkeys(SKIP_REASONS, 0)
        self.outbox: list[Output] = []  # what the node publishes next, in order
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
        self.child_frame_id = "base_link"
        self.scan_frame_id = "laser"
        self.published = 0
        self.keyframes_published = 0
        self.finished = False
        self._topics = dict(topics)
        self.received = dict.fromkeys(self._topics.values(), 0)
        self._end_counts: dict[str, int] | None = None
        self._last_progress = time.monotonic()
        self._seen_skips: set[str] = set()
        self._first_rx: float | None = None
        self._last_rx: dict[str, float] = {}
        self._silent: set[str] = set()

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
        """The id of the current session (``<inbox nonce>-<session number>``)."""
        return f"{self._nonce}-{self.session}"

    @property
    def end_announced(self) -> bool:
        """Whether a valid ``end_of_input`` announcement arrived."""
        return self._end_counts is not None

    def take(self) -> list[Output]:
        """What to publish now, in order (the queue is emptied)."""
        out, self.outbox = self.outbox, []
        return out

    # ------------------------------------------------------------------------------------- input

    def _count(self, key: str) -> bool:
        """Count a message on subscription ``key``; False when it arrives after the end (ignored)."""
        self.received[self._topics[key]] += 1
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

    def odometry(self, msg: Any) -> None:
        """Take an ``odom`` message (nav_msgs/Odometry or any object with its fields)."""

        def read(m: Any) -> tuple[Any, Rejection | None]:
            pose, rejected, normalised = odometry_pose(m)
            if rejected is None:
                if normalised:
                    self.counters["odometry-quaternion-normalized"] += 1
                    self._log_once("quaternion", "normalised an odometry orientation that was not unit")
                self.frame_id = m.header.frame_id or self.frame_id
                self.child_frame_id = m.child_frame_id or self.child_frame_id
            return pose, rejected

        self._take("odom", "odometry", msg, read)

    def scan(self, msg: Any) -> None:
        """Take a ``scan`` message (sensor_msgs/LaserScan or any object with its fields)."""

        def read(m: Any) -> tuple[Any, Rejection | None]:
            payload, rejected = scan_payload(m)
            if rejected is None:
                self.scan_frame_id = m.header.frame_id or self.scan_frame_id
            return payload, rejected

        self._take("scan", "scan", msg, read)

    def image(self, msg: Any) -> None:
        """Take a ``panorama`` message (sensor_msgs/Image or any object with its fields)."""
        self._take("panorama", "image", msg, lambda m: image_payload(m, self.config.model.appearance))

    def _take(
        self, key: str, stream: str, msg: Any, read: Callable[[Any], tuple[Any, Rejection | None]]
    ) -> None:
        """A message of subscription ``key``: counted, its stamp and content checked (``read`` returns
        the content or why it is rejected), admitted to ``stream``'s guard; then the end is checked."""
        if not self._count(key):
            return
        stamp = valid_stamp(msg.header)
        if stamp is None:
            self._skip(f"{stream}-bad-stamp", f"stamp {msg.header.stamp.sec} s {msg.header.stamp.nanosec} ns")
        else:
            payload, rejected = read(msg)
            if rejected is not None:
                self._skip(*rejected)
            else:
                self._admit(stream, stamp, payload)
        self.check_end()

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
        self._past = self._extractor_counters()
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
        """Queue for the map publisher the decimated odometry and the keyframe scans processed since the
        last call (:class:`ptm_ros.maps.mapping.KeyframeStream`)."""
        for stamp, pose, scan in self._keyframes.select(
            self.extractor.take_poses(), self.extractor.take_scans()
        ):
            if scan is None:
                self.outbox.append(MapPose(stamp, pose, self.frame_id, self.child_frame_id))
            else:
                self.outbox.append(MapScan(stamp, scan, self.scan_frame_id))
                self.keyframes_published += 1

    def _emit(self, visits: Sequence[Visit]) -> None:
        self._stream_for_map()
        for v in visits:
            self.outbox.append(VisitOut(v, self.session_id, self.frame_id))
            self.published += 1
            self.session_visits += 1

    # ------------------------------------------------------------------------------ end of input

    def end_of_input(self, text: str) -> None:
        """Take the bag player's ``end_of_input`` message (its JSON text): the messages it sent per topic."""
        try:
            doc = json.loads(text)
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
        self._logger.info(f"end of input announced: {self._end_counts}")
        self.check_end()

    def check_end(self) -> None:
        """Finish when every message the end of input announced arrived, or ``end_timeout`` after the
        last progress."""
        if self._end_counts is None or self.finished:
            return
        done = all(self.received[t] >= n for t, n in self._end_counts.items())
        if not done and time.monotonic() - self._last_progress < self.end_timeout:
            return
        if not done:
            missing = {t: n - self.received[t] for t, n in self._end_counts.items() if self.received[t] < n}
            self._logger.warning(f"end of input: messages never arrived {missing}; finishing anyway")
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
            self.outbox.append(EndOut(json.dumps(end)))
            self._logger.info(f"input finished: {self.published} landmark visits")
        return self.published

    # ------------------------------------------------------------------------------ diagnostics

    def check_silence(self, now: float) -> list[str]:
        """Expected topics silent for more than ``silence_s`` at ``now`` (monotonic s) while another topic
        delivered within ``silence_s``; each new silence is counted and logged once. None with
        ``silence_s`` 0, before the first message and after the end of input (a silence then ends)."""
        if self.silence_s <= 0.0 or self.finished or self._first_rx is None:
            self._silent = set()  # off, over or not started: no topic is silent
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
            "extractor": self._extractor_counters(),
            "time_offset": self.extractor.time_offset,  # the session's (learned once its first scans are in)
            **self.skipped,
            **self.counters,
        }

    def warns(self) -> bool:
        """Whether ``/diagnostics`` says WARN: a message skipped or an error (:meth:`problems`), or an
        expected topic silent now (:meth:`check_silence`)."""
        return self.problems() > 0 or bool(self._silent)

    def problems(self) -> int:
        """Messages skipped by the checks and the extractor, and errors."""
        return (
            sum(self._extractor_counters()["skipped"].values())
            + sum(self.skipped.values())
            + self.counters["internal_errors"]
            + self.counters["extractor_errors"]
        )

    def _extractor_counters(self) -> dict[str, Any]:
        """The extractor's counters, summed over the sessions so far."""
        return sum_counters(self._past, diagnostics_dict(self.extractor.diagnostics))
