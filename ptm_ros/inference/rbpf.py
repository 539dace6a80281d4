r"""The Rao-Blackwellized particle filter over topologies (thesis Ch. 3.7–3.11, Algorithms 7–8, eq. 38–53).

The posterior over topologies is computed one landmark visit at a time (eq. 38–39):

.. math::
    p(L^n \mid z^n) \propto p(L^{n-1} \mid z^{n-1})\, p(L_n \mid L^{n-1})\,
        p(o_{n-1}, s_n \mid L^n, z^{n-1})\, p(a_n \mid L^n, a^{n-1}).

A particle is a topology of the visits so far (a canonical label sequence ``L^n``) with a weight and,
Rao-Blackwellized, an analytic Gaussian over the continuous part of the state given that topology
(eq. 33–34, 40–41). The metric model is exactly the batch model of :mod:`ptm_ros.model.odometry` (odometry
Gaussians, places as points ``p_s`` uniform over an area ``A`` with every visit within ``σ_T`` of its
place once the place's offset ``δ_s`` along the visit's heading is taken off, laser
:class:`~ptm_ros.model.geometry.RelativePose` factors between consecutive visits of a place, the cubic
separation prior), so that with enough particles the filter reproduces :func:`exact_posterior
<ptm_ros.model.posterior.exact_posterior>`.

State per particle
------------------
:math:`\xi = [x_n;\ q_0, δ_0, x_{last(0)};\ \dots;\ q_{M-1}, δ_{M-1}, x_{last(M-1)}]`: the pose of the
current visit (3), and per place its point (2), its offset (1, only with ``odometry.sigma_offset`` > 0)
and the pose of its latest visit (3, kept only when a registrar is given, for the laser factor). Older
visit poses are marginalised out. A visit ``i`` of place ``s`` lies at :math:`p_s + δ_s h_i + ε_i`
(``h_i`` the unit vector of its odometry heading, :func:`~ptm_ros.model.odometry.coincidence_rows`); the
state holds :math:`q_s = p_s + δ_s \bar h_s` (``h̄_s``: the mean heading vector of the place's visits so
far), the point the place's visits centre on, so that the separation prior below reads it as it read
``p_s`` without the offset; a revisit moves ``h̄_s`` and, by a linear change of variables, ``q_s``.
``ξ ~ N(μ, P)`` is the Laplace (Gaussian) projection of eq. 40–41, maintained by an extended Kalman
filter. Given the labels the state
is deterministic, so particles with equal labels would be identical: the particle set holds *distinct*
topologies with log weights, never duplicates.

One step (visit ``n``, odometry :math:`o = u_{n-1} \ominus u_n`, covariance ``Σ`` of
:func:`~ptm_ros.model.odometry.odometry_covariances`)
-------------------------------------------------------------------------------------------------
1. *Predict* :math:`x_n = x_{n-1} \oplus (o + w)`, ``w ~ N(0, Σ)``, linearised: only the rows and
   columns of ``x`` change, :math:`P_{xx} \leftarrow F P_{xx} F^\top + G Σ G^\top`,
   :math:`P_{x\cdot} \leftarrow F P_{x\cdot}` (``G = diag(R(θ), 1)``). The odometry factor integrates
   to one over ``x_n`` (the Jacobian of ``x_n`` in ``w`` has determinant 1), so it contributes no weight
   of its own, as in the batch integral.
2. *Expand* every particle into its children ``k ∈ {0..M-1}`` (revisit place ``k``) and ``M`` (a new
   place), the data-driven proposal of eq. 50–53 done exactly over the discrete choice:

   .. math::
       \log \tilde w_k = \log w + \log p(L_n = k \mid L^{n-1}) + \log p(o_{n-1} \mid k) - \Delta c_k
                         + \log p(a_n \mid k),

   * revisit, the coincidence ``x_n^{xy} - t_k = v``, ``v ~ N(0, σ_T² I)`` observed as 0, with
     :math:`t_k = q_k + δ_k (h_n - \bar h_k)` (``q_k`` without the offset) — the exact Gaussian integral
     of eq. 47–48 under the predicted state: :math:`p(o \mid k) = N(0;\ \hat x_n^{xy} - \hat t_k,\ S_k)`,
     :math:`S_k = \mathrm{cov}(x_n^{xy} - t_k) + σ_T^2 I`;
   * new place: :math:`p(o \mid M) = \int \frac1A N(x_n^{xy}; p + δ h_n, σ_T^2 I)\,dp = 1/A` and
     :math:`q_M \sim N(x_n^{xy}, σ_T^2 I)` and :math:`δ_M \sim N(0, σ_δ^2)` enter the state;
   * separation prior (eq. 15–16), for selection only (:func:`_separation_proxy`): per near place
     ``s``, ``-log E[exp(-|s| c(‖x̄_s - x_n^{xy}‖))]`` on 64 lattice points under the child's Gaussian
     after the coincidence (revisit) or as predicted (new place), summed over the places; replaced after
     selection by the ADF expectation of step 5;
   * appearance: the predictive of eq. 46, per distinct block (:func:`block_log_predictives`, equal to
     :func:`~ptm_ros.model.appearance.appearance_log_predictive`, vectorised).
3. *Select* at most ``N`` children by Fearnhead–Clifford optimal resampling for discrete states
   (:func:`optimal_resample`): distinct topologies, unbiased weights. With ``particles_max`` above
   ``particles``, ``N`` adapts to the posterior's spread (:func:`particle_count`): the smallest
   ``N ≥ particles`` (up to ``particles_max``) at which the children thinned at random, each kept with
   probability ``w / c`` only, hold at most ``thinned_mass`` of the probability. A fixed ``N`` drops, by
   chance, hypotheses that are unlikely now and that a later loop confirms; where the posterior is spread
   the resampling seed then decides the MAP.
4. *Update* the selected children. Revisit of ``k``: the coincidence update (EKF), then, if the registrar
   measures ``z = x_{last(k)} \ominus x_n`` (pair ``(last(k), n)``, the batch model's chaining rule), the
   weight is multiplied by its predictive :math:`N(z;\ h(\hat\xi),\ H P H^\top + R)` times ``V_reg``
   (the "weight keeps the rest" of eq. 50–53; ``V_reg``: see below) and the state is updated, ``h``
   linearised at the mode of the 6-D measurement problem (iterated EKF, :func:`_laser_factor`); finally
   ``x_{last(k)} := x_n`` (the old one is marginalised). New place: ``p_M`` and ``x_{last(M)} := x_n``
   are appended.
5. *Separation prior* (eq. 15–16) of the new pairs ``(i, n)``, ``i`` of another place, by assumed
   density filtering (:func:`_separation_update`): the weight is multiplied by
   :math:`E[\exp(-\sum_{s \ne k} |s|\, c(\lVert \bar x_s - x_n^{xy} \rVert))]` under the child's
   Gaussian after the factors above (the selection proxy divided out), and the state is replaced by the
   moment-matched Gaussian of the tilted density. **Approximation**: past poses are marginalised, so the
   visits of place ``s`` are taken at their mean :math:`\bar x_s` (exactly Gaussian in the state: the
   model's :math:`q_s \mid δ_s, X \sim N(\bar x_s, σ_T^2/|s|\, I)`); and the state stays Gaussian. With
   the offset, visits of one place passed in opposite directions lie up to ``2 δ_s`` from each other, and
   the mean errs more (``test_the_filter_follows_the_visit_offset_with_the_separation_prior``).
   This is the chain rule of the batch integral, which integrates the penalty over the poses
   (importance sampling, eq. 18: what ``ptm-run --method exact`` computes). Evaluating the penalty at
   the means instead (the Laplace estimate's ``c`` at ``X*``; this filter before issue #23) charges a
   split place (two visits a metre apart taken as two places) its penalty at the point, where the
   integral over the visits' uncertainty is much milder, and so undervalued "no loop" topologies
   (``bench/exact.json``; the test ``test_filter_matches_enumeration_where_the_separation_prior_matters``).
   Charging each pair's expectation without updating the state double-charges correlated pairs
   (a split place whose next visit is split too: the first penalty pushes both apart), hence the ADF
   update.
6. The PTM is the normalised particle weights; the effective sample size ``1/Σ w²`` and the number of
   distinct topologies are reported per step (:class:`FilterState`). Each particle also carries its
   sequential metric log evidence (the terms above but the prior and appearance), so that the PTM can be
   weighed with the batch model's instead (:mod:`ptm_ros.inference.reweighting`, :meth:`reweighted`):
   resampling uses the sequential weights, :meth:`ptm_weights` the reweighted ones where the batch
   evidence is sampled, when ``RbpfConfig.reweight`` (off in the bare filter, on in the product:
   ``inference.reweight``).

For a model linear in the poses these steps are the chain rule of the batch integral
:math:`\int f_G\,dX` (the product over steps of the predictive densities), so the particles' weights equal
the exact posterior when no child is ever dropped. With headings the EKF linearises sequentially where
the batch Laplace estimate linearises once at its optimum; the difference shrinks with the heading noise
(``bench/bench_rbpf.py`` measures both against importance sampling). The sum of the per-step
``log_evidence_increment`` estimates :math:`\log p(z^n)` (with optimal resampling, unbiased before the
logarithm in the linear case).

Known limitation (EKF inconsistency): a loop closure that corrects a large heading drift (tens of
degrees) is absorbed by a linear update of a state whose past poses are gone, so the map of that
topology is distorted (``bench/bench_rbpf.py``'s 6×6 world, ``bench/rbpf.json``) and its later
revisits score too low; a wrong topology that avoided the closure can then overtake it. A smoothing
back-end, or re-optimising a particle's poses after a large innovation, would remove this.

Against ``ptm-run --method exact`` (``bench/bench_exact.py``, figures in ``bench/reweighting.md``) the
sequential weights differ in two ways; the reweighting removes both where it applies (the batch evidence
is the reference's), and the filter's choice of which topologies to keep remains:

* the EKF linearisation above, also for moderate closures: a closure several metres off the odometry at
  tens of metres from the pivoting headings is scored with the straight-line (linearised) image of the
  heading errors, where the batch Laplace estimate linearises at the closed path (its arc), and
  importance sampling confirms the batch. The gap vanishes as the heading noise goes to 0. Integrating
  the revisit likelihood along an arc of the turn error instead of its tangent (one pivot, or the
  odometry's pivots since the place's last visit) closes most of it on the simulated runs but moves real
  runs' far closures by tens of nats, both ways, because the state no longer knows the path's pivots;
  a state that keeps them (a Lie-group or smoothing filter) would remove it.
* the alias decision of a laser registration (below): the filter tests a registration against its state
  *with* the topology's earlier registrations, the batch model (:func:`~ptm_ros.model.odometry.alias_test`)
  against the optimum *without* any; both also take for an alias, in every topology, a registration whose
  heading alone the odometry predicts worse than an alias (:func:`~ptm_ros.model.odometry.heading_aliases`).

The laser factor is known only after selection (registrations are expensive, so only the selected
revisits are registered). As in :class:`~ptm_ros.model.posterior.PosteriorModel`, the data are the outcomes of
all pairs, and a pair the topology does not chain has the uninformative density ``1/V_reg``; so, up to a
constant common to all topologies, a used registration contributes the likelihood ratio
:math:`N(z; \cdot) \cdot V_{reg}` and pairs never chained need not be registered; every registered
chained pair (valid match or :class:`~ptm_ros.model.geometry.NoMatch`) adds its fitness evidence
``log_bayes`` (:func:`ptm_ros.perception.laser.fitness_log_bayes`). The log evidence
carries the same constant (it is relative to "every registered pair uninformative").

A valid registration may still be a symmetric alias (a crossing passed in opposite directions by a 180°
laser matches best turned by π): with probability ``ε = registration_outlier`` its outcome is uniform
over ``V_reg``. The predictive is then the mixture :math:`(1-ε) N(z; \cdot) V_{reg} + ε` (relative to
``1/V_reg``), and the state keeps the dominant component of the posterior: no update from an alias
(the batch model's :func:`~ptm_ros.model.odometry.registration_aliases`). A registration whose heading
alone rules out a true match (:func:`~ptm_ros.model.odometry.heading_aliases`) is an alias whatever the
state predicts: it contributes ``ε`` only. Without it, one trusted alias
costs the true topology hundreds of nats and the filter splits the place.

Thesis corrections:

* Algorithms 7–8 draw a parent by weight and then one child: multinomial resampling, which duplicates
  topologies (identical particles, the state being deterministic given the labels). Here the children
  are enumerated and thinned by optimal resampling.
* The data-driven proposal (eq. 52) draws ``L_n ∝ p(L_n | L^{n-1}) p(o | L^n)``, but the weight printed
  after eq. 53, :math:`w_n \propto p(s_n \mid \dots)\, w_{n-1}^{(i-1)}`, leaves out the proposal's
  normaliser :math:`\sum_k p(L_n = k \mid L^{n-1}) p(o \mid k)`, which differs between parents and
  must multiply the weight (here each child carries the full product); ``(i-1)`` should read ``(i)``.
  The odometry written ``o_n`` in eq. 47 and 50–53 is ``o_{n-1}``, the step that ends at visit ``n``.
* With the normalised coincidence model of :mod:`ptm_ros.model.odometry` (its correction of eq. 17), a new
  place contributes ``1/A``, absent from eq. 53.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.blas import dgemm

from ptm_ros.errors import ConfigError, ModelError, PtmError
from ptm_ros.inference.predictive import batch_log_predictive, block_log_predictives
from ptm_ros.inference.resampling import (
    RESAMPLE_METHODS,
    IntArray,
    logsumexp,
    optimal_resample,
    particle_count,
    top_resample,
)
from ptm_ros.inference.reweighting import Reweighted, reweigh, sampled_evidence
from ptm_ros.model.appearance import AppearanceModel, appearance_log_predictive
from ptm_ros.model.geometry import FloatArray, NoMatch, Registrar, RelativePose, between, compose, wrap_angle
from ptm_ros.model.odometry import (
    OdometryConfig,
    heading_aliases,
    new_places,
    odometry_covariances,
    place_log_priors,
)
from ptm_ros.model.partitions import Labels
from ptm_ros.model.posterior import ModelConfig, PosteriorModel
from ptm_ros.model.priors import TopologyPrior
from ptm_ros.model.ptm import Landmark, Ptm, make_ptm
from ptm_ros.model.visits import Visit, visit_fields, visit_from_fields
from ptm_ros.settings import Settings, setting

#: A registrar returns the laser measurement of ``between(x_i, x_j)`` for visits ``i < j``, or None
#: (registration failed its fitness test: no information). Same contract as ``ptm_ros.model.posterior``.

#: Told the visit pairs ``(i, j)`` the filter is about to ask its registrar for (:class:`TopologyFilter`).
Prefetch = Callable[[list[tuple[int, int]]], None]


#: Schema tag of :meth:`TopologyFilter.state_dict`.
STATE_SCHEMA = "ptm_ros.rbpf/3"

_LOG_2PI = math.log(2.0 * math.pi)
_INITIAL_CAPACITY = 4  # place slots allocated at first; grown with slack when a child needs more
_SLACK = 2


@dataclass(frozen=True)
class RbpfConfig(Settings):
    """Settings of the particle filter."""

    particles: int = setting(
        100, ge=1, doc="N, the distinct topologies kept after each visit (the fewest, with ``particles_max``)"
    )
    particles_max: int = setting(
        0,
        ge=0,
        doc=(
            "the most distinct topologies kept where the posterior is spread (``optimal`` resampling; module "
            "docstring, step 3); at or below ``particles`` (the default): always ``particles``"
        ),
    )
    thinned_mass: float = setting(
        0.001,
        ge=0,
        lt=1,
        doc="the probability that optimal resampling may thin at random before it keeps more topologies",
    )
    resample: str = setting(
        "optimal",
        choices=RESAMPLE_METHODS,
        doc='``"optimal"`` (Fearnhead–Clifford) or ``"top"`` (the N heaviest children, biased)',
    )
    record_top: int = setting(
        0,
        ge=0,
        doc=(
            "the most probable topologies each update records in its FilterState (``top``: the PTM after "
            "that visit, eq. 38–39, by the sequential weights); 0 records none"
        ),
    )
    reweight: bool = setting(
        False,
        doc=(
            "weigh the topologies held with the batch metric evidence (importance sampling, eq. 18) "
            "instead of the EKF's sequential one, where it is sampled (:mod:`ptm_ros.inference.reweighting`)"
        ),
    )


@dataclass(frozen=True)
class FilterState:
    """Diagnostics of one filter update.

    Attributes:
        n_visits: visits processed so far.
        n_topologies: distinct topologies (particles) held.
        ess: effective sample size ``1 / Σ w²`` of the normalised weights.
        log_evidence_increment: estimate of ``log p(z_n | z^{n-1})`` (the first visit: ``log p(z_0)``).
        update_s: wall time of the update [s].
        top: the ``RbpfConfig.record_top`` most probable topologies after the update with their
            probabilities, most probable first (ties in particle order): the PTM of the visits so far.
    """

    n_visits: int
    n_topologies: int
    ess: float
    log_evidence_increment: float
    update_s: float
    top: tuple[tuple[Labels, float], ...] = ()


# ------------------------------------------------------------------------------------------- particles


@dataclass(frozen=True, eq=False)
class _Particles:
    """The particle set: distinct topologies, normalised log weights and Gaussian states (padded).

    ``mean`` ``(P, D)`` and ``cov`` ``(P, D, D)`` with ``D = 3 + stride * cap``; place ``k`` occupies
    columns ``3 + stride*k + (0, 1)`` (``q_k``), with the visit offset ``+ 2`` (``δ_k``), and with a
    registrar the next three (``x_last(k)``): :class:`_Layout`. Slots ``k ≥ n_places`` are zero.
    ``counts``/``last`` ``(P, cap)``: visits of each place and the index of its latest visit (0 / -1 when
    unused); ``headings`` ``(P, cap, 2)``: the sum of the unit odometry headings of each place's visits.
    """

    labels: tuple[Labels, ...]
    log_w: FloatArray
    mean: FloatArray
    cov: FloatArray
    counts: IntArray
    last: IntArray
    n_places: IntArray
    blocks: tuple[tuple[tuple[int, ...], ...], ...] | None  # per particle, per place (appearance only)
    penalty: FloatArray  # (P,) separation penalty charged so far [nats] (_separation_update)
    metric: FloatArray  # (P,) sequential metric log evidence, separation prior included (reweighting)
    headings: FloatArray  # (P, cap, 2) sum of the unit headings of each place's visits (the visit offset)


@dataclass(frozen=True)
class _Layout:
    """Where a place's variables sit among its ``stride`` columns: ``q`` at 0–1, ``δ`` at ``delta`` (with
    the visit offset), ``x_last`` at ``x_last`` .. ``x_last + 2`` (with a registrar)."""

    offset: bool
    laser: bool

    @property
    def delta(self) -> int:
        return 2

    @property
    def x_last(self) -> int:
        return 2 + int(self.offset)

    @property
    def stride(self) -> int:
        return self.x_last + (3 if self.laser else 0)


def _place_cols(stride: int, places: ArrayLike, offset: int, width: int) -> IntArray:
    """Columns ``3 + stride*k + offset + (0..width-1)`` for each place ``k``: shape ``(..., width)``."""
    k = np.asarray(places, dtype=np.intp)
    return (3 + stride * k + offset)[..., None] + np.arange(width)


def _duplicate(mean: FloatArray, cov: FloatArray, src: IntArray, dst: IntArray) -> None:
    """In place, per particle ``r``: make the variables ``dst[r]`` ``(C, q)`` copies of ``src`` ``(q,)``."""
    rows = np.arange(len(dst))[:, None]
    mean[rows, dst] = mean[:, src]
    cov[rows, dst, :] = cov[:, src, :]
    cov[rows, :, dst] = cov[:, :, src].transpose(0, 2, 1)


def _shear(mean: FloatArray, cov: FloatArray, dst: IntArray, src: IntArray, a: FloatArray) -> None:
    """In place, per particle ``r``: the variables ``dst[r]`` ``(R, q)`` gain ``a[r]`` ``(R, q)`` times the
    variable ``src[r]`` ``(R,)``, a linear change of variables ``ξ := T ξ``, ``P := T P Tᵀ``."""
    rows = np.arange(len(dst))
    mean[rows[:, None], dst] += a * mean[rows, src][:, None]
    cov[rows[:, None], dst, :] += a[:, :, None] * cov[rows, src, :][:, None, :]
    cov[rows[:, None], :, dst] += a[:, :, None] * cov[rows, :, src][:, None, :]


def _unit(angle: float) -> FloatArray:
    """The unit vector of a heading."""
    return np.array([math.cos(angle), math.sin(angle)])


@dataclass(frozen=True, eq=False)
class _Lever:
    """The visit offset's lever on a revisit of place ``k`` by visit ``n``: ``g_k = h_n - h̄_k``
    ``(P, cap, 2)`` (``h̄_k``: the mean unit heading of the place's visits so far) and the columns of
    ``δ_k`` ``(cap,)``."""

    cols: IntArray
    g: FloatArray


def _add_gram(cov: FloatArray, a: FloatArray, b: FloatArray) -> None:
    """In place ``cov += aᵀ b`` for a C-contiguous ``(D, D)`` ``cov`` and ``a``, ``b`` ``(k, D)`` whose
    ``aᵀ b`` is symmetric term by term (row ``r`` of ``b`` is ``±`` row ``r`` of ``a``).

    One BLAS ``gemm`` with ``β = 1`` writes straight into the covariance, without a ``(D, D)`` temporary:
    ``cov.T`` is ``cov``'s memory in Fortran order, as ``gemm`` wants it, and ``gemm`` adds ``aᵀ b`` to
    ``cov.T``, i.e. ``bᵀ a`` to ``cov``, the same matrix. Element ``(i, j)`` sums the products
    ``a_ri b_rj`` and element ``(j, i)`` the same products in the same order, so a symmetric ``cov`` stays
    symmetric to the last bit.
    """
    target = cov.T
    out = dgemm(1.0, a, b, 1.0, target, trans_a=1, overwrite_c=1)
    if not np.shares_memory(out, target):  # BLAS had to copy: write the result back
        cov[...] = out.T


def _downdate(cov: FloatArray, W: FloatArray) -> None:
    """In place ``cov[r] -= W[r]ᵀ W[r]`` for ``cov`` ``(C, D, D)`` (C-contiguous) and ``W`` ``(C, k, D)``
    (:func:`_add_gram`: no ``(C, D, D)`` temporary, a third less memory traffic in a filter step)."""
    for r in range(len(W)):
        _add_gram(cov[r], W[r], -W[r])


def _cubic(dist: FloatArray, config: OdometryConfig) -> FloatArray:
    """The separation penalty ``c(d) = c_max (1 - d/D)^3`` for ``d < D``, else 0 (eq. 15–16)."""
    gap = 1.0 - dist * (1.0 / config.penalty_radius)
    np.maximum(gap, 0.0, out=gap)
    return config.penalty_max * (gap * gap * gap)


#: Standard normal points of the separation prior's expectation (:func:`_separation_update`): a
#: golden-ratio lattice of the unit square mapped to the plane by Box–Muller (radius from the first
#: coordinate, angle from the second), whitened to sample mean 0 and covariance I. Deterministic: the
#: filter's only randomness stays the resampling. 512 points integrate ``exp(-k c(‖δ‖))`` over a Gaussian
#: ``δ`` to ~0.005 nats and its tilted moments to ~1 % (tested against sampling), from point-like to
#: wider than the radius ``D``.
_PENALTY_POINTS = 512
#: Pairs whose mean distance exceeds ``D`` by more standard deviations contribute nothing: a 2-D normal
#: is beyond ``t`` of its mean with probability ``exp(-t²/2)`` (here 4e-5), which bounds ``1 - E[g]``.
_PENALTY_PRUNE_SD = 4.5


def _penalty_points(count: int = _PENALTY_POINTS) -> FloatArray:
    """``(2, count)`` lattice points whose sample mean is exactly 0 and sample covariance exactly ``I``
    (whitened), so that a factor that is 1 everywhere leaves the moments of :func:`_tilted_moments`, and
    hence the state, unchanged."""
    i = np.arange(count)
    u = (i + 0.5) / count
    angle = 2.0 * math.pi * np.mod(i / ((1.0 + math.sqrt(5.0)) / 2.0), 1.0)
    radius = np.sqrt(-2.0 * np.log1p(-u))
    z = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=0)  # (2, K)
    z -= z.mean(axis=1, keepdims=True)
    chol = np.linalg.cholesky(z @ z.T / count)
    return np.linalg.solve(chol, z)


_Z = _penalty_points()
#: How far the farthest of :data:`_Z` lies from 0 (with a margin for rounding): a Gaussian's lattice points
#: lie within this many ``√λ_max`` of its mean.
_Z_REACH = float(np.max(np.hypot(_Z[0], _Z[1]))) * (1.0 + 1e-9)


def _separation_update(
    mean: FloatArray, cov: FloatArray, counts: IntArray, kk: IntArray, *, stride: int, config: OdometryConfig
) -> FloatArray:
    r"""The separation prior of the new pairs ``(i, n)``, by assumed density filtering; in place.

    Returns ``log E[exp(-Σ_s |s| c(‖x̄_s - x_n^{xy}‖))]`` per child ``(C,)`` and replaces each child's
    Gaussian ``N(mean, cov)`` by the moment-matched (Gaussian) projection of the Gaussian times the
    prior's factor. ``mean``/``cov``: the children's states after the Gaussian factors of visit ``n``;
    ``counts`` ``(C, cap)``: visits of each place *before* ``n`` (the parents' counts); ``kk``: the place
    of visit ``n`` (a revisited place has no new pair with ``n``).

    The pairs ``(i, n)``, ``i`` of another place ``s``, are taken with every visit of ``s`` at the mean
    of its visits, ``x̄_s``. Under the model ``q_s | δ_s, X ~ N(x̄_s, σ_T²/|s| I)`` independently of the
    rest (``q_s = p_s + δ_s h̄_s``, the state's place columns; ``p_s`` without the offset), so
    ``δ_s = x̄_s - x_n^{xy} = q_s - x_n^{xy} - η_s`` is Gaussian with the mean of ``q_s - x_n^{xy}``, its
    covariance minus ``σ_T²/|s| I``, and ``cov(ξ, δ_s) = cov(ξ, q_s - x_n^{xy}) - σ_T²/|s|`` on the rows
    of ``q_s`` (the only state variable correlated with ``η_s``). Each place's factor
    ``g(δ) = exp(-|s| c(‖δ‖))`` is integrated over ``N(δ; m, Σ)`` on the :data:`_Z` points (pairs more
    than :data:`_PENALTY_PRUNE_SD` standard deviations beyond the radius contribute 0), giving the weight
    factor ``E[g]`` and the tilted moments ``m', Σ'``; as ``ξ | δ`` is unchanged by a factor of ``δ``, the
    moment-matched state is ``μ += K(m' - m)``, ``P += K(Σ' - Σ)Kᵀ`` with ``K = cov(ξ, δ) Σ^{-1}``
    (the law of total variance: positive semi-definite). The near places of a child are taken one after
    the other, each under the state updated by the previous ones, so that correlated pairs (a split
    place whose next visits are split too) are not charged twice; the rank-2 covariance updates are
    summed and written once (:func:`_signed_factors`). A pair whose penalty is below
    :data:`_NEGLIGIBLE_PENALTY` on every lattice point is left out, as are the negligible directions of
    the moves (:data:`_NEGLIGIBLE_MOVE`).
    """
    n_child = len(mean)
    out = np.zeros(n_child)
    if config.penalty_max == 0.0 or n_child == 0:
        return out
    cap = counts.shape[1]
    active = (counts > 0) & (np.arange(cap)[None, :] != kk[:, None])
    if not np.any(active):
        return out
    pc = _place_cols(stride, np.arange(cap), 0, 2)  # (cap, 2)
    excess = config.sigma_topology**2 / np.maximum(counts, 1)  # (C, cap)
    m, S = _delta_moments(mean, cov, pc, excess)
    sd_max = np.sqrt(np.maximum(_max_eig2(S), 0.0))
    dist = np.hypot(m[..., 0], m[..., 1])
    near = active & (dist - config.penalty_radius < _PENALTY_PRUNE_SD * sd_max)
    if not np.any(near):
        return out
    order = np.argsort(np.where(near, dist, np.inf), axis=1, kind="stable")  # nearest first
    n_near = near.sum(axis=1)
    n_round = int(n_near.max())
    # Round r's covariance update is K_r (Σ' - Σ)_r K_rᵀ. A round reads only the rows of p_s and x_n, so the
    # updates are kept as factors (Kᵀ stacked, Σ' - Σ block-diagonal) and the (D, D) matrices written once.
    gains = np.zeros((n_child, 2 * n_round, mean.shape[1]))
    moves = np.zeros((n_child, 2 * n_round, 2 * n_round))
    spread = np.zeros((n_child, n_round))  # tr Σ of each round, the scale of a negligible move
    for r in range(n_round):
        rows = np.flatnonzero(n_near > r)
        places = order[rows, r]
        cols = pc[places]  # (R, 2)
        ar = np.arange(len(rows))[:, None]
        m_q = mean[rows[:, None], cols] - mean[rows, :2]
        pick = np.concatenate([cols, np.broadcast_to(np.arange(2), cols.shape)], axis=1)  # rows p_s, x_n
        cov_rows = cov[rows[:, None], pick, :]  # (R, 4, D)
        if r:
            g = gains[rows, : 2 * r]
            g_pick = np.take_along_axis(g, pick[:, None, :], axis=2).transpose(0, 2, 1)
            cov_rows += g_pick @ (moves[rows, : 2 * r, : 2 * r] @ g)
        # cov(δ, ξ) = cov(p_s - x_n, ξ) - cov(η_s, ξ), η_s = p_s - x̄_s: only p_s is correlated with η_s
        c_q = cov_rows[:, :2] - cov_rows[:, 2:]  # (R, 2, D)
        c_q[ar, np.arange(2), cols] -= excess[rows, places][:, None]
        s_q = c_q[ar, :, cols].transpose(0, 2, 1) - c_q[:, :, :2]  # cov(δ): (R, 2, 2)
        s_q = 0.5 * (s_q + s_q.swapaxes(-1, -2))
        # the factor's largest penalty over the lattice points, at the nearest of them: below
        # _NEGLIGIBLE_PENALTY (0 when every point lies beyond the radius) the pair moves nothing
        reach = _Z_REACH * np.sqrt(np.maximum(_max_eig2(s_q), 0.0))
        nearest = np.maximum(np.hypot(m_q[:, 0], m_q[:, 1]) - reach, 0.0)
        hit = counts[rows, places] * _cubic(nearest, config) >= _NEGLIGIBLE_PENALTY
        rows, places, m_q, c_q, s_q = rows[hit], places[hit], m_q[hit], c_q[hit], s_q[hit]
        log_e, shift, s_new = _tilted_moments(m_q, s_q, counts[rows, places], config, _Z)
        out[rows] += log_e
        det = s_q[:, 0, 0] * s_q[:, 1, 1] - s_q[:, 0, 1] * s_q[:, 1, 0]
        ok = (s_q[:, 0, 0] > 0.0) & (det > 1e-12 * np.maximum(np.square(s_q[:, 0, 0] + s_q[:, 1, 1]), 1e-300))
        rows, c_q, s_q, s_new, shift = rows[ok], c_q[ok], s_q[ok], s_new[ok], shift[ok]
        gain_t = np.linalg.solve(s_q, c_q)  # Kᵀ = Σ^{-1} cov(δ, ξ): (R, 2, D)
        mean[rows] += np.einsum("rk,rkd->rd", shift, gain_t)
        gains[rows, 2 * r : 2 * r + 2] = gain_t
        moves[rows, 2 * r : 2 * r + 2, 2 * r : 2 * r + 2] = s_new - s_q
        spread[rows, r] = s_q[:, 0, 0] + s_q[:, 1, 1]
    child, a, b = _signed_factors(gains, moves, spread)
    starts = np.flatnonzero(np.diff(child, prepend=-1))  # each child's first row
    ends = np.append(starts[1:], len(child)) if len(child) else starts
    for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True):
        _add_gram(cov[child[lo]], a[lo:hi], b[lo:hi])  # Σ_r K_r (Σ' - Σ)_r K_rᵀ
    return out


#: A pair whose separation penalty is below this on every lattice point [nats] is left out of the update:
#: its factor is 1 to within as much (and its moments move by less).
_NEGLIGIBLE_PENALTY = 1e-9
#: An eigenvalue of a round's covariance move ``Σ' - Σ`` below this share of ``tr Σ`` is left out of the
#: state's update. The factor of one place tilts ``δ`` mostly along one direction, so that the other
#: eigenvalue is often rounding (~1e-16): most of the rank of the update on a large map.
_NEGLIGIBLE_MOVE = 1e-9


def _signed_factors(
    gains: FloatArray, moves: FloatArray, spread: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray]:
    """The update ``gᵀ M g`` of every child as ``aᵀ b`` over its rows, for the stacked gains ``g``
    ``(C, 2R, D)`` and the block-diagonal ``M`` ``(C, 2R, 2R)`` (symmetric 2×2 blocks ``Σ' - Σ``, one per
    round, whose ``tr Σ`` is ``spread`` ``(C, R)``): each block ``V diag(λ) Vᵀ`` gives rows
    ``a = |λ|^½ vᵀ g`` and ``b = sign(λ) a`` (``v`` a column of ``V``), so that :func:`_add_gram` adds an
    exactly symmetric update with one ``gemm``. Only the rows whose ``|λ|`` exceeds
    :data:`_NEGLIGIBLE_MOVE` ``tr Σ`` are kept: ``(K,)`` their child (ascending), ``a``, ``b`` ``(K, D)``."""
    n_round = spread.shape[1]
    idx = 2 * np.arange(n_round)[:, None] + np.arange(2)  # (R, 2)
    blocks = moves[:, idx[:, :, None], idx[:, None, :]]  # (C, R, 2, 2)
    lam, vec = np.linalg.eigh(blocks)  # (C, R, 2), (C, R, 2, 2)
    ci, ri, ji = np.nonzero(np.abs(lam) > _NEGLIGIBLE_MOVE * spread[..., None])
    lam_k = lam[ci, ri, ji]
    v = vec[ci, ri, :, ji] * np.sqrt(np.abs(lam_k))[:, None]  # (K, 2)
    a = v[:, 0, None] * gains[ci, 2 * ri] + v[:, 1, None] * gains[ci, 2 * ri + 1]
    return ci, a, a * np.sign(lam_k)[:, None]


def _log_expectation(m: FloatArray, S: FloatArray, count: IntArray, config: OdometryConfig) -> FloatArray:
    """``log E[exp(-count · c(‖δ‖))]`` for ``δ ~ N(m, S)`` ``(Q, 2)``, ``(Q, 2, 2)``, on :data:`_Z_PROXY`."""
    if len(m) == 0:
        return np.zeros(0)
    a = np.sqrt(np.maximum(S[:, 0, 0], 0.0))
    b = np.divide(S[:, 1, 0], a, out=np.zeros_like(a), where=a > 0.0)
    d = np.sqrt(np.maximum(S[:, 1, 1] - b * b, 0.0))
    z = _Z_PROXY
    ex = m[:, 0, None] + a[:, None] * z[0]
    ey = m[:, 1, None] + b[:, None] * z[0] + d[:, None] * z[1]
    pen = _cubic(np.hypot(ex, ey), config) * count[:, None].astype(float)
    low = pen.min(axis=1)
    return np.log(np.mean(np.exp(low[:, None] - pen), axis=1)) - low


def _tilted_moments(
    m: FloatArray, S: FloatArray, count: IntArray, config: OdometryConfig, points: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For ``δ ~ N(m, S)`` ``(Q, 2)``, ``(Q, 2, 2)`` and ``g(δ) = exp(-count · c(‖δ‖))``: ``log E[g]``
    ``(Q,)``, the tilted mean minus ``m`` ``(Q, 2)`` and the tilted covariance ``(Q, 2, 2)``, on the
    standard normal ``points`` ``(2, K)``."""
    a = np.sqrt(np.maximum(S[:, 0, 0], 0.0))
    b = np.divide(S[:, 1, 0], a, out=np.zeros_like(a), where=a > 0.0)
    d = np.sqrt(np.maximum(S[:, 1, 1] - b * b, 0.0))
    ex = a[:, None] * points[0]  # δ - m at the points: (Q, K)
    ey = b[:, None] * points[0] + d[:, None] * points[1]
    pen = _cubic(np.hypot(m[:, 0, None] + ex, m[:, 1, None] + ey), config) * count[:, None].astype(float)
    low = pen.min(axis=1, keepdims=True)
    w = np.exp(low - pen)  # scaled weights of the tilted points
    w_sum = w.sum(axis=1)
    log_e = np.log(w_sum / points.shape[1]) - low[:, 0]
    w /= w_sum[:, None]
    mx, my = np.sum(w * ex, axis=1), np.sum(w * ey, axis=1)
    dx, dy = ex - mx[:, None], ey - my[:, None]
    s_new = np.empty_like(S)
    s_new[:, 0, 0] = np.sum(w * dx * dx, axis=1)
    s_new[:, 1, 1] = np.sum(w * dy * dy, axis=1)
    s_new[:, 0, 1] = s_new[:, 1, 0] = np.sum(w * dx * dy, axis=1)
    return log_e, np.stack([mx, my], axis=1), s_new


#: Points of the selection proxy's expectations (:func:`_separation_proxy`): coarser, as the weight is
#: corrected after selection.
_Z_PROXY = _penalty_points(64)
#: Children lighter than the heaviest by more than this [nats] get no separation proxy before selection.
_PROXY_NATS = 25.0


def _separation_proxy(  # noqa: PLR0917 (the step's intermediate arrays, positionally)
    cov: FloatArray,
    p_hat: FloatArray,
    counts: IntArray,
    x_pred: FloatArray,
    pxx: FloatArray,
    cxp: FloatArray,
    cxt: FloatArray,
    lever: _Lever | None,
    S: FloatArray,
    d: FloatArray,
    stride: int,
    config: OdometryConfig,
    *,
    worth_rev: NDArray[np.bool_],
    worth_new: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """``Σ_s -log E[exp(-|s| c(‖δ_s‖))]`` (per near place ``s``) of every child before selection,
    ``(P, cap)`` and ``(P,)``.

    The expectation of :func:`_separation_update` (without its state update, on :data:`_Z_PROXY`),
    under each child's Gaussian after the coincidence: for a revisit of ``k``, with ``e_s = q_s - x_n``,
    ``h_k = x_n - t_k`` (predicted mean ``d``, covariance ``S`` with ``σ_T² I``; ``t_k = q_k + δ_k g_k`` with
    the visit offset's ``lever``, else ``q_k``) and ``C = cov(e_s, h_k)``,
    ``e_s | h_k = 0 ~ N(ê_s - C S^{-1} d, cov(e_s) - C S^{-1} Cᵀ)``; a new place leaves ``x_n`` as
    predicted. ``cov``: the parents' covariances; ``pxx``, ``cxp``, ``cxt`` ``(P, cap, 2, 2)``: the
    predicted ``cov(x_n^{xy})``, ``cov(x_n^{xy}, q_k)`` and ``cov(x_n^{xy}, t_k)``. Only the pairs
    ``(k, s)`` whose place is near ``x_n``'s updated mean (within the pruning distance of
    :func:`_separation_update` by the prior spread of ``e_s``, ``q_s`` taken at its prior mean) are
    integrated: ``O(P · cap)`` work plus the near pairs, not ``O(P · cap²)`` 2×2 algebra; and only for
    the children ``worth_rev`` ``(P, cap)`` / ``worth_new`` ``(P,)`` within :data:`_PROXY_NATS` of the
    heaviest (the weight is corrected after selection anyway, so the proxy only has to be good where
    selection is decided).
    """
    n_part, cap = counts.shape
    pc = _place_cols(stride, np.arange(cap), 0, 2)  # (cap, 2)
    cpx = cxp.swapaxes(-1, -2)  # cov(p_s, x_n): (P, s, 2, 2)
    ar = np.arange(cap)
    px = pxx[:, None, :2, :2]
    cpp_diag = cov[:, pc[:, :, None], pc[:, None, :]]  # cov(p_s): (P, s, 2, 2)
    e_mean = p_hat - x_pred[:, None, :2]  # (P, s, 2)
    e_cov = cpp_diag + px - cpx - cxp  # (P, s, 2, 2)
    excess = config.sigma_topology**2 / np.maximum(counts, 1)  # (P, s)
    reach = _PENALTY_PRUNE_SD * np.sqrt(np.maximum(_max_eig2(e_cov), 0.0)) + config.penalty_radius  # (P, s)
    proxy_rev = np.zeros((n_part, cap))
    proxy_new = np.zeros(n_part)
    used = counts > 0
    # new place: x_n as predicted
    near = used & worth_new[:, None] & (np.hypot(e_mean[..., 0], e_mean[..., 1]) < reach)
    pi, si = np.nonzero(near)
    if len(pi):
        c = e_cov[pi, si].copy()
        c[:, 0, 0] -= excess[pi, si]
        c[:, 1, 1] -= excess[pi, si]
        np.add.at(proxy_new, pi, -_log_expectation(e_mean[pi, si], c, counts[pi, si], config))
    # revisits: x_n moved by the coincidence with p_k (its updated mean, p_s at its prior mean, to select)
    y = np.linalg.solve(S, d[..., None])[..., 0]  # S^{-1} d: (P, k, 2)
    x_upd = x_pred[:, None, :2] - np.einsum("pkab,pkb->pka", px[:, 0][:, None] - cxt, y)  # (P, k, 2)
    gap = p_hat[:, None, :, :] - x_upd[:, :, None, :]  # (P, k, s, 2)
    near = (
        used[:, None, :]
        & worth_rev[:, :, None]
        & (ar[:, None] != ar[None, :])[None]
        & (np.hypot(gap[..., 0], gap[..., 1]) < reach[:, None, :])
    )
    pi, ki, si = np.nonzero(near)
    if len(pi):
        cpt_sk = cov[pi[:, None, None], pc[si][:, :, None], pc[ki][:, None, :]]  # cov(q_s, t_k): (Q, 2, 2)
        if lever is not None:
            c_sd = cov[pi[:, None], pc[si], lever.cols[ki][:, None]]  # cov(q_s, δ_k): (Q, 2)
            cpt_sk += c_sd[:, :, None] * lever.g[pi, ki][:, None, :]
        C = cpx[pi, si] - cpt_sk - px[pi, 0] + cxt[pi, ki]  # cov(e_s, h_k)
        gain = np.linalg.solve(S[pi, ki], C.swapaxes(-1, -2)).swapaxes(-1, -2)  # C S^{-1}
        m = e_mean[pi, si] - np.einsum("qab,qb->qa", gain, d[pi, ki])
        c = e_cov[pi, si] - gain @ C.swapaxes(-1, -2)
        c = 0.5 * (c + c.swapaxes(-1, -2))
        c[:, 0, 0] -= excess[pi, si]
        c[:, 1, 1] -= excess[pi, si]
        close = np.hypot(m[:, 0], m[:, 1]) - config.penalty_radius < _PENALTY_PRUNE_SD * np.sqrt(
            np.maximum(_max_eig2(c), 0.0)
        )  # pruned again with the updated moments
        pi, ki, si = pi[close], ki[close], si[close]
        log_e = _log_expectation(m[close], c[close], counts[pi, si], config)
        np.add.at(proxy_rev, (pi, ki), -log_e)
    return proxy_rev, proxy_new


def _delta_moments(
    mean: FloatArray, cov: FloatArray, pc: IntArray, excess: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Mean ``(C, cap, 2)`` and covariance ``(C, cap, 2, 2)`` of ``δ_s = x̄_s - x_n^{xy}`` for every place."""
    m = mean[:, pc] - mean[:, None, :2]
    cxp = cov[:, :2][:, :, pc].transpose(0, 2, 1, 3)  # cov(x_n, p_s): (C, cap, 2, 2)
    cpp = cov[:, pc[:, :, None], pc[:, None, :]]
    S = cpp + cov[:, None, :2, :2] - cxp - cxp.swapaxes(-1, -2)
    S = 0.5 * (S + S.swapaxes(-1, -2))
    S[..., 0, 0] -= excess
    S[..., 1, 1] -= excess
    return m, S


def _max_eig2(S: FloatArray) -> FloatArray:
    """Largest eigenvalue of symmetric ``(..., 2, 2)`` matrices."""
    half_tr = 0.5 * (S[..., 0, 0] + S[..., 1, 1])
    gap = np.sqrt(np.maximum(0.25 * np.square(S[..., 0, 0] - S[..., 1, 1]) + np.square(S[..., 0, 1]), 0.0))
    return half_tr + gap


def _chol2(S: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Lower Cholesky factor ``[[a, 0], [b, d]]`` of symmetric positive-definite ``(..., 2, 2)``."""
    a = np.sqrt(S[..., 0, 0])
    b = S[..., 1, 0] / a
    d = np.sqrt(S[..., 1, 1] - b * b)
    return a, b, d


def _solve_chol2(a: FloatArray, b: FloatArray, d: FloatArray, v: FloatArray) -> FloatArray:
    """``L^{-1} v`` for the factors of :func:`_chol2`; ``v`` ``(..., 2, K)``."""
    y0 = v[..., 0, :] / a[..., None]
    y1 = (v[..., 1, :] - b[..., None] * y0) / d[..., None]
    return np.stack([y0, y1], axis=-2)


class TopologyFilter:
    """The Rao-Blackwellized particle filter over topologies (see the module docstring).

    Args:
        config: number of particles and resampling scheme.
        prior: the prior over topologies (its sequential ``log_predictive`` is used, eq. 39, 42).
        odometry: the metric model's parameters (the sequential weights use its Gaussian part; the batch
            reweighting, :mod:`ptm_ros.inference.reweighting`, all of it, importance sampling included).
        appearance: a fitted appearance model, or None to ignore appearance (eq. 46).
        registrar: laser measurements between visits ``(i, j)``, ``i < j``, cached per pair; None: no laser.
        seed: seeds ``np.random.default_rng`` for resampling, and the batch evidence's importance samples
            (as :class:`~ptm_ros.model.posterior.PosteriorModel`'s).
        prefetch: told, before a visit's registrations are asked for one by one, the pairs not asked for
            before (e.g. to register them in parallel and cache them behind ``registrar``).
    """

    def __init__(
        self,
        config: RbpfConfig,
        prior: TopologyPrior,
        odometry: OdometryConfig,
        *,
        appearance: AppearanceModel | None = None,
        registrar: Registrar | None = None,
        seed: int = 0,
        prefetch: Prefetch | None = None,
    ) -> None:
        if not isinstance(config, RbpfConfig):
            msg = f"config must be an RbpfConfig, got {type(config).__name__}"
            raise ConfigError(msg)
        if not isinstance(odometry, OdometryConfig):
            msg = f"odometry must be an OdometryConfig, got {type(odometry).__name__}"
            raise ConfigError(msg)
        self.config = config
        self.prior = prior
        self.odometry = odometry
        self.appearance = appearance
        self.registrar = registrar
        self.prefetch = prefetch
        self._layout = _Layout(offset=odometry.sigma_offset > 0.0, laser=registrar is not None)
        self._stride = self._layout.stride
        self._seed = int(seed)
        self._rng = np.random.default_rng(seed)
        self._visits: list[Visit] = []
        self._pairs: dict[tuple[int, int], RelativePose | NoMatch | None] = {}
        self._particles: _Particles | None = None
        self._history: list[FilterState] = []
        self._log_evidence = 0.0
        self._index: dict[Labels, int] | None = None
        self._reweighted: Reweighted | None = None
        #: Why the PTM after the latest visit kept its sequential weights though ``config.reweight``
        #: (the batch model failed on the visits), else None.
        self.reweight_failure: str | None = None

    # ----------------------------------------------------------------------------------- public API

    @property
    def visits(self) -> tuple[Visit, ...]:
        """The visits processed so far, in order."""
        return tuple(self._visits)

    @property
    def history(self) -> tuple[FilterState, ...]:
        """The :class:`FilterState` of every update so far."""
        return tuple(self._history)

    @property
    def log_evidence(self) -> float:
        """Estimate of ``log p(z^n)``: the sum of the per-step increments."""
        return self._log_evidence

    @property
    def n_topologies(self) -> int:
        """Number of distinct topologies (particles) held."""
        return 0 if self._particles is None else len(self._particles.labels)

    def ptm_weights(self) -> dict[Labels, float]:
        """The PTM: normalised weight of every topology held (empty before the first visit), reweighted
        with the batch metric evidence when ``config.reweight`` (:meth:`reweighted`)."""
        if self._particles is None:
            return {}
        w = np.exp(self._log_w())
        return dict(zip(self._particles.labels, w.tolist(), strict=True))

    def log_weights(self) -> dict[Labels, float]:
        """Normalised log weights of the topologies held (those of :meth:`ptm_weights`)."""
        if self._particles is None:
            return {}
        return dict(zip(self._particles.labels, self._log_w().tolist(), strict=True))

    def sequential_weights(self) -> dict[Labels, float]:
        """The particles' own weights, the EKF's sequential evidence (what resampling uses)."""
        if self._particles is None:
            return {}
        return dict(zip(self._particles.labels, np.exp(self._particles.log_w).tolist(), strict=True))

    def reweighted(self) -> Reweighted | None:
        """The particle set weighed with the batch metric evidence (:mod:`ptm_ros.inference.reweighting`),
        computed once per visit; None when ``config.reweight`` is off, before a second visit, or where the
        batch evidence is not an importance-sampling integral (``odometry.n_samples`` 0, or more than
        ``odometry.max_sampled_visits`` visits: see the module), or where the batch model fails on these
        visits (the sequential weights are kept; :attr:`reweight_failure` says why)."""
        st = self._particles
        if not self.config.reweight or st is None or not sampled_evidence(len(self._visits), self.odometry):
            return None
        if self.reweight_failure is not None:
            return None
        if self._reweighted is None:
            start = time.perf_counter()
            model = PosteriorModel(
                self._visits,
                ModelConfig(
                    odometry=self.odometry,
                    use_appearance=False,
                    use_laser=self.registrar is not None,
                ),
                registrar=self._cached_registration if self.registrar is not None else None,
                seed=self._seed,
            )
            try:
                done = reweigh(st.log_w, st.labels, st.metric, lambda labels: model.terms(labels).metric)
            except PtmError as err:  # the batch model's or a registrar's: the PTM keeps its own weights
                self.reweight_failure = f"visit {len(self._visits) - 1}: {err}"
                return None
            self._reweighted = replace(done, seconds=time.perf_counter() - start)
        return self._reweighted

    def _log_w(self) -> FloatArray:
        assert self._particles is not None
        rw = self.reweighted()
        return self._particles.log_w if rw is None else rw.log_w

    def _cached_registration(self, i: int, j: int) -> RelativePose | NoMatch | None:
        return self._registration(i, j, self._pairs)

    def place_positions(self, labels: Sequence[int]) -> FloatArray:
        """``(M, 2)`` posterior means of the place points ``p_s`` of a topology held by the filter."""
        i = self._lookup(labels)
        st = self._particles
        assert st is not None
        m = int(st.n_places[i])
        cols = _place_cols(self._stride, np.arange(m), 0, 2)
        return st.mean[i, cols].copy()

    def place_covariances(self, labels: Sequence[int]) -> FloatArray:
        """``(M, 2, 2)`` posterior covariances of the place points of a topology held by the filter."""
        i = self._lookup(labels)
        st = self._particles
        assert st is not None
        cols = _place_cols(self._stride, np.arange(int(st.n_places[i])), 0, 2)
        return st.cov[i][cols[:, :, None], cols[:, None, :]].copy()

    def pose(self, labels: Sequence[int]) -> tuple[FloatArray, FloatArray]:
        """Mean ``(3,)`` and covariance ``(3, 3)`` of the current visit's pose under a topology held."""
        i = self._lookup(labels)
        st = self._particles
        assert st is not None
        return st.mean[i, :3].copy(), st.cov[i, :3, :3].copy()

    def covariances(self) -> FloatArray:
        """The state covariances of all particles, ``(P, D, D)`` (padded slots are zero); a copy."""
        if self._particles is None:
            return np.zeros((0, 0, 0))
        return self._particles.cov.copy()

    def to_ptm(self, *, top: int | None = None, **kwargs: Any) -> Ptm:
        """The current PTM as a :class:`~ptm_ros.model.ptm.Ptm` (place positions included)."""
        weights = self.ptm_weights()
        landmarks = [Landmark.from_visit(v) for v in self._visits]
        positions = {lab: self.place_positions(lab).tolist() for lab in weights}
        return make_ptm(landmarks, weights, top=top, positions=positions, **kwargs)

    def update(self, visit: Visit) -> FilterState:
        """Process the next visit (``visit.index`` must equal the number of visits so far).

        Raises:
            ModelError: a visit out of order or with non-finite pose/travel/rotation, a measurement the
                models cannot use, a malformed registration. The filter is unchanged and can continue.
        """
        start = time.perf_counter()
        n = len(self._visits)
        _check_visit(visit, n)
        visits_now = (*self._visits, visit)
        pairs = dict(self._pairs)
        rng_state = self._rng.bit_generator.state
        try:
            if self._particles is None:
                new, increment = self._first(visits_now)
            else:
                new, increment = self._step(visits_now, pairs)
        except BaseException:
            self._rng.bit_generator.state = rng_state  # a failed update leaves no trace, not even in the RNG
            raise
        # commit: nothing above modified the filter
        self._particles = new
        self._pairs = pairs
        self._visits.append(visit)
        self._index = None
        self._reweighted = None
        self.reweight_failure = None
        self._log_evidence += increment
        w = np.exp(new.log_w)
        update_s = time.perf_counter() - start
        k = self.config.record_top
        order = np.argsort(-new.log_w, kind="stable")[:k] if k else np.zeros(0, dtype=np.intp)
        state = FilterState(
            n_visits=n + 1,
            n_topologies=len(new.labels),
            ess=float(1.0 / np.sum(w * w)),
            log_evidence_increment=float(increment),
            update_s=update_s,
            top=tuple((new.labels[i], float(w[i])) for i in order.tolist()),
        )
        self._history.append(state)
        return state

    # -------------------------------------------------------------------------------- the filter step

    def _first(self, visits: tuple[Visit, ...]) -> tuple[_Particles, float]:
        """Visit 0: one topology ``(0,)``; ``x_0 := u_0`` exactly (the batch model's gauge)."""
        u0 = np.asarray(visits[0].pose, dtype=float)
        cap = _INITIAL_CAPACITY
        dim = 3 + self._stride * cap
        mean = np.zeros((1, dim))
        cov = np.zeros((1, dim, dim))
        mean[0, :3] = u0
        mean[0, 3:5] = u0[:2]
        cov[0, 3:5, 3:5] = self.odometry.sigma_topology**2 * np.eye(2)
        lay = self._layout
        if lay.offset:
            cov[0, 3 + lay.delta, 3 + lay.delta] = self.odometry.sigma_offset**2
        if lay.laser:
            mean[0, 3 + lay.x_last : 6 + lay.x_last] = u0
        headings = np.zeros((1, cap, 2))
        headings[0, 0] = _unit(u0[2])
        counts = np.zeros((1, cap), dtype=np.intp)
        last = np.full((1, cap), -1, dtype=np.intp)
        counts[0, 0], last[0, 0] = 1, 0
        first = float(place_log_priors(visits[:1], self.odometry)[0])
        increment = float(self.prior.log_predictive([])[0]) + first
        if self.appearance is not None:
            increment += appearance_log_predictive(0, (), visits, self.appearance)
        if not math.isfinite(increment):
            msg = "the first visit has zero probability under the prior or appearance model"
            raise ModelError(msg)
        particles = _Particles(
            labels=((0,),),
            log_w=np.zeros(1),
            mean=mean,
            cov=cov,
            counts=counts,
            last=last,
            n_places=np.ones(1, dtype=np.intp),
            blocks=(((0,),),) if self.appearance is not None else None,
            penalty=np.zeros(1),
            metric=np.array([first]),
            headings=headings,
        )
        return particles, increment

    def _step(
        self, visits: tuple[Visit, ...], pairs: dict[tuple[int, int], RelativePose | NoMatch | None]
    ) -> tuple[_Particles, float]:
        st = self._particles
        assert st is not None
        n = len(visits) - 1
        stride = self._stride
        cfg = self.odometry
        sig2 = cfg.sigma_topology**2
        n_part, dim = st.mean.shape
        cap = (dim - 3) // stride

        # 1. predict x_n = x_{n-1} ⊕ o (virtually: the parents' arrays are not modified)
        o = between(np.asarray(visits[n - 1].pose, float), np.asarray(visits[n].pose, float))
        sigma = odometry_covariances(visits[n - 1 :], cfg)[0]
        th = st.mean[:, 2]
        c, s = np.cos(th), np.sin(th)
        F = np.zeros((n_part, 3, 3))  # ∂x_n/∂x_{n-1}
        F[:, 0, 0] = F[:, 1, 1] = F[:, 2, 2] = 1.0
        F[:, 0, 2] = -s * o[0] - c * o[1]
        F[:, 1, 2] = c * o[0] - s * o[1]
        G = np.zeros((n_part, 3, 3))  # ∂x_n/∂w = diag(R(θ), 1)
        G[:, 0, 0], G[:, 0, 1], G[:, 1, 0], G[:, 1, 1], G[:, 2, 2] = c, -s, s, c, 1.0
        x_pred = compose(st.mean[:, :3], o)
        B = F @ st.cov[:, :3, :]  # predicted rows of x: (P, 3, D)
        pxx = B[:, :, :3] @ F.transpose(0, 2, 1) + G @ sigma @ G.transpose(0, 2, 1)
        pxx = 0.5 * (pxx + pxx.transpose(0, 2, 1))
        B[:, :, :3] = pxx

        # 2. score every child: revisits (P, cap) and a new place (P,)
        pcols = _place_cols(stride, np.arange(cap), 0, 2)  # (cap, 2)
        p_hat = st.mean[:, pcols]  # (P, cap, 2)
        cxp = B[:, :2][:, :, pcols].transpose(0, 2, 1, 3)  # cov(x^xy, p_k): (P, cap, 2, 2)
        cpp = st.cov[:, pcols[:, :, None], pcols[:, None, :]]
        # the revisit's target t_k = q_k + δ_k g_k (the visit offset, g_k = h_n - h̄_k): mean, cov(x^xy, t_k)
        lay = self._layout
        h_n = _unit(float(visits[n].pose[2]))
        lever: _Lever | None = None
        t_hat, cxt, ctt = p_hat, cxp, cpp
        if lay.offset:
            lever = _Lever(
                cols=_place_cols(stride, np.arange(cap), lay.delta, 1)[:, 0],
                g=h_n - st.headings / np.maximum(st.counts, 1)[..., None],
            )
            dcol, g = lever.cols, lever.g
            cxd = B[:, :2][:, :, dcol].transpose(0, 2, 1)  # cov(x^xy, δ_k): (P, cap, 2)
            cqd = st.cov[:, pcols, dcol[:, None]]  # cov(q_k, δ_k): (P, cap, 2)
            gg = g[..., :, None] * g[..., None, :]
            t_hat = p_hat + st.mean[:, dcol][..., None] * g
            cxt = cxp + cxd[..., :, None] * g[..., None, :]
            cqd_g = cqd[..., :, None] * g[..., None, :]
            ctt = cpp + cqd_g + cqd_g.swapaxes(-1, -2) + st.cov[:, dcol, dcol][..., None, None] * gg
        S = pxx[:, None, :2, :2] - cxt - cxt.swapaxes(-1, -2) + ctt
        S = 0.5 * (S + S.swapaxes(-1, -2)) + sig2 * np.eye(2)
        d = x_pred[:, None, :2] - t_hat
        a_, b_, d_ = _chol2(S)
        y = _solve_chol2(a_, b_, d_, d[..., None])[..., 0]  # L^{-1} d
        ll_rev = -_LOG_2PI - np.log(a_ * d_) - 0.5 * np.sum(y * y, axis=-1)
        valid = np.arange(cap)[None, :] < st.n_places[:, None]
        # the places' prior densities move with the visits (a learned area A grows, the steps' density is
        # fitted again): every particle's weight moves exactly, by the change of its new places' log
        # densities (eq. 17's 1/A per place: (A_old / A_new)^{places}), before the new visit is scored
        prior_old, prior_now = place_log_priors(visits[:-1], cfg), place_log_priors(visits, cfg)
        moved = prior_now[:-1] - prior_old
        same = bool(np.all(moved == moved[0]))  # one density for every place (the area's): by the counts
        prior_shift = st.n_places * moved[0] if same else new_places(st.labels) @ moved
        log_w = st.log_w + prior_shift
        ll_new = np.full(n_part, prior_now[-1])
        coincidence_rev, coincidence_new = ll_rev.copy(), ll_new.copy()  # before the selection proxy
        proxy_rev = np.zeros((n_part, cap))  # separation penalty of the new pairs (i, n), for selection
        proxy_new = np.zeros(n_part)
        lp_rev, lp_new = self._discrete_terms(st, visits)
        if cfg.penalty_max > 0.0:
            # children that selection can keep (the others' proxy would not matter: the weight is corrected)
            base_rev = np.where(valid, log_w[:, None] + lp_rev + ll_rev, -np.inf)
            base_new = log_w + lp_new + ll_new
            top = max(float(np.max(base_rev)), float(np.max(base_new)))
            proxy_rev, proxy_new = _separation_proxy(
                st.cov,
                p_hat,
                st.counts,
                x_pred,
                pxx,
                cxp,
                cxt,
                lever,
                S,
                d,
                stride,
                cfg,
                worth_rev=base_rev > top - _PROXY_NATS,
                worth_new=base_new > top - _PROXY_NATS,
            )
            ll_rev -= proxy_rev
            ll_new -= proxy_new
        lw_rev = np.where(valid, log_w[:, None] + lp_rev + ll_rev, -np.inf)
        lw_new = log_w + lp_new + ll_new
        par_rev, k_rev = np.nonzero(valid)
        cand_par = np.concatenate([par_rev, np.arange(n_part)])
        cand_k = np.concatenate([k_rev, st.n_places])
        cand_lw = np.concatenate([lw_rev[par_rev, k_rev], lw_new])
        cand_proxy = np.concatenate([proxy_rev[par_rev, k_rev], proxy_new])
        if np.any(np.isnan(cand_lw)) or not np.any(np.isfinite(cand_lw)):
            msg = f"visit {n}: every topology has zero (or undefined) weight"
            raise ModelError(msg)
        lse_children = float(logsumexp(cand_lw))

        # 3. select distinct children
        if self.config.resample == "optimal":
            rc = self.config
            keep = particle_count(cand_lw, rc.particles, rc.particles_max, rc.thinned_mass)
            sel, sel_lw = optimal_resample(cand_lw, keep, self._rng)
        else:
            sel, sel_lw = top_resample(cand_lw, self.config.particles)
        par, kk, proxy = cand_par[sel], cand_k[sel], cand_proxy[sel]
        is_new = kk == st.n_places[par]

        # registrations of the selected revisits, pair (last(k), n)
        # (and the fitness evidence of every registered pair, valid match or not)
        z_of: dict[int, RelativePose] = {}
        fitness = np.zeros(len(sel))
        if self.registrar is not None:
            if self.prefetch is not None:
                wanted = dict.fromkeys(
                    (int(st.last[p, k]), n) for p, k in zip(par[~is_new], kk[~is_new], strict=True)
                )
                self.prefetch([key for key in wanted if key not in pairs])
            for r in np.flatnonzero(~is_new):
                i = int(st.last[par[r], kk[r]])
                z = self._registration(i, n, pairs)
                if z is not None:
                    fitness[r] = z.log_bayes
                if isinstance(z, RelativePose):
                    z_of[int(r)] = z
        with_z = np.array(sorted(z_of), dtype=np.intp)
        no_z = np.flatnonzero(~is_new & ~np.isin(np.arange(len(sel)), with_z))
        order = np.concatenate([with_z, no_z, np.flatnonzero(is_new)])
        par, kk, is_new, sel_lw, proxy = par[order], kk[order], is_new[order], sel_lw[order], proxy[order]
        fitness = fitness[order]
        n_z, n_rev, n_child = len(with_z), len(with_z) + len(no_z), len(order)

        # 4. build and update the children's states
        need = int(np.max(st.n_places[par] + is_new))
        new_cap = cap if need <= cap else need + _SLACK  # capacity only grows (places are never removed)
        new_dim = 3 + stride * new_cap
        mean = np.zeros((n_child, new_dim))
        mean[:, :dim] = st.mean[par]
        if new_cap == cap:
            cov = st.cov[par]
        else:
            cov = np.zeros((n_child, new_dim, new_dim))
            cov[:, :dim, :dim] = st.cov[par]
        mean[:, :3] = x_pred[par]
        Bp = B[par]
        cov[:, :3, :dim] = Bp
        cov[:, :dim, :3] = Bp.transpose(0, 2, 1)

        # revisits: the coincidence x^xy - q_k - δ_k g_k = 0 with noise σ_T² I
        rv = slice(0, n_rev)
        pk = _place_cols(stride, kk[rv], 0, 2)  # (R, 2)
        rows = np.arange(n_rev)[:, None]
        hp = cov[rv, 0:2, :] - cov[rows, pk, :]  # H P: (R, 2, D)
        innov = mean[rv, 0:2] - mean[rows, pk]  # predicted x^xy - t_k
        if lever is not None:
            dk = lever.cols[kk[rv]]  # (R,)
            g_r = lever.g[par[rv], kk[rv]]  # (R, 2)
            hp -= g_r[:, :, None] * cov[rows[:, 0], dk, :][:, None, :]
            innov -= mean[rows[:, 0], dk][:, None] * g_r
        s_c = hp[:, :, 0:2] - np.take_along_axis(hp, pk[:, None, :], axis=2)  # H P Hᵀ
        if lever is not None:
            s_c -= hp[rows[:, 0], :, dk][:, :, None] * g_r[:, None, :]
        s_c = 0.5 * (s_c + s_c.swapaxes(-1, -2)) + sig2 * np.eye(2)
        a_, b_, d_ = _chol2(s_c)
        W = _solve_chol2(a_, b_, d_, hp)  # L^{-1} H P
        v = _solve_chol2(a_, b_, d_, innov[:, :, None])[..., 0]
        mean[rv] -= np.einsum("rki,rk->ri", W, v)

        # laser factors of the revisits with a registration, z = x_last(k) ⊖ x_n + noise, on the state
        # after the coincidence; both low-rank downdates of the covariance are then applied in one pass
        laser_ll = np.zeros(n_child)
        if n_z:
            lc = _place_cols(stride, kk[:n_z], lay.x_last, 3)  # (Z, 3) columns of x_last(k)
            sub = np.concatenate([lc, np.broadcast_to(np.arange(3), (n_z, 3))], axis=1)  # x_last(k), x_n
            w1 = W[:n_z]
            rows6 = cov[np.arange(n_z)[:, None], sub, :]
            rows6 -= np.take_along_axis(w1, sub[:, None, :], axis=2).transpose(0, 2, 1) @ w1  # rows of P'
            zs = [z_of[int(r)] for r in with_z]
            w2, v2, laser_ll[:n_z] = _laser_factor(mean[:n_z], rows6, lc, zs)
            laser_ll[:n_z] += math.log(cfg.registration_volume)  # ratio against "not one place": 1/V_reg
            eps = cfg.registration_outlier
            if eps > 0.0:  # a valid match may be an alias (uniform over V_reg): mixture predictive, and
                # the state keeps the posterior's dominant component (no update from an alias); one whose
                # heading the odometry alone rules out is an alias in every topology (heading_aliases)
                match = math.log1p(-eps) + laser_ll[:n_z]
                on_heading = heading_aliases(visits, zs, cfg)
                alias = (match < math.log(eps)) | on_heading
                laser_ll[:n_z] = np.where(on_heading, math.log(eps), np.logaddexp(match, math.log(eps)))
                w2[alias] = 0.0
                v2[alias] = 0.0
            mean[:n_z] += np.einsum("zki,zk->zi", w2, v2)
            _downdate(cov[:n_z], np.concatenate([w1, w2], axis=1))
        _downdate(cov[n_z:n_rev], W[n_z:])
        if lever is not None:  # the revisited place's mean heading h̄_k moves by g_k / (|k| + 1): so does q_k
            _shear(mean[rv], cov[rv], pk, dk, g_r / (st.counts[par[rv], kk[rv]] + 1.0)[:, None])

        # x_last(k) := x_n for revisits; q_M (and δ_M) and x_last(M) for new places
        if n_child > n_rev:
            nw = slice(n_rev, n_child)
            _duplicate(mean[nw], cov[nw], np.arange(2), _place_cols(stride, kk[nw], 0, 2))
            cols = _place_cols(stride, kk[nw], 0, 2)
            new_rows = np.arange(n_child - n_rev)[:, None] + n_rev
            cov[new_rows, cols, cols] += sig2
            if lay.offset:
                dcols = _place_cols(stride, kk[nw], lay.delta, 1)
                cov[new_rows, dcols, dcols] = cfg.sigma_offset**2
        if lay.laser:
            _duplicate(mean, cov, np.arange(3), _place_cols(stride, kk, lay.x_last, 3))
            angles = 3 + stride * np.arange(new_cap) + lay.x_last + 2
            mean[:, angles] = wrap_angle(mean[:, angles])
        mean[:, 2] = wrap_angle(mean[:, 2])

        # bookkeeping, the separation prior of the new pairs (i, n), and the weights
        counts = np.zeros((n_child, new_cap), dtype=np.intp)
        last = np.full((n_child, new_cap), -1, dtype=np.intp)
        counts[:, :cap] = st.counts[par]
        last[:, :cap] = st.last[par]
        ar = np.arange(n_child)
        counts[ar, kk] += 1
        last[ar, kk] = n
        headings = np.zeros((n_child, new_cap, 2))
        headings[:, :cap] = st.headings[par]
        headings[ar, kk] += h_n
        log_sep = _separation_update(mean, cov, st.counts[par], kk, stride=stride, config=cfg)
        if lay.laser:
            mean[:, angles] = wrap_angle(mean[:, angles])
        mean[:, 2] = wrap_angle(mean[:, 2])
        penalty = st.penalty[par] - log_sep
        lw = sel_lw + laser_ll + fitness + proxy + log_sep  # the proxy (selection only) was in sel_lw
        coincidence = np.where(is_new, coincidence_new[par], coincidence_rev[par, np.minimum(kk, cap - 1)])
        metric = st.metric[par] + prior_shift[par] + coincidence + laser_ll + fitness + log_sep
        lse = float(logsumexp(lw))
        increment = lse_children + lse
        labels = tuple(st.labels[p] + (int(k),) for p, k in zip(par.tolist(), kk.tolist(), strict=True))
        blocks = None
        if st.blocks is not None:
            blocks = tuple(
                _extend_blocks(st.blocks[p], int(k), n)
                for p, k in zip(par.tolist(), kk.tolist(), strict=True)
            )
        particles = _Particles(
            labels=labels,
            log_w=lw - lse,
            mean=mean,
            cov=cov,
            counts=counts,
            last=last,
            n_places=st.n_places[par] + is_new,
            blocks=blocks,
            penalty=penalty,
            metric=metric,
            headings=headings,
        )
        return particles, increment

    def _discrete_terms(self, st: _Particles, visits: tuple[Visit, ...]) -> tuple[FloatArray, FloatArray]:
        """Prior (eq. 39) plus appearance (eq. 46) predictives of every child: ``(P, cap)`` and ``(P,)``."""
        lp_rev, lp_new = batch_log_predictive(self.prior, st.counts, st.n_places)
        model = self.appearance
        if model is None or st.blocks is None:
            return lp_rev, lp_new
        n = len(visits) - 1
        lp_new += appearance_log_predictive(n, (), visits, model)  # also validates visit n's measurements
        distinct = list(
            dict.fromkeys(b for places in st.blocks for b in places)
        )  # blocks recur across particles
        value = dict(zip(distinct, block_log_predictives(n, distinct, visits, model).tolist(), strict=True))
        for i, places in enumerate(st.blocks):
            lp_rev[i, : len(places)] += [value[b] for b in places]
        return lp_rev, lp_new

    def _registration(
        self, i: int, j: int, pairs: dict[tuple[int, int], RelativePose | NoMatch | None]
    ) -> RelativePose | NoMatch | None:
        """The registrar's measurement of pair ``(i, j)``, cached in ``pairs`` and validated."""
        key = (i, j)
        if key in pairs:
            return pairs[key]
        assert self.registrar is not None
        z = self.registrar(i, j)
        if z is not None:
            z = _check_registration(z, i, j)
        pairs[key] = z
        return z

    def _lookup(self, labels: Sequence[int]) -> int:
        if self._particles is None:
            msg = "the filter holds no topology yet"
            raise ModelError(msg)
        if self._index is None:
            self._index = {lab: i for i, lab in enumerate(self._particles.labels)}
        key = tuple(int(v) for v in labels)
        if key not in self._index:
            msg = f"topology {key} is not held by the filter"
            raise ModelError(msg)
        return self._index[key]

    # ---------------------------------------------------------------------------------- persistence

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the filter, as plain numbers, lists and numpy arrays."""
        st = self._particles
        out: dict[str, Any] = {
            "schema": STATE_SCHEMA,
            "stride": self._stride,
            "config": {f.name: getattr(self.config, f.name) for f in fields(self.config)},
            "rng": self._rng.bit_generator.state,
            "log_evidence": self._log_evidence,
            "visits": [visit_dict(v) for v in self._visits],
            "registrations": [registration_row(i, j, z) for (i, j), z in self._pairs.items()],
            "history": [[getattr(h, f.name) for f in fields(FilterState)] for h in self._history],
        }
        if st is not None:
            out.update(
                labels=[list(lab) for lab in st.labels],
                log_weights=st.log_w.copy(),
                mean=st.mean.copy(),
                cov=st.cov.copy(),
                counts=st.counts.copy(),
                last=st.last.copy(),
                n_places=st.n_places.copy(),
                penalty=st.penalty.copy(),
                metric=st.metric.copy(),
                headings=st.headings.copy(),
            )
        return out

    @classmethod
    def from_state_dict(
        cls,
        state: dict[str, Any],
        config: RbpfConfig,
        prior: TopologyPrior,
        odometry: OdometryConfig,
        *,
        appearance: AppearanceModel | None = None,
        registrar: Registrar | None = None,
        prefetch: Prefetch | None = None,
    ) -> TopologyFilter:
        """A filter restored from :meth:`state_dict`, continuing exactly where it stopped.

        Raises:
            ModelError: a state of another schema, or a registrar given/missing unlike when it was saved.
        """
        if state.get("schema") != STATE_SCHEMA:
            msg = f"not an RBPF state ({STATE_SCHEMA}), got schema {state.get('schema')!r}"
            raise ModelError(msg)
        flt = cls(config, prior, odometry, appearance=appearance, registrar=registrar, prefetch=prefetch)
        if int(state["stride"]) != flt._stride:
            msg = (
                "the filter state was saved with a different laser setting (registrar given or not) or visit"
                " offset (odometry.sigma_offset zero or not)"
            )
            raise ModelError(msg)
        flt._rng.bit_generator.state = state["rng"]
        flt._log_evidence = float(state["log_evidence"])
        flt._visits = [visit_from_dict(d) for d in state["visits"]]
        for row in state["registrations"]:
            flt._pairs[(int(row[0]), int(row[1]))] = registration_from_row(row)
        flt._history = [FilterState(*row) for row in state["history"]]
        if "labels" in state:
            labels = tuple(tuple(int(v) for v in lab) for lab in state["labels"])
            blocks = None
            if appearance is not None:
                blocks = tuple(_blocks_of(lab) for lab in labels)
            flt._particles = _Particles(
                labels=labels,
                log_w=np.asarray(state["log_weights"], dtype=float).copy(),
                mean=np.asarray(state["mean"], dtype=float).copy(),
                cov=np.asarray(state["cov"], dtype=float).copy(),
                counts=np.asarray(state["counts"], dtype=np.intp).copy(),
                last=np.asarray(state["last"], dtype=np.intp).copy(),
                n_places=np.asarray(state["n_places"], dtype=np.intp).copy(),
                blocks=blocks,
                penalty=np.asarray(state["penalty"], dtype=float).copy(),
                metric=np.asarray(state["metric"], dtype=float).copy(),
                headings=np.asarray(state["headings"], dtype=float).copy(),
            )
            if len(flt._visits) != len(labels[0]):
                msg = f"state holds {len(flt._visits)} visits but topologies of {len(labels[0])}"
                raise ModelError(msg)
        return flt


# ------------------------------------------------------------------------------------------- helpers


def _between_jacobians(xa: FloatArray, xb: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``h = x_a ⊖ x_b`` ``(Z, 3)`` and its Jacobians ``∂h/∂x_a``, ``∂h/∂x_b`` ``(Z, 3, 3)``.

    With ``t = R(θ_a)ᵀ(t_b - t_a)``: ``∂t/∂t_a = -R(θ_a)ᵀ``, ``∂t/∂θ_a = (t_y, -t_x)``, ``∂t/∂t_b = R(θ_a)ᵀ``.
    """
    h = between(xa, xb)
    c, s = np.cos(xa[:, 2]), np.sin(xa[:, 2])
    ja = np.zeros((len(h), 3, 3))
    ja[:, 0, 0], ja[:, 0, 1], ja[:, 0, 2] = -c, -s, h[:, 1]
    ja[:, 1, 0], ja[:, 1, 1], ja[:, 1, 2] = s, -c, -h[:, 0]
    ja[:, 2, 2] = -1.0
    jb = np.zeros((len(h), 3, 3))
    jb[:, 0, 0], jb[:, 0, 1] = c, s
    jb[:, 1, 0], jb[:, 1, 1] = -s, c
    jb[:, 2, 2] = 1.0
    return h, ja, jb


#: Gauss–Newton (iterated EKF) iterations of the laser update, and their convergence threshold [m, rad].
_LASER_ITERATIONS = 10
_LASER_TOLERANCE = 1e-9


def _laser_factor(
    mean: FloatArray, rows: FloatArray, lc: IntArray, meas: list[RelativePose]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Iterated-EKF terms of laser measurements ``z = x_last(k) ⊖ x_n + v``, ``v ~ N(0, R)`` (eq. 49).

    ``mean`` ``(Z, D)``; ``rows`` ``(Z, 6, D)``: the covariance rows of ``x_last(k)`` (columns ``lc``
    ``(Z, 3)``) and of ``x_n``. The measurement involves those 6 variables only, so Gauss–Newton finds
    the mode ``y*`` of ``N(z; h(y), R) N(y; μ_y, P_yy)`` in 6-D, and ``h`` is linearised there
    (``h(y) ≈ h(y*) + H (y - y*)``): the Laplace estimate of the predictive, as the batch model's
    (App. B), rather than a linearisation at the prior mean. Returns ``W = L^{-1} H P`` ``(Z, 3, D)``,
    ``L^{-1} e`` ``(Z, 3)`` (``S = H P Hᵀ + R = L Lᵀ``, ``e = z ⊟ (h(y*) + H(μ_y - y*))``) and the log
    predictives ``log N(e; 0, S)`` ``(Z,)``; the update is ``μ += Wᵀ L^{-1} e``, ``P -= Wᵀ W``.
    """
    nz = len(meas)
    z = np.stack([m.mean for m in meas])
    R = np.stack([m.cov for m in meas])
    sub = np.concatenate([lc, np.broadcast_to(np.arange(3), (nz, 3))], axis=1)
    mu = np.take_along_axis(mean, sub, axis=1)  # (Z, 6)
    pyy = np.take_along_axis(rows, sub[:, None, :], axis=2)  # (Z, 6, 6)
    pyy = 0.5 * (pyy + pyy.transpose(0, 2, 1))
    y = mu.copy()
    for _ in range(_LASER_ITERATIONS):
        h, ja, jb = _between_jacobians(y[:, :3], y[:, 3:])
        H = np.concatenate([ja, jb], axis=2)  # (Z, 3, 6)
        e = z - h - np.einsum("zij,zj->zi", H, mu - y)
        e[:, 2] = wrap_angle(e[:, 2])
        ph = pyy @ H.transpose(0, 2, 1)  # (Z, 6, 3)
        S = H @ ph + R
        step = mu + np.einsum("zij,zj->zi", ph, np.linalg.solve(S, e[:, :, None])[..., 0]) - y
        y += step
        if np.max(np.abs(step)) < _LASER_TOLERANCE:
            break
    h, ja, jb = _between_jacobians(y[:, :3], y[:, 3:])
    H = np.concatenate([ja, jb], axis=2)
    e = z - h - np.einsum("zij,zj->zi", H, mu - y)
    e[:, 2] = wrap_angle(e[:, 2])
    hp = ja @ rows[:, 0:3] + jb @ rows[:, 3:6]  # H P: (Z, 3, D)
    S = H @ pyy @ H.transpose(0, 2, 1) + R
    S = 0.5 * (S + S.transpose(0, 2, 1))
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError as err:
        msg = "a laser innovation covariance is not positive definite"
        raise ModelError(msg) from err
    W = cast("FloatArray", np.linalg.solve(L, hp))  # float64 (numpy types linalg results floating)
    v = np.linalg.solve(L, e[:, :, None])[..., 0]
    log_det = 2.0 * np.sum(np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1)
    return W, v, -1.5 * _LOG_2PI - 0.5 * log_det - 0.5 * np.sum(v * v, axis=1)


def _check_visit(visit: Visit, n: int) -> None:
    index = getattr(visit, "index", None)
    if index != n:
        msg = f"visits must arrive in order: expected visit index {n}, got {index!r}"
        raise ModelError(msg)
    pose = np.asarray(getattr(visit, "pose", None), dtype=float)
    if pose.shape != (3,) or not np.all(np.isfinite(pose)):
        msg = f"visit {n}: pose must be 3 finite numbers, got {visit.pose!r}"
        raise ModelError(msg)
    for name in ("travel", "rotation"):
        value = float(getattr(visit, name))
        if not (math.isfinite(value) and value >= 0.0):
            msg = f"visit {n}: {name} must be finite and >= 0, got {value!r}"
            raise ModelError(msg)


def registration_row(i: int, j: int, z: RelativePose | NoMatch | None) -> list[Any]:
    """``[i, j, mean, cov, log_bayes]`` (mean/cov None for a NoMatch; everything None for no outcome)."""
    if z is None:
        return [i, j, None, None, None]
    if isinstance(z, NoMatch):
        return [i, j, None, None, z.log_bayes]
    return [i, j, z.mean.tolist(), z.cov.tolist(), z.log_bayes]


def registration_from_row(row: Sequence[Any]) -> RelativePose | NoMatch | None:
    """Inverse of :func:`registration_row` (rows of 4 entries, saved before ``log_bayes``, read too)."""
    i, j, m, c = row[:4]
    lb = row[4] if len(row) > 4 else 0.0
    if m is not None:
        return RelativePose(int(i), int(j), np.asarray(m, float), np.asarray(c, float), float(lb))
    return None if lb is None or len(row) == 4 else NoMatch(int(i), int(j), float(lb))


def _check_registration(z: RelativePose | NoMatch, i: int, j: int) -> RelativePose | NoMatch:
    if (int(z.i), int(z.j)) != (i, j):
        msg = f"the registrar answered pair ({z.i}, {z.j}) when asked for ({i}, {j})"
        raise ModelError(msg)
    if not math.isfinite(z.log_bayes):
        msg = f"registration ({i}, {j}): log_bayes must be finite, got {z.log_bayes}"
        raise ModelError(msg)
    if isinstance(z, NoMatch):
        return z
    mean = np.asarray(z.mean, dtype=float)
    cov = np.asarray(z.cov, dtype=float)
    finite = bool(np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)))
    if mean.shape != (3,) or cov.shape != (3, 3) or not finite:
        msg = f"registration ({i}, {j}): mean must be 3 and cov 3x3 finite numbers"
        raise ModelError(msg)
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12) or np.any(np.linalg.eigvalsh(cov) <= 0.0):
        msg = f"registration ({i}, {j}): covariance must be symmetric positive definite"
        raise ModelError(msg)
    return RelativePose(i, j, mean, cov, float(z.log_bayes))


def _extend_blocks(blocks: tuple[tuple[int, ...], ...], k: int, n: int) -> tuple[tuple[int, ...], ...]:
    if k == len(blocks):
        return (*blocks, (n,))
    return (*blocks[:k], (*blocks[k], n), *blocks[k + 1 :])


def _blocks_of(labels: Labels) -> tuple[tuple[int, ...], ...]:
    out: list[list[int]] = []
    for i, lab in enumerate(labels):
        if lab == len(out):
            out.append([])
        out[lab].append(i)
    return tuple(tuple(b) for b in out)


def visit_dict(v: Visit) -> dict[str, Any]:
    """A visit as plain Python + numpy copies (for :meth:`TopologyFilter.state_dict` and persistence)."""
    return visit_fields(v, lambda a: np.asarray(a).copy())


def visit_from_dict(d: dict[str, Any]) -> Visit:
    """Inverse of :func:`visit_dict`, arrays as float64 (``words`` int64); dicts saved before
    ``odom_pose`` or ``signature_spread`` existed are read too."""
    return visit_from_fields(d, np.asarray)


def run_filter(
    visits: Sequence[Visit],
    config: RbpfConfig,
    prior: TopologyPrior,
    odometry: OdometryConfig,
    *,
    appearance: AppearanceModel | None = None,
    registrar: Registrar | None = None,
    seed: int = 0,
    progress: Callable[[Iterable[Visit], int], Iterable[Visit]] | None = None,
) -> TopologyFilter:
    """Run the filter over a whole visit sequence (the offline pipeline, ``ptm-run --method rbpf``).

    ``progress`` may wrap the iteration (e.g. a tqdm bar); it receives the visits and their number.
    """
    flt = TopologyFilter(config, prior, odometry, appearance=appearance, registrar=registrar, seed=seed)
    items: Iterable[Visit] = visits if progress is None else progress(visits, len(visits))
    for visit in items:
        flt.update(visit)
    return flt
