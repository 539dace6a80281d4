"""From sensor streams to landmark visits: the streaming visit extractor (thesis Ch. 3.10, Fig. 48; Ch. 4).

:class:`VisitExtractor` turns odometry, laser scans and panoramas into :class:`~ptm_ros.model.visits.Visit`
objects, each carrying what the topology inference needs: the odometry pose of the visit (an odometry
sample; with scans, corrected by :class:`ptm_ros.perception.laser_odometry.LaserOdometry` as the stream is
processed: every odometry sample is carried by the correction of the latest scan before it), the
travel and rotation since the previous visit, the Fourier signature of the panorama nearest in time and
the local laser patch of the passage through the place.

Determinism. The offline pipeline (``ptm-run``) and the detector node must produce *identical* visits
although over DDS the three topics interleave differently. The extractor therefore re-sequences its
input: messages are queued and processed strictly in (stamp, topic) order, a message only once every
expected topic has delivered a stamp at least as late (a watermark; each topic must be in order on its
own, which ROS publishers and bags guarantee). Everything downstream (the detector, patches, signatures)
sees one canonical sequence, so the output depends only on the data, never on arrival order.

A visit is declared at an odometry sample (the detector fires at a stamp; the visit snaps to the
odometry sample nearest to it), and completed once the processed stream has passed both the end of the
passage through its patch radius and ``image_max_dt`` after it: the patch = scans taken while the
robot's odometry stays within ``laser.patch_radius`` of the visit pose (the contiguous run around the
visit, at most ``max_passage_s`` long), placed with odometry interpolated at the scan stamps; the
signature = the panorama nearest in time within ``image_max_dt``. The patch is
:func:`ptm_ros.perception.patches.passage_patch` over the buffered scans (the passage's keyframes with their
odometry corrected by scan matching); it only depends on the scans up to the completion stamp, which is
itself fixed by the canonical sequence.

Bad input is counted in :attr:`VisitExtractor.diagnostics` and skipped, never raised: non-finite
odometry, stamps going backwards on a topic, malformed scans, undecodable images.
"""

from __future__ import annotations

import base64
import heapq
import json
import math
from collections import deque
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import DataError, ModelError, PtmError
from ptm_ros.model.appearance import AppearanceConfig, panorama_signature
from ptm_ros.model.geometry import FloatArray, interpolate_poses, wrap_angle
from ptm_ros.model.visits import MAX_COORDINATE, Visit, visit_fields, visit_from_fields
from ptm_ros.perception.detectors import Detector, EquidistantDetector
from ptm_ros.perception.laser import LaserConfig, WorkerPool
from ptm_ros.perception.laser_odometry import (
    LaserOdometry,
    LaserOdometryConfig,
    OffsetEstimate,
    RunInput,
    learn_time_offset,
)
from ptm_ros.perception.patches import ScanPoints, passage_patch, passage_slice, usable_points

ODOM, SCAN, IMAGE = 0, 1, 2  # topic priority for equal stamps: odometry first
#: The reasons (keys of ``ExtractorDiagnostics.skipped``) for which a landmark the detector declared
#: became no visit, with what each means; the other reasons count input messages.
LANDMARK_DROPS = {
    "landmark-at-same-odometry-sample": (
        "fell on the odometry sample of the visit before (two landmarks closer in time than the odometry's "
        "sampling period) and merged into that visit"
    ),
    "visit-invalid": "had unusable odometry since the visit before (travel or turn out of range)",
}
TOPIC_NAMES = {ODOM: "odometry", SCAN: "scan", IMAGE: "image"}
VISIT_SCHEMA = "ptm_ros.visit/1"
#: A scan as the extractor keeps it: ``(ranges, angle_min, angle_increment, range_min, range_max)``.
ScanFields = tuple[NDArray[np.float64], float, float, float, float]


