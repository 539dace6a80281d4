r"""Two reference methods a user might run instead of a PTM; each commits to one topology.

A PTM keeps a posterior over topologies (thesis §0.3); the methods below are the maximum-likelihood
approaches it argues against (§0.4, existing approaches: "the decision is binding once taken"; Fig. 7:
under aliasing the most likely topology can be wrong). Each returns a single canonical label tuple,
which a benchmark wraps as a PTM with probability 1 and scores like any other.

Greedy nearest-neighbour association (maximum likelihood, Lisien et al.'s hierarchical atlas)
--------------------------------------------------------------------------------------------
Visits are processed in order. Before visit ``n`` is decided, the pose graph of visits ``0..n`` is
optimised with the labels chosen so far and visit ``n`` as a place of its own
(:func:`ptm_ros.model.odometry.optimize_poses`: odometry factors and the coincidence factors of the places,
gauge :math:`x_0 = u_0`). For every existing place ``s`` the innovation is

.. math::
    \nu_s = x_n^{xy} - \bar x_s, \qquad \bar x_s = \tfrac{1}{|s|} \sum_{i \in s} x_i^{xy},
    \qquad S_s = A_s H^{-1} A_s^\top + \sigma_T^2 \big(1 + \tfrac{1}{|s|}\big) I_2,
    \qquad d_s^2 = \nu_s^\top S_s^{-1} \nu_s,

with ``H = JᵀJ`` the Gauss–Newton information at the optimum and ``A_s`` the ``2 × 3(n)`` selector of
:math:`x_n^{xy} - \bar x_s`. **Approximation**: ``H⁻¹`` is the Laplace (linearised) covariance of the
poses given odometry and the decisions so far, with ``x_0`` fixed; the place point :math:`p_s` of the
odometry model (uniform prior, every visit within :math:`\sigma_T` of it) has posterior
:math:`\mathcal N(\bar x_s, \sigma_T^2/|s|)` given the poses, and the new visit would lie within
:math:`\sigma_T` of it, hence the :math:`\sigma_T^2 (1 + 1/|s|)` term. Visit ``n`` joins the place of
smallest :math:`d_s^2` if it lies inside the chi-square gate (2 degrees of freedom, headings are not
constrained by a place), else it opens a new place; a decision is never revisited.

Cost: one pose-graph optimisation (warm-started) and one dense ``3n × 3n`` Cholesky factorisation per
visit, :math:`O(N^4)` in all: fine for a few hundred visits.

Robust pose-graph loop closure (a slam_toolbox / Cartographer-style back end)
---------------------------------------------------------------------------
1. *Candidates*: the odometry-only optimum of the pose graph is the odometry itself (every factor is
   met exactly), so candidates are the pairs ``i < j`` whose odometry positions lie within
   ``search_radius`` (every pair when ``N <= all_pairs_below``), nearest first, at most
   ``max_candidates``.
2. *Registration*: each candidate is registered (:func:`ptm_ros.perception.laser.register_patches`, visit
``j``'s
   patch onto visit ``i``'s, initial guess ``(0, 0, yaw_j - yaw_i)``) or answered by the caller's
   registrar; valid registrations are :class:`~ptm_ros.model.geometry.RelativePose` loop factors.
3. *Robust optimisation* (:func:`robust_pose_graph`): odometry factors plus loop factors under a
   Geman–McClure kernel :math:`\rho(r^2) = c^2 r^2 / (c^2 + r^2)` on the whitened loop residual ``r``,
   minimised by Graduated Non-Convexity (Yang, Antonante, Tzoumas, Carlone, RA-L 2020): the surrogate
   :math:`\rho_\mu(r^2) = \mu c^2 r^2 / (\mu c^2 + r^2)` is near-quadratic for large ``μ``; starting at
   :math:`\mu = 2 \max_k r_k^2 / c^2` (residuals of the plain least-squares solution), each step solves
   the weighted least squares with the Black–Rangarajan weights
   :math:`w_k = (\mu c^2 / (r_k^2 + \mu c^2))^2` and divides ``μ`` by ``gnc_factor`` down to 1, where
   the weights are iterated to a fixed point, a stationary point of the Geman–McClure cost.
4. *Topology*: loops with final weight ``>= inlier_threshold`` are inliers; an inlier whose registered
   translation is at most ``max_offset`` joins its two visits into one place (a valid registration of
   two nearby but distinct places is a correct metric constraint, not a revisit); places are the
   connected components.

Thesis: no equation of the thesis is implemented here; the innovation uses the odometry model of
:mod:`ptm_ros.model.odometry` (eq. 17 as corrected there: normalised, place points uniform over the area).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import LinAlgError, cho_factor, cho_solve, cholesky, solve_triangular

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.maps.posegraph import RelativeFactors, levenberg_marquardt, relative_jacobian, relative_residuals
from ptm_ros.model.geometry import FloatArray, Registrar, RelativePose, between, compose, wrap_angle
from ptm_ros.model.odometry import (
    OdometryConfig,
    odometry_covariances,
    optimize_poses,
    relative_odometry,
)
from ptm_ros.model.partitions import Labels, canonical
from ptm_ros.model.visits import Visit, poses_array
from ptm_ros.perception.laser import LaserConfig, patch_registrar

#: A registrar returns the laser measurement of ``between(x_i, x_j)`` for visits ``i < j``, or None
#: (no valid registration). Same contract as :mod:`ptm_ros.model.posterior` and :mod:`ptm_ros.inference.rbpf`.

__all__ = [
    "GreedyAssociation",
    "GreedyConfig",
    "Innovations",
    "LoopClosureConfig",
    "LoopClosureDetails",
    "RobustResult",
    "greedy_association",
    "loop_candidates",
    "patch_registrar",
    "place_innovations",
    "robust_loop_closure",
    "robust_pose_graph",
]


# ------------------------------------------------------------------------------------------ configs


def _check_float(owner: str, name: str, value: object, *, low: float, strict: bool) -> None:
    ok = (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and (value > low if strict else value >= low)
    )
    if not ok:
        bound = f"> {low}" if strict else f">= {low}"
        msg = f"{owner}.{name} must be a finite number {bound}, got {value!r}"
        raise ConfigError(msg)


def _check_int(owner: str, name: str, value: object, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        msg = f"{owner}.{name} must be an integer >= {low}, got {value!r}"
        raise ConfigError(msg)


@dataclass(frozen=True)
class GreedyConfig:
    """Greedy nearest-neighbour association.

    Attributes:
        gate_probability: a visit may join a place only if its squared Mahalanobis distance is below the
            chi-square quantile of this probability (2 degrees of freedom).
    """

    gate_probability: float = 0.99

    def __post_init__(self) -> None:
        p = self.gate_probability
        if not (isinstance(p, int | float) and 0.0 < p < 1.0):
            msg = f"GreedyConfig.gate_probability must be in (0, 1), got {p!r}"
            raise ConfigError(msg)

    @property
    def gate(self) -> float:
        """The gate on the squared Mahalanobis distance: the chi-square (2 dof) quantile ``-2 log(1 - p)``."""
        return -2.0 * math.log1p(-self.gate_probability)


@dataclass(frozen=True)
class LoopClosureConfig:
    """Robust pose-graph loop closure (lengths in m; residuals in standard deviations).

    Attributes:
        search_radius: a pair of visits is a loop candidate when their odometry positions are this close.
        all_pairs_below: with at most this many visits every pair is a candidate.
        max_candidates: at most this many candidates are registered, nearest first.
        max_offset: an inlier loop joins two visits into one place only if its registered translation
            is at most this long.
        kernel_scale: ``c`` of the Geman–McClure kernel on the whitened loop residual; the default makes
            weight 1/2 fall at ``r² = (√2 - 1) c² ≈ 14.9`` (the 99.8 % quantile of chi-square, 3 dof).
        inlier_threshold: loops whose final weight is at least this are inliers.
        gnc_factor: ``μ`` is divided by this at each GNC step (Yang et al. use 1.4; the slower default
            escaped local minima that rejected true loops in long synthetic runs with heavy drift).
        max_gnc_steps: cap on GNC steps, including the fixed-point iterations at ``μ = 1``.
        max_iterations: Levenberg–Marquardt iterations of each weighted least-squares solve.
        tolerance: relative cost decrease below which a solve stops; weight change below which the
            fixed-point iteration at ``μ = 1`` stops.
    """

    search_radius: float = 5.0
    all_pairs_below: int = 12
    max_candidates: int = 500
    max_offset: float = 1.5
    kernel_scale: float = 6.0
    inlier_threshold: float = 0.5
    gnc_factor: float = 1.2
    max_gnc_steps: int = 200
    max_iterations: int = 100
    tolerance: float = 1e-9

    def __post_init__(self) -> None:
        owner = "LoopClosureConfig"
        for name in ("search_radius", "max_offset", "kernel_scale", "tolerance"):
            _check_float(owner, name, getattr(self, name), low=0.0, strict=True)
        _check_float(owner, "gnc_factor", self.gnc_factor, low=1.0, strict=True)
        if not (isinstance(self.inlier_threshold, int | float) and 0.0 < self.inlier_threshold < 1.0):
            msg = f"{owner}.inlier_threshold must be in (0, 1), got {self.inlier_threshold!r}"
            raise ConfigError(msg)
        _check_int(owner, "all_pairs_below", self.all_pairs_below, 0)
        for name in ("max_candidates", "max_gnc_steps", "max_iterations"):
            _check_int(owner, name, getattr(self, name), 1)


# ------------------------------------------------------------------------------- greedy association


@dataclass(frozen=True)
class Innovations:
    """Where the last visit lies relative to every existing place (see the module docstring).

    Attributes:
        mean: ``(M, 2)`` innovations ``x_n^{xy} - x̄_s`` at the optimum.
        cov: ``(M, 2, 2)`` their covariances ``S_s``.
        d2: ``(M,)`` squared Mahalanobis distances.
        poses: ``(N, 3)`` optimised poses of all visits, the last one as a place of its own.
    """

    mean: FloatArray
    cov: FloatArray
    d2: FloatArray
    poses: FloatArray


def place_innovations(
    labels: Sequence[int],
    visits: Sequence[Visit],
    odometry_config: OdometryConfig,
    initial: ArrayLike | None = None,
) -> Innovations:
    """Innovations of the last of ``visits`` against the places of ``labels`` (one per earlier visit).

    ``initial`` ``(N, 3)`` warm-starts the pose-graph optimisation (default: the odometry poses).
    """
    n = len(visits)
    if n < 2 or len(labels) != n - 1:
        msg = f"need N >= 2 visits and N - 1 labels, got {n} visits and {len(labels)} labels"
        raise ModelError(msg)
    lab = np.asarray(canonical(labels), dtype=np.intp)
    m = int(lab.max()) + 1
    full = (*lab.tolist(), m)  # the last visit as a place of its own
    poses, info, _ = optimize_poses(full, visits, odometry_config, initial=initial)
    try:
        factor = cho_factor(info.toarray(), lower=True)
    except LinAlgError as err:
        msg = "the pose-graph information matrix is not positive definite"
        raise ModelError(msg) from err
    d = 3 * (n - 1)
    sizes = np.bincount(lab, minlength=m)
    # A: rows (2s, 2s+1) select x_n - mean_s on x and y; visit i >= 1 owns columns 3(i-1) + (0, 1)
    A = np.zeros((2 * m, d))
    rows = 2 * lab[1:, None] + np.arange(2)
    cols = 3 * np.arange(n - 2)[:, None] + np.arange(2)
    A[rows, cols] = -1.0 / sizes[lab[1:], None]
    A[np.arange(2 * m), 3 * (n - 2) + np.tile(np.arange(2), m)] += 1.0
    Y = cho_solve(factor, A.T)  # (d, 2M) = H^{-1} A^T
    blocks_ = np.einsum("sij,sjk->sik", A.reshape(m, 2, d), Y.T.reshape(m, 2, d).transpose(0, 2, 1))
    spread = odometry_config.sigma_topology**2 * (1.0 + 1.0 / sizes)
    cov = blocks_ + spread[:, None, None] * np.eye(2)
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    means = np.stack([np.bincount(lab, weights=poses[:-1, k], minlength=m) / sizes for k in range(2)], axis=1)
    nu = poses[-1, :2] - means
    d2 = np.einsum("si,si->s", nu, np.linalg.solve(cov, nu[..., None])[..., 0])
    return Innovations(mean=nu, cov=cov, d2=d2, poses=poses)


class GreedyAssociation:
    """Greedy association fed one visit at a time, as a robot runs it: :meth:`add` decides the newest
    visit (join the place of smallest Mahalanobis distance inside the gate, else a new place) and the
    decision is final; the optimised poses warm-start the next decision."""

    def __init__(self, odometry_config: OdometryConfig, config: GreedyConfig | None = None) -> None:
        self.odometry_config = odometry_config
        self.config = config or GreedyConfig()
        self._labels: list[int] = []
        self._poses: FloatArray = np.zeros((0, 3))

    @property
    def labels(self) -> Labels:
        """The decisions so far, one canonical label per visit."""
        return tuple(self._labels)

    def add(self, visits: Sequence[Visit]) -> int:
        """Decide the last of ``visits`` (the visits decided so far, then one more); returns its label.

        Raises:
            ModelError: not exactly one visit more than decided so far, or a pose graph that cannot be
                solved (the decisions so far stay).
        """
        n = len(self._labels)
        if len(visits) != n + 1:
            msg = f"greedy association decided {n} visits: expected {n + 1}, got {len(visits)}"
            raise ModelError(msg)
        if n == 0:
            self._labels.append(0)
            self._poses = poses_array(visits)
            return 0
        step = relative_odometry(visits[-2:])[0]
        warm = np.vstack([self._poses, compose(self._poses[-1], step)])
        inn = place_innovations(self._labels, visits, self.odometry_config, initial=warm)
        best = int(np.argmin(inn.d2))
        label = best if inn.d2[best] <= self.config.gate else len(inn.d2)
        self._labels.append(label)
        self._poses = inn.poses
        return label


def greedy_association(
    visits: Sequence[Visit], odometry_config: OdometryConfig, config: GreedyConfig
) -> Labels:
    """Greedy maximum-likelihood data association on odometry (see the module docstring).

    Each visit joins the place of smallest Mahalanobis distance inside the gate, or opens a new place;
    decisions are final (:class:`GreedyAssociation` over the visits in order). Returns canonical labels.
    """
    greedy = GreedyAssociation(odometry_config, config)
    for k in range(len(visits)):
        greedy.add(visits[: k + 1])
    return canonical(greedy.labels)


# -------------------------------------------------------------------------------- robust pose graph


@dataclass(frozen=True)
class RobustResult:
    """Result of :func:`robust_pose_graph`.

    Attributes:
        poses: ``(N, 3)`` optimised poses (``poses[0]`` = the gauge, headings wrapped).
        weights: ``(L,)`` final Geman–McClure weights of the loops, in ``[0, 1]``.
        residuals2: ``(L,)`` squared whitened residuals of the loops at ``poses``.
        gnc_steps: weighted least-squares solves after the initial plain one.
    """

    poses: FloatArray
    weights: FloatArray
    residuals2: FloatArray
    gnc_steps: int


@dataclass(frozen=True)
class _Factors(RelativeFactors):
    """Relative-pose factors: odometry first, then ``n_loops`` loops."""

    n_loops: int


def _whitening(cov: FloatArray, what: str) -> FloatArray:
    try:
        chol = cholesky(cov, lower=True)
    except LinAlgError as err:
        msg = f"{what}: covariance is not positive definite"
        raise ModelError(msg) from err
    return solve_triangular(chol, np.eye(3), lower=True)


def _check_relative(loop: RelativePose, n: int, what: str) -> tuple[int, int, FloatArray, FloatArray]:
    i, j = int(loop.i), int(loop.j)
    mean = np.asarray(loop.mean, dtype=float)
    cov = np.asarray(loop.cov, dtype=float)
    if not 0 <= i < j < n:
        msg = f"{what}: need 0 <= i < j < {n}, got ({i}, {j})"
        raise ModelError(msg)
    finite = (
        mean.shape == (3,) and cov.shape == (3, 3) and np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))
    )
    if not finite:
        msg = f"{what} ({i}, {j}): mean must be 3 and cov 3x3 finite numbers"
        raise ModelError(msg)
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12):
        msg = f"{what} ({i}, {j}): covariance is not symmetric"
        raise ModelError(msg)
    return i, j, mean, cov


def _factors(odometry: FloatArray, odometry_cov: FloatArray, loops: Sequence[RelativePose]) -> _Factors:
    n = len(odometry)
    a = [np.arange(n - 1, dtype=np.intp)]
    b = [np.arange(1, n, dtype=np.intp)]
    z = [between(odometry[:-1], odometry[1:]).reshape(-1, 3)]
    w = [
        np.array([_whitening(c, f"odometry segment {k}") for k, c in enumerate(odometry_cov)]).reshape(
            -1, 3, 3
        )
    ]
    for k, loop in enumerate(loops):
        i, j, mean, cov = _check_relative(loop, n, f"loop {k}")
        a.append(np.array([i], dtype=np.intp))
        b.append(np.array([j], dtype=np.intp))
        z.append(mean.reshape(1, 3))
        w.append(_whitening(cov, f"loop {k} ({i}, {j})")[None])
    return _Factors(
        a=np.concatenate(a), b=np.concatenate(b), z=np.concatenate(z), w=np.concatenate(w), n_loops=len(loops)
    )


def _weighted_cost(x: FloatArray, f: _Factors, sqrt_w: FloatArray) -> float:
    r, _, _ = relative_residuals(x, f)
    return 0.5 * float(np.sum((sqrt_w[:, None] * r) ** 2))


def _solve_weighted(
    x0: FloatArray, f: _Factors, weights: FloatArray, config: LoopClosureConfig
) -> FloatArray:
    """Levenberg–Marquardt on ``½ Σ_q w_q |r_q|²`` (odometry weights 1, loops ``weights``), ``x_0`` fixed."""
    sqrt_w = np.sqrt(np.concatenate([np.ones(len(f.a) - f.n_loops), weights]))
    if len(x0) == 1:
        return x0.copy()

    def normal_equations(x: FloatArray) -> tuple[sp.csc_matrix, FloatArray]:
        r, tx, ty = relative_residuals(x, f)
        jac = sp.diags(np.repeat(sqrt_w, 3)) @ relative_jacobian(x, f, tx, ty)
        return (jac.T @ jac).tocsc(), jac.T @ (sqrt_w[:, None] * r).ravel()

    return levenberg_marquardt(
        x0,
        lambda x: _weighted_cost(x, f, sqrt_w),
        normal_equations,
        max_iterations=config.max_iterations,
        tolerance=config.tolerance,
    )


def _loop_residuals2(x: FloatArray, f: _Factors) -> FloatArray:
    r, _, _ = relative_residuals(x, f)
    return np.sum(r[len(f.a) - f.n_loops :] ** 2, axis=1)


def robust_pose_graph(
    odometry: ArrayLike,
    odometry_cov: ArrayLike,
    loops: Sequence[RelativePose],
    config: LoopClosureConfig,
) -> RobustResult:
    """Pose graph of odometry and loop factors, loops under a Geman–McClure kernel, solved by GNC.

    Args:
        odometry: ``(N, 3)`` odometry poses ``u`` (relative odometry ``u_k ⊖ u_{k+1}``; gauge ``x_0 = u_0``;
            also the starting point).
        odometry_cov: ``(N-1, 3, 3)`` covariances of the relative odometry.
        loops: loop factors, measurements of ``between(x_i, x_j)``.
        config: kernel scale, GNC schedule and solver settings.
    """
    u = np.array(odometry, dtype=float)
    cov = np.asarray(odometry_cov, dtype=float)
    if u.ndim != 2 or u.shape[1] != 3 or len(u) < 1 or not np.all(np.isfinite(u)):
        msg = f"odometry must be finite poses of shape (N, 3), N >= 1, got shape {u.shape}"
        raise ModelError(msg)
    if cov.shape != (len(u) - 1, 3, 3):
        msg = f"odometry_cov must have shape ({len(u) - 1}, 3, 3), got {cov.shape}"
        raise ModelError(msg)
    f = _factors(u, cov, loops)
    c2 = config.kernel_scale**2
    x = _solve_weighted(u, f, np.ones(f.n_loops), config)
    r2 = _loop_residuals2(x, f)
    steps = 0
    if f.n_loops:
        mu = max(1.0, 2.0 * float(np.max(r2)) / c2)
        weights = np.ones(f.n_loops)
        while steps < config.max_gnc_steps:
            new_weights = (mu * c2 / (r2 + mu * c2)) ** 2
            if mu == 1.0 and steps > 0 and np.max(np.abs(new_weights - weights)) < config.tolerance:
                break
            weights = new_weights
            x = _solve_weighted(x, f, weights, config)
            r2 = _loop_residuals2(x, f)
            steps += 1
            mu = max(1.0, mu / config.gnc_factor)
    weights = (c2 / (r2 + c2)) ** 2
    x[:, 2] = wrap_angle(x[:, 2])
    return RobustResult(poses=x, weights=weights, residuals2=r2, gnc_steps=steps)


# --------------------------------------------------------------------------------- loop closure


@dataclass(frozen=True)
class LoopClosureDetails:
    """What :func:`robust_loop_closure` did.

    Attributes:
        candidates: pairs ``(i, j)`` that were registered, nearest first.
        loops: the valid registrations (loop factors), in candidate order.
        weights: ``(L,)`` final kernel weight of each loop.
        inliers: ``(L,)`` bool, weight at least the inlier threshold.
        joined: pairs whose inlier loop joined them into one place.
        poses: ``(N, 3)`` robustly optimised poses.
        gnc_steps: weighted solves of the GNC.
    """

    candidates: tuple[tuple[int, int], ...]
    loops: tuple[RelativePose, ...]
    weights: FloatArray
    inliers: NDArray[np.bool_]
    joined: tuple[tuple[int, int], ...]
    poses: FloatArray
    gnc_steps: int

    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly summary (for ``ptm.json`` extras)."""
        return {
            "candidates": [list(p) for p in self.candidates],
            "loops": [[lp.i, lp.j] for lp in self.loops],
            "weights": [float(w) for w in self.weights],
            "inliers": [bool(v) for v in self.inliers],
            "joined": [list(p) for p in self.joined],
            "poses": self.poses.tolist(),
            "gnc_steps": self.gnc_steps,
        }


