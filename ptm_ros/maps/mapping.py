"""The metric map of a topology: its smoothed trajectory and the occupancy grid of the scans along it.

The thesis turns the MAP topology into a globally consistent metric map (Ch. 5, Fig. 50/52): the
odometry plus the topology's same-place constraints and laser registrations, solved as a pose graph
(:mod:`ptm_ros.maps.smoothing`) and refined by keyframe scan matches along revisited passages
(:mod:`ptm_ros.maps.refinement`), with the scans drawn along the result (:mod:`ptm_ros.maps.occupancy`).
Offline, ``ptm-run`` does it once for the whole run (:mod:`ptm_ros.tools.pipeline`); online, the map publisher
keeps an :class:`OnlineMap` of the odometry the visits were measured in and of keyframe scans, and
redraws the map whenever the MAP topology changes. Both call :func:`topology_trajectory` and
:func:`grid_along`, so a map built online from the same samples equals the offline one (online, the
refinement sees the keyframe scans only).

:class:`OnlineMap` keeps every odometry sample it is given (the detector sends them decimated, below;
the visits' own samples are merged in exactly when the map is built), a scan only as a keyframe after
``keyframe_xy`` / ``keyframe_yaw`` of motion since the previous keyframe, scans waiting for the odometry to
reach their stamp at most ``max_pending_scans``. An odometry stream that goes back in
time (a bag looped, a clock reset) or jumps farther than ``max_speed · Δt + 1 m`` (a teleport) is a new
session of the detector: everything kept so far is dropped (``resets``).

The detector sends only what the map needs (:class:`KeyframeStream`): odometry samples every ``pose_xy``
/ ``pose_yaw`` of motion (or ``pose_interval`` seconds) and the keyframe scans, each with its pose; at
robot rates (100 Hz odometry, 40 Hz scans) that is two orders of magnitude fewer messages than the raw
streams, which a Python node could not take at a fast replay's rate (issue #9's load run).
"""

from __future__ import annotations

import heapq
import math
from array import array
from bisect import bisect_right
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import DataError
from ptm_ros.maps.occupancy import OccupancyConfig, OccupancyGrid, build_grid
from ptm_ros.maps.refinement import Mapper, RefinementConfig, refine_trajectory
from ptm_ros.maps.smoothing import smooth_topology
from ptm_ros.model.geometry import FloatArray, Registrar, RelativePose, interpolate_poses, moved
from ptm_ros.model.posterior import ModelConfig, chained_registrations, split_aliases
from ptm_ros.model.visits import Visit
from ptm_ros.perception.laser import LaserConfig
from ptm_ros.perception.patches import usable_points
from ptm_ros.settings import Settings, setting

TELEPORT_SLACK_M = 1.0  # m added to max_speed · Δt before an odometry step counts as a teleport
SAME_STAMP_S = 1e-6  # s: an odometry sample this close to a visit's stamp is that visit's sample


@dataclass(frozen=True)
class MappingConfig(Settings):
    """The map publisher's online metric map (lengths in m, angles in rad)."""

    period: float = setting(
        2.0,
        ge=0,
        doc=(
            "wall-clock time between two rebuilds of the map at least [s]; a rebuild that took d seconds "
            "also waits 4 d, so drawing the map never takes more than a fifth of a core."
        ),
    )
    keyframe_xy: float = setting(
        0.2, ge=0, doc="a scan joins the map after the odometry moved this far [m] since the last keyframe …"
    )
    keyframe_yaw: float = setting(
        0.1, ge=0, doc="… or turned this much [rad] (both 0: every scan, as ``ptm-run``'s map)."
    )
    pose_xy: float = setting(
        0.05,
        ge=0,
        doc="the detector sends an odometry sample after this much motion [m] since the last one …",
    )
    pose_yaw: float = setting(0.05, ge=0, doc="… or this much rotation [rad] (both 0: every sample) …")
    pose_interval: float = setting(
        1.0, ge=0, doc="… or this many seconds (the detector's stream; 0: time alone sends every one)."
    )
    max_pending_scans: int = setting(
        10000,
        ge=1,
        doc=(
            "scans waiting for the odometry to reach their stamp; older ones are dropped (a fast replay can "
            "run the scans far ahead of the detector's odometry: 10000 scans of 360 beams are 15 MB)."
        ),
    )
    max_speed: float = setting(
        5.0,
        gt=0,
        doc=(
            "top speed [m/s]; a longer odometry step (``max_speed · Δt + 1 m``) is a teleport: a new "
            "session, the map restarts."
        ),
    )


