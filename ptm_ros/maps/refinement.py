"""Laser refinement of a topology's smoothed trajectory: scan matches along revisited passages.

The smoothing of :mod:`ptm_ros.maps.smoothing` constrains a topology's trajectory at its *visits* only: the
odometry between visits, the topology's same-place coincidences and the registrations of the visits'
patches. When the robot drives a corridor again, the two passages overlap for many metres, yet between
the visits nothing ties them together, and the odometry's drift along them stays (thesis Fig. 52 shows the
same for its Lu–Milios maps). This module adds what a metric SLAM back end adds there, *given* the
topology: keyframe-to-keyframe scan matches between passages that the topology's smoothed trajectory
brings close together.

1. **Keyframes**: a scan every ``keyframe_xy`` of odometry travel or ``keyframe_yaw`` of turning. Each
   carries a *submap*: the scans within ``submap_travel`` of travel before and after it, placed by the
   odometry (locally accurate) in the frame of the keyframe's odometry node.
2. **Graph**: the nodes are the odometry samples of the keyframes and of the visits; consecutive nodes are
   tied by the relative odometry with the covariance of :mod:`ptm_ros.model.odometry`'s noise model for the
   travel and turning between them (``a_xy Δd``, ``a_th Δθ + c_th Δd``; the per-segment floors
   ``b_xy``, ``b_th`` belong to the visit-to-visit segments of the thesis and are not split here); the
   visits keep the topology's place coincidences and validated registrations, as in
   :func:`ptm_ros.maps.smoothing.robust_visit_poses`.
3. **Closures**, in ``rounds`` rounds: for each keyframe, the ``max_candidates`` nearest keyframes (under
   the current estimate) within ``search_radius`` and at least ``min_travel`` of odometry travel later.
   Their submaps are registered with :func:`ptm_ros.perception.laser.register_patches` from the estimated
   relative pose (one initial heading) and its validity test (inlier fraction, a sharp optimum, no ambiguity);
   a valid match no farther than ``max_shift`` from the estimate becomes a relative-pose factor with the
   registration's covariance, robust (Cauchy, as the place coincidences: a scan match may be wrong where
   the topology is). A match that fails only because it slides along a corridor (sharp across the
   corridor and in heading) still fixes the passages' lateral offset and relative heading: it enters
   with ``corridor_std`` added to its covariance along the corridor's axis. The graph is re-solved
   (:func:`ptm_ros.maps.smoothing.robust_optimum`) after each round.
4. The full trajectory is the odometry deformed through the optimised nodes
   (:func:`ptm_ros.maps.smoothing.smoothed_trajectory`).

Nothing here changes the topology: candidates come from where the topology's smoothing put the passages.
A topology that separates two corridors keeps them apart (no candidates); one that merges them, wrongly,
gets scan matches only where the scans agree. Measured on the Intel, ACES and MIT-CSAIL runs and the
simulated worlds: see ``bench/results.md`` (``ate_smoothed_m``) and the closing notes of issue #8.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ModelError, RegistrationError
from ptm_ros.maps.posegraph import RelativeFactors
from ptm_ros.maps.smoothing import (
    RobustGraph,
    SmoothingConfig,
    place_pairs,
    robust_optimum,
    robust_visit_poses,
    smoothed_trajectory,
    whitening,
)
from ptm_ros.model.geometry import (
    FloatArray,
    RelativePose,
    between,
    interpolate_poses,
    transform_points,
    wrap_angle,
)
from ptm_ros.model.odometry import OdometryConfig, optimize_poses
from ptm_ros.model.partitions import canonical
from ptm_ros.model.visits import Visit
from ptm_ros.perception.laser import LaserConfig, Registration, register_patches, voxel_downsample
from ptm_ros.settings import Settings, setting

_NUMERIC_VARIANCE = 1e-6  # m², rad²: keeps a zero-travel odometry factor finite


class RegistrationJob(NamedTuple):
    """One submap registration of a refinement round (the arguments of
    :func:`ptm_ros.perception.laser.register_patches`); picklable, for a process pool."""

    source: FloatArray
    target: FloatArray
    initial: FloatArray
    laser: LaserConfig
    slide_axis: bool


def register_job(job: RegistrationJob) -> Registration | None:
    """The registration of a job, or None when a submap is too small to register."""
    try:
        return register_patches(job.source, job.target, job.initial, job.laser, slide_axis=job.slide_axis)
    except RegistrationError:
        return None


class Mapper(Protocol):
    """``mapper(register_job, jobs)``: the outcomes of the jobs, in order. The builtin ``map`` (one after
    the other) or a process pool's ``map``: the registrations of a round are independent of each other,
    so the refinement is the same either way."""

    def __call__(
        self, fn: Callable[[RegistrationJob], Registration | None], jobs: Iterable[RegistrationJob], /
    ) -> Iterable[Registration | None]: ...


@dataclass(frozen=True)
class RefinementConfig(Settings):
    """Keyframe scan matching along revisited passages (module docstring; lengths in m, angles in rad)."""

    enabled: bool = setting(
        True, doc="refine smoothed trajectories (``ptm-run``'s and the map publisher's) when scans exist."
    )
    keyframe_xy: float = setting(
        1.0, gt=0, doc="a scan becomes a keyframe after this much odometry travel [m] since the last one …"
    )
    keyframe_yaw: float = setting(0.5, gt=0, doc="… or this much turning [rad].")
    submap_travel: float = setting(
        2.0, gt=0, doc="scans within this odometry travel [m] before and after a keyframe form its submap."
    )
    min_travel: float = setting(
        5.0,
        gt=0,
        doc=(
            "two keyframes are a candidate pair only this much odometry travel [m] apart or more (nearer "
            "ones are tied by the odometry)."
        ),
    )
    search_radius: float = setting(
        2.0, gt=0, doc="… and at most this far apart [m] under the current estimate."
    )
    max_candidates: int = setting(3, ge=1, doc="nearest candidates registered per keyframe and round.")
    max_shift: float = setting(
        2.0, gt=0, doc="a match farther than this [m] from the estimated relative pose is rejected."
    )
    rounds: int = setting(
        2, ge=1, doc="search-and-solve rounds (a round without a new valid match ends early)."
    )
    corridors: bool = setting(
        True,
        doc=(
            "also use matches that slide along a corridor (sharp across it and in heading, "
            ":attr:`ptm_ros.perception.laser.Registration.slide_axis`), with ``corridor_std`` added along the"
            " axis."
        ),
    )
    corridor_std: float = setting(
        2.0, gt=0, doc="standard deviation [m] added along a corridor match's axis."
    )


@dataclass(frozen=True)
class Closure:
    """A scan match (valid, or a corridor match) between keyframe nodes ``a < b``: ``mean`` measures
    ``between(x_a, x_b)``; ``weight`` is its final Cauchy weight (1: satisfied; near 0: let go);
    ``slide_axis``: for a match that slides along a corridor, the corridor's unit axis in node ``a``'s
    frame (``cov`` widened along it); None for a sharp match."""

    a: int
    b: int
    mean: FloatArray
    cov: FloatArray
    weight: float
    slide_axis: FloatArray | None = None


@dataclass(frozen=True)
class Refinement:
    """A refined trajectory and how it came about.

    Attributes:
        trajectory: ``(T, 3)`` poses at the odometry stamps.
        nodes: odometry sample indices of the graph's nodes (keyframes and visits), increasing.
        keyframes: how many of the nodes are keyframes with a submap.
        closures: the valid scan matches, in the order found.
        tried: registrations run.
        rounds: search rounds run.
    """

    trajectory: FloatArray
    nodes: NDArray[np.intp]
    keyframes: int
    closures: tuple[Closure, ...]
    tried: int
    rounds: int


def keyframe_scans(travel: ArrayLike, turned: ArrayLike, min_xy: float, min_yaw: float) -> NDArray[np.intp]:
    """Indices of the keyframes among scans whose cumulative odometry ``travel`` and absolute ``turned``
    heading ``(S,)`` are given: the first scan, then each after ``min_xy`` travel or ``min_yaw`` turning
    since the last keyframe."""
    d = np.asarray(travel, dtype=float).reshape(-1)
    r = np.asarray(turned, dtype=float).reshape(-1)
    if len(d) == 0:
        return np.zeros(0, dtype=np.intp)
    out = [0]
    for k in range(1, len(d)):
        if d[k] - d[out[-1]] >= min_xy or r[k] - r[out[-1]] >= min_yaw:
            out.append(k)
    return np.array(out, dtype=np.intp)


def _cumulative(poses: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Cumulative travel and absolute turning along ``poses (T, 3)``."""
    step = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))
    turn = np.abs(wrap_angle(np.diff(poses[:, 2])))
    return np.concatenate([[0.0], np.cumsum(step)]), np.concatenate([[0.0], np.cumsum(turn)])


