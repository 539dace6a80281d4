"""Which input messages are usable: one check per message kind, shared by the bag reader and the nodes.

:func:`ptm_ros.io.bag.read_run` (``ptm-run``, ``ptm-eval``, ``ptm-calibrate``) and the landmark detector
and map publisher nodes read odometry, scans and panoramas through these functions, so that a message one
of them skips the others skip too, under the same name (the reasons of the landmark detector's module
docstring). Each returns the usable content or a :data:`Rejection` ``(reason, detail)``, never raises on
bad content.

Stamp order differs by nature between the two paths. A node sees one message at a time and holds stamp
jumps until later messages confirm them (:class:`ptm_ros.nodes.stream_guard.StreamGuard`). A bag is read
whole, so :func:`stamp_order` keeps, per topic, the longest run of messages whose stamps increase
strictly (in log order) and skips the others: a stretch stamped back in time, a lone message stamped
ahead, a repeated stamp. Every skip is counted by its reason: ``<topic>-duplicate`` (the stamp of the
kept message before it), ``<topic>-stamp-backwards`` (earlier than it), ``<topic>-outlier`` (later than
the kept message after it).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import PtmError
from ptm_ros.io.bag import NS_PER_S, decode_image, ns_to_stamp, quaternion_to_yaw

if TYPE_CHECKING:
    from ptm_ros.model.appearance import AppearanceConfig

Rejection = tuple[str, str]  # (reason, detail)
ScanPayload = tuple[NDArray[np.float32], float, float, float, float]

MAX_POSITION = 1e7  # m: odometry farther from its origin is not a position
QUATERNION_TOLERANCE = 1e-3  # |‖q‖ − 1| above this: normalised before decoding the yaw


def header_stamp_ns(header: Any) -> int | None:
    """A header's stamp in integer nanoseconds, or None when it is no ROS time (``sec < 0`` or
    ``nanosec >= 10⁹``)."""
    sec, nanosec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < NS_PER_S:
        return None
    return sec * NS_PER_S + nanosec


def valid_stamp(header: Any) -> float | None:
    """A message header's stamp in seconds, or None when it is no ROS time (:func:`header_stamp_ns`)."""
    ns = header_stamp_ns(header)
    return None if ns is None else ns_to_stamp(ns)