def every_sample(config: MappingConfig) -> MappingConfig:
    """``config`` with the detector's stream and the keyframes thinned by nothing (``keyframe_*``,
    ``pose_*`` 0): the map publisher then draws from every odometry sample and every scan the detector
    used, the inputs of ``ptm-run``'s map, so the two maps are the same (``ptm-bringup`` on a bag)."""
    return replace(config, keyframe_xy=0.0, keyframe_yaw=0.0, pose_xy=0.0, pose_yaw=0.0, pose_interval=0.0)


def topology_trajectory(
    stamps: ArrayLike,
    poses: ArrayLike,
    labels: Sequence[int],
    visits: Sequence[Visit],
    model: ModelConfig,
    *,
    registration: Registrar | None = None,
    scans: ScanLog | None = None,
    refinement: RefinementConfig | None = None,
    laser: LaserConfig | None = None,
    mapper: Mapper = map,
) -> FloatArray:
    """The odometry ``poses (T, 3)`` at ``stamps`` smoothed for a topology (thesis Fig. 50/52): the visit
    poses optimised under odometry, the topology's laser registrations (each visit against the previous
    visit of its place, aliases left out: :func:`ptm_ros.model.posterior.split_aliases`) and a robust place
    coincidence, the path between deformed to fit (:func:`ptm_ros.maps.smoothing.smooth_topology`). Without a
    ``registration`` (or with ``model.use_laser`` off) only odometry and places constrain the poses. With
    ``scans`` and an enabled ``refinement``, keyframe scan matches along revisited passages refine the
    result (:func:`ptm_ros.maps.refinement.refine_trajectory`; ``laser`` configures the scans and the
    matching, ``mapper`` runs the registrations of each round).
    The visits must sit on odometry samples (their stamps among ``stamps``)."""
    loops: tuple[RelativePose, ...] = ()
    if registration is not None and model.use_laser and len(visits) > 1:
        measured = chained_registrations(labels, registration)
        loops, _ = split_aliases(labels, visits, model.odometry, measured)
    if scans is None or refinement is None or not refinement.enabled:
        return smooth_topology(stamps, poses, labels, visits, model.odometry, loops=loops)
    lcfg = LaserConfig() if laser is None else laser
    scan_stamps, points = scan_points(scans, lcfg)
    res = refine_trajectory(
        stamps,
        poses,
        scan_stamps,
        points,
        labels,
        visits,
        model.odometry,
        loops=loops,
        laser=lcfg,
        config=refinement,
        mapper=mapper,
    )
    return res.trajectory


def scan_points(scans: ScanLog, laser: LaserConfig) -> tuple[FloatArray, list[FloatArray]]:
    """The scans' stamps (increasing) and points in the robot frame
    (:func:`ptm_ros.perception.patches.usable_points`, beams beyond ``laser.max_range`` dropped); a malformed
    scan has no points."""
    st = np.asarray(scans.stamps, dtype=float).reshape(-1)
    order = np.argsort(st, kind="stable")
    points = []
    for k in order:
        res = usable_points(
            scans.ranges[int(k)],
            float(scans.angle_min[k]),
            float(scans.angle_increment[k]),
            float(scans.range_min[k]),
            float(scans.range_max[k]),
            laser,
        )
        points.append(np.zeros((0, 2)) if res is None else res.points)
    return st[order], points


class ScanLog(Protocol):
    """Scans as arrays over the scans ``(S,)`` (``ranges``: one array per scan, or ``(S, B)``): the
    offline run's :class:`ptm_ros.io.bag.ScanData`, or :class:`Keyframes` (read only)."""

    @property
    def stamps(self) -> FloatArray: ...
    @property
    def ranges(self) -> NDArray[np.floating[Any]] | Sequence[NDArray[np.floating[Any]]]: ...
    @property
    def angle_min(self) -> FloatArray: ...
    @property
    def angle_increment(self) -> FloatArray: ...
    @property
    def range_min(self) -> FloatArray: ...
    @property
    def range_max(self) -> FloatArray: ...


@dataclass(frozen=True)
class Keyframes:
    """The keyframe scans of an :class:`OnlineMap` (a :class:`ScanLog`)."""

    stamps: FloatArray
    ranges: list[NDArray[np.float32]] = field(repr=False)
    angle_min: FloatArray = field(repr=False)
    angle_increment: FloatArray = field(repr=False)
    range_min: FloatArray = field(repr=False)
    range_max: FloatArray = field(repr=False)


