r"""The metric likelihood ``P(O, S | T)`` of odometry and laser matches (thesis Ch. 2.2–2.4, 3.10.4, App. B).

Odometry and scan matches are metric, a topology is not; the thesis bridges the gap by introducing the
true visit poses and integrating them out (eq. 14, 47). This module implements that integral.

Model
-----
Visits ``i = 0..N-1`` have raw odometry poses :math:`u_i \in SE(2)` and relative odometry
:math:`o_k = u_k \ominus u_{k+1}` (:func:`ptm_ros.model.geometry.between`). The latent true poses are
:math:`x_i = (x_i^{xy}, x_i^\theta)`; the gauge is fixed by :math:`x_0 := u_0` (the integrand is
invariant to a global rigid motion). For a topology (a canonical label tuple, blocks ``s`` = places)
the integrand over :math:`X = (x_1, \dots, x_{N-1})` (``d = 3(N-1)`` dimensions) is

.. math::
    f(X) = \prod_{k=0}^{N-2} \mathcal N\big((x_k \ominus x_{k+1}) \boxminus o_k;\ 0, \Sigma_k\big)
           \prod_{s} g_s(X)
           \prod_{(i,j)\ \text{same}} \mathcal N\big((x_i \ominus x_j) \boxminus z_{ij};\ 0, R_{ij}\big)
           \prod_{(i,j)\ \text{diff}} V_{reg}^{-1}
           \exp\Big(-\!\!\sum_{i<j,\ \text{diff}} c\big(\lVert x_i^{xy} - x_j^{xy}\rVert\big)\Big)

* :math:`\boxminus` is the component-wise difference with the angle wrapped to ``[-π, π)``;
* odometry noise (eq. 17, first term, written as a normalised Gaussian):
  :math:`\Sigma_k = \mathrm{diag}(s_{xy}^2, s_{xy}^2, s_\theta^2)`, :math:`s_{xy}^2 = a_{xy}\,\ell_{k+1} +
  b_{xy}`, :math:`s_\theta^2 = a_\theta\,\rho_{k+1} + c_\theta\,\ell_{k+1} + b_\theta` with travel
  :math:`\ell` and absolute rotation :math:`\rho` of visit ``k+1`` (:class:`ptm_ros.model.visits.Visit`);
* topology coincidence (replaces eq. 17, second term): place ``s`` is a point :math:`p_s` uniform over
  the mapped area ``A`` and each visit passes within :math:`\sigma_T` of its place,

  .. math::
      g_s = \frac1A \int \prod_{i \in s} \mathcal N(x_i^{xy}; p, \sigma_T^2 I_2)\, dp
          = \frac{1}{A\,|s|\,(2\pi\sigma_T^2)^{|s|-1}}
            \exp\Big(-\sum_{i\in s} \frac{\lVert x_i^{xy} - \bar x_s\rVert^2}{2\sigma_T^2}\Big),

  (headings are not constrained by the topology). With ``sigma_offset`` :math:`\sigma_\delta > 0` (the
  default) each place also has an offset :math:`\delta_s \sim \mathcal N(0, \sigma_\delta^2)` along the
  visits' headings, integrated out in closed form (:func:`coincidence_rows`): a detector that fires before
  (or after) a place in the direction of travel puts visits passed in opposite directions up to
  :math:`2\delta_s` apart (issue #23, ``bench/visit_offset.md``).

  Unlike the thesis' unnormalised eq. 17, which sums :math:`((l_{i1}-l_{i2})/\sigma_T)^2` over ordered
  pairs and has no normalising constant, this makes ``P(O | T)`` a proper density of the odometry, so
  topologies with different numbers of places compare fairly: a merge gains about
  ``A / (2π · uncertainty area)``, a Bayes factor. With ``place_prior`` steps (the default) the ``1/A`` of a
  place's first visit is the density of the run's own steps at that visit's step
  (:func:`place_log_priors`), so a merge gains what a step like the run's others costs;
* laser registrations :math:`z_{ij}` (:class:`ptm_ros.model.geometry.RelativePose`, only those that passed
  their fitness test) are Gaussian measurements of :math:`x_i \ominus x_j` when ``i`` and ``j`` are the
  same place, and a uniform outcome over the registration search volume :math:`V_{reg}` (m²·rad)
  otherwise (eq. 49);
* the landmark separation prior (eq. 15–16, Fig. 20) is the cubic :math:`c(d) = c_{max}(1 - d/D)^3` for
  ``d < D`` and 0 beyond, summed over pairs of visits of *different* places.

Computation (eq. 18, App. B)
----------------------------
All factors but the cubic prior form :math:`f_G(X) = C\,\exp(-\tfrac12\lVert r(X)\rVert^2)` with a
whitened residual vector ``r``. Its analytic Jacobian ``J`` is sparse: a ``3 × 6`` block per odometry
segment or laser pair and constant rows for the topology (:func:`metric_residuals` returns it as SciPy
CSR). Levenberg–Marquardt (thesis Ch. 2.4, App. B.1), warm-started at the odometry poses or a given
``initial``, assembles :math:`J^\top J` and :math:`J^\top r` block by block (no per-visit Python loop)
and finds :math:`X^\star = \arg\max f_G`; the Gauss–Newton information :math:`H = J^\top J` (eq. 90)
gives the Laplace estimate

.. math::
    \log \int f \approx \log f_G(X^\star) + \tfrac d2 \log 2\pi - \tfrac12 \log|H|
                        - \sum c(\cdot)\big|_{X^\star},

and importance sampling (eq. 18) with a Gaussian proposal ``q`` of information ``H`` at ``X*`` gives
:math:`\log \frac1S \sum_s f(X^{(s)}) / q(X^{(s)})` in log space, and its effective sample size
:math:`(\sum w)^2 / \sum w^2`. Because ``c ≥ 0``, :math:`f \le f_G`, the bound the thesis uses to justify
the proposal (it calls ``-log f_G`` a lower bound of ``-log f``).

Proposal coordinates. The thesis' :math:`q = \mathcal N(X^\star, H^{-1})` over the absolute poses
(``proposal="absolute"``) is a poor fit along a long path: heading errors bend the path, so the poses
spread on curved "bananas" and the effective sample size collapses (for six 5 m segments with default
noise, about 190 of 4000 samples even without merges). By default (``proposal="relative"``) the same
Gaussian is placed on the odometry increments :math:`\delta_k = x_k \ominus x_{k+1}`: with
:math:`y \sim \mathcal N(0, H^{-1})`, :math:`\delta = \delta^\star + D y` where
:math:`D = \partial\delta/\partial X` at ``X*``, and the poses are recomposed
:math:`x_{k+1} = x_k \oplus \delta_k`. Recomposition is a bijection with unit Jacobian determinant
(each step is a rigid motion), and so is ``D``; hence for :math:`y = L^{-\top} z`, :math:`H = L L^\top`,
:math:`\log q = -\tfrac d2 \log 2\pi + \tfrac12 \log|H| - \tfrac12 \lVert z\rVert^2` in both
coordinates. Without merges, laser and separation penalty, ``f`` is exactly Gaussian in ``δ`` and every
weight is equal.

Headings live on the circle and ``f`` is :math:`2\pi`-periodic in every heading increment. Under ``q`` a
:math:`2\pi` image of a sample has density :math:`\lesssim e^{-2\pi^2/\sigma^2}` for an increment
standard deviation ``σ`` (below ``e^{-78}`` for ``σ ≤ 0.5 rad``), so the Gaussian on ``R^d`` serves as
the proposal on the torus.

Thesis corrections: eq. 17 lacks the factor ½ of a Gaussian exponent, counts each pair twice and is not
normalised (see above); App. B's :math:`\sqrt{|2\pi/A|}` is :math:`(2\pi)^{d/2}|A|^{-1/2}` and its Hessian
is :math:`\partial^2/\partial x_i \partial x_j`.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.special import logsumexp

from ptm_ros.errors import ModelError
from ptm_ros.model.geometry import FloatArray, RelativePose, between, wrap_angle
from ptm_ros.model.partitions import Labels, canonical
from ptm_ros.model.visits import Visit, poses_array
from ptm_ros.settings import Settings, setting

#: Largest number of visits accepted (the normal matrix is factored densely, ``d = 3(N-1)``).
MAX_VISITS = 1000

_LOG_2PI = math.log(2.0 * math.pi)

#: Coordinates in which the importance-sampling proposal is Gaussian.
PROPOSALS = ("relative", "absolute")

#: How the area ``A`` of eq. 17 is learned from the visits (:func:`place_area`).
AREA_MODELS = ("swept", "extent")

#: Where a new place can be (:func:`place_log_priors`).
PLACE_PRIORS = ("area", "steps")

#: With fewer visit-to-visit steps than this, a new place is uniform over ``A`` whatever ``place_prior``.
MIN_STEPS = 3

#: Raster cell of :class:`SweptArea` [m].
SWEPT_CELL = 0.25


@dataclass(frozen=True)
class OdometryConfig(Settings):
    """Parameters of the metric likelihood (units in brackets; defaults for an indoor wheeled robot)."""

    a_xy: float = setting(0.05**2, ge=0, doc="translation variance per metre travelled [m²/m] (5 cm/√m).")
    b_xy: float = setting(0.01**2, gt=0, doc="translation variance floor per odometry segment [m²].")
    a_th: float = setting(0.05**2, ge=0, doc="heading variance per radian turned [rad²/rad].")
    b_th: float = setting(0.01**2, gt=0, doc="heading variance floor per odometry segment [rad²].")
    c_th: float = setting(0.02**2, ge=0, doc="heading variance per metre travelled [rad²/m].")
    sigma_topology: float = setting(0.5, gt=0, doc="σ_T, how far a visit passes from its place [m].")
    sigma_offset: float = setting(
        0.5,
        ge=0,
        doc=(
            "σ_δ, the spread of where along its heading the detector puts the visits of one place [m]: each "
            "place's visits lie ``δ_s`` ahead of it, ``δ_s ~ N(0, σ_δ²)``, so visits of one place passed in "
            "opposite directions may lie ``2 δ_s`` apart along the path (0: none). With ``learn_offset`` the "
            "prior guess."
        ),
    )
    learn_offset: bool = setting(
        True,
        doc=(
            "learn ``sigma_offset`` from the run's laser registrations (:mod:`ptm_ros.model.visit_offset`) "
            "while the filter runs; off: the value as given."
        ),
    )
    area_m2: float = setting(
        0.0,
        ge=0,
        doc=(
            "A, area of the mapped environment over which places are uniform [m²]; 0 (the default): learned "
            "from the visits as ``area_model`` says."
        ),
    )
    area_model: str = setting(
        "swept",
        choices=AREA_MODELS,
        doc=(
            'how ``A`` is learned when ``area_m2`` is 0: ``"swept"`` (default) the area the robot\'s path '
            'covers (:func:`swept_area`), ``"extent"`` the rectangle spanned by the visits '
            "(:func:`mapped_area`). Both are floored at ``penalty_radius²``."
        ),
    )
    place_prior: str = setting(
        "steps",
        choices=PLACE_PRIORS,
        doc=(
            'where a new place can be: ``"steps"`` (default) where the robot\'s step from the previous visit '
            'takes it, by the density of the run\'s own visit-to-visit odometry steps; ``"area"`` uniform '
            "over ``A`` (eq. 17) (:func:`place_log_priors`)."
        ),
    )
    step_floor: float = setting(
        0.05,
        gt=0,
        lt=1,
        doc=(
            "ρ, with ``place_prior`` steps: the weight of the uniform ``1/A`` in a new place's density (a "
            "step unlike the run's others)."
        ),
    )
    penalty_radius: float = setting(
        3.0, gt=0, doc="D, distance below which distinct places are penalised (eq. 15) [m]."
    )
    penalty_max: float = setting(
        5.0, ge=0, doc="c_max, the penalty (negative log prior) at distance 0 [nats]; 0 disables the prior."
    )
    registration_volume: float = setting(
        25.0,
        gt=0,
        doc="V_reg, volume of registration outcomes when two visits are different places [m²·rad].",
    )
    learn_heading: bool = setting(
        True,
        doc=(
            "learn a scale on the heading noise (``a_th``, ``b_th``, ``c_th``) from the run's laser "
            "registrations (:mod:`ptm_ros.model.heading_noise`) while the filter runs; off: the values as "
            "given."
        ),
    )
    heading_prior_sd: float = setting(
        1.0,
        gt=0,
        doc="s, the standard deviation of the log-normal prior of that scale around 1 (the values as given).",
    )
    registration_outlier: float = setting(
        0.132,
        ge=0,
        lt=1,
        doc=(
            "ε, probability that a registration passing its fitness tests between two visits of one place is "
            "nevertheless a false match, uniform over ``V_reg``: a symmetric alias (a crossing or corridor "
            "passed in opposite directions by a 180° laser matches best turned by π). 0 trusts every valid "
            "registration (the Gaussian of eq. 49 alone). The default is the share of valid registrations "
            "of one place found off their true relative pose on the shared runs (``bench/fitness_loo.md``, "
            "also fitted leave one run out)."
        ),
    )
    n_samples: int = setting(
        200, ge=0, doc="importance samples (eq. 18); 0 returns the Laplace estimate (fast path)."
    )
    max_sampled_visits: int = setting(
        40,
        ge=1,
        doc=(
            "importance sampling only for up to this many visits; beyond, the Laplace estimate. In ``d = "
            "3(N-1)`` dimensions the weights degenerate: on the real runs' MAP topologies the effective "
            "sample size falls to a few samples beyond some 40 visits, and the estimate's spread over seeds "
            "grows to the size of the differences between topologies, while the Laplace estimate stays close "
            "to the samples' mean (``bench/odometry.json`` records the effective sample size against N)."
        ),
    )
    proposal: str = setting(
        "relative",
        choices=PROPOSALS,
        doc=(
            'coordinates of the Gaussian proposal: ``"relative"`` (odometry increments, default) or '
            '``"absolute"`` (visit poses, as printed in the thesis); see the module docstring.'
        ),
    )
    max_iterations: int = setting(50, ge=1, doc="most Levenberg–Marquardt iterations.")
    tolerance: float = setting(
        1e-6, gt=0, doc="LM stops after a step that lowers ``-log f_G`` by less than this [nats]."
    )


@dataclass(frozen=True)
class MetricResult:
    """The metric likelihood of one topology.

    Attributes:
        log_likelihood: ``log P(O, S | T)``: the importance-sampling estimate, or the Laplace estimate
            when ``n_samples = 0`` or beyond ``max_sampled_visits`` visits.
        log_laplace: the Laplace estimate (App. B) with the landmark prior evaluated at ``X*``.
        ess: effective sample size of the importance weights (0 for the Laplace path).
        poses: ``(N, 3)`` optimised visit poses ``X*`` including ``x_0 = u_0`` (headings wrapped).
        place_positions: ``(M, 2)`` mean position of each place's visits at ``X*``, canonical label order.
        iterations: Levenberg–Marquardt iterations used.
    """

    log_likelihood: float
    log_laplace: float
    ess: float
    poses: FloatArray
    place_positions: FloatArray
    iterations: int


def mapped_area(xy: ArrayLike, floor: float) -> float:
    """``A``, the area over which places are uniform, learned from the ``(N, 2)`` visit positions: the
    rectangle aligned with their principal axes whose extents are the positions' ranges times
    ``(N+1)/(N-1)`` (the unbiased range of N uniform samples), each at least ``floor`` m (a corridor is
    at least a place wide); ``floor²`` for fewer than two visits."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    n = len(p)
    if n < 2:
        return floor * floor
    centred = p - p.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    proj = centred @ axes
    extent = np.maximum((proj.max(axis=0) - proj.min(axis=0)) * (n + 1) / (n - 1), floor)
    return float(extent[0] * extent[1])


