"""Laser patch registration: the scan measurement of two visits (thesis Ch. 3.10.4).

The RBPF weight of a topology sample integrates the landmark locations out of the joint likelihood of
the scan and odometry measurements (eq. 47–48); given the locations, scan and odometry factor
(eq. 49). The scan measurement ``s_n`` of visit ``n`` is a *local map patch* (Fig. 48,
:mod:`ptm_ros.perception.patches`). Whether two visits are one place, and where they lie relative to each
other, is then read off a registration of their patches (the thesis uses point-to-plane matching, Chen &
Medioni). This module turns that into a Gaussian measurement of the relative pose of two visits,

.. math::
    z_{ij} = x_i \\ominus x_j + v, \\qquad v \\sim \\mathcal{N}(0, \\Sigma_{ij}),

(:class:`~ptm_ros.model.geometry.RelativePose`) which the metric likelihood (:mod:`ptm_ros.model.odometry`)
consumes; a registration that fails its fitness test yields *no* measurement, never a false match.

* :class:`LaserConfig` — the parameters of patch building and patch registration;
* :func:`register_patches` — kiss-icp point-to-point ICP (coarse, then fine voxel map) from several
  initial headings, a point-to-plane Gauss–Newton polish whose inverse information is the covariance,
  and a validity test: symmetric inlier fraction, a sharp optimum, no equally good distinct solution;
* :func:`to_relative_pose` — the measurement, or None when the registration is not valid;
  :func:`fitness_log_bayes` and :func:`laser_outcome` — the fitness of every registration as evidence
  for or against one place;
* :class:`PatchRegistrar` — the registrations of a visit sequence's patches, each prepared once;
* helpers shared with :mod:`ptm_ros.perception.patches` (which imports this module, never the reverse):
  :func:`voxel_downsample`, the kiss-icp alignment and the point-to-plane polish, which keeps the guess
  along the directions a scan hardly constrains (:func:`weak_directions`, :func:`keep_unobserved`).

Direction convention: ``register_patches(source, target, …)`` estimates
``between(x_target, x_source)``, the pose of the *source* visit in the frame of the *target* visit, so
``transform_points(mean, source)`` lands on ``target``; ``to_relative_pose(reg, i=target, j=source)``.

kiss-icp (1.3) is imported lazily inside the functions that run ICP (core modules stay numpy/scipy
only); it is used through ``kiss_icp.mapping.VoxelHashMap`` and ``kiss_icp.registration.Registration``
with one thread, on ``(N, 3)`` points with ``z = 0`` (no deskewing: patches are already static).
"""

from __future__ import annotations

import math
from collections.abc import Callable, MutableMapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import LinAlgError, eigh
from scipy.linalg.lapack import dpotrf, dpotrs
from scipy.spatial import cKDTree
from scipy.special import betaln, xlog1py, xlogy

from ptm_ros.errors import ModelError, RegistrationError
from ptm_ros.model.geometry import (
    FloatArray,
    NoMatch,
    RelativePose,
    compose,
    inverse,
    moved,
    transform_points,
    wrap_angle,
)
from ptm_ros.model.visits import Visit
from ptm_ros.settings import Settings, setting

__all__ = [
    "FLAT_OPTIMUM",
    "LaserConfig",
    "Registration",
    "fitness_log_bayes",
    "laser_outcome",
    "register_patches",
    "to_relative_pose",
    "voxel_downsample",
]


_IDENTITY = np.zeros(3)
FLAT_OPTIMUM = "flat optimum"  # how Registration.reason starts when the match slides (a corridor)
_NORMAL_NEIGHBOURS = 16  # target points in the PCA of a normal
_MAX_CURVATURE = 0.05  # eigenvalue ratio above which a neighbourhood has no normal (corner, clutter)
_PREPARED_PATCHES = 512  # patches PatchRegistrar keeps prepared (least recently used dropped)
_T = TypeVar("_T")
_GN_ITERATIONS = 30  # point-to-plane Gauss–Newton iterations after kiss-icp
_MIN_RESIDUAL_VARIANCE = 1e-12  # m², keeps the information finite on noise-free data


# --------------------------------------------------------------------------------------------- config


