"""The ``map_publisher`` node's inputs without rclpy: the ensemble, the visits and the map's samples.

:class:`MapInbox` takes the topology filter's ``ptm_graph`` documents (:meth:`MapInbox.graph`, as text),
the detector's ``landmark_visits`` (:meth:`MapInbox.visit`) and the odometry samples and keyframe scans
of the map, already converted from their messages (:meth:`MapInbox.odometry`, :meth:`MapInbox.scan`). It
keeps the latest valid ensemble, the current detector session's visits with a registrar of their laser
patches, and an :class:`~ptm_ros.maps.mapping.OnlineMap`, counts and logs (once per kind) what it drops, and
hands out what the map of the MAP topology is drawn from (:meth:`MapInbox.snapshot`). The node
(:mod:`ptm_ros.nodes.map_publisher`) converts the messages, draws in its thread and publishes. Nothing here
imports rclpy (a contract of ``.importlinter``).
"""

from __future__ import annotations

import json
import math
from typing import Any

from ptm_ros.config import PtmConfig
from ptm_ros.errors import DataError
from ptm_ros.factories import cached
from ptm_ros.io.validation import Rejection, ScanPayload, odometry_xy_yaw, scan_payload, valid_stamp
from ptm_ros.maps.mapping import MapInputs, OnlineMap
from ptm_ros.model.geometry import Registrar
from ptm_ros.model.ptm import Ptm
from ptm_ros.model.visits import Visit
from ptm_ros.nodes.logs import Logger, OnceLogger
from ptm_ros.nodes.messages import parse_graph, parse_visit_envelope
from ptm_ros.perception.laser import patch_registrar

PREPARED_PATCHES = 16  # patches kept prepared for registration (each MAP pair is registered once, cached)
COUNTERS = (
    "messages",
    "invalid",
    "duplicates",
    "internal_errors",
    "visits_ignored",
    "odometry_invalid",
    "scans_invalid",
    "maps",
    "map_errors",
)