@dataclass
class SweptArea:
    """The area within ``radius`` of a growing polyline, rasterised on the fixed lattice of cell centres
    ``((i + ½)·cell, (j + ½)·cell)``: a cell counts once however many segments pass it, and extending
    the path adds only the new segment's cells, so the area of a path and of its prefixes agree.

    Attributes:
        radius: half-width of the swept band [m].
        cell: lattice spacing [m].
        cells: keys of the covered cells (``i · 2³² + j``, both offset to be non-negative).
        end: the polyline's last point, ``None`` while empty.
    """

    radius: float
    cell: float = SWEPT_CELL
    cells: set[int] = field(default_factory=set)
    end: tuple[float, float] | None = None

    @property
    def area(self) -> float:
        """The covered area [m²]."""
        return len(self.cells) * self.cell * self.cell

    def extended(self, xy: ArrayLike) -> SweptArea:
        """A copy with the polyline continued through the ``(K, 2)`` points ``xy``."""
        out = SweptArea(self.radius, self.cell, set(self.cells), self.end)
        for point in np.asarray(xy, dtype=float).reshape(-1, 2):
            b = (float(point[0]), float(point[1]))
            out.cells.update(_segment_cells(out.end or b, b, self.radius, self.cell))
            out.end = b
        return out


def _segment_cells(a: tuple[float, float], b: tuple[float, float], radius: float, cell: float) -> list[int]:
    """Keys of the lattice cells whose centre lies within ``radius`` of the segment ``a``–``b``."""
    pa, pb = np.array(a), np.array(b)
    lo = np.floor((np.minimum(pa, pb) - radius) / cell - 0.5).astype(np.int64)
    hi = np.ceil((np.maximum(pa, pb) + radius) / cell - 0.5).astype(np.int64)
    i, j = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    q = (np.stack([i.ravel(), j.ravel()], axis=1) + 0.5) * cell
    ab = pb - pa
    den = float(ab @ ab)
    t = np.clip((q - pa) @ ab / den, 0.0, 1.0) if den > 0.0 else np.zeros(len(q))
    d2 = np.sum((q - pa - t[:, None] * ab) ** 2, axis=1)
    keep = d2 <= radius * radius
    offset = np.int64(1 << 31)
    return (((i.ravel()[keep] + offset) << 32) + (j.ravel()[keep] + offset)).tolist()