def odometry_xy_yaw(msg: Any) -> tuple[float, float, float]:
    """``(x, y, yaw)`` of a ``nav_msgs/Odometry`` as :func:`ptm_ros.io.bag.read_run` decodes it, bit for
    bit (non-finite values passed through, for the caller to count)."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return float(p.x), float(p.y), quaternion_to_yaw(q.x, q.y, q.z, q.w)


def odometry_pose(msg: Any) -> tuple[NDArray[np.float64] | None, Rejection | None, bool]:
    """``(pose, None, normalised)`` of a valid Odometry message, else ``(None, (reason, detail), False)``:
    ``odometry-non-finite``, ``odometry-out-of-range`` (beyond :data:`MAX_POSITION`) or
    ``odometry-bad-quaternion`` (non-finite or zero norm).

    The yaw is :func:`ptm_ros.io.bag.quaternion_to_yaw` of the orientation, bit for bit; an orientation
    whose norm is off 1 by more than :data:`QUATERNION_TOLERANCE` is normalised first (``normalised``).
    """
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    x, y = float(p.x), float(p.y)
    if not (math.isfinite(x) and math.isfinite(y)):
        return None, ("odometry-non-finite", f"position ({x}, {y})"), False
    if abs(x) > MAX_POSITION or abs(y) > MAX_POSITION:
        detail = f"position ({x:.6g}, {y:.6g}) beyond {MAX_POSITION:g} m"
        return None, ("odometry-out-of-range", detail), False
    quat = (float(q.x), float(q.y), float(q.z), float(q.w))
    norm = math.sqrt(math.fsum(c * c for c in quat)) if all(map(math.isfinite, quat)) else math.nan
    if not (math.isfinite(norm) and norm > 1e-9):
        return None, ("odometry-bad-quaternion", f"orientation {quat} (norm {norm})"), False
    normalised = abs(norm - 1.0) > QUATERNION_TOLERANCE
    if normalised:
        quat = (quat[0] / norm, quat[1] / norm, quat[2] / norm, quat[3] / norm)
    return np.array([x, y, quaternion_to_yaw(*quat)]), None, normalised


def scan_payload(msg: Any) -> tuple[ScanPayload | None, Rejection | None]:
    """``((ranges, angle_min, angle_increment, range_min, range_max), None)`` of a usable LaserScan, else
    ``(None, (reason, detail))``: ``scan-empty`` (no ranges), ``scan-non-finite`` (not one finite range:
    NaN- or inf-filled), ``scan-malformed`` (non-finite angles, a zero increment with several beams, not
    ``0 <= range_min < range_max``) or ``scan-length-mismatch`` (the angles imply a beam count more than
    one off the ranges'). Single non-finite or out-of-range beams are no reason: the extractor drops
    them and counts them (``scan_beams_dropped``)."""
    ranges = np.asarray(msg.ranges, dtype=np.float32).reshape(-1)
    n = ranges.size
    if n == 0:
        return None, ("scan-empty", "a scan without ranges")
    if not np.any(np.isfinite(ranges)):
        return None, ("scan-non-finite", f"none of {n} ranges is finite")
    amin, amax, ainc = float(msg.angle_min), float(msg.angle_max), float(msg.angle_increment)
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    if not (math.isfinite(amin) and math.isfinite(amax) and math.isfinite(ainc)):
        return None, ("scan-malformed", f"angles min {amin}, max {amax}, increment {ainc}")
    if ainc == 0.0 and n > 1:
        return None, ("scan-malformed", f"angle_increment 0 with {n} beams")
    if not (math.isfinite(rmin) and rmin >= 0.0 and rmax > rmin):
        return None, ("scan-malformed", f"need 0 <= range_min < range_max, got {rmin}, {rmax}")
    if n > 1:
        beams = (amax - amin) / ainc + 1.0
        if not abs(beams - n) <= 1.0 + 1e-6:
            return None, ("scan-length-mismatch", f"angles imply {beams:.6g} beams, ranges has {n}")
    return (ranges, amin, ainc, rmin, rmax), None


def image_payload(
    msg: Any, appearance: AppearanceConfig | None = None
) -> tuple[NDArray[Any] | None, Rejection | None]:
    """``(pixels, None)`` of a usable panorama, else ``(None, (reason, detail))``:
    ``image-unsupported-encoding`` (outside :data:`ptm_ros.io.bag.IMAGE_ENCODINGS`), ``image-malformed``
    (``step`` shorter than a row, ``data`` shorter than ``height·step``), ``image-too-small`` (narrower
    than ``2·n_coeffs`` or fewer rows than ``bands`` of ``appearance``; no size check without it)."""
    try:
        image = decode_image(msg)
    except (PtmError, ValueError) as err:
        return None, ("image-malformed", str(err))
    if image is None:
        return None, ("image-unsupported-encoding", f"encoding {msg.encoding!r}")
    h, w = image.shape[:2]
    if appearance is not None and (w < 2 * appearance.n_coeffs or h < appearance.bands):
        need = f"{appearance.bands} x {2 * appearance.n_coeffs}"
        return None, ("image-too-small", f"panorama {h} x {w} (need at least {need})")
    return image, None


def stamp_order(stamps_ns: Sequence[int]) -> tuple[list[int], list[str]]:
    """The messages of one topic to keep (stamps in log order): the longest subsequence of strictly
    increasing stamps, the earliest messages among equally long ones (a message stamped back is
    dropped, not the one before it; a repeated stamp drops the repeat), and for each skipped message its
    reason suffix: ``duplicate``, ``stamp-backwards`` or ``outlier`` (module docstring). ``O(n log n)``.

    Returns:
        ``(kept, reasons)``: the indices kept, increasing; one reason per skipped index, in index order.
    """
    n = len(stamps_ns)
    # longest[i]: the longest strictly increasing run starting at message i (patience sorting, backwards)
    longest = [0] * n
    tails: list[int] = []  # tails[k]: the largest negated stamp starting a run of length k + 1 (sorted)
    for i in range(n - 1, -1, -1):
        v = -stamps_ns[i]
        k = bisect.bisect_left(tails, v)
        if k == len(tails):
            tails.append(v)
        else:
            tails[k] = v
        longest[i] = k + 1
    kept: list[int] = []
    need = len(tails)
    for i in range(n):  # greedy: the first message that still starts a run of the length needed
        if need and longest[i] == need and (not kept or stamps_ns[i] > stamps_ns[kept[-1]]):
            kept.append(i)
            need -= 1
    reasons: list[str] = []
    j = 0  # kept[j] is the first kept index after the current one
    for i in range(n):
        if j < len(kept) and kept[j] == i:
            j += 1
            continue
        prev = stamps_ns[kept[j - 1]] if j else None
        if prev is not None and stamps_ns[i] == prev:
            reasons.append("duplicate")
        elif prev is not None and stamps_ns[i] < prev:
            reasons.append("stamp-backwards")
        else:
            reasons.append("outlier")
    return kept, reasons