class MapInbox:
    """The map publisher's inputs (see the module docstring)."""

    def __init__(self, config: PtmConfig, logger: Logger) -> None:
        self.config = config
        self.doc: dict[str, Any] | None = None
        self.ptm: Ptm | None = None
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.online = OnlineMap(config.mapping)
        self.scans_received = 0
        self.scans_expected: int | None = None  # keyframes the detector sent, from its end marker
        self.dirty = False  # the ensemble, the visits or the keyframes changed since the last snapshot
        self._visits: list[Visit] = []
        self._visit_session: str | None = None
        self._registrar = self._session_registrar()
        self._text: str | None = None  # the latest document as received
        self._log_once = OnceLogger(logger)

    @property
    def complete(self) -> bool:
        """Whether the latest document says the filter had every visit of a finished input."""
        return bool(self.doc is not None and self.doc.get("stream", {}).get("complete", False))

    @property
    def scans_complete(self) -> bool:
        """Whether the detector's end marker came and every keyframe scan it counts has been received."""
        return self.scans_expected is not None and self.scans_received >= self.scans_expected

    def graph(self, text: str) -> Ptm | None:
        """Take a ``ptm_graph`` document: the new ensemble, or None when it is dropped (invalid, or a
        repetition of the latest; the latest stays in force)."""
        self.counters["messages"] += 1
        if text == self._text:
            self.counters["duplicates"] += 1
            self._log_once("duplicate-graph", "dropped a repeated ptm_graph message")
            return None
        try:
            doc, ptm = parse_graph(text)
        except DataError as err:
            self.counters["invalid"] += 1
            self._log_once("invalid-graph", f"dropped an invalid ptm_graph message: {err}")
            return None
        self.doc, self.ptm, self._text = doc, ptm, text
        self.dirty = True
        return ptm

    def visit(self, text: str) -> None:
        """Take a ``landmark_visits`` message: a visit of the current detector session (visit 0 of another
        session starts a new one, with its own registrations), or the end marker's keyframe count."""
        try:
            visit, session = parse_visit_envelope(text)
        except DataError as err:
            self._ignore_visit("visit-invalid", f"dropped an invalid landmark_visits message: {err}")
            return
        if not isinstance(visit, Visit):  # an end marker: the keyframes the detector sent until then
            keyframes = json.loads(text).get("keyframes")
            if isinstance(keyframes, int) and not isinstance(keyframes, bool) and keyframes >= 0:
                self.scans_expected = keyframes
            return
        if visit.index == 0 and (session != self._visit_session or not self._visits or session is None):
            self._visits = [visit]
            self._visit_session = session
            self._registrar = self._session_registrar()
        elif session == self._visit_session and visit.index == len(self._visits):
            self._visits.append(visit)
        else:
            self._ignore_visit("visit-sequence", f"visit {visit.index} of session {session} out of sequence")
            return
        self.dirty = True

    def _session_registrar(self) -> Registrar:
        """Laser registration of the current session's visits, each pair once (cached)."""
        return cached(patch_registrar(self._visits, self.config.laser, keep_prepared=PREPARED_PATCHES))

    def _ignore_visit(self, key: str, text: str) -> None:
        self.counters["visits_ignored"] += 1
        self._log_once(key, text)

    def odometry_message(self, msg: Any) -> None:
        """Take a ``landmark_odom`` message (nav_msgs/Odometry or any object with its fields)."""
        self.odometry(valid_stamp(msg.header), odometry_xy_yaw(msg))

    def scan_message(self, msg: Any) -> None:
        """Take a ``landmark_scans`` message (sensor_msgs/LaserScan or any object with its fields)."""
        payload, rejected = scan_payload(msg)
        self.scan(valid_stamp(msg.header), payload, rejected)

    def odometry(self, stamp: float | None, pose: tuple[float, float, float]) -> None:
        """Take an odometry sample of the map (``stamp`` None: not a valid ROS time)."""
        if stamp is None or not all(map(math.isfinite, pose)):
            self.counters["odometry_invalid"] += 1
            self._log_once("odometry-invalid", "skipped a landmark_odom sample with a bad stamp or pose")
            return
        before = self.online.keyframes
        if self.online.add_pose(stamp, pose):
            self._log_once("map-reset", "the visits' odometry restarted (new session): the map starts afresh")
            self.dirty = True
        # a sample that reaches scans held for it turns them into keyframes: the map has changed too
        self.dirty = self.dirty or self.online.keyframes != before

    def scan(
        self, stamp: float | None, payload: ScanPayload | None, rejected: Rejection | None = None
    ) -> None:
        """Take a keyframe scan of the map (``payload`` None: malformed, for the ``rejected`` reason)."""
        self.scans_received += 1
        if stamp is None or payload is None:
            self.counters["scans_invalid"] += 1
            reason = "bad stamp" if stamp is None else f"{rejected[0]}: {rejected[1]}" if rejected else "?"
            self._log_once("scan-invalid", f"skipped a scan for the map: {reason}")
            return
        before = self.online.keyframes
        self.online.add_scan(stamp, *payload)
        self.dirty = self.dirty or self.online.keyframes != before

    def map_inputs(self) -> tuple[list[Visit], tuple[int, ...]] | None:
        """The visits of the latest ensemble (matched by index and stamp) and its MAP labels; None while
        the ensemble is empty or its visits have not all arrived."""
        ptm = self.ptm
        if ptm is None or not ptm.landmarks or not ptm.topologies:
            return None
        n = len(ptm.landmarks)
        visits = self._visits[:n]
        if len(visits) < n or any(
            abs(v.stamp - lm.stamp) > 1e-6 for v, lm in zip(visits, ptm.landmarks, strict=True)
        ):
            return None
        return visits, tuple(ptm.topologies[0].labels)

    def snapshot(self) -> tuple[MapInputs, tuple[int, ...], str, Registrar] | None:
        """What the map of the latest ensemble is drawn from (copies), or None when it cannot be yet."""
        inputs = self.map_inputs()
        if inputs is None or self.ptm is None:
            return None
        visits, labels = inputs
        try:
            snap = self.online.snapshot(visits)
        except DataError as err:
            self.counters["map_errors"] += 1
            self._log_once("map-inputs", f"cannot draw the map: {err}")
            return None
        return snap, labels, self.ptm.frame_id, self._registrar