_SWEPT_MEMO: OrderedDict[tuple[float, float, bytes], SweptArea] = OrderedDict()
_SWEPT_MEMO_SIZE = 16
_SWEPT_LOCK = threading.Lock()


def swept_area(xy: ArrayLike, radius: float, cell: float = SWEPT_CELL) -> float:
    """Area [m²] within ``radius`` of the polyline through the ``(N, 2)`` positions (a disc for one).

    Memoised, and computed incrementally from a memoised prefix: the filter asks for the path of
    visits ``0..n`` right after ``0..n-1`` and the batch model asks for one path many times."""
    p = np.ascontiguousarray(np.asarray(xy, dtype=float).reshape(-1, 2))
    if len(p) == 0:
        return 0.0
    key = (float(radius), float(cell), p.tobytes())
    with _SWEPT_LOCK:
        swept = _SWEPT_MEMO.get(key)
        prefix = _SWEPT_MEMO.get((key[0], key[1], p[:-1].tobytes())) if swept is None else None
    if swept is None:
        swept = prefix.extended(p[-1:]) if prefix is not None else SweptArea(radius, cell).extended(p)
    with _SWEPT_LOCK:
        _SWEPT_MEMO[key] = swept
        _SWEPT_MEMO.move_to_end(key)
        while len(_SWEPT_MEMO) > _SWEPT_MEMO_SIZE:
            _SWEPT_MEMO.popitem(last=False)
    return swept.area


def place_area(visits: Sequence[Visit], config: OdometryConfig) -> float:
    r"""``A`` of eq. 17: ``config.area_m2``, or learned from the visits' positions.

    ``"swept"``: places are where the robot went, so ``A`` is the area within ``r = √π σ_T`` of its path
    through the visits. The band's width ``2r = √(2π · 2σ_T²)`` is the width of the uniform density
    whose height equals the peak of the cross-track offset between two visits of one place (each
    ``σ_T`` from it): with it, a merge's Occam factor ``A / (2π · 2σ_T²)`` counts the places that fit
    along the path, not the empty rectangle around it. The path is rasterised in the first visit's
    frame. ``"extent"``: :func:`mapped_area`. Both are at least ``penalty_radius²``."""
    if config.area_m2 > 0.0:
        return config.area_m2
    floor = config.penalty_radius
    if config.area_model == "extent":
        return mapped_area([v.pose[:2] for v in visits], floor)
    if not visits:
        return floor * floor
    # the lattice lies in the first visit's frame, so that A is invariant to a global rigid motion
    local = between(np.asarray(visits[0].pose, dtype=float), poses_array(visits))
    return max(swept_area(local[:, :2], math.sqrt(math.pi) * config.sigma_topology), floor * floor)


def place_log_priors(visits: Sequence[Visit], config: OdometryConfig) -> FloatArray:
    r"""``(N,)`` :math:`\log \pi_j`: the log density of the point of the place visit ``j`` creates, when it is
    a new place (the ``1/A`` of :math:`g_s`, module docstring).

    ``place_prior`` ``"area"``: every entry is :math:`-\log A` (:func:`place_area`), eq. 17's place uniform
    over the mapped area. ``"steps"``: a new place lies where the robot's step from the previous visit
    takes it, not anywhere in ``A``: for ``j ≥ 1``

    .. math::
        \pi_j = (1-\rho)\,\mathcal N(u_j;\ \mu, S + \sigma_T^2 I) + \rho / A,

    ``u_j`` the step from visit ``j−1`` in its frame (:func:`relative_odometry`), ``μ`` and ``S`` the mean and
    covariance of the run's steps so far (empirical Bayes: learned from the run, no ground truth), ``σ_T²``
    the place's own spread around the visit, ``ρ`` = ``step_floor``. Under ``"area"`` each merged place
    gains ``log A``: along two parallel corridors visited at the same spacing, every lined-up visit after
    the first gains it again, though the robot's steps, not chance, line them up; under ``"steps"`` a
    merge gains what a step like the run's others costs (``bench/thesis_protocol.md``). The density is
    taken at the odometry step rather than at the place's position (a constant of the topology, as ``A``
    is), and the first visit's place stays uniform over ``A`` (common to every topology). Below
    :data:`MIN_STEPS` steps, ``"area"``. What ``"steps"`` gives up: nothing but the separation prior keeps a
    new place off an old one, so where all steps are alike and only odometry speaks (a square driven
    twice), a fresh place where the steps lead is about as likely as the return: the loop stays open
    at a few nats either way, as Sec. 2.6 of the thesis finds of odometry alone; registrations and the
    appearance must decide it.
    """
    n = len(visits)
    area = place_area(visits, config)
    out = np.full(n, -math.log(area))
    if config.place_prior == "area" or n - 1 < MIN_STEPS:
        return out
    u = relative_odometry(visits)[:, :2]
    centred = u - u.mean(axis=0)
    cov = centred.T @ centred / len(u) + config.sigma_topology**2 * np.eye(2)
    y = np.linalg.solve(np.linalg.cholesky(cov), centred.T)
    log_n = -0.5 * np.sum(y * y, axis=0) - _LOG_2PI - 0.5 * math.log(float(np.linalg.det(cov)))
    rho = config.step_floor
    out[1:] = np.logaddexp(math.log1p(-rho) + log_n, math.log(rho) - math.log(area))
    return out


def new_places(labels: ArrayLike) -> NDArray[np.bool_]:
    """Which visits are the first of their place, for canonical labels ``(..., N)`` (a label that exceeds
    every label before it)."""
    lab = np.asarray(labels, dtype=np.int64)
    out = np.ones(lab.shape, dtype=bool)
    if lab.shape[-1] > 1:
        out[..., 1:] = lab[..., 1:] > np.maximum.accumulate(lab, axis=-1)[..., :-1]
    return out


def relative_odometry(visits: Sequence[Visit]) -> FloatArray:
    """``(N-1, 3)`` relative odometry ``o_k = u_k ⊖ u_{k+1}`` (pose of visit k+1 in the frame of visit k)."""
    u = poses_array(visits)
    return between(u[:-1], u[1:]).reshape(-1, 3)


def odometry_covariances(visits: Sequence[Visit], config: OdometryConfig) -> FloatArray:
    """``(N-1, 3, 3)`` diagonal covariances ``Σ_k`` of the relative odometry (from visit k+1's travel)."""
    var = odometry_variances(visits, config)
    cov = np.zeros((len(var), 3, 3))
    idx = np.arange(3)
    cov[:, idx, idx] = var
    return cov


def odometry_variances(visits: Sequence[Visit], config: OdometryConfig) -> FloatArray:
    """``(N-1, 3)`` the variances of eq. 17 of each relative odometry ``o_k`` (x, y, heading; from visit
    k+1's travel and rotation)."""
    travel = np.array([v.travel for v in visits[1:]], dtype=float)
    rotation = np.array([v.rotation for v in visits[1:]], dtype=float)
    var_xy = config.a_xy * travel + config.b_xy
    var_th = config.a_th * rotation + config.c_th * travel + config.b_th
    return np.stack([var_xy, var_xy, var_th], axis=-1).reshape(-1, 3)


def path_heading_variances(visits: Sequence[Visit], config: OdometryConfig) -> FloatArray:
    """``(N,)`` cumulative heading variance of the odometry from visit 0 to each visit (eq. 17's heading
    variances summed), so that the heading variance of the path from visit ``i`` to visit ``j`` is
    ``c[j] - c[i]``."""
    return np.concatenate([[0.0], np.cumsum(odometry_variances(visits, config)[:, 2])])