def _odometry_factors(
    nodes: NDArray[np.intp], poses: FloatArray, travel: FloatArray, turned: FloatArray, config: OdometryConfig
) -> RelativeFactors:
    """Relative odometry between consecutive nodes, whitened by the noise model (module docstring)."""
    a, b = nodes[:-1], nodes[1:]
    dd, dr = travel[b] - travel[a], turned[b] - turned[a]
    var_xy = config.a_xy * dd + _NUMERIC_VARIANCE
    var_th = config.a_th * dr + config.c_th * dd + _NUMERIC_VARIANCE
    w = np.zeros((len(a), 3, 3))
    w[:, 0, 0] = w[:, 1, 1] = 1.0 / np.sqrt(var_xy)
    w[:, 2, 2] = 1.0 / np.sqrt(var_th)
    return RelativeFactors(
        a=np.arange(len(a), dtype=np.intp),
        b=np.arange(1, len(a) + 1, dtype=np.intp),
        z=between(poses[a], poses[b]),
        w=w,
    )


def _graph(
    odometry: RelativeFactors,
    visit_nodes: NDArray[np.intp],
    labels: Sequence[int],
    loops: Sequence[RelativePose],
    *,
    closures: Sequence[tuple[int, int, FloatArray, FloatArray]],
    config: OdometryConfig,
) -> RobustGraph:
    """Odometry, the visits' registrations (Gaussian) and the closures (Cauchy) as one graph, with the
    visits' place pairs."""
    same = [z for z in loops if labels[z.i] == labels[z.j]]
    pairs, scales = place_pairs(labels, config.sigma_topology)
    cl = [RelativePose(i=a, j=b, mean=m, cov=c) for a, b, m, c in closures]
    factors = RelativeFactors(
        a=np.concatenate([odometry.a, visit_nodes[[z.i for z in same]], [z.i for z in cl]]).astype(np.intp),
        b=np.concatenate([odometry.b, visit_nodes[[z.j for z in same]], [z.j for z in cl]]).astype(np.intp),
        z=np.concatenate([odometry.z, np.reshape([z.mean for z in same + cl], (-1, 3))]),
        w=np.concatenate([odometry.w, whitening(same), whitening(cl)]),
    )
    robust = np.zeros(len(factors.a), dtype=bool)
    robust[len(factors.a) - len(cl) :] = True
    return RobustGraph(factors=factors, robust=robust, pairs=visit_nodes[pairs], scales=scales)