def grid_along(
    stamps: ArrayLike, trajectory: ArrayLike, scans: ScanLog, config: OccupancyConfig | None = None
) -> OccupancyGrid | None:
    """The occupancy grid (:func:`ptm_ros.maps.occupancy.build_grid`) of the scans taken within the
    trajectory's time span, each at the pose of ``trajectory (T, 3)`` (given at ``stamps``) interpolated
    at its stamp; None when no scan lies within the span."""
    t = np.asarray(stamps, dtype=float).reshape(-1)
    st = np.asarray(scans.stamps, dtype=float).reshape(-1)
    if len(t) == 0 or len(st) == 0:
        return None
    keep = np.flatnonzero((st >= t[0]) & (st <= t[-1]))
    if len(keep) == 0:
        return None
    poses = interpolate_poses(t, trajectory, st[keep])
    ranges = scans.ranges
    used = ranges[keep] if isinstance(ranges, np.ndarray) else [ranges[int(k)] for k in keep]

    def field_of(value: ArrayLike) -> FloatArray:
        return np.broadcast_to(np.asarray(value, dtype=float).reshape(-1), st.shape)[keep]

    return build_grid(
        poses,
        used,
        field_of(scans.angle_min),
        field_of(scans.angle_increment),
        field_of(scans.range_max),
        range_min=field_of(scans.range_min),
        config=config,
    )


class KeyframeStream:
    """What the detector sends the map publisher (``landmark_odom``, ``landmark_scans``): of the odometry
    the visits are measured in, a sample after ``pose_xy`` / ``pose_yaw`` of motion or ``pose_interval``
    seconds; of the scans, the keyframes (``keyframe_xy`` / ``keyframe_yaw`` of motion since the last),
    each preceded by an odometry sample at its own stamp so it is posed exactly. One detector session (a
    new session needs a new stream)."""

    def __init__(self, config: MappingConfig | None = None) -> None:
        self.config = config if config is not None else MappingConfig()
        self._sent: tuple[float, FloatArray] | None = None  # last odometry sample sent
        self._keyframe: FloatArray | None = None  # pose of the last keyframe

    def select(
        self, poses: Sequence[tuple[float, ArrayLike]], scans: Sequence[tuple[float, Any, ArrayLike]]
    ) -> list[tuple[float, FloatArray, Any | None]]:
        """The messages to send for the odometry samples ``(stamp, pose)`` and scans ``(stamp, scan, pose)``
        processed since the last call (each list in stamp order), merged in stamp order (odometry first on
        ties): ``(stamp, pose, None)`` an odometry sample, ``(stamp, pose, scan)`` a keyframe scan."""
        cfg = self.config
        events = heapq.merge(
            ((float(t), 0, p, None) for t, p in poses),
            ((float(t), 1, p, sc) for t, sc, p in scans),
            key=lambda e: e[:2],
        )
        out: list[tuple[float, FloatArray, Any | None]] = []
        for stamp, kind, pose, scan in events:
            p = np.asarray(pose, dtype=float)
            if kind == 1:
                if self._keyframe is not None and not moved(
                    self._keyframe, p, cfg.keyframe_xy, cfg.keyframe_yaw
                ):
                    continue
                self._keyframe = p
                if self._sent is None or stamp > self._sent[0]:
                    out.append((stamp, p, None))
                out.append((stamp, p, scan))
            elif self._sent is not None and (
                stamp - self._sent[0] < cfg.pose_interval
                and not moved(self._sent[1], p, cfg.pose_xy, cfg.pose_yaw)
            ):
                continue
            else:
                out.append((stamp, p, None))
            self._sent = (stamp, p)
        return out


@dataclass
class MappingCounters:
    """What :class:`OnlineMap` did with its input (the map publisher's ``/diagnostics``)."""

    poses: int = 0  # odometry samples received
    poses_invalid: int = 0  # non-finite or duplicate stamps: ignored
    scans: int = 0  # scans received
    keyframes: int = 0
    scans_unposed: int = 0  # before the odometry's start, older than the last keyframe, or queue overflow
    resets: int = 0  # the odometry went back in time or teleported: a new session


@dataclass(frozen=True)
class MapResult:
    """One build of the map: the smoothed trajectory at ``stamps`` and the grid (None without scans)."""

    stamps: FloatArray
    trajectory: FloatArray
    keyframe_stamps: FloatArray
    keyframe_poses: FloatArray  # smoothed poses of the keyframes
    grid: OccupancyGrid | None