def heading_residuals_of(
    visits: Sequence[Visit], loops: Sequence[RelativePose], config: OdometryConfig
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For registrations of visits ``i < j``: the heading residual against the odometry's own heading
    change, ``wrap(z_θ − (u_j^θ − u_i^θ))``, the odometry's heading variance ``V_ij`` from ``i`` to ``j``
    (eq. 17) and the registration's ``R_θθ``, each ``(L,)`` (:func:`heading_aliases`)."""
    cum = path_heading_variances(visits, config)
    heading = poses_array(visits)[:, 2]
    i = np.array([z.i for z in loops], dtype=np.intp)
    j = np.array([z.j for z in loops], dtype=np.intp)
    error = wrap_angle(np.array([z.mean[2] for z in loops], dtype=float) - (heading[j] - heading[i]))
    return error, cum[j] - cum[i], np.array([z.cov[2, 2] for z in loops], dtype=float)


def heading_aliases(
    visits: Sequence[Visit], loops: Sequence[RelativePose], config: OdometryConfig
) -> NDArray[np.bool_]:
    r"""Which laser loops the odometry's own heading change already rules out as true matches.

    Headings compose additively, so a true match ``z`` of visits ``i < j`` has, before any topology, the
    heading residual :math:`e = \mathrm{wrap}(z_\theta - (u_j^\theta - u_i^\theta)) \sim
    \mathcal N(0, V_{ij} + R_{\theta\theta})` exactly (no linearisation), ``V_ij`` the odometry's
    heading variance from ``i`` to ``j`` (eq. 17); an alias is uniform over ``V_reg``, so its heading is
    uniform over ``2π``. The loop is an alias when :math:`(1-\varepsilon)\,\mathcal N(e; 0, V_{ij} +
    R_{\theta\theta}) < \varepsilon / 2\pi`: the max-mixture's decision (:func:`alias_test`) made on the
    heading's marginal, the same for every topology. It catches what the decision at a topology's optimum
    cannot: a chain of aliased registrations along identical sections (a ring's rotated sides), whose
    place coincidences have already bent that optimum until the aliases fit (``bench/reweighting.md``).
    All False when ``ε = 0``.
    """
    eps = config.registration_outlier
    out = np.zeros(len(loops), dtype=bool)
    if eps == 0.0 or not loops:
        return out
    e, path, reg = heading_residuals_of(visits, loops, config)
    var = path + reg
    log_match = math.log1p(-eps) - 0.5 * (e * e / var + np.log(2.0 * math.pi * var))
    return np.asarray(log_match < math.log(eps / (2.0 * math.pi)), dtype=bool)


@dataclass(frozen=True)
class _Problem:
    """Everything about one (topology, visits, loops, config) that does not depend on ``X``."""

    n: int
    origin: FloatArray  # u_0, (3,)
    odometry: FloatArray  # u, (N, 3): the default starting point
    labels: Labels
    pair_a: NDArray[np.intp]  # relative constraints (odometry then same-place laser), (Q,)
    pair_b: NDArray[np.intp]
    pair_z: FloatArray  # (Q, 3)
    pair_w: FloatArray  # (Q, 3, 3) whitening W with W^T W = R^{-1}
    centering: FloatArray  # (Qt, 2N): coincidence rows over (x_0, y_0, x_1, ...) (coincidence_rows)
    prior_i: NDArray[np.intp]  # visit pairs of different places, (Pp,)
    prior_j: NDArray[np.intp]
    log_const: float  # log C, the normalising constants of f_G
    h_index: NDArray[np.intp]  # flat index into H (d*d) of each kept entry of the (Q, 6, 6) pair blocks
    h_keep: NDArray[np.intp]  # which entries of the raveled (Q, 6, 6) blocks are kept (no gauge column)
    g_index: NDArray[np.intp]  # index into g (d,) of each kept entry of the (Q, 6) pair gradients
    g_keep: NDArray[np.intp]
    h_topo: FloatArray  # constant topology part of H, (d, d)


def _validate_labels(labels: Sequence[int], n: int) -> Labels:
    if len(labels) != n:
        msg = f"topology has {len(labels)} labels but there are {n} visits"
        raise ModelError(msg)
    return canonical(labels)


def _build_problem(
    labels: Sequence[int], visits: Sequence[Visit], config: OdometryConfig, loops: Sequence[RelativePose]
) -> _Problem:
    n = len(visits)
    if n < 1 or n > MAX_VISITS:
        msg = f"the metric likelihood needs 1 <= N <= {MAX_VISITS} visits, got {n}"
        raise ModelError(msg)
    lab = _validate_labels(labels, n)
    lab_arr = np.asarray(lab, dtype=np.intp)
    u = poses_array(visits)
    if not np.all(np.isfinite(u)):
        msg = "visit poses must be finite"
        raise ModelError(msg)

    # relative constraints: odometry (diagonal whitening) then laser pairs of the same place
    var = odometry_variances(visits, config)
    odo_w = np.zeros((n - 1, 3, 3))
    idx3 = np.arange(3)
    odo_w[:, idx3, idx3] = 1.0 / np.sqrt(var)
    log_const = float(-0.5 * np.sum(np.log(var)) - 1.5 * (n - 1) * _LOG_2PI)
    a_list = [np.arange(n - 1, dtype=np.intp)]
    b_list = [np.arange(1, n, dtype=np.intp)]
    z_list = [relative_odometry(visits)]
    w_list = [odo_w]
    ij, means, covs = _loop_arrays(loops, n)
    same = lab_arr[ij[:, 0]] == lab_arr[ij[:, 1]]
    n_diff_laser = int(np.sum(~same))
    if np.any(same):
        chol = _cholesky_3(covs[same], "laser constraint", np.flatnonzero(same), ij[same])
        log_const += float(-np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2))) - 1.5 * _LOG_2PI * len(chol))
        a_list.append(ij[same, 0])
        b_list.append(ij[same, 1])
        z_list.append(means[same])
        w_list.append(_lower_inverse_3(chol))
    log_const -= n_diff_laser * math.log(config.registration_volume)
    pair_a = np.concatenate(a_list)
    pair_b = np.concatenate(b_list)
    pair_z = np.concatenate(z_list)
    pair_w = np.concatenate(w_list)

    # topology coincidence: whitened centring residuals of multi-visit places, plus the g_s constants
    m = int(lab_arr.max()) + 1
    sizes = np.bincount(lab_arr, minlength=m)
    sig2 = config.sigma_topology**2
    centering, log_spread = coincidence_rows(lab_arr, u[:, 2], config.sigma_topology, config.sigma_offset)
    log_const += float(
        np.sum(place_log_priors(visits, config)[new_places(lab_arr)])
        - np.sum(np.log(sizes))
        - np.sum(sizes - 1) * math.log(2.0 * math.pi * sig2)
        - log_spread
    )

    # landmark separation prior over pairs of different places
    ii, jj = np.triu_indices(n, 1)
    diff = lab_arr[ii] != lab_arr[jj]
    prior_i, prior_j = ii[diff], jj[diff]

    h_index, h_keep, g_index, g_keep, h_topo = _normal_pattern(pair_a, pair_b, centering)
    return _Problem(
        n=n,
        origin=u[0].copy(),
        odometry=u,
        labels=lab,
        pair_a=pair_a,
        pair_b=pair_b,
        pair_z=pair_z,
        pair_w=pair_w,
        centering=centering,
        prior_i=prior_i,
        prior_j=prior_j,
        log_const=log_const,
        h_index=h_index,
        h_keep=h_keep,
        g_index=g_index,
        g_keep=g_keep,
        h_topo=h_topo,
    )


def coincidence_rows(
    labels: NDArray[np.intp], headings: FloatArray, sigma_topology: float, sigma_offset: float = 0.0
) -> tuple[FloatArray, float]:
    r"""The whitened residual rows of the topology coincidence terms ``g_s`` and their extra log-determinant.

    Returns ``C`` ``(Q, 2N)`` over the interleaved positions ``(x_0, y_0, x_1, y_1, …)``, two rows per visit
    of a multi-visit place, so that :math:`\prod_s g_s \propto \exp(-\tfrac12 \lVert C x\rVert^2)`, and
    :math:`\tfrac12 \sum_s \log(1 + \sigma_\delta^2 \lVert c_s\rVert^2 / \sigma_T^2)`, to be subtracted from
    ``log g``.

    A visit ``i`` of place ``s`` lies at :math:`p_s + \delta_s h_i + \epsilon_i`, with ``h_i`` the unit vector
    of its odometry heading, :math:`\epsilon_i \sim \mathcal N(0, \sigma_T^2 I_2)` and, per place,
    :math:`\delta_s \sim \mathcal N(0, \sigma_\delta^2)`: a detector that fires a little before (or after)
    the place in the direction of travel puts visits passed in opposite directions ``2 δ_s`` apart, and
    visits passed the same way together. Integrating ``p_s`` (uniform) leaves the centred positions
    :math:`y = P x_s` (``P`` removes the place's mean), Gaussian on the ``2|s| - 2`` dimensions of ``P``'s
    range with covariance :math:`\sigma_T^2 I + \sigma_\delta^2 c c^\top`, :math:`c = P h` the centred
    headings. Its whitening is :math:`W = (I - \beta \hat c \hat c^\top) / \sigma_T` with
    :math:`1 - \beta = (1 + \sigma_\delta^2 \lVert c\rVert^2 / \sigma_T^2)^{-1/2}`, and the determinant
    adds the returned log term to the ``(2\pi\sigma_T^2)^{|s|-1}`` of the module docstring's ``g_s``.
    With ``σ_δ = 0``, or a place passed one way only (``c = 0``), ``C`` is the plain centring
    :math:`(\delta_{ij} - 1/|s|)/\sigma_T` on each axis. The headings are the odometry's (fixed), so the
    rows stay constant in ``x``.
    """
    n = len(labels)
    sizes = np.bincount(labels)
    in_multi = np.flatnonzero(sizes[labels] > 1)
    same = labels[in_multi][:, None] == labels[None, :]
    plain = (in_multi[:, None] == np.arange(n)[None, :]) - same / sizes[labels[in_multi]][:, None]
    centering = np.kron(plain, np.eye(2))  # P per axis; rows and columns (x_i, y_i) interleaved
    place = np.repeat(labels[in_multi], 2)  # the place of each row
    c = centering @ np.stack([np.cos(headings), np.sin(headings)], axis=1).ravel()  # centred headings
    norm2 = np.bincount(place, weights=c * c, minlength=len(sizes))  # |c_s|² per place
    spread = sigma_offset**2 * norm2 / sigma_topology**2
    beta = 1.0 - 1.0 / np.sqrt(1.0 + spread)
    c_hat = np.divide(c, np.sqrt(norm2[place]), out=np.zeros_like(c), where=norm2[place] > 0.0)
    proj = np.zeros((len(sizes), 2 * n))
    np.add.at(proj, place, c_hat[:, None] * centering)  # ĉ_sᵀ P_s per place
    centering -= (beta[place] * c_hat)[:, None] * proj[place]
    log_spread = 0.5 * float(np.sum(np.log1p(spread)))  # 0 for places passed one way and single visits
    centering /= sigma_topology
    return centering, log_spread