def refine_trajectory(  # noqa: PLR0917 - the smoothing's inputs plus the scans
    odom_stamps: ArrayLike,
    odom_poses: ArrayLike,
    scan_stamps: ArrayLike,
    scan_points: Sequence[FloatArray],
    labels: Sequence[int],
    visits: Sequence[Visit],
    odometry: OdometryConfig,
    *,
    loops: Sequence[RelativePose] = (),
    laser: LaserConfig | None = None,
    config: RefinementConfig | None = None,
    smoothing: SmoothingConfig | None = None,
    mapper: Mapper = map,
) -> Refinement:
    """The odometry trajectory ``(T, 3)`` of a topology refined by keyframe scan matches (module docstring).

    ``odom_poses`` are the poses the visits' poses come from (the visits sit on odometry samples);
    ``scan_points`` are the scans' points in the robot frame
    (:func:`ptm_ros.perception.patches.scan_to_points`), taken at ``scan_stamps`` (increasing); ``labels``,
    ``visits``, ``odometry`` and ``loops`` are those of
    :func:`ptm_ros.maps.smoothing.robust_visit_poses`. ``mapper`` runs each round's registrations
    (:class:`Mapper`).

    Raises:
        ModelError: mismatched inputs, visits off the odometry samples, or what
            :func:`ptm_ros.model.odometry.optimize_poses` rejects.
    """
    cfg = RefinementConfig() if config is None else config
    lcfg = replace(LaserConfig() if laser is None else laser, n_rotations=1)  # from the estimate only
    scfg = SmoothingConfig() if smoothing is None else smoothing
    t = np.asarray(odom_stamps, dtype=float).reshape(-1)
    u = np.asarray(odom_poses, dtype=float).reshape(-1, 3)
    st = np.asarray(scan_stamps, dtype=float).reshape(-1)
    if len(t) != len(u) or len(st) != len(scan_points):
        msg = f"need matching stamps/poses: {len(t)}/{len(u)} odometry, {len(st)}/{len(scan_points)} scans"
        raise ModelError(msg)
    if np.any(np.diff(st) < 0):
        msg = "scan stamps must be increasing"
        raise ModelError(msg)
    vidx = np.searchsorted(t, [v.stamp for v in visits])
    if np.any(vidx >= len(t)) or np.any(t[np.minimum(vidx, len(t) - 1)] != [v.stamp for v in visits]):
        msg = "visit stamps must be odometry stamps"
        raise ModelError(msg)
    inside = np.flatnonzero((st >= t[0]) & (st <= t[-1]))
    if not any(len(scan_points[int(k)]) for k in inside):  # nothing to match: the smoothing as it is
        res = robust_visit_poses(labels, visits, odometry, loops, scfg)
        traj = smoothed_trajectory(t, u, t[vidx], res.poses)
        nodes = vidx.astype(np.intp)
        return Refinement(trajectory=traj, nodes=nodes, keyframes=0, closures=(), tried=0, rounds=0)
    x_visits, _, _ = optimize_poses(labels, visits, odometry, loops)  # validates the topology
    scan_pose = interpolate_poses(t, u, st[inside])
    s_travel, s_turned = _cumulative(scan_pose)
    keys = inside[keyframe_scans(s_travel, s_turned, cfg.keyframe_xy, cfg.keyframe_yaw)]
    # a keyframe's node is the odometry sample at or just before its scan; its submap is in that frame
    knode = np.clip(np.searchsorted(t, st[keys], side="right") - 1, 0, len(t) - 1)
    nodes, inverse_idx = np.unique(np.concatenate([knode, vidx]), return_inverse=True)
    key_node = inverse_idx[: len(keys)]
    visit_node = inverse_idx[len(keys) :]
    submaps = _submaps(u, knode, keys, inside, s_travel, scan_pose, scan_points, cfg.submap_travel)

    travel, turned = _cumulative(u)
    odo = _odometry_factors(nodes, u, travel, turned, odometry)
    canon = canonical(labels)
    # start: the Gaussian optimum's visit poses, the odometry between them deformed to fit
    x = smoothed_trajectory(t, u, t[vidx], x_visits)[nodes]
    found: list[tuple[int, int, FloatArray, FloatArray]] = []
    axes: list[FloatArray | None] = []  # each found match's corridor axis (None: a sharp match)
    seen: set[tuple[int, int]] = set()
    g = _graph(odo, visit_node, canon, loops, closures=found, config=odometry)
    x, weights, _ = robust_optimum(x, g, scfg)
    tried = rounds = 0
    key_travel = travel[knode]
    for _ in range(cfg.rounds):
        rounds += 1
        new = 0
        kx = x[key_node]
        pairs: list[tuple[int, int]] = []
        jobs: list[RegistrationJob] = []
        for i in range(len(keys)):
            d = np.hypot(kx[:, 0] - kx[i, 0], kx[:, 1] - kx[i, 1])
            cand = np.flatnonzero((d <= cfg.search_radius) & (key_travel - key_travel[i] >= cfg.min_travel))
            for j in cand[np.argsort(d[cand], kind="stable")][: cfg.max_candidates]:
                source, target = submaps[j], submaps[i]
                if (i, j) in seen or source is None or target is None:
                    continue
                seen.add((i, j))
                pairs.append((i, int(j)))
                jobs.append(RegistrationJob(source, target, between(kx[i], kx[j]), lcfg, cfg.corridors))
        tried += len(jobs)
        for (i, j), job, reg in zip(pairs, jobs, mapper(register_job, jobs), strict=True):
            if reg is None:
                continue
            cov = _closure_cov(reg, cfg)
            if cov is not None and math.hypot(*(reg.mean[:2] - job.initial[:2])) <= cfg.max_shift:
                found.append((int(key_node[i]), int(key_node[j]), reg.mean, cov))
                axes.append(reg.slide_axis)  # None for a valid (sharp) match
                new += 1
        if new == 0:
            break
        g = _graph(odo, visit_node, canon, loops, closures=found, config=odometry)
        x, weights, _ = robust_optimum(x, g, scfg)
    n_cl = len(found)
    final_w = weights.factors[len(weights.factors) - n_cl :] if n_cl else np.zeros(0)
    closures = tuple(
        Closure(a=a, b=b, mean=m, cov=c, weight=float(w), slide_axis=k)
        for (a, b, m, c), w, k in zip(found, final_w, axes, strict=True)
    )
    x[:, 2] = wrap_angle(x[:, 2])
    traj = smoothed_trajectory(t, u, t[nodes], x)
    return Refinement(
        trajectory=traj, nodes=nodes, keyframes=len(keys), closures=closures, tried=tried, rounds=rounds
    )


