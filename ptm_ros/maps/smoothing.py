"""Smoothed trajectories for a topology (thesis Ch. 5, Fig. 50/52, 56–57).

Given a topology, :func:`ptm_ros.model.odometry.optimize_poses` gives the maximum-likelihood visit poses X*
under the odometry, the topology's same-place constraints and the laser registrations. The full
trajectory between two visits is then the odometry deformed to fit them: a sample at time t between
visits k and k+1 is carried forward from X*_k and backward from X*_{k+1} by the raw odometry increments,

.. math::
    a_t = X^*_k \\oplus (u_k \\ominus u_t), \\qquad b_t = X^*_{k+1} \\oplus (u_{k+1} \\ominus u_t),

and the two are blended by the fraction of odometry travel s ∈ [0, 1] from k to k+1 (positions linearly,
headings along the shortest arc). At the visits the result equals X* exactly; before the first and after
the last visit the odometry is carried rigidly. This spreads each inter-visit correction along the path in
proportion to distance travelled, as odometry error accumulates.

Robust place coincidence (:func:`robust_visit_poses`, :func:`smooth_topology`). The metric likelihood
asks every visit of a place to pass within σ_T of the place point, a Gaussian. Written over pairs, the
same term is :math:`\\sum_{i<j \\in s} \\lVert x_i^{xy} - x_j^{xy}\\rVert^2 / (2\\,|s|\\,\\sigma_T^2)` (the
sum of squared deviations from the place mean equals the pair sum divided by ``|s|``). That is right for
*scoring* topologies, where a visit far from its place must cost dearly. For the *trajectory* of one
chosen topology it is too brittle: a single wrong merge of the MAP topology (MIT CSAIL: two visits 8.4 m
apart) or a wide place (real laser-surprise places: visits up to 3–4 m apart, σ_T = 0.5 m) pulls the
whole pose graph towards an impossible coincidence. The smoothing therefore replaces each pair's Gaussian
by a Cauchy (Student-t, ν = 1) density of the same scale :math:`s_{ij} = \\sigma_T \\sqrt{|s|}`,

.. math::
    -\\log p(x_i, x_j) = \\log\\big(1 + \\lVert x_i^{xy} - x_j^{xy}\\rVert^2 / s_{ij}^2\\big) + \\text{const},

which is the Gaussian near coincidence and lets a pair that cannot coincide go. Odometry and the
topology's laser registrations (validated measurements, :mod:`ptm_ros.perception.laser`) stay Gaussian, as in
:mod:`ptm_ros.model.odometry`. The optimum is found by iteratively reweighted least squares (each round a
Levenberg–Marquardt solve with pair weights :math:`w = 1 / (1 + r^2)`), started at the Gaussian optimum
of :func:`ptm_ros.model.odometry.optimize_poses`; each round lowers the Cauchy cost (majorise–minimise).
The solver, :func:`robust_optimum`, takes any :class:`RobustGraph`: relative factors, each Gaussian or
Cauchy in its whitened residual (``1 + |r|²``), and place pairs; :mod:`ptm_ros.maps.refinement` adds its
keyframe scan matches to it as Cauchy factors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.maps.posegraph import RelativeFactors, levenberg_marquardt, relative_jacobian, relative_residuals
from ptm_ros.model.geometry import FloatArray, RelativePose, between, compose, wrap_angle
from ptm_ros.model.odometry import (
    OdometryConfig,
    odometry_covariances,
    optimize_poses,
    relative_odometry,
)
from ptm_ros.model.partitions import Labels, blocks, canonical
from ptm_ros.model.visits import Visit


def smoothed_trajectory(
    odom_stamps: ArrayLike, odom_poses: ArrayLike, visit_stamps: ArrayLike, visit_poses: ArrayLike
) -> NDArray[np.float64]:
    """The odometry trajectory ``(T, 3)`` deformed to pass through the optimised visit poses.

    ``visit_stamps`` must be odometry stamps (visits sit on odometry samples) in increasing order;
    ``visit_poses`` ``(N, 3)`` are the optimised poses at those stamps.
    """
    t = np.asarray(odom_stamps, dtype=float).reshape(-1)
    u = np.asarray(odom_poses, dtype=float).reshape(-1, 3)
    vs = np.asarray(visit_stamps, dtype=float).reshape(-1)
    x = np.asarray(visit_poses, dtype=float).reshape(-1, 3)
    if len(t) != len(u) or len(vs) != len(x) or len(vs) == 0:
        msg = f"need matching stamps/poses: {len(t)}/{len(u)} odometry, {len(vs)}/{len(x)} visits"
        raise ModelError(msg)
    idx = np.searchsorted(t, vs)
    if np.any(idx >= len(t)) or np.any(t[np.minimum(idx, len(t) - 1)] != vs) or np.any(np.diff(idx) <= 0):
        msg = "visit stamps must be increasing odometry stamps"
        raise ModelError(msg)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(u[:, 0]), np.diff(u[:, 1])))])
    out = np.empty_like(u)
    # before the first and after the last visit: rigid transport of the odometry
    out[: idx[0]] = compose(x[0], between(u[idx[0]], u[: idx[0]]))
    out[idx[-1] :] = compose(x[-1], between(u[idx[-1]], u[idx[-1] :]))
    for k in range(len(idx) - 1):
        lo, hi = idx[k], idx[k + 1]
        seg = u[lo : hi + 1]
        a = compose(x[k], between(u[lo], seg))
        b = compose(x[k + 1], between(u[hi], seg))
        span = travel[hi] - travel[lo]
        s = (travel[lo : hi + 1] - travel[lo]) / span if span > 0 else np.linspace(0.0, 1.0, hi - lo + 1)
        xy = (1.0 - s)[:, None] * a[:, :2] + s[:, None] * b[:, :2]
        yaw = wrap_angle(a[:, 2] + s * wrap_angle(b[:, 2] - a[:, 2]))
        out[lo : hi + 1] = np.column_stack([xy, yaw])
    out[idx] = x  # exactly the optimised poses at the visits
    return out


@dataclass(frozen=True)
class SmoothingConfig:
    """Robust optimisation of the visit poses of one topology (:func:`robust_visit_poses`).

    Attributes:
        robust_places: Cauchy place coincidence (module docstring); False returns the Gaussian optimum of
            :func:`ptm_ros.model.odometry.optimize_poses` unchanged.
        max_rounds: reweighting rounds at most.
        max_iterations: Levenberg–Marquardt iterations of each weighted solve.
        tolerance: the reweighting stops when no pair weight changes by more than this.
    """

    robust_places: bool = True
    max_rounds: int = 100
    max_iterations: int = 50
    tolerance: float = 1e-4

    def __post_init__(self) -> None:
        if not isinstance(self.robust_places, bool):
            msg = f"SmoothingConfig.robust_places must be a bool, got {self.robust_places!r}"
            raise ConfigError(msg)
        for name in ("max_rounds", "max_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                msg = f"SmoothingConfig.{name} must be an integer >= 1, got {value!r}"
                raise ConfigError(msg)
        tol = self.tolerance
        if isinstance(tol, bool) or not isinstance(tol, int | float) or not (math.isfinite(tol) and tol > 0):
            msg = f"SmoothingConfig.tolerance must be a finite number > 0, got {tol!r}"
            raise ConfigError(msg)


@dataclass(frozen=True)
class VisitPoses:
    """Optimised visit poses of one topology.

    Attributes:
        poses: ``(N, 3)`` visit poses (``poses[0]`` is the gauge ``u_0``; headings wrapped).
        pairs: ``(P, 2)`` visit pairs ``i < j`` of the same place.
        weights: ``(P,)`` final Cauchy weight ``1 / (1 + r²)`` of each pair (1: coincide; near 0: let go).
        rounds: reweighting rounds run (0: the Gaussian optimum).
    """

    poses: FloatArray
    pairs: NDArray[np.intp]
    weights: FloatArray
    rounds: int


def place_pairs(labels: Sequence[int], sigma_topology: float) -> tuple[NDArray[np.intp], FloatArray]:
    """Every pair ``i < j`` of visits of one place ``(P, 2)`` and its scale ``σ_T √|s|`` ``(P,)``: the
    pairwise form of the Gaussian coincidence term of :mod:`ptm_ros.model.odometry` (module docstring)."""
    pairs, scales = [], []
    for block in blocks(labels):
        k = len(block)
        for a in range(k):
            for b in range(a + 1, k):
                pairs.append((block[a], block[b]))
                scales.append(sigma_topology * math.sqrt(k))
    return np.array(pairs, dtype=np.intp).reshape(-1, 2), np.array(scales, dtype=float)


@dataclass(frozen=True)
class RobustGraph:
    """A pose graph of relative factors and place pairs (:func:`robust_optimum`).

    Attributes:
        factors: relative-pose factors (:mod:`ptm_ros.maps.posegraph`), whitened.
        robust: ``(Q,)`` which factors are Cauchy (a measurement that may be wrong, e.g. a scan match
            between keyframes); the others stay Gaussian (odometry, validated visit registrations).
        pairs: ``(P, 2)`` node pairs of one place, Cauchy in the distance of their positions …
        scales: ``(P,)`` … at scale ``s_ij`` (module docstring).
    """

    factors: RelativeFactors
    robust: NDArray[np.bool_]
    pairs: NDArray[np.intp]
    scales: FloatArray


def _graph(
    labels: Labels, visits: Sequence[Visit], odometry: OdometryConfig, loops: Sequence[RelativePose]
) -> RobustGraph:
    n = len(visits)
    var = np.diagonal(odometry_covariances(visits, odometry), axis1=1, axis2=2)
    odo_w = np.zeros((n - 1, 3, 3))
    odo_w[:, np.arange(3), np.arange(3)] = 1.0 / np.sqrt(var)
    same = [lp for lp in loops if labels[lp.i] == labels[lp.j]]
    pairs, scales = place_pairs(labels, odometry.sigma_topology)
    factors = RelativeFactors(
        a=np.concatenate([np.arange(n - 1), [lp.i for lp in same]]).astype(np.intp),
        b=np.concatenate([np.arange(1, n), [lp.j for lp in same]]).astype(np.intp),
        z=np.concatenate([relative_odometry(visits), np.reshape([lp.mean for lp in same], (-1, 3))]),
        w=np.concatenate([odo_w, whitening(same)]),
    )
    return RobustGraph(
        factors=factors, robust=np.zeros(len(factors.a), dtype=bool), pairs=pairs, scales=scales
    )


def whitening(measurements: Sequence[RelativePose]) -> FloatArray:
    """``(M, 3, 3)`` whitening ``W = L⁻¹`` (``Σ = L Lᵀ``) of relative-pose measurements."""
    return np.reshape(
        [np.linalg.inv(np.linalg.cholesky(np.asarray(z.cov, dtype=float))) for z in measurements], (-1, 3, 3)
    )


def _pair_residuals(x: FloatArray, g: RobustGraph) -> FloatArray:
    """``(x_i^{xy} - x_j^{xy}) / s_ij`` of the place pairs, ``(P, 2)``."""
    return (x[g.pairs[:, 0], :2] - x[g.pairs[:, 1], :2]) / g.scales[:, None]


@dataclass(frozen=True)
class RobustWeights:
    """IRLS weights of the robust terms: ``factors`` ``(Q,)`` (1 for the Gaussian ones) and ``pairs``."""

    factors: FloatArray
    pairs: FloatArray


def _weighted_factors(g: RobustGraph, weights: RobustWeights) -> RelativeFactors:
    f = g.factors
    return RelativeFactors(a=f.a, b=f.b, z=f.z, w=f.w * np.sqrt(weights.factors)[:, None, None])


def _weighted_cost(x: FloatArray, g: RobustGraph, weights: RobustWeights) -> float:
    r, _, _ = relative_residuals(x, _weighted_factors(g, weights))
    rp = _pair_residuals(x, g)
    return 0.5 * (float(np.sum(r * r)) + float(weights.pairs @ np.sum(rp * rp, axis=1)))


def _normal_equations(
    x: FloatArray, g: RobustGraph, weights: RobustWeights
) -> tuple[sp.csc_matrix, FloatArray]:
    """``H = Jᵀ J`` (sparse) and ``Jᵀ r`` of the weighted residuals w.r.t. ``x_1..x_{N-1}`` (x_0 fixed):
    the relative factors (:mod:`ptm_ros.maps.posegraph`), then the place pairs scaled by ``√w``."""
    factors = _weighted_factors(g, weights)
    r, tx, ty = relative_residuals(x, factors)
    p, n = len(g.pairs), len(x)
    root_w = np.sqrt(weights.pairs)
    pair_rows = 2 * np.arange(p)[:, None] + np.arange(2)  # (P, 2)
    r_rows, r_cols, r_vals = [], [], []
    for side, sign in ((0, 1.0), (1, -1.0)):
        c = 3 * (g.pairs[:, side] - 1)[:, None] + np.arange(2)
        v = np.broadcast_to((sign * root_w / g.scales)[:, None], c.shape)
        ok = c >= 0  # visit 0 is the gauge
        r_rows.append(pair_rows[ok])
        r_cols.append(c[ok])
        r_vals.append(v[ok])
    pair_jac = sp.csr_matrix(
        (np.concatenate(r_vals), (np.concatenate(r_rows), np.concatenate(r_cols))), shape=(2 * p, 3 * (n - 1))
    )
    jac = sp.vstack([relative_jacobian(x, factors, tx, ty), pair_jac], format="csr")
    res = np.concatenate([r.ravel(), (root_w[:, None] * _pair_residuals(x, g)).ravel()])
    return (jac.T @ jac).tocsc(), jac.T @ res


def _cauchy_weights(x: FloatArray, g: RobustGraph) -> RobustWeights:
    """``1 / (1 + |r|²)`` of every robust term at ``x`` (whitened residuals; 1 for Gaussian factors)."""
    r, _, _ = relative_residuals(x, g.factors)
    fw = np.where(g.robust, 1.0 / (1.0 + np.sum(r * r, axis=1)), 1.0)
    rp = _pair_residuals(x, g)
    return RobustWeights(factors=fw, pairs=1.0 / (1.0 + np.sum(rp * rp, axis=1)))


def robust_optimum(
    x0: FloatArray, g: RobustGraph, config: SmoothingConfig
) -> tuple[FloatArray, RobustWeights, int]:
    """Poses minimising the Gaussian factors plus the Cauchy terms of ``g`` (``x_0`` fixed), by iteratively
    reweighted least squares from ``x0``: each round a Levenberg–Marquardt solve with the weights
    ``w = 1 / (1 + r²)`` of the previous optimum (majorise–minimise: every round lowers the Cauchy cost),
    until no weight changes by more than ``config.tolerance`` or ``config.max_rounds`` rounds ran.
    Returns the poses, the final weights and the rounds run."""
    x = x0.copy()
    weights = _cauchy_weights(x, g)
    rounds = 0
    while (len(g.pairs) or np.any(g.robust)) and rounds < config.max_rounds:
        rounds += 1
        x = levenberg_marquardt(
            x,
            partial(_weighted_cost, g=g, weights=weights),
            partial(_normal_equations, g=g, weights=weights),
            max_iterations=config.max_iterations,
            tolerance=1e-10,
        )
        new = _cauchy_weights(x, g)
        change = max(
            float(np.max(np.abs(new.factors - weights.factors), initial=0.0)),
            float(np.max(np.abs(new.pairs - weights.pairs), initial=0.0)),
        )
        weights = new
        if change <= config.tolerance:
            break
    return x, weights, rounds


def robust_visit_poses(
    labels: Sequence[int],
    visits: Sequence[Visit],
    odometry: OdometryConfig,
    loops: Sequence[RelativePose] = (),
    config: SmoothingConfig | None = None,
) -> VisitPoses:
    """Visit poses of a topology under odometry, its same-place laser registrations and the Cauchy place
    coincidence of the module docstring (iteratively reweighted from the Gaussian optimum).

    ``labels``, ``visits``, ``odometry`` and ``loops`` are those of
    :func:`ptm_ros.model.odometry.optimize_poses` (which validates them); registrations of visits of different
    places are ignored, as there.
    """
    cfg = SmoothingConfig() if config is None else config
    x, _, _ = optimize_poses(labels, visits, odometry, loops)  # validates; raises ModelError
    g = _graph(canonical(labels), visits, odometry, loops)
    rounds = 0
    if cfg.robust_places:
        x, weights, rounds = robust_optimum(x, g, cfg)
    else:
        weights = _cauchy_weights(x, g)
    out = x.copy()
    out[:, 2] = wrap_angle(out[:, 2])
    return VisitPoses(poses=out, pairs=g.pairs, weights=weights.pairs, rounds=rounds)


def smooth_topology(
    odom_stamps: ArrayLike,
    odom_poses: ArrayLike,
    labels: Sequence[int],
    visits: Sequence[Visit],
    odometry: OdometryConfig,
    *,
    loops: Sequence[RelativePose] = (),
    config: SmoothingConfig | None = None,
) -> FloatArray:
    """The odometry trajectory ``(T, 3)`` smoothed for a topology: :func:`robust_visit_poses`, then the
    path between the visits deformed to fit (:func:`smoothed_trajectory`). The visits' poses must come
    from ``odom_poses`` at their stamps (odometry stamps)."""
    res = robust_visit_poses(labels, visits, odometry, loops, config)
    return smoothed_trajectory(odom_stamps, odom_poses, [v.stamp for v in visits], res.poses)