def _loop_arrays(loops: Sequence[RelativePose], n: int) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """The laser loops as arrays, validated: visit pairs ``(K, 2)``, means ``(K, 3)``, covariances
    ``(K, 3, 3)``."""
    k = len(loops)
    ij = np.zeros((k, 2), dtype=np.intp)
    means = np.zeros((k, 3))
    covs = np.zeros((k, 3, 3))
    for q, loop in enumerate(loops):
        i, j = int(loop.i), int(loop.j)
        if not 0 <= i < j < n:
            msg = f"laser constraint {q}: need 0 <= i < j < {n}, got ({i}, {j})"
            raise ModelError(msg)
        mean = np.asarray(loop.mean, dtype=float)
        cov = np.asarray(loop.cov, dtype=float)
        if mean.shape != (3,) or cov.shape != (3, 3):
            msg = f"laser constraint {q} ({i}, {j}): mean must be 3 and cov 3x3 finite numbers"
            raise ModelError(msg)
        ij[q] = i, j
        means[q] = mean
        covs[q] = cov
    finite = np.isfinite(means).all(axis=1) & np.isfinite(covs).all(axis=(1, 2))
    scale = np.abs(covs).max(axis=(1, 2), initial=0.0)
    asymmetric = np.abs(covs - covs.transpose(0, 2, 1)).max(axis=(1, 2), initial=0.0) > 1e-12 + 1e-9 * scale
    bad = np.flatnonzero(~finite | asymmetric)
    if len(bad):
        q = bad[0]
        finite_q = np.isfinite(means[q]).all() and np.isfinite(covs[q]).all()
        what = "mean must be 3 and cov 3x3 finite numbers" if not finite_q else "covariance is not symmetric"
        msg = f"laser constraint {q} ({ij[q, 0]}, {ij[q, 1]}): {what}"
        raise ModelError(msg)
    return ij, means, covs


def _cholesky_3(s: FloatArray, what: str, index: NDArray[np.intp], ij: NDArray[np.intp]) -> FloatArray:
    """Lower Cholesky factors of ``(K, 3, 3)`` symmetric matrices; names the first that is not positive
    definite (``what`` ``index[k]`` ``(i, j)``)."""
    try:
        return cast("FloatArray", np.linalg.cholesky(s))  # float64 in, float64 out (numpy types it floating)
    except np.linalg.LinAlgError:
        for k in range(len(s)):
            try:
                np.linalg.cholesky(s[k])
            except np.linalg.LinAlgError as err:
                msg = f"{what} {index[k]} ({ij[k, 0]}, {ij[k, 1]}): covariance is not positive definite"
                raise ModelError(msg) from err
        raise


def _lower_inverse_3(chol: FloatArray) -> FloatArray:
    """Inverses of lower-triangular ``(K, 3, 3)`` matrices, in closed form (exactly lower triangular)."""
    a, c, f = chol[:, 0, 0], chol[:, 1, 1], chol[:, 2, 2]
    b, d, e = chol[:, 1, 0], chol[:, 2, 0], chol[:, 2, 1]
    out = np.zeros_like(chol)
    out[:, 0, 0] = 1.0 / a
    out[:, 1, 1] = 1.0 / c
    out[:, 2, 2] = 1.0 / f
    out[:, 1, 0] = -b / (a * c)
    out[:, 2, 1] = -e / (c * f)
    out[:, 2, 0] = (b * e - c * d) / (a * c * f)
    return out


def _normal_pattern(
    pair_a: NDArray[np.intp], pair_b: NDArray[np.intp], centering: FloatArray
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], FloatArray]:
    """Where the blocks ``[J_a J_b]^T [J_a J_b]`` ``(Q, 6, 6)`` and gradients ``(Q, 6)`` land in ``H``, ``g``.

    Columns of visit 0 (the fixed gauge) are dropped. The topology residuals are linear in the positions
    with the constant Jacobian ``C`` of :func:`coincidence_rows`, so their part of ``H`` is the constant
    ``C^T C`` on the x and y columns.
    """
    n = centering.shape[1] // 2
    d = 3 * (n - 1)
    var = np.concatenate(
        [3 * (pair_a - 1)[:, None] + np.arange(3), 3 * (pair_b - 1)[:, None] + np.arange(3)], axis=1
    )  # (Q, 6) variable index, negative for visit 0
    valid = var >= 0
    g_keep = np.flatnonzero(valid.ravel())
    g_index = var.ravel()[g_keep]
    both = valid[:, :, None] & valid[:, None, :]
    flat = var[:, :, None] * d + var[:, None, :]
    h_keep = np.flatnonzero(both.ravel())
    h_index = flat.ravel()[h_keep]
    xy = (3 * np.arange(n - 1)[:, None] + np.arange(2)).ravel()  # columns of x_1, y_1, x_2, …
    h_topo = np.zeros((d, d))
    h_topo[np.ix_(xy, xy)] = (centering.T @ centering)[2:, 2:]
    return h_index, h_keep, g_index, g_keep, h_topo