@dataclass(frozen=True)
class ExtractorConfig:
    """What the extractor needs to know besides the models' own configs."""

    use_scans: bool = True  # wait for scans (laser patches); False: visits carry no patch
    use_images: bool = True  # wait for panoramas (signatures); False: visits carry no signature
    image_max_dt: float = 1.0  # s
    max_passage_s: float = 120.0  # s: longest passage a patch is built from (bounds memory)
    stall_s: float = 5.0  # s of odometry after which a silent expected topic no longer holds the stream
    record_corrections: bool = False  # keep (stamp, correction) of every scan (offline smoothing; grows)
    stream_poses: bool = False  # keep each odometry sample and scan used, with its pose, until taken
    spread_distance: float = 0.0  # m: a visit's signature spread is against a panorama this far (0: none)


@dataclass
class ExtractorDiagnostics:
    """Counters of what was received, used and skipped (published on /diagnostics by the node)."""

    received: dict[str, int] = field(default_factory=lambda: {"odometry": 0, "scan": 0, "image": 0})
    skipped: dict[str, int] = field(default_factory=dict)
    scan_beams_dropped: int = 0
    visits: int = 0
    visits_without_panorama: int = 0
    visits_without_patch: int = 0
    stalled_topics: int = 0
    laser_odometry: dict[str, int] = field(default_factory=dict)  # LaserOdometryCounters when enabled

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1


@dataclass
class _Held:
    """The messages held while the time offset is learned (``LaserOdometryConfig.learn_time_offset``),
    in processing order, and the odometry and scan points the estimate reads."""

    messages: list[tuple[float, int, Any]] = field(default_factory=list)
    odom_t: list[float] = field(default_factory=list)
    odom_p: list[NDArray[np.float64]] = field(default_factory=list)
    scan_t: list[float] = field(default_factory=list)
    scan_points: list[NDArray[np.float64]] = field(default_factory=list)


def _ready(patch: FloatArray | Future[FloatArray] | None) -> bool:
    return not isinstance(patch, Future) or patch.done()


@dataclass
class _Finished:
    """A visit complete but for its patch (a patch being built elsewhere is a future)."""

    pending: _Pending
    patch: FloatArray | Future[FloatArray] | None
    signature: NDArray[np.float64] | None
    spread: NDArray[np.float64] | None


@dataclass
class _Pending:
    k: int  # index of the odometry sample in the extractor's odometry log
    stamp: float
    pose: NDArray[np.float64]
    travel: float
    rotation: float
    first_in: float  # stamp of the odometry sample just before the passage (scans are kept from here)
    wheel: NDArray[np.float64] | None = None  # input odometry pose of the visit when ``pose`` is corrected
    exit_stamp: float | None = None  # first odometry sample after the visit outside the patch radius


