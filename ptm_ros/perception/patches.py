"""Scans and the visits' local map patches: the scan measurement of a visit (thesis Ch. 3.10.4, Fig. 48).

The scan measurement ``s_n`` of visit ``n`` is a *local map patch*: the laser scans taken while the robot
passes through the landmark's neighbourhood, concatenated in the frame of the visit (Fig. 48).
:mod:`ptm_ros.perception.laser` registers two patches into a relative-pose measurement.

* :func:`scan_to_points` — one ``LaserScan`` to 2-D points in the sensor frame (:func:`usable_points`:
  the beams within ``LaserConfig.max_range``);
* :func:`passage_patch` (offline) or :class:`PatchBuilder` (online, same result) — the patch of a visit:
  the scans of one passage within ``patch_radius`` (:func:`passage_slice`), thinned to
  :func:`keyframes`, their odometry corrected by scan-to-map ICP (:func:`refine_scan_poses`; the
  thesis concatenates by odometry, which on the Intel log bends a 6 m passage by several degrees),
  concatenated in the visit frame and voxel-downsampled deterministically. :func:`build_patch` is the
  plain odometry concatenation;
* :class:`ScanMap` / :func:`align_scan_to_map` — one scan aligned onto a local map (kiss-icp, then the
  point-to-plane polish of :mod:`ptm_ros.perception.laser`), also used by
  :mod:`ptm_ros.perception.laser_odometry`.

The parameters are :class:`~ptm_ros.perception.laser.LaserConfig`'s. This module imports
:mod:`ptm_ros.perception.laser` (the configuration, ``voxel_downsample`` and the ICP helpers), never the
reverse. kiss-icp is imported lazily inside the functions that run ICP, as there.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ConfigError, ModelError, PtmError
from ptm_ros.model.geometry import FloatArray, between, compose, inverse, moved, transform_points
from ptm_ros.perception.laser import (
    _IDENTITY,
    LaserConfig,
    _align,
    _as_points,
    _as_pose,
    _keep_guess_along,
    _lift,
    _Overlap,
    _point_to_plane,
    _PointAligner,
    _Target,
    voxel_downsample,
    weak_directions,
)

__all__ = [
    "PatchBuilder",
    "ScanMap",
    "ScanPoints",
    "align_scan_to_map",
    "build_patch",
    "keyframes",
    "passage_patch",
    "passage_slice",
    "refine_scan_poses",
    "scan_to_points",
    "usable_points",
]


_MIN_SCAN_POINTS = 10  # fewer points than this: a scan keeps its odometry pose in refine_scan_poses
_MAX_STEP_CORRECTION = (0.5, 0.2)  # (m, rad): larger ICP corrections of one odometry step are rejected
_STEP_PRIOR_STD = np.array([0.1, 0.1, 0.05])  # m, m, rad: trust in kiss-icp along unseen directions


# ------------------------------------------------------------------------------------------ scans


@dataclass(frozen=True)
class ScanPoints:
    """The usable beams of one scan: ``points`` ``(P, 2)`` in the sensor frame, ``dropped`` beams."""

    points: FloatArray
    dropped: int


def scan_to_points(
    ranges: ArrayLike,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    *,
    angle_max: float | None = None,
) -> ScanPoints:
    """Convert a ``LaserScan``'s ranges to points; beam ``k`` points at ``angle_min + k·angle_increment``.

    Beams that are NaN, infinite, shorter than ``range_min`` or longer than ``range_max`` are dropped
    (sensor_msgs/LaserScan: values outside ``[range_min, range_max]`` are discarded). ``angle_max``,
    when given, must agree with the beam count to within one beam (drivers differ on the last beam).
    Empty ``ranges`` give 0 points.
    """
    r = np.asarray(ranges, dtype=float)
    if r.ndim != 1:
        msg = f"ranges must be 1-D, got shape {r.shape}"
        raise ModelError(msg)
    for name, value in (("angle_min", angle_min), ("angle_increment", angle_increment)):
        if not math.isfinite(value):
            msg = f"{name} must be finite, got {value}"
            raise ModelError(msg)
    if not (math.isfinite(range_min) and range_min >= 0.0 and range_max > range_min):
        msg = f"need 0 <= range_min < range_max, got range_min={range_min}, range_max={range_max}"
        raise ModelError(msg)
    n = len(r)
    if angle_increment == 0.0 and n > 1:
        msg = f"angle_increment is 0 but the scan has {n} beams"
        raise ModelError(msg)
    if angle_max is not None and n > 0:
        if not math.isfinite(angle_max):
            msg = f"angle_max must be finite, got {angle_max}"
            raise ModelError(msg)
        if angle_increment != 0.0:
            span = (angle_max - angle_min) / angle_increment
            if span < -1e-6:
                msg = (
                    f"angle_min={angle_min}, angle_max={angle_max}, angle_increment={angle_increment} "
                    f"imply a negative beam count ({span:.3f})"
                )
                raise ModelError(msg)
            if abs(span + 1.0 - n) > 1.0 + 1e-6:
                msg = f"angle_min/angle_max/angle_increment imply {span + 1.0:.1f} beams, got {n}"
                raise ModelError(msg)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(r) & (r >= range_min) & (r <= range_max)
    angles = angle_min + angle_increment * np.flatnonzero(keep)
    rk = r[keep]
    points = np.column_stack([rk * np.cos(angles), rk * np.sin(angles)]).reshape(-1, 2)
    return ScanPoints(points=points, dropped=int(n - keep.sum()))


def usable_points(  # noqa: PLR0917 - the LaserScan fields read best positionally
    ranges: ArrayLike,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    laser: LaserConfig,
) -> ScanPoints | None:
    """:func:`scan_to_points` with the beams beyond ``laser.max_range`` dropped, None for a malformed
    scan: the points the laser odometry and the patches use."""
    try:
        return scan_to_points(ranges, angle_min, angle_increment, range_min, min(range_max, laser.max_range))
    except PtmError:
        return None


# ---------------------------------------------------------------------------------------- patches


def passage_slice(
    scan_stamps: ArrayLike, scan_poses: ArrayLike, visit_stamp: float, visit_pose: ArrayLike, radius: float
) -> slice:
    """The scans of one passage through a visit: the longest run of consecutive scans within ``radius``
    of ``visit_pose`` that contains the scan nearest in time to ``visit_stamp`` (empty if that scan is
    outside the radius). Other passages through the same place are left out, so two visits of one
    place never share scans.
    """
    stamps = np.asarray(scan_stamps, dtype=float).reshape(-1)
    poses = _as_poses(scan_poses, "scan_poses")
    if len(stamps) != len(poses):
        msg = f"{len(stamps)} scan stamps but {len(poses)} scan poses"
        raise ModelError(msg)
    _check_positive(radius=radius)
    if len(stamps) == 0:
        return slice(0, 0)
    inside = _within(poses, _as_pose(visit_pose, "visit_pose"), radius)
    centre = int(np.argmin(np.abs(stamps - visit_stamp)))
    if not inside[centre]:
        return slice(centre, centre)
    lo = centre
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    hi = centre + 1
    while hi < len(inside) and inside[hi]:
        hi += 1
    return slice(lo, hi)


def build_patch(
    scans_points: Sequence[ArrayLike],
    scan_poses: ArrayLike,
    visit_pose: ArrayLike,
    radius: float,
    voxel: float,
    *,
    sensor_offset: ArrayLike | None = None,
) -> FloatArray:
    """The local map patch of a visit (Fig. 48) from odometry alone: points ``(P, 2)`` in the visit frame.

    Scans ``scans_points[k]`` (sensor frame) taken at robot odometry poses ``scan_poses[k]`` within
    ``radius`` of ``visit_pose`` are moved into the visit frame, ``visit_pose ⊖ (scan_pose ⊕
    sensor_offset)``, concatenated in order and voxel-downsampled (:func:`voxel_downsample`). Pass the
    scans of one passage (:func:`passage_slice`); :func:`passage_patch` also corrects the odometry.
    """
    poses = _as_poses(scan_poses, "scan_poses")
    if len(scans_points) != len(poses):
        msg = f"{len(scans_points)} scans but {len(poses)} scan poses"
        raise ModelError(msg)
    _check_positive(radius=radius, voxel=voxel)
    visit = _as_pose(visit_pose, "visit_pose")
    offset = _offset(sensor_offset)
    inside = np.flatnonzero(_within(poses, visit, radius))
    scans = [_as_points(scans_points[int(k)], f"scans_points[{k}]") for k in inside]
    return _concatenate(scans, poses[inside], visit, offset, voxel)


def keyframes(scan_poses: ArrayLike, min_xy: float, min_yaw: float) -> NDArray[np.intp]:
    """Indices of the scans kept for a patch: the first, then each that moved at least ``min_xy`` or turned
    at least ``min_yaw`` since the last kept one (bounds a patch's memory while the robot stands still)."""
    poses = _as_poses(scan_poses, "scan_poses")
    kept: list[int] = []
    for k in range(len(poses)):
        if not kept or moved(poses[kept[-1]], poses[k], min_xy, min_yaw):
            kept.append(k)
    return np.array(kept, dtype=np.intp)


def refine_scan_poses(
    scans_points: Sequence[ArrayLike],
    scan_poses: ArrayLike,
    config: LaserConfig | None = None,
    *,
    sensor_offset: ArrayLike | None = None,
) -> FloatArray:
    """Correct the odometry along one passage by scan-to-map ICP (kiss-icp): robot poses ``(S, 3)``.

    The first scan keeps its odometry pose and seeds a voxel map; each next scan starts from the
    previous corrected pose plus the odometry increment, is aligned to the map (kiss-icp, then
    point-to-plane Gauss–Newton against the map points) and added to it. A
    correction larger than 0.5 m or 0.2 rad over the odometry increment, or a scan with fewer than 10
    points, falls back to odometry. The thesis concatenates scans by odometry (Fig. 48); on real logs
    (Intel) the rotational odometry drift over a 6 m passage distorts patches by several degrees.
    """
    cfg = LaserConfig() if config is None else config
    poses = _as_poses(scan_poses, "scan_poses")
    if len(scans_points) != len(poses):
        msg = f"{len(scans_points)} scans but {len(poses)} scan poses"
        raise ModelError(msg)
    if len(poses) == 0:
        return poses
    offset = _offset(sensor_offset)
    scans = [_as_points(p, f"scans_points[{k}]") for k, p in enumerate(scans_points)]

    from kiss_icp.mapping import VoxelHashMap
    from kiss_icp.registration import Registration as KissRegistration

    icp = KissRegistration(
        max_num_iterations=cfg.max_iterations, convergence_criterion=1e-4, max_num_threads=1
    )
    extent = cfg.max_range + cfg.patch_radius  # only points added with update() are culled by it
    voxel_map = VoxelHashMap(voxel_size=cfg.voxel, max_distance=extent, max_points_per_voxel=20)
    sensor = compose(poses, offset)
    refined = sensor.copy()
    map_points = np.empty((0, 2))
    for k, pts in enumerate(scans):
        if k > 0:
            guess = compose(refined[k - 1], between(sensor[k - 1], sensor[k]))
            refined[k] = guess
            aligned = _polished_alignment(
                icp, pts, voxel_map, map_points, guess, cfg, cfg.voxel, cfg.correspondence_distance
            )
            if aligned is not None and not moved(guess, aligned.pose, *_MAX_STEP_CORRECTION):
                refined[k] = aligned.pose
        world = transform_points(refined[k], pts)
        voxel_map.add_points(_lift(voxel_downsample(world, 0.5 * cfg.voxel)))
        map_points = voxel_downsample(np.vstack([map_points, world]), cfg.patch_voxel)
    return compose(refined, inverse(offset))


class Alignment(NamedTuple):
    """A scan's aligned world pose, and how many translation directions kept the guess there
    (:func:`weak_directions`; 0 without the polish or with ``degenerate_ratio`` 0)."""

    pose: FloatArray
    weak: int


class ScanMap:
    """A local map (world-frame points) prepared once for many scan alignments: kiss-icp voxel map,
    target points at ``patch_voxel`` with their KD-tree and normals. (Used by
    :mod:`ptm_ros.perception.laser_odometry`, rebuilt when a keyframe joins the map.)"""

    def __init__(
        self, map_points: ArrayLike, config: LaserConfig | None = None, *, voxel: float | None = None
    ):
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration as KissRegistration

        self.config = LaserConfig() if config is None else config
        self.voxel = self.config.voxel if voxel is None else float(voxel)
        pts = _as_points(map_points, "map_points")
        self.n_points = len(voxel_downsample(pts, self.voxel))
        self._icp = KissRegistration(
            max_num_iterations=self.config.max_iterations, convergence_criterion=1e-4, max_num_threads=1
        )
        self._voxel_map = VoxelHashMap(voxel_size=self.voxel, max_distance=1e6, max_points_per_voxel=20)
        self._voxel_map.add_points(_lift(voxel_downsample(pts, 0.5 * self.voxel)))
        self._target = _Target(voxel_downsample(pts, self.config.patch_voxel), 0.5 * self.voxel)

    def align(
        self,
        points: ArrayLike,
        guess: ArrayLike,
        *,
        correspondence_distance: float | None = None,
        refine: bool = True,
        min_points: int = _MIN_SCAN_POINTS,
        degenerate_ratio: float = 0.0,
    ) -> Alignment | None:
        """The world pose of a scan (``points`` in the robot frame) aligned onto the map from ``guess``:
        kiss-icp point-to-point, then (``refine``) the point-to-plane polish of :func:`register_patches`
        with the guess kept along the directions the scan hardly constrains (``degenerate_ratio``,
        :func:`keep_unobserved`). None when the scan or the map has fewer than ``min_points`` points after
        downsampling, or ICP diverged."""
        cfg = self.config
        if self.n_points < min_points:
            return None
        dist = (
            cfg.correspondence_distance if correspondence_distance is None else float(correspondence_distance)
        )
        return _polished_alignment(
            self._icp,
            _as_points(points, "points"),
            self._voxel_map,
            self._target.pts,
            _as_pose(guess, "guess"),
            cfg,
            self.voxel,
            dist,
            refine=refine,
            min_points=min_points,
            target=self._target,
            degenerate_ratio=degenerate_ratio,
        )

    def inlier_fraction(self, points: ArrayLike, pose: ArrayLike) -> float:
        """Fraction of a scan's points (robot frame, downsampled at half the voxel) within
        ``inlier_distance`` of the map when the scan is placed at ``pose``."""
        src = voxel_downsample(_as_points(points, "points"), 0.5 * self.voxel)
        if len(src) == 0 or len(self._target.pts) == 0:
            return 0.0
        dist, _ = self._target.tree.query(transform_points(_as_pose(pose, "pose"), src))
        return float(np.mean(dist <= self.config.inlier_distance))


def align_scan_to_map(
    points: ArrayLike,
    map_points: ArrayLike,
    guess: ArrayLike,
    config: LaserConfig | None = None,
    *,
    voxel: float | None = None,
    correspondence_distance: float | None = None,
    refine: bool = True,
    min_points: int = _MIN_SCAN_POINTS,
) -> FloatArray | None:
    """:meth:`ScanMap.align` of one scan onto a map built for it (``voxel`` >= 0.25 and
    ``correspondence_distance`` default to the config's)."""
    aligned = ScanMap(map_points, config, voxel=voxel).align(
        points, guess, correspondence_distance=correspondence_distance, refine=refine, min_points=min_points
    )
    return None if aligned is None else aligned.pose


def _polished_alignment(  # noqa: PLR0917 - internal helper shared by two callers
    icp: _PointAligner,
    pts: FloatArray,
    voxel_map: object,
    map_points: FloatArray,
    guess: FloatArray,
    cfg: LaserConfig,
    voxel: float,
    distance: float,
    *,
    refine: bool = True,
    min_points: int = _MIN_SCAN_POINTS,
    target: _Target | None = None,
    degenerate_ratio: float = 0.0,
) -> Alignment | None:
    """kiss-icp alignment of a scan (downsampled at ``voxel``) onto ``voxel_map`` from ``guess``, then the
    point-to-plane polish against ``map_points`` (or a prepared ``target`` of them) with the prior at the
    odometry ``guess`` (directions the planes do not see stay at the odometry), and the guess's
    translation kept along directions constrained less than ``degenerate_ratio`` times the best one
    (:func:`keep_unobserved`); None with too few points or when ICP diverged."""
    src = voxel_downsample(pts, voxel)
    if len(src) < min_points or len(map_points) < min_points:
        return None
    aligned = _align(icp, src, voxel_map, guess, distance)
    if aligned is None or not refine:
        return None if aligned is None else Alignment(aligned, 0)
    surface = _Target(map_points, 0.5 * voxel) if target is None else target
    overlap = _Overlap(_Target(pts, 0.5 * voxel), surface, cfg.inlier_distance)
    aligned, _, information = _point_to_plane(aligned, overlap, cfg, _STEP_PRIOR_STD, prior_mean=guess)
    weak = weak_directions(information, degenerate_ratio)
    return Alignment(_keep_guess_along(aligned, guess, weak), len(weak))


def passage_patch(
    scans_points: Sequence[ArrayLike],
    scan_stamps: ArrayLike,
    scan_poses: ArrayLike,
    visit_stamp: float,
    visit_pose: ArrayLike,
    *,
    config: LaserConfig | None = None,
    sensor_offset: ArrayLike | None = None,
) -> FloatArray:
    """The patch of a visit from a whole scan sequence (offline, Fig. 48): points ``(P, 2)``, visit frame.

    Takes the :func:`passage_slice` within ``config.patch_radius``, its :func:`keyframes`, corrects their
    poses with :func:`refine_scan_poses` when ``config.refine`` and concatenates them at
    ``config.patch_voxel``. The visit frame is the visit's odometry pose carried along with the
    correction of the kept scan nearest in time. :class:`PatchBuilder` gives the same patch online.
    """
    cfg = LaserConfig() if config is None else config
    stamps = np.asarray(scan_stamps, dtype=float).reshape(-1)
    poses = _as_poses(scan_poses, "scan_poses")
    if not len(scans_points) == len(stamps) == len(poses):
        msg = f"{len(scans_points)} scans, {len(stamps)} stamps and {len(poses)} poses differ in number"
        raise ModelError(msg)
    sl = passage_slice(stamps, poses, visit_stamp, visit_pose, cfg.patch_radius)
    keep = sl.start + keyframes(poses[sl], cfg.keyframe_xy, cfg.keyframe_yaw)
    scans = [_as_points(scans_points[k], f"scans_points[{k}]") for k in keep]
    visit = _as_pose(visit_pose, "visit_pose")
    return _passage_patch(
        scans, stamps[keep], poses[keep], visit_stamp, visit, cfg=cfg, offset=_offset(sensor_offset)
    )


@dataclass
class _OpenPatch:
    key: int
    stamp: float
    pose: FloatArray
    scans: list[tuple[float, FloatArray, FloatArray]]  # (stamp, robot pose, sensor points) keyframes
    entered: bool = False


class PatchBuilder:
    """Online patch accumulator for the filter; the patch of a visit equals :func:`passage_patch`'s.

    Feed every scan with :meth:`add_scan` and declare visits with :meth:`add_visit`, possibly late: the
    last ``max_scans`` keyframe scans (moved ``keyframe_xy`` or turned ``keyframe_yaw`` since the
    previous buffered one) are kept for that. A visit's patch is complete once the robot leaves
    ``config.patch_radius`` of the visit pose; :meth:`pop_ready` then returns it. Memory is bounded:
    ``max_scans`` buffered scans, and per open visit at most ``max_scans`` keyframes. (A scan skipped
    from the buffer for standing still right at the radius boundary can make a late visit's patch
    start one scan later than :func:`passage_patch`'s.)
    """

    def __init__(
        self,
        config: LaserConfig | None = None,
        *,
        sensor_offset: ArrayLike | None = None,
        max_scans: int = 2000,
    ) -> None:
        self.config = LaserConfig() if config is None else config
        if isinstance(max_scans, bool) or not isinstance(max_scans, int) or max_scans < 1:
            msg = f"max_scans must be an integer >= 1, got {max_scans!r}"
            raise ConfigError(msg)
        self._max_scans = max_scans
        self._offset = _offset(sensor_offset)
        self._scans: deque[tuple[float, FloatArray, FloatArray]] = deque(maxlen=max_scans)
        self._open: list[_OpenPatch] = []
        self._ready: list[tuple[int, FloatArray]] = []
        self._keys: set[int] = set()

    @property
    def n_buffered(self) -> int:
        """Scans currently buffered for visits declared late."""
        return len(self._scans)

    @property
    def n_open(self) -> int:
        """Visits whose patch is still open."""
        return len(self._open)

    def add_scan(self, stamp: float, pose: ArrayLike, points: ArrayLike) -> None:
        """Ingest one scan: header stamp (s), robot odometry pose, points ``(P, 2)`` in the sensor frame."""
        robot = _as_pose(pose, "pose")
        pts = _as_points(points, "points")
        if not math.isfinite(stamp):
            msg = f"scan stamp must be finite, got {stamp}"
            raise ModelError(msg)
        if self._scans and stamp < self._scans[-1][0]:
            msg = f"scan stamps must not decrease: {stamp} after {self._scans[-1][0]}"
            raise ModelError(msg)
        scan = (float(stamp), robot, pts)
        cfg = self.config
        if not self._scans or moved(self._scans[-1][1], robot, cfg.keyframe_xy, cfg.keyframe_yaw):
            self._scans.append(scan)
        still_open = []
        for patch in self._open:
            if _within(robot[None, :], patch.pose, cfg.patch_radius)[0]:
                self._extend(patch, scan)
                still_open.append(patch)
            elif patch.entered or stamp >= patch.stamp:
                self._close(patch)
            else:
                still_open.append(patch)
        self._open = still_open

    def add_visit(self, key: int, stamp: float, pose: ArrayLike) -> None:
        """Declare visit ``key`` at header stamp ``stamp`` (s) and odometry pose ``pose``."""
        visit = _as_pose(pose, "pose")
        if not math.isfinite(stamp):
            msg = f"visit stamp must be finite, got {stamp}"
            raise ModelError(msg)
        if key in self._keys:
            msg = f"visit {key} was already declared"
            raise ModelError(msg)
        self._keys.add(key)
        patch = _OpenPatch(key=key, stamp=float(stamp), pose=visit, scans=[])
        if not self._scans:
            self._open.append(patch)
            return
        stamps = np.array([s[0] for s in self._scans])
        poses = np.array([s[1] for s in self._scans])
        sl = passage_slice(stamps, poses, stamp, visit, self.config.patch_radius)
        for k in range(sl.start, sl.stop):
            self._extend(patch, self._scans[k])
        still_inside = sl.stop == len(stamps) and sl.stop > sl.start
        if still_inside or (sl.stop == sl.start and stamp >= stamps[-1]):
            self._open.append(patch)
        else:
            self._close(patch)

    def pop_ready(self) -> list[tuple[int, FloatArray]]:
        """The completed ``(key, patch)`` pairs since the last call, in completion order."""
        ready, self._ready = self._ready, []
        return ready

    def flush(self) -> list[tuple[int, FloatArray]]:
        """Close every open patch (end of data) and return all completed ones."""
        for patch in self._open:
            self._close(patch)
        self._open = []
        return self.pop_ready()

    def _extend(self, patch: _OpenPatch, scan: tuple[float, FloatArray, FloatArray]) -> None:
        patch.entered = True
        cfg = self.config
        if len(patch.scans) >= self._max_scans:
            return
        if not patch.scans or moved(patch.scans[-1][1], scan[1], cfg.keyframe_xy, cfg.keyframe_yaw):
            patch.scans.append(scan)

    def _close(self, patch: _OpenPatch) -> None:
        stamps = np.array([s[0] for s in patch.scans])
        poses = np.array([s[1] for s in patch.scans]).reshape(-1, 3)
        scans = [s[2] for s in patch.scans]
        points = _passage_patch(
            scans, stamps, poses, patch.stamp, patch.pose, cfg=self.config, offset=self._offset
        )
        self._ready.append((patch.key, points))


def _passage_patch(
    scans: list[FloatArray],
    stamps: FloatArray,
    poses: FloatArray,
    visit_stamp: float,
    visit: FloatArray,
    *,
    cfg: LaserConfig,
    offset: FloatArray,
) -> FloatArray:
    """Crop to ``max_range``, refine (optionally) and concatenate the keyframes of one passage."""
    if not scans:
        return np.empty((0, 2))
    scans = [pts[np.hypot(pts[:, 0], pts[:, 1]) <= cfg.max_range] for pts in scans]
    refined = refine_scan_poses(scans, poses, cfg, sensor_offset=offset) if cfg.refine else poses
    c = int(np.argmin(np.abs(stamps - visit_stamp)))
    frame = compose(refined[c], between(poses[c], visit))
    return _concatenate(scans, refined, frame, offset, cfg.patch_voxel)


def _concatenate(
    scans: Sequence[FloatArray], poses: FloatArray, visit: FloatArray, offset: FloatArray, voxel: float
) -> FloatArray:
    """Scans moved into the visit frame, stacked in order, voxel-downsampled."""
    if not scans:
        return np.empty((0, 2))
    parts = [
        transform_points(between(visit, compose(pose, offset)), pts)
        for pose, pts in zip(poses, scans, strict=True)
    ]
    return voxel_downsample(np.vstack(parts), voxel)


# ------------------------------------------------------------------------------------------ helpers


def _as_poses(poses: ArrayLike, name: str) -> FloatArray:
    p = np.asarray(poses, dtype=float)
    if p.size == 0:
        return np.empty((0, 3))
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        msg = f"{name} must be finite with shape (S, 3), got shape {p.shape}"
        raise ModelError(msg)
    return p


def _check_positive(**values: float) -> None:
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0.0):
            msg = f"{name} must be finite and > 0, got {value}"
            raise ModelError(msg)


def _offset(sensor_offset: ArrayLike | None) -> FloatArray:
    return _IDENTITY if sensor_offset is None else _as_pose(sensor_offset, "sensor_offset")


def _within(poses: FloatArray, centre: FloatArray, radius: float) -> np.ndarray:
    return np.hypot(poses[:, 0] - centre[0], poses[:, 1] - centre[1]) <= radius


def _to_visit_frame(visit: FloatArray, robot: FloatArray, offset: FloatArray, pts: FloatArray) -> FloatArray:
    return transform_points(between(visit, compose(robot, offset)), pts)