@dataclass(frozen=True)
class LaserConfig(Settings):
    """Parameters of patch building and patch registration (lengths in m, angles in rad)."""

    patch_radius: float = setting(
        3.0, gt=0, doc="scans taken within this distance of the visit pose form its patch (Fig. 48)."
    )
    patch_voxel: float = setting(
        0.05, gt=0, doc="resolution at which patches are stored (first point per voxel)."
    )
    keyframe_xy: float = setting(
        0.05, ge=0, doc="a scan joins a patch only after the robot moved this far since the last one …"
    )
    keyframe_yaw: float = setting(0.05, ge=0, doc="… or turned this much.")
    refine: bool = setting(
        True, doc="correct the odometry along a passage by scan-to-map ICP before concatenating."
    )
    voxel: float = setting(
        0.5,
        ge=0.25,
        doc=(
            "kiss-icp map voxel of the fine ICP stage (at least 0.25 for kiss-icp); the coarse stage uses "
            "twice this."
        ),
    )
    max_range: float = setting(
        30.0,
        gt=0,
        doc=(
            "longest beam used; pass ``min(scan.range_max, max_range)`` to :func:`scan_to_points`; patches "
            "drop points farther from their sensor."
        ),
    )
    correspondence_distance: float = setting(
        1.0, gt=0, doc="maximum point distance of a correspondence in the fine ICP stage."
    )
    n_rotations: int = setting(
        8, ge=1, doc="initial headings tried, evenly spaced over the full turn around the guess."
    )
    inlier_distance: float = setting(
        0.15, gt=0, doc="a source point within this distance of the target is an inlier."
    )
    min_inlier_fraction: float = setting(
        0.4,
        gt=0,
        le=1,
        doc=(
            "a registration is valid only if at least this fraction of the source points lie near the target "
            "*and* of the target points near the source."
        ),
    )
    min_points: int = setting(
        30,
        ge=4,
        doc=(
            "fewest points a (downsampled) patch may have to be registered, and fewest inliers of a valid "
            "registration."
        ),
    )
    distinct_xy: float = setting(1.0, gt=0, doc="translation at which two solutions count as distinct.")
    distinct_yaw: float = setting(0.17, gt=0, doc="rotation at which two solutions count as distinct.")
    min_peak_drop: float = setting(
        0.2,
        ge=0,
        lt=1,
        doc=(
            "the match must be a sharp peak: moving the solution by ``distinct_xy`` (in any of 8 directions) "
            "or turning it by ``±distinct_yaw`` must lose at least this inlier fraction (rejects corridors "
            "and other sliding matches)."
        ),
    )
    ambiguity_margin: float = setting(
        0.1,
        ge=0,
        lt=1,
        doc=(
            "the registration is invalid when a distinct solution from another initial heading comes within "
            "this inlier fraction of the best one (symmetric rooms)."
        ),
    )
    min_std_xy: float = setting(0.05, gt=0, doc="covariance floor, translation standard deviation.")
    min_std_yaw: float = setting(0.02, gt=0, doc="covariance floor, heading standard deviation.")
    max_iterations: int = setting(100, ge=1, doc="ICP iterations per stage.")
    use_fitness: bool = setting(
        True,
        doc=(
            "besides the relative pose of a valid match, score the fitness ``f`` (the symmetric inlier "
            "fraction of the best alignment) of every registration of a chained pair as evidence for or "
            "against one place (:func:`fitness_log_bayes`); a failed match is then evidence too."
        ),
    )
    fitness_same_a: float = setting(
        1.6, gt=0, doc="shape ``a`` of the Beta density of the fitness ``f`` for two visits of one place."
    )
    fitness_same_b: float = setting(
        1.6, gt=0, doc="shape ``b`` of the Beta density of the fitness ``f`` for two visits of one place."
    )
    fitness_different_a: float = setting(
        6.5,
        gt=0,
        doc="shape ``a`` of the Beta density of the fitness ``f`` for visits of different places.",
    )
    fitness_different_b: float = setting(
        31.3,
        gt=0,
        doc="shape ``b`` of the Beta density of the fitness ``f`` for visits of different places.",
    )
    fitness_outlier: float = setting(
        0.05,
        ge=0,
        lt=1,
        doc="weight of a uniform component mixed into both fitness densities (robustness).",
    )