class VisitExtractor:
    """Streaming landmark visits from odometry, scans and panoramas (see the module docstring).

    Feed messages with :meth:`on_odometry`, :meth:`on_scan`, :meth:`on_image` in any interleaving (each
    topic in order); each returns the visits completed by it, in visit order. :meth:`flush` completes
    everything at the end of the data.

    ``patches`` (optional) builds the patches elsewhere while the stream goes on: a visit is then returned
    by the first call after its patch is ready (the visits, their order and the counters are the same).
    The learned time offset's candidate passes run there too (the same estimate).
    """

    def __init__(
        self,
        detector: Detector | None = None,
        *,
        laser: LaserConfig | None = None,
        appearance: AppearanceConfig | None = None,
        config: ExtractorConfig | None = None,
        laser_odometry: LaserOdometryConfig | None = None,
        patches: WorkerPool | None = None,
    ) -> None:
        self.detector = detector if detector is not None else EquidistantDetector()
        self.patches = patches
        self.laser = laser or LaserConfig()
        self.appearance = appearance or AppearanceConfig()
        self.config = config or ExtractorConfig()
        self.diagnostics = ExtractorDiagnostics()
        lo_cfg = laser_odometry or LaserOdometryConfig()
        #: s, <= 0: the scans' time frame relative to the stamps (``LaserOdometryConfig.time_offset``; applies
        #: to the odometry whether or not the laser odometry runs)
        self.time_offset = lo_cfg.time_offset
        self._lo_config = lo_cfg
        learn = lo_cfg.learn_time_offset and not lo_cfg.time_offset and self.config.use_scans
        self._held: _Held | None = _Held() if learn else None
        #: what the learning found (None until learned, and without learning)
        self.time_offset_estimate: OffsetEstimate | None = None
        self.laser_odometry = (
            LaserOdometry(lo_cfg, self.laser) if self.config.use_scans and lo_cfg.enabled else None
        )
        self._wheel: NDArray[np.float64] | None = None  # latest wheel odometry pose (scan time frame)
        self._raw: deque[tuple[float, NDArray[np.float64]]] = deque()  # recent input, for time_offset
        self.corrections: list[tuple[float, NDArray[np.float64]]] = []  # if config.record_corrections
        self._poses_out: list[tuple[float, NDArray[np.float64]]] = []  # if config.stream_poses
        self._scans_out: list[tuple[float, ScanFields, NDArray[np.float64]]] = []  # if config.stream_poses
        self._queue: list[tuple[float, int, int, Any]] = []
        self._seq = 0
        self._watermark = {ODOM: -math.inf, SCAN: -math.inf, IMAGE: -math.inf}
        self._expected = {
            ODOM,
            *([SCAN] if self.config.use_scans else []),
            *([IMAGE] if self.config.use_images else []),
        }
        self._odom_t: list[float] = []
        self._odom_p: list[NDArray[np.float64]] = []  # poses used (laser-corrected when enabled)
        self._odom_w: list[NDArray[np.float64]] = []  # input (wheel) poses
        self._odom_base = 0  # odometry samples dropped from the front of the log
        self._scans: deque[tuple[float, NDArray[np.float64]]] = deque()
        self._images: deque[tuple[float, NDArray[np.float64] | None]] = deque()
        self._pending: deque[_Pending] = deque()
        self._finished: deque[_Finished] = deque()  # in visit order, waiting for their patches
        self._requests: list[float] = []  # detector firings waiting for the odometry around them
        self._last_visit_k: int | None = None
        self._processed = -math.inf
        self._count = 0
        self._flushing = False  # set by flush(): firings after the last odometry then resolve anyway

    # ------------------------------------------------------------------------------------ input

    def on_odometry(self, stamp: float, pose: Any) -> list[Visit]:
        """One odometry message (x, y, yaw) at ``stamp`` (s)."""
        p = np.asarray(pose, dtype=float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)) or not math.isfinite(stamp):
            self.diagnostics.skip("odometry-non-finite")
            return []
        if max(abs(p[0]), abs(p[1])) > MAX_COORDINATE:
            self.diagnostics.skip("odometry-out-of-range")
            return []
        return self._push(ODOM, float(stamp), p)

    def on_scan(  # noqa: PLR0917 - the LaserScan fields read best positionally
        self,
        stamp: float,
        ranges: Any,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
    ) -> list[Visit]:
        """One laser scan (sensor_msgs/LaserScan fields)."""
        if not math.isfinite(stamp):
            self.diagnostics.skip("scan-bad-stamp")
            return []
        scan = (np.asarray(ranges, dtype=float).reshape(-1), angle_min, angle_increment, range_min, range_max)
        return self._push(SCAN, float(stamp), scan)

    def on_image(self, stamp: float, image: Any) -> list[Visit]:
        """One panorama (H, W) or (H, W, 3), column 0 = robot heading."""
        if not math.isfinite(stamp):
            self.diagnostics.skip("image-bad-stamp")
            return []
        return self._push(IMAGE, float(stamp), image)

    def take_poses(self) -> list[tuple[float, NDArray[np.float64]]]:
        """``(stamp, pose)`` of every odometry sample processed since the last call, in stamp order: the
        odometry the visits' poses are taken from (laser-corrected when enabled), for a map built beside
        the visits (the detector node publishes it). Empty unless ``config.stream_poses``."""
        out, self._poses_out = self._poses_out, []
        return out

    def take_scans(self) -> list[tuple[float, ScanFields, NDArray[np.float64]]]:
        """``(stamp, (ranges, angle_min, angle_increment, range_min, range_max), pose)`` of every scan
        processed since the last call (after the first odometry sample), with the pose of the latest
        odometry sample (:meth:`take_poses`) at or before it. Empty unless ``config.stream_poses``."""
        out, self._scans_out = self._scans_out, []
        return out

    def flush(self) -> list[Visit]:
        """End of data: process everything queued and complete every pending visit."""
        self._flushing = True
        out = self._drain(math.inf)
        if self._held is not None:
            out += self._learn_time_offset()
        if self.detector.flush():
            self._fire(self._processed)
        self._resolve_requests()
        out += self._complete(math.inf)
        return out

    def rewind(self, name: str) -> int:
        """Forget the timeline of the ``"scan"`` or ``"image"`` topic: its messages queued and not yet
        processed are dropped (each counted as ``<name>-off-clock``) and its next message may be stamped
        before the last one received (no ``-stamp-backwards``; one before the stream's position is still
        ``-late``). For a caller that finds the topic's latest messages were on another clock than the
        odometry and that it has come back to the odometry's (the detector node); returns the number
        dropped."""
        topic = {v: k for k, v in TOPIC_NAMES.items() if k != ODOM}.get(name)
        if topic is None:
            msg = f"only the scan and image topics can be rewound, not {name!r}"
            raise ModelError(msg)
        kept = [entry for entry in self._queue if entry[1] != topic]
        dropped = len(self._queue) - len(kept)
        heapq.heapify(kept)
        self._queue = kept
        self._watermark[topic] = -math.inf
        for _ in range(dropped):
            self.diagnostics.skip(f"{name}-off-clock")
        return dropped

    # ------------------------------------------------------------------------------- sequencing

    def _push(self, topic: int, stamp: float, payload: Any) -> list[Visit]:
        name = TOPIC_NAMES[topic]
        self.diagnostics.received[name] += 1
        if stamp < self._watermark[topic]:
            self.diagnostics.skip(f"{name}-stamp-backwards")
            return []
        if stamp < self._processed:
            self.diagnostics.skip(f"{name}-late")  # arrived after the stream had moved past its stamp
            return []
        self._watermark[topic] = stamp
        heapq.heappush(self._queue, (stamp, topic, self._seq, payload))
        self._seq += 1
        return self._drain(self._horizon())

    def _horizon(self) -> float:
        odom = self._watermark[ODOM]
        marks = []
        for topic in self._expected:
            mark = self._watermark[topic]
            if topic != ODOM and odom - mark > self.config.stall_s and mark < odom:
                self.diagnostics.stalled_topics += int(
                    mark == -math.inf or odom - mark <= self.config.stall_s + 1e-9
                )
                mark = odom - self.config.stall_s  # a silent topic stops holding the stream back
            marks.append(mark)
        return min(marks)

    def _drain(self, horizon: float) -> list[Visit]:
        out: list[Visit] = []
        while self._queue and self._queue[0][0] <= horizon:
            stamp, topic, _, payload = heapq.heappop(self._queue)
            self._processed = stamp
            if self._held is None:
                out += self._process(stamp, topic, payload)
            elif self._hold(self._held, stamp, topic, payload) or self._scans_stalled(self._held):
                out += self._learn_time_offset()
        return out

    def _process(self, stamp: float, topic: int, payload: Any) -> list[Visit]:
        if topic == ODOM:
            self._process_odometry(stamp, payload)
        elif topic == SCAN:
            self._process_scan(stamp, payload)
        else:
            self._process_image(stamp, payload)
        return self._complete(stamp)

    # ------------------------------------------------------------------------- learned time offset

    def _hold(self, held: _Held, stamp: float, topic: int, payload: Any) -> bool:
        """Hold one message while the time offset is learned; True once ``learn_scans`` scans are in."""
        held.messages.append((stamp, topic, payload))
        if topic == ODOM:
            held.odom_t.append(stamp)
            held.odom_p.append(payload)
        elif topic == SCAN:
            res = self._scan_points(payload)
            if res is not None:
                held.scan_t.append(stamp)
                held.scan_points.append(res.points)
        return len(held.scan_t) >= self._lo_config.learn_scans

    def _scans_stalled(self, held: _Held) -> bool:
        """The scans fell silent for ``stall_s`` of odometry (or never came): the learning stops with what
        it holds rather than hold the visits back until the end of the data."""
        if not held.odom_t:
            return False
        last = self._watermark[SCAN] if held.scan_t else held.odom_t[0]
        return held.odom_t[-1] - last > self.config.stall_s

    def _learn_time_offset(self) -> list[Visit]:
        """Learn the time offset from the held messages
        (:func:`~ptm_ros.perception.laser_odometry.learn_time_offset`; 0 with fewer than two odometry samples
        or no scan), then process them all with it."""
        held, self._held = self._held, None
        if held is None:
            return []
        if len(held.odom_t) >= 2 and held.scan_t:
            run = RunInput.of(held.odom_t, held.odom_p, held.scan_t, held.scan_points)
            self.time_offset_estimate = learn_time_offset(
                run, self._lo_config, self.laser, workers=self.patches
            )
            self.time_offset = self.time_offset_estimate.offset
        out: list[Visit] = []
        for stamp, topic, payload in held.messages:
            out += self._process(stamp, topic, payload)
        return out

    # ------------------------------------------------------------------------------- processing

    def _fire(self, stamp: float) -> None:
        when = self.detector.last_landmark_stamp
        self._requests.append(float(when) if when is not None else stamp)

    def _process_odometry(self, stamp: float, raw: NDArray[np.float64]) -> None:
        wheel = self._at_scan_time(stamp, raw)
        self._wheel = wheel
        pose = self.laser_odometry.correct(wheel) if self.laser_odometry is not None else wheel
        self._odom_t.append(stamp)
        self._odom_p.append(pose)
        self._odom_w.append(raw)
        if self.config.stream_poses:
            self._poses_out.append((stamp, pose))
        try:
            if self.detector.on_odometry(stamp, pose):
                self._fire(stamp)
        except PtmError:
            self.diagnostics.skip("odometry-rejected-by-detector")
        self._resolve_requests()
        self._track_passages(stamp, pose)

    def _at_scan_time(self, stamp: float, raw: NDArray[np.float64]) -> NDArray[np.float64]:
        """The input odometry ``time_offset`` s from ``stamp`` (interpolated over the recent input; the
        first pose before the input began): the robot's pose in the scans' time frame."""
        offset = self.time_offset
        if not offset:
            return raw
        self._raw.append((stamp, raw))
        while len(self._raw) > 2 and self._raw[1][0] <= stamp + offset:
            self._raw.popleft()
        t = [q for q, _ in self._raw]
        return interpolate_poses(t, [w for _, w in self._raw], stamp + offset)[0]

    def _scan_points(self, scan: ScanFields) -> ScanPoints | None:
        """The scan's points (robot frame) within the laser's ``max_range``; None when malformed."""
        return usable_points(*scan, self.laser)

    def _process_scan(self, stamp: float, scan: ScanFields) -> None:
        ranges, amin, ainc, rmin, rmax = scan
        res = self._scan_points(scan)
        if res is None:
            self.diagnostics.skip("scan-malformed")
            return
        self.diagnostics.scan_beams_dropped += res.dropped
        if self.laser_odometry is not None and self._wheel is not None:
            self.laser_odometry.on_scan(self._wheel, res.points, stamp)
            self.diagnostics.laser_odometry = dict(vars(self.laser_odometry.counters))  # flat ints
            if self.config.record_corrections:
                self.corrections.append((stamp, self.laser_odometry.correction))
        if self.config.stream_poses and self._odom_p:  # posed as the latest odometry sample (streamed)
            self._scans_out.append((stamp, scan, self._odom_p[-1]))
        if self.config.use_scans:
            self._scans.append((stamp, res.points))
        try:
            if self.detector.on_scan(
                stamp, ranges, angle_min=amin, angle_increment=ainc, range_min=rmin, range_max=rmax
            ):
                self._fire(stamp)
        except PtmError:
            self.diagnostics.skip("scan-rejected-by-detector")
        self._resolve_requests()

    def _process_image(self, stamp: float, image: Any) -> None:
        sig = None
        try:
            sig = panorama_signature(image, self.appearance)
        except PtmError:
            self.diagnostics.skip("image-undecodable")
        if self.config.use_images and sig is not None:
            self._images.append((stamp, sig))
        try:
            if self.detector.on_image(stamp, image):
                self._fire(stamp)
        except PtmError:
            self.diagnostics.skip("image-rejected-by-detector")
        self._resolve_requests()

    def _resolve_requests(self) -> None:
        """Snap detector firings to the nearest odometry sample once the odometry around them is known."""
        while self._requests and self._odom_t:
            when = self._requests[0]
            if self._odom_t[-1] < when and not self._flushing:
                return  # the odometry sample after the firing is not known yet
            t = np.asarray(self._odom_t)
            k = int(np.argmin(np.abs(t - when)))
            self._requests.pop(0)
            k_abs = k + self._odom_base
            if self._last_visit_k is not None and k_abs <= self._last_visit_k:
                self.diagnostics.skip("landmark-at-same-odometry-sample")
                continue
            self._open_visit(k)

    def _open_visit(self, k: int) -> None:
        t = self._odom_t
        p = self._odom_p
        prev = None if self._last_visit_k is None else self._last_visit_k - self._odom_base
        travel = rotation = 0.0
        if prev is not None:
            lo = max(prev, 0)
            seg = np.asarray(p[lo : k + 1])
            travel = float(np.sum(np.hypot(np.diff(seg[:, 0]), np.diff(seg[:, 1])))) if len(seg) > 1 else 0.0
            rotation = float(np.sum(np.abs(wrap_angle(np.diff(seg[:, 2]))))) if len(seg) > 1 else 0.0
        pose = p[k]
        first = k
        limit = t[k] - self.config.max_passage_s
        while first > 0 and t[first - 1] >= limit and self._inside(p[first - 1], pose):
            first -= 1
        pending = _Pending(
            k=k + self._odom_base,
            stamp=t[k],
            pose=pose,
            travel=travel,
            rotation=rotation,
            first_in=t[max(first - 1, 0)],
            wheel=None if self.laser_odometry is None and not self.time_offset else self._odom_w[k],
        )
        # the passage may already be over if odometry after k is known
        for j in range(k + 1, len(t)):
            if not self._inside(p[j], pose) or t[j] - t[k] > self.config.max_passage_s:
                pending.exit_stamp = t[j]
                break
        self._pending.append(pending)
        self._last_visit_k = k + self._odom_base

    def _inside(self, a: NDArray[np.float64], centre: NDArray[np.float64]) -> bool:
        return math.hypot(a[0] - centre[0], a[1] - centre[1]) <= self.laser.patch_radius

    def _track_passages(self, stamp: float, pose: NDArray[np.float64]) -> None:
        for v in self._pending:
            left = not self._inside(pose, v.pose) or stamp - v.stamp > self.config.max_passage_s
            if v.exit_stamp is None and stamp > v.stamp and left:
                v.exit_stamp = stamp

    def _complete(self, processed: float) -> list[Visit]:
        while self._pending:
            v = self._pending[0]
            exit_stamp = (
                v.exit_stamp if v.exit_stamp is not None else (math.inf if processed < math.inf else v.stamp)
            )
            if processed < math.inf and (
                processed < exit_stamp or processed < v.stamp + self.config.image_max_dt
            ):
                break
            self._pending.popleft()
            try:
                self._finished.append(self._finish(v))
            except ModelError:
                self.diagnostics.skip("visit-invalid")
        self._prune()
        out: list[Visit] = []
        while self._finished and (processed == math.inf or _ready(self._finished[0].patch)):
            try:
                out.append(self._emit(self._finished.popleft()))
            except ModelError:  # e.g. a travel beyond visits.MAX_TRAVEL: no odometry
                self.diagnostics.skip("visit-invalid")
        return out

    def _finish(self, v: _Pending) -> _Finished:
        """Everything of visit ``v`` that needs the buffers as they are now; the patch maybe on its way."""
        patch = self._patch(v) if self.config.use_scans and self._scans else None
        signature = spread = None
        if self.config.use_images and self._images:
            stamps = np.array([s for s, _ in self._images])
            j = int(np.argmin(np.abs(stamps - v.stamp)))
            if abs(stamps[j] - v.stamp) <= self.config.image_max_dt:
                signature = self._images[j][1]
                spread = self._signature_spread(stamps, j)
        return _Finished(v, patch, signature, spread)

    def _patch(self, v: _Pending) -> FloatArray | Future[FloatArray] | None:
        """The patch of visit ``v`` (:func:`~ptm_ros.perception.patches.passage_patch` of its passage), built
        here or submitted to :attr:`patches`."""
        stamps = np.array([s for s, _ in self._scans])
        poses = interpolate_poses(self._odom_t, self._odom_p, stamps)
        try:
            sl = passage_slice(stamps, poses, v.stamp, v.pose, self.laser.patch_radius)
        except PtmError:
            self.diagnostics.skip("patch-failed")
            return None
        scans = [pts for _, pts in list(self._scans)[sl]]
        if self.patches is not None:
            return self.patches.submit(
                passage_patch, scans, stamps[sl], poses[sl], v.stamp, v.pose, config=self.laser
            )
        return self._built(
            lambda: passage_patch(scans, stamps[sl], poses[sl], v.stamp, v.pose, config=self.laser)
        )

    def _built(self, build: Callable[[], FloatArray]) -> FloatArray | None:
        """A patch, None (counted) when it cannot be built or has too few points."""
        try:
            patch = build()
        except PtmError:
            self.diagnostics.skip("patch-failed")
            return None
        return patch if len(patch) >= self.laser.min_points else None

    def _emit(self, f: _Finished) -> Visit:
        v, patch = f.pending, f.patch
        if isinstance(patch, Future):
            patch = self._built(patch.result)
        self.diagnostics.visits_without_patch += int(self.config.use_scans and patch is None)
        self.diagnostics.visits_without_panorama += int(self.config.use_images and f.signature is None)
        visit = Visit(
            index=self._count,
            stamp=v.stamp,
            pose=(float(v.pose[0]), float(v.pose[1]), float(v.pose[2])),
            travel=v.travel,
            rotation=v.rotation,
            signature=f.signature,
            patch=patch,
            odom_pose=None if v.wheel is None else (float(v.wheel[0]), float(v.wheel[1]), float(v.wheel[2])),
            signature_spread=f.spread,
        )
        self._count += 1
        self.diagnostics.visits += 1
        return visit

    def _signature_spread(self, stamps: NDArray[np.float64], j: int) -> NDArray[np.float64] | None:
        """``½ (s_j - s_k)²`` per component, ``k`` the buffered panorama whose odometry position lies
        nearest to ``spread_distance`` from panorama ``j``'s (within a factor 2 of it); None without one."""
        target = self.config.spread_distance
        sig_j = self._images[j][1]
        if target <= 0.0 or sig_j is None or len(stamps) < 2 or len(self._odom_t) < 2:
            return None
        xy = interpolate_poses(self._odom_t, self._odom_p, stamps)[:, :2]
        dist = np.hypot(*(xy - xy[j]).T)
        ok = (dist >= 0.5 * target) & (dist <= 2.0 * target)
        ok &= np.array([sig is not None and sig.shape == sig_j.shape for _, sig in self._images])
        if not ok.any():
            return None
        k = int(np.argmin(np.where(ok, np.abs(dist - target), np.inf)))
        sig_k = self._images[k][1]
        assert sig_k is not None  # selected above
        return 0.5 * (sig_j - sig_k) ** 2

    def _prune(self) -> None:
        """Drop data no pending or future visit can need (bounded memory on long runs)."""
        if not self._odom_t:
            return
        now = self._odom_t[-1]
        keep_from = now - self.config.max_passage_s - 1.0
        if self._pending:
            keep_from = min(keep_from, self._pending[0].first_in)
        if self._last_visit_k is not None:
            # travel since the last visit is computed from the odometry log
            last_t = self._odom_t[max(self._last_visit_k - self._odom_base, 0)]
            keep_from = min(keep_from, last_t)
        drop = 0
        while drop < len(self._odom_t) - 2 and self._odom_t[drop + 1] < keep_from:
            drop += 1
        if drop:
            del self._odom_t[:drop]
            del self._odom_p[:drop]
            del self._odom_w[:drop]
            self._odom_base += drop
        while self._scans and self._scans[0][0] < keep_from:
            self._scans.popleft()
        image_from = min(keep_from, now - 2 * self.config.image_max_dt)
        while len(self._images) > 1 and self._images[0][0] < image_from - self.config.image_max_dt:
            self._images.popleft()