def loop_candidates(poses: ArrayLike, config: LoopClosureConfig) -> list[tuple[int, int]]:
    """Pairs ``i < j`` to register: positions within ``search_radius`` (all pairs for small N), nearest
    first (ties by index), at most ``max_candidates``."""
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    n = len(p)
    ii, jj = np.triu_indices(n, 1)
    dist = np.hypot(p[jj, 0] - p[ii, 0], p[jj, 1] - p[ii, 1])
    keep = np.ones(len(ii), bool) if n <= config.all_pairs_below else dist <= config.search_radius
    order = np.lexsort((jj[keep], ii[keep], dist[keep]))[: config.max_candidates]
    return [(int(i), int(j)) for i, j in zip(ii[keep][order], jj[keep][order], strict=True)]


def _components(n: int, edges: Sequence[tuple[int, int]]) -> Labels:
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in edges:
        ri, rj = root(i), root(j)
        if ri != rj:
            parent[max(ri, rj)] = min(ri, rj)
    return canonical([root(i) for i in range(n)])


def robust_loop_closure(
    visits: Sequence[Visit],
    odometry_config: OdometryConfig,
    laser_config: LaserConfig | None,
    config: LoopClosureConfig,
    registrar: Registrar | None = None,
) -> tuple[Labels, LoopClosureDetails]:
    """Robust pose-graph loop closure; the topology = connected components of the kept loops.

    Args:
        visits: the landmark visits (patches used by the default registrar).
        odometry_config: odometry noise model (covariances of the odometry factors).
        laser_config: registration parameters of the default registrar (None: defaults).
        config: candidate search, kernel and inlier settings.
        registrar: optional ``(i, j) -> RelativePose | None`` (e.g. cached registrations); default
            :func:`patch_registrar`.
    """
    n = len(visits)
    u = poses_array(visits)
    if n == 0:
        empty = np.zeros(0)
        return (), LoopClosureDetails((), (), empty, empty.astype(bool), (), u, 0)
    register: Registrar = (
        patch_registrar(visits, LaserConfig() if laser_config is None else laser_config)
        if registrar is None
        else registrar
    )
    candidates = loop_candidates(u, config)
    loops = []
    for i, j in candidates:
        z = register(i, j)
        if not isinstance(z, RelativePose):  # None (nothing registered) or NoMatch: no loop closure
            continue
        if (int(z.i), int(z.j)) != (i, j):
            msg = f"the registrar answered pair ({z.i}, {z.j}) when asked for ({i}, {j})"
            raise ModelError(msg)
        loops.append(z)
    result = robust_pose_graph(u, odometry_covariances(visits, odometry_config), loops, config)
    inliers = result.weights >= config.inlier_threshold
    joined = tuple(
        (int(lp.i), int(lp.j))
        for lp, keep in zip(loops, inliers, strict=True)
        if keep and math.hypot(float(lp.mean[0]), float(lp.mean[1])) <= config.max_offset
    )
    details = LoopClosureDetails(
        candidates=tuple(candidates),
        loops=tuple(loops),
        weights=result.weights,
        inliers=inliers,
        joined=joined,
        poses=result.poses,
        gnc_steps=result.gnc_steps,
    )
    return _components(n, joined), details