@dataclass(frozen=True)
class MapInputs:
    """What a map is drawn from: the odometry ``stamps (T,)``, ``poses (T, 3)`` with the visits' samples
    merged in, the visits and the keyframe scans (:meth:`OnlineMap.snapshot`)."""

    stamps: FloatArray
    poses: FloatArray
    visits: tuple[Visit, ...]
    keyframes: Keyframes


def draw_map(
    inputs: MapInputs,
    labels: Sequence[int],
    model: ModelConfig,
    occupancy: OccupancyConfig | None = None,
    registration: Registrar | None = None,
    *,
    refinement: RefinementConfig | None = None,
    laser: LaserConfig | None = None,
) -> MapResult:
    """The map of a topology: :func:`topology_trajectory` (refined by the keyframes' scans when
    ``refinement`` is enabled), then :func:`grid_along` of the keyframes.

    Raises:
        ModelError: from the smoothing (labels that do not fit the visits).
    """
    t, kf = inputs.stamps, inputs.keyframes
    traj = topology_trajectory(
        t,
        inputs.poses,
        labels,
        inputs.visits,
        model,
        registration=registration,
        scans=kf,
        refinement=refinement,
        laser=laser,
    )
    grid = grid_along(t, traj, kf, occupancy)
    inside = (kf.stamps >= t[0]) & (kf.stamps <= t[-1])
    kposes = interpolate_poses(t, traj, kf.stamps[inside]) if np.any(inside) else np.zeros((0, 3))
    return MapResult(t, traj, kf.stamps[inside], kposes, grid)


@dataclass
class _Scan:
    stamp: float
    ranges: NDArray[np.float32] = field(repr=False)
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float