# ------------------------------------------------------------------------------------ visit codec


def _encode(a: NDArray[Any]) -> dict[str, Any]:
    arr = np.ascontiguousarray(a)
    return {
        "dtype": arr.dtype.str,
        "shape": list(arr.shape),
        "data": base64.b64encode(arr.tobytes()).decode(),
    }


def _decode(d: dict[str, Any], dtype: type[np.generic], /) -> NDArray[Any]:
    """An array as :func:`_encode` wrote it, in the dtype it was sent in (not ``dtype``, the field's own)."""
    try:
        arr = np.frombuffer(base64.b64decode(d["data"], validate=True), dtype=np.dtype(d["dtype"]))
        return arr.reshape(d["shape"]).copy()
    except (KeyError, TypeError, ValueError) as err:
        msg = f"malformed array in visit JSON: {err}"
        raise DataError(msg) from err


def visit_to_json(visit: Visit) -> str:
    """The lossless JSON form of a visit (schema ``ptm_ros.visit/1``; arrays base64 in native dtype)."""
    return json.dumps({"schema": VISIT_SCHEMA, **visit_fields(visit, _encode)})


def visit_from_json(text: str) -> Visit:
    """Parse :func:`visit_to_json` output (any array may be left out: None); malformed input raises
    :class:`DataError`."""
    try:
        d = json.loads(text)
    except json.JSONDecodeError as err:
        msg = f"visit message is not JSON: {err}"
        raise DataError(msg) from err
    if not isinstance(d, dict) or d.get("schema") != VISIT_SCHEMA:
        msg = f"visit message schema must be {VISIT_SCHEMA!r}"
        raise DataError(msg)
    try:
        return visit_from_fields(d, _decode, arrays_optional=True)
    except (KeyError, TypeError, ValueError, PtmError) as err:
        msg = f"malformed visit message: {err}"
        raise DataError(msg) from err