# ----------------------------------------------------------------------------------- registration


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register_patches`.

    Attributes:
        mean: ``(3,)`` estimate of ``between(x_target, x_source)`` (source visit in the target frame).
        cov: ``(3, 3)`` symmetric positive-definite covariance of ``mean`` (floored).
        inlier_fraction: the smaller of ``source_fraction`` and ``target_fraction``.
        source_fraction: fraction of (downsampled) source points within ``inlier_distance`` of the target.
        target_fraction: fraction of (downsampled) target points within ``inlier_distance`` of the source.
        rmse: root-mean-square distance of the source inliers (m); NaN without inliers.
        n_inliers: number of source inliers.
        n_points: number of (downsampled) source points.
        valid: whether the registration passes the fitness, sharpness and ambiguity tests.
        reason: why it is not valid (empty when valid).
    """

    mean: FloatArray
    cov: FloatArray
    inlier_fraction: float
    source_fraction: float
    target_fraction: float
    rmse: float
    n_inliers: int
    n_points: int
    valid: bool
    reason: str = ""
    candidates: tuple[tuple[float, float, float, float], ...] = field(default=(), repr=False)
    """``(x, y, yaw, inlier_fraction)`` of the ICP solution from every initial heading, best first."""
    slide_axis: FloatArray | None = None
    """Asked for (``register_patches(..., slide_axis=True)``) and the registration invalid only because
    its optimum is flat: the unit ``(2,)`` axis (target frame) it slides along when that is a
    *corridor*, sharp across the axis and in heading, with no ambiguous solution off the axis
    (:func:`_slide_axis`); None otherwise (valid ones included)."""


def register_patches(
    source: ArrayLike,
    target: ArrayLike,
    initial: ArrayLike = (0.0, 0.0, 0.0),
    config: LaserConfig | None = None,
    *,
    slide_axis: bool = False,
) -> Registration:
    """Register patch ``source`` onto patch ``target`` (both in their own visit's frame).

    ``initial`` is a guess of ``between(x_target, x_source)`` (e.g. ``(0, 0, 0)`` when the two visits
    are hypothesised to be one place). ICP (kiss-icp, point-to-point, coarse then fine voxel map) starts
    from ``initial ⊕ (0, 0, 2πk/K)``, ``K = config.n_rotations``, because two visits of one place may
    face any heading. The solution with the largest symmetric inlier fraction is polished by
    point-to-plane Gauss–Newton (Chen & Medioni, as in the thesis); its covariance is the inverse
    information ``(Σ_k g_k g_kᵀ / σ² + P⁻¹)⁻¹`` (target normals from local PCA, ``σ²`` the residual
    variance, ``P`` a weak prior of one patch radius / π), floored at
    ``(min_std_xy, min_std_xy, min_std_yaw)``.

    The result is valid when (1) at least ``min_inlier_fraction`` of the source points lie within
    ``inlier_distance`` of the target and of the target points near the source, with at least
    ``min_points`` inliers; (2) the optimum is sharp: shifting it by ``distinct_xy`` or turning it by
    ``distinct_yaw`` loses at least ``min_peak_drop`` of that fraction; (3) no distinct solution from
    another heading comes within ``ambiguity_margin`` of it. With ``slide_axis``, a registration that
    fails only the sharpness test reports the corridor it slides along, if it is one
    (:attr:`Registration.slide_axis`).

    Raises:
        ModelError: malformed inputs.
        RegistrationError: a patch has fewer than ``config.min_points`` points after downsampling
            (kiss-icp would silently return the initial guess).
    """
    cfg = LaserConfig() if config is None else config
    src = _as_points(source, "source")
    tgt = _as_points(target, "target")
    guess = _as_pose(initial, "initial")
    return _register(_PreparedPatch(src, cfg), _PreparedPatch(tgt, cfg), guess, cfg, slide_axis=slide_axis)


def _register(
    source: _PreparedPatch,
    target: _PreparedPatch,
    guess: FloatArray,
    cfg: LaserConfig,
    *,
    slide_axis: bool = False,
) -> Registration:
    """:func:`register_patches` of two patches prepared with ``cfg`` (:class:`_PreparedPatch`)."""
    n_src, n_tgt = len(source.surface.eval), len(target.surface.eval)
    if min(n_src, n_tgt) < cfg.min_points:
        msg = (
            f"patches too small to register: source {n_src}, target {n_tgt} points after "
            f"{0.5 * cfg.voxel:.3g} m downsampling (need {cfg.min_points})"
        )
        raise RegistrationError(msg)

    from kiss_icp.registration import Registration as KissRegistration

    fine_map, coarse_map = target.voxel_maps()
    icp = KissRegistration(
        max_num_iterations=cfg.max_iterations, convergence_criterion=1e-4, max_num_threads=1
    )
    coarse_distance = 3.0 * (2.0 * cfg.voxel)
    poses = []
    for k in range(cfg.n_rotations):
        pose: FloatArray | None = compose(guess, np.array([0.0, 0.0, 2.0 * np.pi * k / cfg.n_rotations]))
        pose = _align(icp, source.coarse, coarse_map, pose, coarse_distance)
        pose = _align(icp, source.fine, fine_map, pose, cfg.correspondence_distance)
        if pose is not None:
            poses.append(pose)
    if not poses:
        msg = "ICP diverged from every initial heading"
        raise RegistrationError(msg)
    overlap = _Overlap(source.surface, target.surface, cfg.inlier_distance)
    fits = overlap.fits(poses)
    fits.sort(key=lambda f: (-f.fraction, f.rmse if f.n_inliers else math.inf))
    prior_std = np.array([cfg.patch_radius, cfg.patch_radius, np.pi])
    refined, cov, _ = _point_to_plane(fits[0].pose, overlap, cfg, prior_std)
    fits[0] = best = overlap(refined)
    reason = _invalid_reason(fits, overlap, cfg)
    axis = _slide_axis(fits, overlap, cfg) if slide_axis and reason.startswith(FLAT_OPTIMUM) else None
    floor = np.array([cfg.min_std_xy, cfg.min_std_xy, cfg.min_std_yaw])
    return Registration(
        mean=best.pose,
        cov=_floor_cov(cov, floor),
        inlier_fraction=best.fraction,
        source_fraction=best.source_fraction,
        target_fraction=best.target_fraction,
        rmse=best.rmse,
        n_inliers=best.n_inliers,
        n_points=n_src,
        valid=not reason,
        reason=reason,
        candidates=tuple((float(f.pose[0]), float(f.pose[1]), float(f.pose[2]), f.fraction) for f in fits),
        slide_axis=axis,
    )


@dataclass(frozen=True)
class _Fit:
    """Symmetric fitness of one relative pose."""

    pose: FloatArray
    source_fraction: float
    target_fraction: float
    n_inliers: int
    rmse: float

    @property
    def fraction(self) -> float:
        return min(self.source_fraction, self.target_fraction)


class _Target:
    """A point set with its evaluation points (downsampled at ``voxel``), KD-tree and normals, each
    computed once on first use (reusable by every alignment onto it)."""

    def __init__(self, tgt: FloatArray, voxel: float) -> None:
        self.pts = tgt
        self.voxel = voxel
        self._normals = np.full((len(tgt), 2), np.nan)
        self._flat = np.zeros(len(tgt), dtype=bool)

    @cached_property
    def eval(self) -> FloatArray:
        """The points downsampled at ``voxel`` (where fitness is evaluated)."""
        return voxel_downsample(self.pts, self.voxel)

    @cached_property
    def tree(self) -> cKDTree:
        """KD-tree of all the points."""
        return cKDTree(self.pts)

    def normals_at(self, idx: np.ndarray) -> tuple[FloatArray, np.ndarray]:
        """Normals of points ``idx`` and whether each is line-like (computed once, on demand)."""
        missing = idx[np.isnan(self._normals[idx, 0])]
        if len(missing):
            todo = np.zeros(len(self.pts), dtype=bool)
            todo[missing] = True
            todo = np.flatnonzero(todo)  # sorted and unique
            self._normals[todo], self._flat[todo] = _normals(self.pts, self.tree, todo)
        return self._normals[idx], self._flat[idx]


class _PreparedPatch:
    """A patch prepared once for any number of registrations (:func:`_register`), as source or target:
    its :class:`_Target` at half the fine voxel (fitness points, KD-tree, normals), its points at the
    fine and the coarse ICP voxel, and, on first use as a target, its kiss-icp voxel maps."""

    def __init__(self, points: FloatArray, cfg: LaserConfig) -> None:
        self.surface = _Target(points, 0.5 * cfg.voxel)
        self.fine = voxel_downsample(points, cfg.voxel)
        self.coarse = voxel_downsample(points, 2.0 * cfg.voxel)
        self._voxel = cfg.voxel
        self._extent = cfg.max_range + cfg.patch_radius  # only points added with update() are culled by it
        self._maps: tuple[object, object] | None = None

    def voxel_maps(self) -> tuple[object, object]:
        """kiss-icp voxel maps of all the patch's points at the fine and at the coarse voxel."""
        if self._maps is None:
            from kiss_icp.mapping import VoxelHashMap

            pts = _lift(self.surface.pts)
            fine = VoxelHashMap(voxel_size=self._voxel, max_distance=self._extent, max_points_per_voxel=20)
            fine.add_points(pts)
            coarse = VoxelHashMap(
                voxel_size=2.0 * self._voxel, max_distance=self._extent, max_points_per_voxel=20
            )
            coarse.add_points(pts)
            self._maps = (fine, coarse)
        return self._maps


class _Overlap:
    """Inlier test of two patches under a relative pose, both ways (source → target, target → source).

    Evaluation points are each side's :attr:`_Target.eval`; distances are to the other side's full
    points. KD-tree searches are pruned just beyond ``inlier_distance`` (farther points are outliers
    whatever their distance), which leaves every inlier's distance and neighbour unchanged.
    """

    def __init__(self, source: _Target, target: _Target, inlier_distance: float) -> None:
        self.source = source
        self.target = target
        self.inlier_distance = inlier_distance
        self._bound = inlier_distance * (1.0 + 1e-9)

    @property
    def src_eval(self) -> FloatArray:
        return self.source.eval

    @property
    def tgt(self) -> FloatArray:
        return self.target.pts

    def normals_at(self, idx: np.ndarray) -> tuple[FloatArray, np.ndarray]:
        """Normals of target points ``idx`` and whether each is line-like."""
        return self.target.normals_at(idx)

    def near_target(self, pts: FloatArray) -> tuple[FloatArray, np.ndarray]:
        """Distance and index of the nearest target point of each of ``pts`` (exact within
        ``inlier_distance``; beyond it the distance may be ``inf`` and the index ``len(target)``)."""
        return self.target.tree.query(pts, distance_upper_bound=self._bound)

    def _source_distances(self, poses: Sequence[FloatArray]) -> FloatArray:
        """``(K, N)``: distances of the source evaluation points placed at each pose to the target."""
        src = self.source.eval
        d, _ = self.near_target(np.vstack([transform_points(p, src) for p in poses]))
        return d.reshape(len(poses), len(src))

    def _target_distances(self, poses: Sequence[FloatArray]) -> FloatArray:
        """``(K, M)``: distances of the target evaluation points to the source placed at each pose."""
        tgt = self.target.eval
        placed = np.vstack([transform_points(inverse(p), tgt) for p in poses])
        d, _ = self.source.tree.query(placed, distance_upper_bound=self._bound)
        return d.reshape(len(poses), len(tgt))

    def __call__(self, pose: FloatArray) -> _Fit:
        return self.fits([pose])[0]

    def fits(self, poses: Sequence[FloatArray]) -> list[_Fit]:
        """The fit of each pose (two KD-tree queries for all of them)."""
        d_src = self._source_distances(poses)
        d_tgt = self._target_distances(poses)
        out = []
        for pose, ds, dt in zip(poses, d_src, d_tgt, strict=True):
            inl = ds <= self.inlier_distance
            out.append(
                _Fit(
                    pose=pose,
                    source_fraction=float(inl.mean()),
                    target_fraction=float(np.mean(dt <= self.inlier_distance)),
                    n_inliers=int(inl.sum()),
                    rmse=float(np.sqrt(np.mean(ds[inl] ** 2))) if inl.any() else math.nan,
                )
            )
        return out

    def best_fraction(self, poses: Sequence[FloatArray]) -> float:
        """``max(self(p).fraction for p in poses)``; a pose's target side is evaluated only when its
        source fraction (an upper bound of its symmetric fraction) exceeds the maximum so far."""
        source = np.mean(self._source_distances(poses) <= self.inlier_distance, axis=1)
        best = -math.inf
        for pose, s in zip(poses, source, strict=True):
            if s > best:
                t = float(np.mean(self._target_distances([pose])[0] <= self.inlier_distance))
                best = max(best, min(float(s), t))
        return best


def _invalid_reason(fits: Sequence[_Fit], overlap: _Overlap, cfg: LaserConfig) -> str:
    """Why the best (first) fit is no trustworthy match (empty string when it is one)."""
    best = fits[0]
    if best.fraction < cfg.min_inlier_fraction:
        return (
            f"inlier fraction {best.fraction:.3f} < {cfg.min_inlier_fraction} "
            f"(source {best.source_fraction:.3f}, target {best.target_fraction:.3f})"
        )
    if best.n_inliers < cfg.min_points:
        return f"{best.n_inliers} inliers < {cfg.min_points}"
    angles = np.arange(8) * (np.pi / 4.0)
    shifts = [best.pose + cfg.distinct_xy * np.array([np.cos(a), np.sin(a), 0.0]) for a in angles]
    turns = [compose(best.pose, np.array([0.0, 0.0, s * cfg.distinct_yaw])) for s in (-1.0, 1.0)]
    nearby = overlap.best_fraction(shifts + turns)
    if best.fraction - nearby < cfg.min_peak_drop:
        return (
            f"{FLAT_OPTIMUM}: moving {cfg.distinct_xy} m or turning {cfg.distinct_yaw} rad keeps inlier "
            f"fraction {nearby:.3f} of {best.fraction:.3f}"
        )
    for other in fits[1:]:
        if other.fraction < best.fraction - cfg.ambiguity_margin:
            break
        if moved(best.pose, other.pose, cfg.distinct_xy, cfg.distinct_yaw):
            return (
                f"ambiguous: distinct solution {np.round(other.pose, 3).tolist()} has inlier fraction "
                f"{other.fraction:.3f} vs {best.fraction:.3f}"
            )
    return ""


def _slide_axis(fits: Sequence[_Fit], overlap: _Overlap, cfg: LaserConfig) -> FloatArray | None:
    """The corridor axis of a flat best (first) fit, or None when the optimum is not a corridor.

    The axis is the direction the matched surfaces do not constrain: the eigenvector of the smallest
    eigenvalue of ``Σ n_k n_kᵀ`` over the line-like target normals ``n_k`` at the source inliers. The fit
    is a corridor when moving it ``distinct_xy`` across that axis (both ways) or turning it
    ``distinct_yaw`` (both ways) loses at least ``min_peak_drop`` of its inlier fraction, and no solution
    from another initial heading within ``ambiguity_margin`` of it lies ``distinct_xy`` across the axis or
    ``distinct_yaw`` turned.
    """
    best = fits[0]
    placed = transform_points(best.pose, overlap.src_eval)
    dist, idx = overlap.near_target(placed)
    n, line = overlap.normals_at(idx[dist <= cfg.inlier_distance])
    n = n[line]
    if len(n) < cfg.min_points:
        return None
    _, vecs = np.linalg.eigh(n.T @ n)
    axis = vecs[:, 0]
    across = np.array([-axis[1], axis[0], 0.0]) * cfg.distinct_xy
    probes = [best.pose + across, best.pose - across]
    probes += [compose(best.pose, np.array([0.0, 0.0, s * cfg.distinct_yaw])) for s in (-1.0, 1.0)]
    if best.fraction - overlap.best_fraction(probes) < cfg.min_peak_drop:
        return None
    for other in fits[1:]:
        if other.fraction < best.fraction - cfg.ambiguity_margin:
            break
        off = other.pose - best.pose
        if (
            abs(off[0] * axis[1] - off[1] * axis[0]) >= cfg.distinct_xy
            or abs(wrap_angle(off[2])) >= cfg.distinct_yaw
        ):
            return None
    return axis


def fitness_log_bayes(fraction: float, config: LaserConfig | None = None) -> float:
    """log p(f | one place) − log p(f | different places) of a registration's fitness ``f`` ∈ [0, 1].

    ``f`` is the symmetric inlier fraction of the best alignment (:func:`register_patches`). The thesis
    keeps only the relative pose of a match (eq. 48–49) and treats a failed match as no information; but
    two patches of one place overlap far better than two of different places, whether or not the
    match passes the validity tests. Both densities are Beta mixed with a uniform of weight ``ε``:
    ``p(f) = (1 − ε) Beta(f; a, b) + ε``. Defaults were fitted (maximum likelihood) to 182 pairs of
    visits less than 1.5 m apart and 750 more than 4 m apart on the Intel, ACES and MIT runs
    (``../shared/datasets``, laser-surprise visits): one place Beta(1.6, 1.6), median 0.50; different
    places Beta(6.5, 31.3), median 0.16. The ratio is ≈ −2.0 at f = 0.15, 0 near 0.28, +3.2 at 0.5.
    """
    cfg = LaserConfig() if config is None else config
    f = float(np.clip(fraction, 0.0, 1.0)) if math.isfinite(fraction) else 0.0
    eps = cfg.fitness_outlier
    same = (1.0 - eps) * beta_pdf(f, cfg.fitness_same_a, cfg.fitness_same_b) + eps
    diff = (1.0 - eps) * beta_pdf(f, cfg.fitness_different_a, cfg.fitness_different_b) + eps
    return float(math.log(same) - math.log(diff))


def beta_pdf(f: float, a: float, b: float) -> float:
    """The Beta(a, b) density at ``f`` ∈ [0, 1], ``f^(a-1) (1-f)^(b-1) / B(a, b)`` (``0^0 = 1``), from
    :mod:`scipy.special` rather than :mod:`scipy.stats`, whose import (about 0.3 s) would otherwise fall
    into the first registration's outcome, inside a visit's update."""
    return float(np.exp(xlogy(a - 1.0, f) + xlog1py(b - 1.0, -f) - betaln(a, b)))


def to_relative_pose(registration: Registration, i: int, j: int) -> RelativePose | None:
    """The measurement of ``between(x_i, x_j)`` from a registration of patch j (source) onto patch i
    (target); None when the registration is not valid ("no information", never a false match)."""
    if i == j:
        msg = f"a relative pose needs two different visits, got i = j = {i}"
        raise ModelError(msg)
    if not registration.valid:
        return None
    return RelativePose(i=i, j=j, mean=registration.mean.copy(), cov=registration.cov.copy())


def laser_outcome(
    registration: Registration, i: int, j: int, config: LaserConfig
) -> RelativePose | NoMatch | None:
    """What the topology inference uses of a registration of patch j onto patch i: the relative pose of a
    valid match, else a :class:`~ptm_ros.model.geometry.NoMatch`; each with the fitness evidence
    (:func:`fitness_log_bayes`) when ``config.use_fitness`` (else a failed match is None)."""
    lb = fitness_log_bayes(registration.inlier_fraction, config) if config.use_fitness else 0.0
    z = to_relative_pose(registration, i, j)
    if z is not None:
        return RelativePose(i=z.i, j=z.j, mean=z.mean, cov=z.cov, log_bayes=lb)
    return NoMatch(i=i, j=j, log_bayes=lb) if config.use_fitness else None


# ------------------------------------------------------------------------------------------ helpers


def voxel_downsample(points: ArrayLike, voxel: float) -> FloatArray:
    """Keep the first point (in input order) of every ``voxel``-sized grid cell, sorted by cell.

    Deterministic, and idempotent on concatenations: ``voxel_downsample(vstack([voxel_downsample(A),
    B]))`` equals ``voxel_downsample(vstack([A, B]))``.
    """
    pts = _as_points(points, "points")
    if not (math.isfinite(voxel) and voxel > 0.0):
        msg = f"voxel must be finite and > 0, got {voxel}"
        raise ModelError(msg)
    if len(pts) == 0:
        return pts
    cells = np.floor(pts / voxel).astype(np.int64)
    lo, hi = cells.min(axis=0), cells.max(axis=0)
    cols, rows = int(hi[0]) - int(lo[0]) + 1, int(hi[1]) - int(lo[1]) + 1
    if cols * rows < 2**62:  # one integer key per cell, ordered like (cx, cy): a fast 1-D sort
        key = (cells[:, 0] - lo[0]) * rows + (cells[:, 1] - lo[1])
        _, first = np.unique(key, return_index=True)
    else:  # astronomically spread points: sort the cell pairs themselves
        _, first = np.unique(cells, axis=0, return_index=True)
    return pts[first]


def _as_points(points: ArrayLike, name: str) -> FloatArray:
    pts = np.asarray(points, dtype=float)
    if pts.size == 0:
        return np.empty((0, 2))
    if pts.ndim != 2 or pts.shape[1] != 2:
        msg = f"{name} must have shape (P, 2), got {pts.shape}"
        raise ModelError(msg)
    if not np.all(np.isfinite(pts)):
        msg = f"{name} holds non-finite coordinates"
        raise ModelError(msg)
    return pts


def _as_pose(pose: ArrayLike, name: str) -> FloatArray:
    p = np.asarray(pose, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        msg = f"{name} must be 3 finite numbers (x, y, yaw), got {p!r}"
        raise ModelError(msg)
    return p


def _lift(points: FloatArray) -> FloatArray:
    return np.ascontiguousarray(np.column_stack([points, np.zeros(len(points))]))


def _se3(pose: FloatArray) -> FloatArray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = pose[:2]
    return m


def _se2(matrix: FloatArray) -> FloatArray:
    """Project a 4×4 rigid transform to SE(2): planar translation, yaw from the rotated x-axis."""
    yaw = math.atan2(matrix[1, 0], matrix[0, 0])
    return np.array([matrix[0, 3], matrix[1, 3], float(wrap_angle(yaw))])


class _PointAligner(Protocol):
    """What :func:`_align` calls of a ``kiss_icp.registration.Registration`` (kiss-icp ships no types)."""

    def align_points_to_map(
        self,
        *,
        points: FloatArray,
        voxel_map: object,
        initial_guess: FloatArray,
        max_correspondance_distance: float,
        kernel: float,
    ) -> ArrayLike:
        """The 4×4 transform taking ``points`` onto ``voxel_map``, ICP from ``initial_guess``."""
        ...


def _align(
    icp: _PointAligner, src: FloatArray, voxel_map: object, pose: FloatArray | None, max_dist: float
) -> FloatArray | None:
    """One kiss-icp alignment of ``src`` onto ``voxel_map`` from ``pose``; None if it failed."""
    if pose is None:
        return None
    matrix = np.asarray(
        icp.align_points_to_map(
            points=_lift(src),
            voxel_map=voxel_map,
            initial_guess=_se3(pose),
            max_correspondance_distance=max_dist,
            kernel=max_dist / 3.0,
        ),
        dtype=float,
    )
    if not np.all(np.isfinite(matrix)):
        return None
    return _se2(matrix)


def _point_to_plane(
    pose: FloatArray,
    overlap: _Overlap,
    cfg: LaserConfig,
    prior_std: FloatArray,
    prior_mean: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gauss–Newton point-to-plane refinement of an ICP ``pose`` (Chen & Medioni, thesis Ch. 3.10.4),
    its covariance (before flooring) and the information of the residuals alone (without the prior).

    Each source point ``s_k`` (the fitness sample) within ``inlier_distance`` of its nearest target point
    ``m_k`` with a line-like neighbourhood and unit normal ``n_k`` gives the residual
    ``e_k = n_kᵀ (R s_k + t − m_k)`` with gradient ``g_k = (n_x, n_y, (R s_k) × n_k)`` with respect to
    ``(x, y, yaw)``. A Gaussian prior centred on ``prior_mean`` (default: the ICP pose) with standard
    deviations ``prior_std`` keeps the directions the residuals do not see (a corridor's axis) there:
    scan-to-map matching passes the odometry guess, because point-to-point ICP slides along a corridor.
    At convergence the covariance is ``(Σ g_k g_kᵀ / σ² + P⁻¹)⁻¹`` with
    ``σ² = Σ e_k² / (N − 3)``. If the refinement wanders farther than ``distinct_xy``/``distinct_yaw``
    the ICP pose is kept.
    """
    src, tgt = overlap.src_eval, overlap.tgt
    prior = np.diag(np.asarray(prior_std, dtype=float) ** -2)
    centre = pose if prior_mean is None else np.asarray(prior_mean, dtype=float)
    current = pose.copy()
    info = prior
    seen: dict[bytes, int] = {}  # pose entering each iteration -> the first iteration it entered
    done: list[tuple[FloatArray, FloatArray]] = []  # (information, pose) after each iteration
    for it in range(_GN_ITERATIONS):
        start = seen.setdefault(current.tobytes(), it)
        if start < it:
            # An iteration is a function of the pose alone, and none since ``start`` met the stopping
            # test: the iterations repeat with period it - start. Take the last one's result directly.
            info, current = done[start + (_GN_ITERATIONS - 1 - start) % (it - start)]
            break
        placed = transform_points(current, src)
        dist, idx = overlap.near_target(placed)
        close = np.flatnonzero(dist <= cfg.inlier_distance)
        n, flat = overlap.normals_at(idx[close])
        inl = close[flat]
        n = n[flat]
        if len(inl) <= 3:
            return pose, _spd_inverse(prior), np.zeros((3, 3))
        q = placed[inl]
        e = np.einsum("ij,ij->i", n, q - tgt[idx[inl]])
        arm = q - current[:2]
        g = np.column_stack([n, arm[:, 0] * n[:, 1] - arm[:, 1] * n[:, 0]])
        sigma2 = max(float(e @ e) / (len(e) - 3), _MIN_RESIDUAL_VARIANCE)
        info = prior + g.T @ g / sigma2
        offset = current - centre
        offset[2] = wrap_angle(offset[2])
        step = -_spd_solve(info, g.T @ e / sigma2 + prior @ offset)
        current = np.array(
            [current[0] + step[0], current[1] + step[1], float(wrap_angle(current[2] + step[2]))]
        )
        done.append((info, current))
        if np.max(np.abs(step)) < 1e-7:
            break
    if moved(pose, current, cfg.distinct_xy, cfg.distinct_yaw):
        current = pose
    cov = _spd_inverse(info)
    return current, 0.5 * (cov + cov.T), info - prior


def weak_directions(information: FloatArray, ratio: float) -> FloatArray:
    """Unit translation directions ``(k, 2)`` that a scan constrains less than ``ratio`` times its
    best-constrained one: eigenvectors of the translation block of the residuals' ``information`` whose
    eigenvalue is below ``ratio`` times the largest (none for ``ratio`` 0 or no information at all)."""
    if ratio <= 0.0:  # off: no eigen-decomposition per scan
        return np.zeros((0, 2))
    block = 0.5 * (information[:2, :2] + information[:2, :2].T)
    values, vectors = np.linalg.eigh(block)
    if values[-1] <= 0.0:
        return np.zeros((0, 2))
    return np.asarray(vectors[:, values < ratio * float(values[-1])].T, dtype=float)


def keep_unobserved(pose: FloatArray, guess: FloatArray, information: FloatArray, ratio: float) -> FloatArray:
    """``pose`` with its translation away from ``guess`` removed along the :func:`weak_directions` (solution
    remapping, Zhang, Kaess & Singh, ICRA 2016): there the guess (the wheel odometry) is kept. A
    corridor's walls fix the cross-track position and the heading, and only noise in the estimated normals
    "sees" the along-track one: point-to-point ICP and the polish then slide along the corridor by a
    fraction of every step, erasing the travel. ``ratio`` 0, or no information at all (the polish found no
    planes: ``pose`` is ICP's), keep ``pose``."""
    return _keep_guess_along(pose, guess, weak_directions(information, ratio))


def _keep_guess_along(pose: FloatArray, guess: FloatArray, weak: FloatArray) -> FloatArray:
    """``pose`` with the translation of ``guess`` along the unit directions ``weak`` ``(k, 2)``."""
    if not len(weak):
        return pose
    shift = pose[:2] - guess[:2]
    for v in weak:
        shift = shift - float(v @ shift) * v
    return np.array([guess[0] + shift[0], guess[1] + shift[1], pose[2]])


def _spd_solve(matrix: FloatArray, rhs: FloatArray) -> FloatArray:
    """``matrix⁻¹ rhs`` for a symmetric positive-definite ``matrix``: LAPACK's Cholesky (``potrf``, upper) and
    its solve (``potrs``) called directly, the numbers of scipy's ``cho_solve(cho_factor(...))`` without
    their per-call checks, which cost more than the 3 × 3 solve of a Gauss–Newton step.

    Raises:
        LinAlgError: ``matrix`` is not positive definite.
    """
    factor, info = dpotrf(matrix, lower=0, clean=0)
    if info != 0:
        msg = f"{info}-th leading minor not positive definite"
        raise LinAlgError(msg)
    return dpotrs(factor, rhs, lower=0)[0]  # its info flags illegal arguments only, not these


def _spd_inverse(matrix: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive-definite matrix (Cholesky)."""
    return _spd_solve(matrix, np.eye(len(matrix)))


def _normals(
    tgt: FloatArray, tree: cKDTree, which: np.ndarray, k: int = _NORMAL_NEIGHBOURS
) -> tuple[FloatArray, np.ndarray]:
    """Unit normals ``(M, 2)`` of target points ``which`` from the PCA of their ``k`` nearest neighbours,
    and whether each neighbourhood is line-like (smaller/larger scatter eigenvalue at most
    ``_MAX_CURVATURE``; corners and clutter have no reliable normal)."""
    k = min(k, len(tgt))
    _, nb = tree.query(tgt[which], k=k)
    nb_pts = tgt[nb.reshape(len(which), k)]
    centred = nb_pts - nb_pts.mean(axis=1, keepdims=True)
    scatter = np.einsum("mki,mkj->mij", centred, centred)
    vals, vecs = np.linalg.eigh(scatter)
    return vecs[:, :, 0], vals[:, 0] <= _MAX_CURVATURE * vals[:, 1]


def _floor_cov(cov: FloatArray, min_std: FloatArray) -> FloatArray:
    """Floor a covariance: raise the eigenvalues of ``D⁻¹ cov D⁻¹``, ``D = diag(min_std)``, to at least 1.

    The result is ⪰ ``cov`` and ⪰ ``D²`` (Loewner order) and equals ``cov`` when ``cov`` ⪰ ``D²`` already.
    """
    w = cov / np.outer(min_std, min_std)
    vals, vecs = eigh(w)
    floored = (vecs * np.maximum(vals, 1.0)) @ vecs.T
    out = floored * np.outer(min_std, min_std)
    return 0.5 * (out + out.T)


class WorkerPool(Protocol):
    """Runs a function elsewhere, :meth:`concurrent.futures.Executor.submit`'s shape (``ptm-run``'s worker
    processes)."""

    def submit(self, fn: Callable[..., _T], /, *args: Any, **kwargs: Any) -> Future[_T]: ...


def _same_place_registration(
    source: _PreparedPatch, target: _PreparedPatch, config: LaserConfig
) -> Registration | None:
    """``source`` registered onto ``target`` from ``(0, 0, 0)``; None when it cannot be registered."""
    try:
        return _register(source, target, _IDENTITY, config)
    except RegistrationError:
        return None


def register_patch_pair(target: FloatArray, source: FloatArray, config: LaserConfig) -> Registration | None:
    """Patch ``source`` registered onto patch ``target`` from ``(0, 0, 0)`` (:class:`PatchRegistrar`'s
    registration of one pair, with both patches prepared afresh); None when one cannot be registered."""
    return _same_place_registration(
        _PreparedPatch(_as_points(source, "source"), config),
        _PreparedPatch(_as_points(target, "target"), config),
        config,
    )


class PatchRegistrar:
    """Registrar over a visit sequence: visit j's patch registered onto visit i's from ``(0, 0, 0)`` (the
    "same place" hypothesis; the rotations tried cover any heading, and odometry drift makes an
    odometry-based guess meaningless). The outcome is :func:`laser_outcome`'s; None when a patch is
    missing or too small to register. ``counters`` (optional) accumulates ``registrations`` and
    ``registrations_valid``.

    ``visits`` may grow between calls. Each patch is prepared for registration (downsampled, its KD-tree,
    normals and voxel maps built) once and kept for the ``keep_prepared`` (default
    :data:`_PREPARED_PATCHES`) most recently used visits; a visit whose patch object changed is prepared
    afresh. The outcomes equal :func:`register_patches`' whatever ``keep_prepared``, and :meth:`many`'s.
    """

    def __init__(
        self,
        visits: Sequence[Visit],
        config: LaserConfig | None = None,
        counters: MutableMapping[str, int] | None = None,
        *,
        keep_prepared: int = _PREPARED_PATCHES,
    ) -> None:
        self.visits = visits
        self.config = LaserConfig() if config is None else config
        self.counters = counters
        self.keep_prepared = keep_prepared
        self._prepared: dict[int, tuple[FloatArray, _PreparedPatch]] = {}

    def _prepare(self, k: int, patch: FloatArray, role: str) -> _PreparedPatch:
        hit = self._prepared.pop(k, None)
        if hit is None or hit[0] is not patch:
            hit = (patch, _PreparedPatch(_as_points(patch, role), self.config))
        self._prepared[k] = hit  # most recently used last
        while len(self._prepared) > max(self.keep_prepared, 1):
            del self._prepared[next(iter(self._prepared))]
        return hit[1]

    def _outcome(self, reg: Registration | None, i: int, j: int) -> RelativePose | NoMatch | None:
        if reg is None:
            return None
        if self.counters is not None:
            self.counters["registrations"] = self.counters.get("registrations", 0) + 1
            self.counters["registrations_valid"] = self.counters.get("registrations_valid", 0) + int(
                reg.valid
            )
        return laser_outcome(reg, i, j, self.config)

    def __call__(self, i: int, j: int) -> RelativePose | NoMatch | None:
        a, b = self.visits[i].patch, self.visits[j].patch
        if a is None or b is None:
            return None
        source, target = self._prepare(j, b, "source"), self._prepare(i, a, "target")
        return self._outcome(_same_place_registration(source, target, self.config), i, j)

    def many(
        self, pairs: Sequence[tuple[int, int]], workers: WorkerPool
    ) -> dict[tuple[int, int], RelativePose | NoMatch | None]:
        """The outcomes of ``pairs``, registered by ``workers`` (:func:`register_patch_pair`), in order."""
        futures = {}
        for i, j in pairs:
            a, b = self.visits[i].patch, self.visits[j].patch
            futures[(i, j)] = (
                None if a is None or b is None else workers.submit(register_patch_pair, a, b, self.config)
            )
        return {
            (i, j): None if f is None else self._outcome(f.result(), i, j) for (i, j), f in futures.items()
        }


def patch_registrar(
    visits: Sequence[Visit],
    config: LaserConfig | None = None,
    counters: MutableMapping[str, int] | None = None,
    *,
    keep_prepared: int = _PREPARED_PATCHES,
) -> PatchRegistrar:
    """A :class:`PatchRegistrar` over ``visits``."""
    return PatchRegistrar(visits, config, counters, keep_prepared=keep_prepared)