class OnlineMap:
    """The odometry and keyframe scans of one session, and the map of a topology over them (module
    docstring). Feed :meth:`add_pose` (the odometry the visits are measured in, in stamp order) and
    :meth:`add_scan` in any interleaving; :meth:`build` draws the map of a topology of the visits."""

    def __init__(self, config: MappingConfig | None = None) -> None:
        self.config = config if config is not None else MappingConfig()
        self.counters = MappingCounters()
        self._clear()

    def _clear(self) -> None:
        self._t = array("d")
        self._x = array("d")
        self._y = array("d")
        self._yaw = array("d")
        self._pending: deque[_Scan] = deque()
        self._kf: list[_Scan] = []
        self._kf_pose: FloatArray | None = None  # odometry pose of the last keyframe

    @property
    def keyframes(self) -> int:
        """Keyframe scans kept."""
        return len(self._kf)

    @property
    def _latest(self) -> tuple[float, FloatArray] | None:
        """The newest odometry sample (every sample is kept), None before the first."""
        if not self._t:
            return None
        return self._t[-1], np.array([self._x[-1], self._y[-1], self._yaw[-1]])

    @property
    def span(self) -> tuple[float, float] | None:
        """``(first, latest)`` odometry stamp of the session; None before the first sample."""
        return (self._t[0], self._t[-1]) if self._t else None

    # ------------------------------------------------------------------------------------ input

    def add_pose(self, stamp: float, pose: ArrayLike) -> bool:
        """One odometry sample ``(x, y, yaw)``; True when it started a new session (see module docstring)."""
        self.counters.poses += 1
        p = np.asarray(pose, dtype=float).reshape(-1)
        if p.shape != (3,) or not (np.all(np.isfinite(p)) and math.isfinite(stamp)):
            self.counters.poses_invalid += 1
            return False
        reset = False
        if self._latest is not None:
            t0, p0 = self._latest
            if stamp == t0:
                self.counters.poses_invalid += 1
                return False
            step = math.hypot(p[0] - p0[0], p[1] - p0[1])
            if stamp < t0 or step > self.config.max_speed * (stamp - t0) + TELEPORT_SLACK_M:
                self.counters.resets += 1
                self._clear()
                reset = True
        self._keep(stamp, p)
        self._settle()
        return reset

    def add_scan(  # noqa: PLR0917 - the LaserScan fields read best positionally
        self,
        stamp: float,
        ranges: ArrayLike,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
    ) -> None:
        """One laser scan (LaserScan fields; validated by the caller); used once the odometry reaches it."""
        self.counters.scans += 1
        if not math.isfinite(stamp) or (self._t and stamp < self._t[0]):
            self.counters.scans_unposed += 1
            return
        r = np.asarray(ranges, dtype=np.float32).reshape(-1)
        self._pending.append(_Scan(float(stamp), r, angle_min, angle_increment, range_min, range_max))
        while len(self._pending) > self.config.max_pending_scans:
            self._pending.popleft()
            self.counters.scans_unposed += 1
        self._settle()

    def _keep(self, stamp: float, p: FloatArray) -> None:
        self._t.append(float(stamp))
        self._x.append(float(p[0]))
        self._y.append(float(p[1]))
        self._yaw.append(float(p[2]))

    def _pose_at(self, stamp: float) -> FloatArray:
        """The odometry pose at a stamp within the span (interpolated between the bracketing samples)."""
        k = bisect_right(self._t, stamp)
        lo_t, lo_p = self._t[k - 1], np.array([self._x[k - 1], self._y[k - 1], self._yaw[k - 1]])
        if k == len(self._t):  # the latest sample itself
            return lo_p
        hi_t, hi_p = self._t[k], np.array([self._x[k], self._y[k], self._yaw[k]])
        return interpolate_poses([lo_t, hi_t], np.stack([lo_p, hi_p]), [stamp])[0]

    def _settle(self) -> None:
        """Pose the pending scans the odometry has reached; keep the keyframes among them."""
        if not self._t:
            return
        cfg = self.config
        while self._pending and self._pending[0].stamp <= self._t[-1]:
            scan = self._pending.popleft()
            if scan.stamp < self._t[0] or (self._kf and scan.stamp <= self._kf[-1].stamp):
                self.counters.scans_unposed += 1
                continue
            pose = self._pose_at(scan.stamp)
            if self._kf_pose is None or moved(self._kf_pose, pose, cfg.keyframe_xy, cfg.keyframe_yaw):
                self._kf.append(scan)
                self._kf_pose = pose
                self.counters.keyframes += 1

    # ------------------------------------------------------------------------------------ output

    def trajectory(self, visits: Sequence[Visit] = ()) -> tuple[FloatArray, FloatArray]:
        """``(stamps (T,), poses (T, 3))``: the odometry samples, with the visits' own samples merged in (a
        visit's pose replaces a sample within 1 µs of its stamp), sorted."""
        t = np.frombuffer(self._t, dtype=float).copy()
        p = np.column_stack([np.frombuffer(a, dtype=float) for a in (self._x, self._y, self._yaw)])
        if visits:
            vt = np.array([v.stamp for v in visits], dtype=float)
            vp = np.array([v.pose for v in visits], dtype=float).reshape(-1, 3)
            k = np.searchsorted(vt, t)
            left, right = vt[np.clip(k - 1, 0, len(vt) - 1)], vt[np.clip(k, 0, len(vt) - 1)]
            keep = np.minimum(np.abs(t - left), np.abs(t - right)) > SAME_STAMP_S
            t = np.concatenate([t[keep], vt])
            p = np.vstack([p.reshape(-1, 3)[keep], vp])
            order = np.argsort(t, kind="stable")
            t, p = t[order], p[order]
        return t, p.reshape(-1, 3)

    def snapshot(self, visits: Sequence[Visit]) -> MapInputs:
        """Copies of what a map of ``visits`` is drawn from (:func:`draw_map`; cheap, so the drawing can
        run elsewhere while samples keep arriving).

        Raises:
            DataError: no visit, or the visits all precede the session's odometry (another session's;
                visits before the odometry's start, e.g. a map publisher started late, are joined by
                straight segments).
        """
        if not visits:
            msg = "the map needs at least one visit"
            raise DataError(msg)
        span = self.span
        if span is None or visits[-1].stamp < span[0] - SAME_STAMP_S:
            msg = f"the last visit ({visits[-1].stamp:.6f} s) precedes the session's odometry {span}"
            raise DataError(msg)
        t, u = self.trajectory(visits)
        return MapInputs(t, u, tuple(visits), self.keyframe_scans())

    def build(
        self,
        visits: Sequence[Visit],
        labels: Sequence[int],
        model: ModelConfig,
        occupancy: OccupancyConfig | None = None,
        registration: Registrar | None = None,
        *,
        refinement: RefinementConfig | None = None,
        laser: LaserConfig | None = None,
    ) -> MapResult:
        """The map of a topology of ``visits`` now: :meth:`snapshot` then :func:`draw_map`."""
        return draw_map(
            self.snapshot(visits), labels, model, occupancy, registration, refinement=refinement, laser=laser
        )

    def keyframe_scans(self) -> Keyframes:
        """The keyframe scans kept so far."""
        kf = self._kf

        def per_scan(name: str) -> FloatArray:
            return np.array([getattr(s, name) for s in kf], dtype=float)

        return Keyframes(
            per_scan("stamp"),
            [s.ranges for s in kf],
            per_scan("angle_min"),
            per_scan("angle_increment"),
            per_scan("range_min"),
            per_scan("range_max"),
        )