def diagnostics_dict(diag: ExtractorDiagnostics) -> dict[str, Any]:
    """Plain-dict counters (for ptm.json and /diagnostics)."""
    return asdict(diag)


#: Key of ptm.json's ``diagnostics`` holding the input messages skipped before the extractor saw them.
INPUT_SKIPPED_KEY = "read_skipped"


def with_input_skips(extractor: Mapping[str, Any], skipped: Mapping[str, int]) -> dict[str, Any]:
    """ptm.json's ``diagnostics`` of a run's input: the extractor's counters (:func:`diagnostics_dict`) with
    the messages skipped before it (``skipped``, by reason: ``ptm-run``'s bag reader, the landmark detector
    node's input checks, :mod:`ptm_ros.io.validation`) added to its ``skipped`` and kept apart under
    :data:`INPUT_SKIPPED_KEY` (their share). Reasons counted 0 are left out."""
    before = {str(k): int(v) for k, v in skipped.items() if v}
    total = {str(k): int(v) for k, v in dict(extractor.get("skipped") or {}).items()}
    for reason, n in before.items():
        total[reason] = total.get(reason, 0) + n
    return {**extractor, "skipped": total, INPUT_SKIPPED_KEY: before}


def landmark_accounting(visits: int, skipped: Mapping[str, int], declared: int | None = None) -> str | None:
    """One sentence reconciling the landmarks a detector declared with the ``visits`` they became, naming
    the landmarks dropped by reason (:data:`LANDMARK_DROPS` in ``skipped``, the extractor's counters);
    None when every declared landmark became a visit. ``declared`` (e.g. the surprise trace's landmarks)
    defaults to the visits plus the drops; a difference the drops do not explain is named as such."""
    drops = {r: int(skipped.get(r, 0)) for r in LANDMARK_DROPS if skipped.get(r, 0)}
    dropped = sum(drops.values())
    total = visits + dropped if declared is None else max(int(declared), visits + dropped)
    if total == visits and not dropped:
        return None
    parts = [f"{n} {LANDMARK_DROPS[r]} ({r})" for r, n in drops.items()]
    unexplained = total - visits - dropped
    if unexplained:
        parts.append(f"{unexplained} for no recorded reason")
    return (
        f"the detector declared {total} landmarks and {visits} became visits: "
        f"{total - visits} dropped ({'; '.join(parts)})"
    )


ExtractorFactory = Callable[[], VisitExtractor]