def _relative_errors(P: FloatArray, prob: _Problem) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Errors ``(x_a ⊖ x_b) ⊟ z`` ``(S, Q, 3)`` and the raw ``x_a ⊖ x_b`` translation ``(S, Q)`` ×2."""
    pa = P[:, prob.pair_a]
    pb = P[:, prob.pair_b]
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    dx = pb[..., 0] - pa[..., 0]
    dy = pb[..., 1] - pa[..., 1]
    tx = c * dx + s * dy
    ty = -s * dx + c * dy
    e = np.stack(
        [
            tx - prob.pair_z[:, 0],
            ty - prob.pair_z[:, 1],
            wrap_angle(pb[..., 2] - pa[..., 2] - prob.pair_z[:, 2]),
        ],
        axis=-1,
    )
    return e, tx, ty


def _residuals(P: FloatArray, prob: _Problem) -> FloatArray:
    """Whitened residuals ``r(X)`` of ``f_G``, ``(S, m)`` for poses ``P`` ``(S, N, 3)``."""
    e, _, _ = _relative_errors(P, prob)
    r_rel = np.einsum("qij,sqj->sqi", prob.pair_w, e, optimize=True)
    r_top = P[..., :2].reshape(len(P), -1) @ prob.centering.T
    return np.concatenate([r_rel.reshape(len(P), -1), r_top], axis=1)


def _log_prior(
    P: FloatArray, prob: _Problem, config: OdometryConfig, center: FloatArray | None = None
) -> FloatArray:
    """``-Σ c(d_ij)`` over pairs of different places (eq. 15–16), ``(S,)`` for poses ``P`` ``(S, N, 3)``.

    With ``center`` ``(N, 3)`` (the samples' mode), pairs that no sample can bring within ``D`` are
    skipped exactly: ``d_ij(s) ≥ d_ij(center) - δ_i - δ_j`` with ``δ_i = max_s |x_i^{xy}(s) - center_i|``.
    """
    if config.penalty_max == 0.0 or len(prob.prior_i) == 0:
        return np.zeros(len(P))
    pi, pj = prob.prior_i, prob.prior_j
    if center is not None:
        reach = np.sqrt(np.max(np.sum((P[..., :2] - center[:, :2]) ** 2, axis=-1), axis=0))
        gap0 = np.hypot(*(center[pi, :2] - center[pj, :2]).T) - reach[pi] - reach[pj]
        near = gap0 < config.penalty_radius
        pi, pj = pi[near], pj[near]
        if len(pi) == 0:
            return np.zeros(len(P))
    dx = P[:, pi, 0] - P[:, pj, 0]
    dy = P[:, pi, 1] - P[:, pj, 1]
    gap = 1.0 - np.sqrt(dx * dx + dy * dy) / config.penalty_radius
    np.maximum(gap, 0.0, out=gap)
    return -config.penalty_max * np.einsum("sp,sp,sp->s", gap, gap, gap)


def between_derivatives(
    x: FloatArray, a: NDArray[np.intp], b: NDArray[np.intp], tx: FloatArray, ty: FloatArray
) -> FloatArray:
    """``∂(x_a ⊖ x_b)/∂(x_a, x_b)`` ``(Q, 3, 6)`` at poses ``x`` ``(N, 3)``, given ``t = (t_x, t_y)``.

    With ``t = R(θ_a)^T (t_b - t_a)``: ``∂t/∂t_a = -R^T``, ``∂t/∂θ_a = (t_y, -t_x)``, ``∂t/∂t_b = R^T``;
    the (wrapped) heading difference has derivatives ``-1`` and ``+1``.
    """
    c, s = np.cos(x[a, 2]), np.sin(x[a, 2])
    de = np.zeros((len(a), 3, 6))
    de[:, 0, 0] = -c
    de[:, 0, 1] = -s
    de[:, 0, 2] = ty
    de[:, 1, 0] = s
    de[:, 1, 1] = -c
    de[:, 1, 2] = -tx
    de[:, 2, 2] = -1.0
    de[:, 0, 3] = c
    de[:, 0, 4] = s
    de[:, 1, 3] = -s
    de[:, 1, 4] = c
    de[:, 2, 5] = 1.0
    return de


def _pair_jacobians(x: FloatArray, prob: _Problem) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residuals ``r`` ``(m,)`` at poses ``x`` ``(N, 3)``, Jacobian blocks ``[J_a J_b] = W ∂e/∂(x_a, x_b)``
    ``(Q, 3, 6)`` of the relative constraints ``W((x_a ⊖ x_b) ⊟ z)`` and their residuals ``(Q, 3)``."""
    e, tx, ty = _relative_errors(x[None], prob)
    jab = prob.pair_w @ between_derivatives(x, prob.pair_a, prob.pair_b, tx[0], ty[0])
    r_rel = (prob.pair_w @ e[0, :, :, None])[:, :, 0]
    r_top = prob.centering @ x[:, :2].ravel()
    return np.concatenate([r_rel.ravel(), r_top]), jab, r_rel


def _scatter(blocks: FloatArray, prob: _Problem) -> FloatArray:
    """The ``(Q, 6, 6)`` blocks over ``(x_a, x_b)`` summed into a dense ``(d, d)`` matrix (gauge dropped)."""
    d = 3 * (prob.n - 1)
    # with weights, bincount sums them in float64 (numpy's stub types every bincount as intp)
    summed = cast(
        "FloatArray", np.bincount(prob.h_index, weights=blocks.ravel()[prob.h_keep], minlength=d * d)
    )
    return summed.reshape(d, d)


def _newton_hessian(x: FloatArray, prob: _Problem, info: FloatArray) -> FloatArray:
    """The full Hessian of ``½|r|²`` at ``x``: ``info = JᵀJ`` plus ``Σ_k r_k ∇²r_k`` of the relative
    constraints (the topology residuals are linear).

    With ``λ = Wᵀ r`` and ``t = R(θ_a)ᵀ(t_b − t_a)``, only ``θ_a`` enters nonlinearly:
    ``∂²t/∂θ_a² = −t``, ``∂²t/∂θ_a∂t_a = −dR(θ_a)ᵀ/dθ`` and ``∂²t/∂θ_a∂t_b = dR(θ_a)ᵀ/dθ``.
    """
    e, tx, ty = _relative_errors(x[None], prob)
    lam = np.einsum("qki,qkj,qj->qi", prob.pair_w, prob.pair_w, e[0])  # Wᵀ r
    theta = x[prob.pair_a, 2]
    c, s = np.cos(theta), np.sin(theta)
    lx, ly = lam[:, 0], lam[:, 1]
    u = lx * s + ly * c  # ∂²(λ·t)/∂θ_a ∂x_a
    v = ly * s - lx * c  # ∂²(λ·t)/∂θ_a ∂y_a
    blocks = np.zeros((len(theta), 6, 6))
    blocks[:, 2, 2] = -(lx * tx[0] + ly * ty[0])
    for col, value in ((0, u), (1, v), (3, -u), (4, -v)):
        blocks[:, 2, col] = value
        blocks[:, col, 2] = value
    return info + _scatter(blocks, prob)


def _normal_equations(x: FloatArray, prob: _Problem) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``r`` ``(m,)``, ``H = J^T J`` ``(d, d)`` and ``g = J^T r`` ``(d,)``, assembled block by block."""
    r, jab, r_rel = _pair_jacobians(x, prob)
    d = 3 * (prob.n - 1)
    info = _scatter(jab.transpose(0, 2, 1) @ jab, prob) + prob.h_topo  # (a new array also when d = 0)
    grad = cast(  # float64 (see _scatter)
        "FloatArray",
        np.bincount(
            prob.g_index, weights=np.einsum("qki,qk->qi", jab, r_rel).ravel()[prob.g_keep], minlength=d
        ),
    )
    g_top = (prob.centering.T @ r[3 * len(prob.pair_a) :]).reshape(-1, 2)  # (N, 2)
    grad = grad.reshape(-1, 3)
    grad[:, :2] += g_top[1:]
    return r, info, grad.ravel()


def _sparse_jacobian(jab: FloatArray, prob: _Problem) -> sp.csr_matrix:
    """The full Jacobian ``∂r/∂(x_1..x_{N-1})`` as a sparse CSR matrix ``(m, 3(N-1))``."""
    q = len(prob.pair_a)
    d = 3 * (prob.n - 1)
    var = np.concatenate(
        [3 * (prob.pair_a - 1)[:, None] + np.arange(3), 3 * (prob.pair_b - 1)[:, None] + np.arange(3)], axis=1
    )
    rows = np.broadcast_to(3 * np.arange(q)[:, None, None] + np.arange(3)[None, :, None], jab.shape)
    cols = np.broadcast_to(var[:, None, :], jab.shape)
    keep = cols >= 0
    tq, tn = np.nonzero(prob.centering[:, 2:])
    t_rows = 3 * q + tq
    t_cols = 3 * (tn // 2) + tn % 2  # coordinate k of visit tn // 2 + 1 -> column 3 (tn // 2) + k
    t_vals = prob.centering[tq, tn + 2]
    m = 3 * q + prob.centering.shape[0]
    return sp.csr_matrix(
        (
            np.concatenate([jab[keep], t_vals]),
            (np.concatenate([rows[keep], t_rows]), np.concatenate([cols[keep], t_cols])),
        ),
        shape=(m, d),
    )


def metric_residuals(
    poses: ArrayLike,
    labels: Sequence[int],
    visits: Sequence[Visit],
    config: OdometryConfig,
    loops: Sequence[RelativePose] = (),
) -> tuple[FloatArray, sp.csr_matrix]:
    """Whitened residuals ``r`` ``(m,)`` of the Gaussian part ``f_G = C exp(-½|r|²)`` at ``poses`` ``(N, 3)``
    and their analytic Jacobian w.r.t. ``x_1..x_{N-1}``, sparse ``(m, 3(N-1))`` (columns ``3(i-1)+c``).

    Rows: ``3`` per odometry segment, ``3`` per same-place laser pair, then ``2`` per visit of each place
    with several visits (``(x_i^{xy} - x̄_s)/σ_T``). ``poses[0]`` enters the residuals but is not a variable.
    """
    prob = _build_problem(labels, visits, config, loops)
    x = _check_poses(poses, prob.n, "poses")
    r, jab, _ = _pair_jacobians(x, prob)
    return r, _sparse_jacobian(jab, prob)


def _check_poses(poses: ArrayLike, n: int, name: str) -> FloatArray:
    x = np.array(poses, dtype=float)
    if x.shape != (n, 3):
        msg = f"{name} must have shape ({n}, 3), got {x.shape}"
        raise ModelError(msg)
    if not np.all(np.isfinite(x)):
        msg = f"{name} must be finite"
        raise ModelError(msg)
    return x


@dataclass(frozen=True)
class _Optimum:
    poses: FloatArray  # (N, 3), headings unwrapped as optimised
    information: FloatArray  # dense J^T J, (d, d)
    chol: FloatArray  # lower Cholesky factor of the dense information, (d, d)
    log_gauss: float  # log f_G(X*)
    iterations: int


#: Newton steps once an accepted step lowered ``½|r|²`` by less than this [nats] (near the optimum).
NEWTON_BELOW_NATS = 1.0


def _damped_step(
    hess: FloatArray | None, info: FloatArray, damp: FloatArray, grad: FloatArray
) -> FloatArray | None:
    """The step ``-(A + diag(damp))⁻¹ g`` with ``A = hess`` (Newton) when given and the damped matrix is
    positive definite, else ``A = JᵀJ`` (Gauss–Newton); None when neither factors."""
    idx = np.arange(len(grad))
    for matrix in (info,) if hess is None else (hess, info):
        damped = matrix.copy()
        damped[idx, idx] += damp
        try:
            factor = cho_factor(damped, lower=True, check_finite=False)
        except LinAlgError:
            continue
        step = -cho_solve(factor, grad, check_finite=False)
        if np.all(np.isfinite(step)):
            return step
    return None


def _optimize(prob: _Problem, config: OdometryConfig, initial: ArrayLike | None) -> _Optimum:
    """Levenberg–Marquardt on ``½|r|²`` with the analytic block-sparse Jacobian (thesis Ch. 2.4, App. B.1),
    taking Newton steps on the full Hessian ``∇² = JᵀJ + Σ r_k ∇²r_k`` where it is positive definite.

    Gauss–Newton (``JᵀJ`` alone) converges only linearly here: on the real runs the left-out curvature is
    up to ~70 % of ``JᵀJ`` along some directions (long odometry chains bent by the topology's
    coincidence terms), so it took ~20 iterations at a rate of ~0.5; Newton's steps converge
    quadratically from close by, but far from the optimum (large residuals) its quadratic model
    overshoots (a synthetic 100-visit loop: 20 iterations instead of Gauss–Newton's 6). Each step solves
    ``(A + λ diag(JᵀJ)) δ = -g`` with ``A = ∇²`` once an accepted step lowered the cost by less than
    :data:`NEWTON_BELOW_NATS` and the damped ``∇²`` is positive definite, else ``A = JᵀJ``
    (:func:`_damped_step`); ``λ`` follows Nielsen's gain-ratio update (start ``1e-6``); a step
    that raises the cost multiplies ``λ`` by ``ν = 2, 4, 8, …``. Stops when a step lowers the cost, or
    the undamped model predicts the next one would, by less than ``config.tolerance``. The Laplace
    estimate uses the Gauss–Newton information ``JᵀJ`` at the optimum (eq. 90).
    """
    x = prob.odometry.copy() if initial is None else _check_poses(initial, prob.n, "initial")
    x[0] = prob.origin
    if prob.n == 1:  # nothing to integrate: f = 1/A
        empty = np.zeros((0, 0))
        return _Optimum(poses=x, information=empty, chol=empty, log_gauss=prob.log_const, iterations=0)
    r, info, grad = _normal_equations(x, prob)
    cost = 0.5 * float(r @ r)
    lam, nu = 1e-6, 2.0
    iterations = 0
    near = False  # Gauss–Newton while far: the full Hessian's model overshoots where residuals are large
    hess: FloatArray | None = None  # the full Hessian at x, computed once Newton steps are due
    while iterations < config.max_iterations and lam < 1e12:
        iterations += 1
        damp = lam * np.diag(info)
        if near and hess is None:
            hess = _newton_hessian(x, prob, info)
        step = _damped_step(hess if near else None, info, damp, grad)
        if step is None:
            lam, nu = lam * nu, 2.0 * nu
            continue
        descent = -float(grad @ step)  # = δᵀ(A + λD)δ > 0 for the positive definite matrix used
        predicted = 0.5 * (descent + float(step @ (damp * step)))  # decrease of ½|r|² by the quadratic model
        if predicted < config.tolerance and lam < 1e-3:
            break  # (nearly) Newton predicts less than the tolerance: converged
        x_new = x.copy()
        x_new[1:] += step.reshape(-1, 3)
        r_new, info_new, grad_new = _normal_equations(x_new, prob)
        cost_new = 0.5 * float(r_new @ r_new)
        decrease = cost - cost_new
        if decrease < -1e-12 * (1.0 + cost):
            lam, nu = lam * nu, 2.0 * nu  # reject: damp harder (Levenberg–Marquardt, Nielsen's update)
            continue
        rho = decrease / predicted if predicted > 0.0 else 1.0
        lam, nu = lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
        x, r, info, grad, hess, cost = x_new, r_new, info_new, grad_new, None, cost_new
        if decrease < config.tolerance:
            break
        near = decrease < NEWTON_BELOW_NATS
    try:
        chol = cast("FloatArray", np.linalg.cholesky(info))  # float64 (numpy types it floating)
    except np.linalg.LinAlgError as err:
        msg = "the information matrix J^T J at the optimum is not positive definite"
        raise ModelError(msg) from err
    return _Optimum(
        poses=x, information=info, chol=chol, log_gauss=prob.log_const - cost, iterations=iterations
    )


def optimize_poses(
    labels: Sequence[int],
    visits: Sequence[Visit],
    config: OdometryConfig,
    loops: Sequence[RelativePose] = (),
    initial: ArrayLike | None = None,
) -> tuple[FloatArray, sp.csr_matrix, float]:
    """``X* = argmax f_G`` and its Gauss–Newton information (thesis Ch. 2.4, App. B).

    Args:
        labels: topology, one label per visit (canonicalised here).
        visits: the landmark visits, ``N >= 1``.
        config: model parameters.
        loops: laser registrations (``RelativePose``) that passed their fitness test.
        initial: optional ``(N, 3)`` starting poses (``initial[0]`` is replaced by the gauge ``u_0``);
            default: the odometry poses.

    Returns:
        ``poses`` ``(N, 3)`` (headings wrapped), the information matrix ``J^T J`` (sparse CSR,
        ``3(N-1)`` square) and ``log f_G(X*)``.
    """
    prob = _build_problem(labels, visits, config, loops)
    opt = _optimize(prob, config, initial)
    poses = opt.poses.copy()
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses, sp.csr_matrix(opt.information), opt.log_gauss


@dataclass(frozen=True)
class AliasTest:
    """The outcome of :func:`alias_test` for one topology.

    Attributes:
        aliases: ``(L,)`` which laser loops are explained as symmetric aliases.
        poses: ``(N, 3)`` the optimum ``X*`` without laser loops (headings as optimised), the natural
            start of the optimisation with the loops kept; ``None`` when nothing was tested.
    """

    aliases: NDArray[np.bool_]
    poses: FloatArray | None


def alias_test(
    labels: Sequence[int], visits: Sequence[Visit], config: OdometryConfig, loops: Sequence[RelativePose]
) -> AliasTest:
    """Which laser loops of a topology are better explained as symmetric aliases than as true matches.

    A valid registration of two visits of one place is a true match ``z ~ N(x_i ⊖ x_j, R)`` with
    probability ``1 − ε`` and an alias uniform over ``V_reg`` with probability ``ε``
    (``ε = config.registration_outlier``). Each loop is tested against the odometry and the topology
    alone, as the particle filter tests a registration against its predicted state: with ``x* , H`` the
    optimum and information without laser loops, the predictive is
    ``N(z; x*_i ⊖ x*_j, J H⁻¹ Jᵀ + R)`` (``J`` the Jacobian of ``x_i ⊖ x_j``), and the loop is an alias
    when ``(1 − ε) N(·) < ε / V_reg``: the mixture's dominant component (a max-mixture, after Olson &
    Agarwal 2013). Testing before optimising with the loops matters: an optimum that includes a
    confident alias bends the path until the alias fits. A loop whose heading alone the odometry predicts
    worse than an alias is one too (:func:`heading_aliases`), whatever the optimum. No alias and no
    optimisation when ``ε = 0`` or there are no loops.
    """
    eps = config.registration_outlier
    out = np.zeros(len(loops), dtype=bool)
    if eps == 0.0 or not loops:
        return AliasTest(aliases=out, poses=None)
    on_heading = heading_aliases(visits, loops, config)
    prob = _build_problem(labels, visits, config, ())
    opt = _optimize(prob, config, None)
    x = opt.poses
    ij, means, r_covs = _loop_arrays(loops, prob.n)
    # only the 3×3 covariance blocks of the visits the loops join: H⁻¹ restricted to their columns, padded
    # with a zero block for x_0 (the fixed gauge: no variance)
    involved = np.unique(ij[ij > 0])
    slot = np.full(prob.n, len(involved), dtype=np.intp)
    slot[involved] = np.arange(len(involved))
    cols = (3 * (involved - 1)[:, None] + np.arange(3)).ravel()
    cov_pad = np.zeros((len(cols) + 3, len(cols) + 3))
    if len(cols):
        unit = np.zeros((3 * (prob.n - 1), len(cols)))
        unit[cols, np.arange(len(cols))] = 1.0
        cov_pad[: len(cols), : len(cols)] = cho_solve((opt.chol, True), unit)[cols]  # (3V, 3V) of H⁻¹
    threshold = math.log(eps) - math.log1p(-eps) - math.log(config.registration_volume)
    a, b = ij[:, 0], ij[:, 1]
    rel = between(x[a], x[b])
    jac = between_derivatives(x, a, b, rel[:, 0], rel[:, 1])  # (K, 3, 6): ∂/∂(x_i, x_j)
    idx = (3 * slot[ij][:, :, None] + np.arange(3)).reshape(-1, 6)  # (K, 6) rows of cov_pad
    c_ij = cov_pad[idx[:, :, None], idx[:, None, :]]
    s = jac @ c_ij @ jac.transpose(0, 2, 1) + r_covs
    e = means - rel
    e[:, 2] = wrap_angle(e[:, 2])
    chol = _cholesky_3(0.5 * (s + s.transpose(0, 2, 1)), "laser loop", np.arange(len(ij)), ij)
    v = np.einsum("kij,kj->ki", _lower_inverse_3(chol), e)
    log_det = np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)
    out = (-1.5 * _LOG_2PI - log_det - 0.5 * np.sum(v * v, axis=1) < threshold) | on_heading
    return AliasTest(aliases=out, poses=x)


def registration_aliases(
    labels: Sequence[int], visits: Sequence[Visit], config: OdometryConfig, loops: Sequence[RelativePose]
) -> NDArray[np.bool_]:
    """Which laser loops of a topology are aliases (:func:`alias_test`); all False when ``ε = 0``."""
    return alias_test(labels, visits, config, loops).aliases


def log_integrand(
    X_batch: ArrayLike,
    labels: Sequence[int],
    visits: Sequence[Visit],
    config: OdometryConfig,
    loops: Sequence[RelativePose] = (),
) -> FloatArray:
    """``log f(X)`` for a batch of pose sets ``X_batch`` ``(S, N, 3)`` (``x_0`` included), ``(S,)``.

    ``f`` is the full integrand of the module docstring: ``f_G`` times the landmark separation prior.
    """
    prob = _build_problem(labels, visits, config, loops)
    P = np.asarray(X_batch, dtype=float)
    if P.ndim != 3 or P.shape[1:] != (prob.n, 3):
        msg = f"X_batch must have shape (S, {prob.n}, 3), got {P.shape}"
        raise ModelError(msg)
    if not np.all(np.isfinite(P)):
        msg = "X_batch must be finite"
        raise ModelError(msg)
    return _log_integrand(P, prob, config)


def _log_integrand(P: FloatArray, prob: _Problem, config: OdometryConfig) -> FloatArray:
    r = _residuals(P, prob)
    return prob.log_const - 0.5 * np.einsum("sm,sm->s", r, r) + _log_prior(P, prob, config)


def _proposal_draws(z: FloatArray, opt: _Optimum, prob: _Problem, coordinates: str) -> FloatArray:
    """Poses ``(S, N, 3)`` from standard normal draws ``z`` ``(S, d)`` under ``q`` (see the module docstring).

    ``y = L^{-T} z`` ~ N(0, H^{-1}) with ``H = L L^T``. In ``"absolute"`` coordinates ``X = X* + y``.
    In ``"relative"`` coordinates the odometry increments ``δ_k = x_k ⊖ x_{k+1}`` are perturbed by the
    linearised image ``D y`` (``D = ∂δ/∂X`` at ``X*``, block bidiagonal with ``det D = 1``) and the
    poses recomposed from ``x_0``: the same Gaussian to first order, with the same density ``q``
    (``½|z|²`` and ``log|H|``), but curved along the path as heading errors curve it.
    """
    n_s, n = len(z), prob.n
    # numpy's solver: SciPy's threaded trsm is erratically slow on busy machines
    y = np.linalg.solve(opt.chol.T, z.T).T.reshape(n_s, n - 1, 3)
    x_star = opt.poses
    if coordinates == "absolute":
        P = np.repeat(x_star[None], n_s, axis=0)
        P[:, 1:] += y
        return P
    a = np.arange(n - 1)
    delta = between(x_star[:-1], x_star[1:])
    delta[:, 2] = x_star[1:, 2] - x_star[:-1, 2]  # unwrapped, so that recomposition returns X* at z = 0
    de = between_derivatives(x_star, a, a + 1, delta[:, 0], delta[:, 1])
    y_full = np.concatenate([np.zeros((n_s, 1, 3)), y], axis=1)
    d_delta = np.einsum("kij,skj->ski", de[:, :, :3], y_full[:, :-1], optimize=True)
    d_delta += np.einsum("kij,skj->ski", de[:, :, 3:], y_full[:, 1:], optimize=True)
    steps = delta[None] + d_delta  # (S, N-1, 3)
    theta = x_star[0, 2] + np.concatenate([np.zeros((n_s, 1)), np.cumsum(steps[..., 2], axis=1)], axis=1)
    c, s = np.cos(theta[:, :-1]), np.sin(theta[:, :-1])
    moves = np.stack([c * steps[..., 0] - s * steps[..., 1], s * steps[..., 0] + c * steps[..., 1]], axis=-1)
    P = np.empty((n_s, n, 3))
    P[:, 0, :2] = x_star[0, :2]
    P[:, 1:, :2] = x_star[0, :2] + np.cumsum(moves, axis=1)
    P[..., 2] = theta
    return P


def metric_log_likelihood(  # noqa: PLR0917 (positional order fixed by the module's API)
    labels: Sequence[int],
    visits: Sequence[Visit],
    config: OdometryConfig,
    loops: Sequence[RelativePose] = (),
    rng: np.random.Generator | None = None,
    initial: ArrayLike | None = None,
) -> MetricResult:
    """``log P(O, S | T)`` by Laplace's method and importance sampling (thesis eq. 14, 18, 47; App. B).

    Args:
        labels: topology, one label per visit (canonicalised here).
        visits: the landmark visits, ``N >= 1``.
        config: model parameters; ``config.n_samples = 0`` or more than ``config.max_sampled_visits``
            visits skip importance sampling.
        loops: laser registrations (``RelativePose``) that passed their fitness test.
        rng: source of the importance samples; ``None`` uses ``np.random.default_rng(0)``, so equal
            inputs give equal results (common random numbers across topologies).
        initial: optional ``(N, 3)`` warm start for the optimiser (e.g. a parent particle's poses).
    """
    prob = _build_problem(labels, visits, config, loops)
    opt = _optimize(prob, config, initial)
    d = 3 * (prob.n - 1)
    x_star = opt.poses
    log_det = 2.0 * float(np.sum(np.log(np.diag(opt.chol))))
    log_prior_star = float(_log_prior(x_star[None], prob, config)[0])
    log_laplace = opt.log_gauss + 0.5 * d * _LOG_2PI - 0.5 * log_det + log_prior_star

    n_s = config.n_samples if prob.n <= config.max_sampled_visits else 0
    if n_s == 0 or d == 0:
        log_lik, ess = log_laplace, float(n_s)
    else:
        gen = np.random.default_rng(0) if rng is None else rng
        z = gen.standard_normal((n_s, d))
        P = _proposal_draws(z, opt, prob, config.proposal)
        log_q = -0.5 * d * _LOG_2PI + 0.5 * log_det - 0.5 * np.einsum("sd,sd->s", z, z)
        r = _residuals(P, prob)
        log_f = prob.log_const - 0.5 * np.einsum("sm,sm->s", r, r) + _log_prior(P, prob, config, x_star)
        log_w = log_f - log_q
        if not np.all(np.isfinite(log_w) | (log_w == -np.inf)):
            msg = "importance weights are not finite"
            raise ModelError(msg)
        lse = float(logsumexp(log_w))
        log_lik = lse - math.log(n_s)
        ess = float(np.exp(2.0 * lse - logsumexp(2.0 * log_w)))

    poses = x_star.copy()
    poses[:, 2] = wrap_angle(poses[:, 2])
    lab = np.asarray(prob.labels)
    m = int(lab.max()) + 1
    counts = np.bincount(lab, minlength=m)
    place_positions = (
        np.stack(
            [
                np.bincount(lab, weights=poses[:, 0], minlength=m),
                np.bincount(lab, weights=poses[:, 1], minlength=m),
            ],
            axis=1,
        )
        / counts[:, None]
    )
    return MetricResult(
        log_likelihood=float(log_lik),
        log_laplace=float(log_laplace),
        ess=ess,
        poses=poses,
        place_positions=place_positions,
        iterations=opt.iterations,
    )