def _closure_cov(reg: Registration, config: RefinementConfig) -> FloatArray | None:
    """The covariance a registration enters the graph with: its own when valid; for a corridor match
    (:attr:`ptm_ros.perception.laser.Registration.slide_axis`, with ``config.corridors``) its own plus
    ``corridor_std²`` along the axis; None when it does not enter."""
    if reg.valid:
        return reg.cov
    if not config.corridors or reg.slide_axis is None:
        return None
    cov = reg.cov.copy()
    cov[:2, :2] += config.corridor_std**2 * np.outer(reg.slide_axis, reg.slide_axis)
    return cov


def _submaps(  # noqa: PLR0917 - internal helper
    poses: FloatArray,
    knode: NDArray[np.intp],
    keys: NDArray[np.intp],
    inside: NDArray[np.intp],
    s_travel: FloatArray,
    scan_pose: FloatArray,
    scan_points: Sequence[FloatArray],
    reach: float,
) -> list[FloatArray | None]:
    """Each keyframe's submap: the scans within ``reach`` of travel, in the frame of its node's odometry
    pose, voxel-downsampled at 5 cm; None when no scan has points."""
    where = {int(s): k for k, s in enumerate(inside)}
    out: list[FloatArray | None] = []
    for key, node in zip(keys, knode, strict=True):
        k = where[int(key)]
        near = np.flatnonzero(np.abs(s_travel - s_travel[k]) <= reach)
        frame = poses[node]
        clouds = [
            transform_points(between(frame, scan_pose[m]), np.asarray(scan_points[inside[m]], dtype=float))
            for m in near
            if len(scan_points[inside[m]])
        ]
        out.append(voxel_downsample(np.vstack(clouds), 0.05) if clouds else None)
    return out
