r"""The particle filter's PTM weighed with the batch metric evidence (thesis eq. 14, 18, 38–41, 47–48).

The filter (:mod:`ptm_ros.inference.rbpf`) scores a topology's metric data, odometry, place coincidences
and laser registrations, by the product of its sequential predictives under an extended Kalman filter:
:math:`\hat m(L) = \sum_n \log \hat p(o_{n-1}, s_n \mid L^n, z^{n-1})`. The EKF linearises every heading
error where the robot was when it drove, never where the closed loop puts it; the batch model
(:func:`ptm_ros.model.odometry.metric_log_likelihood`: Laplace's method at the optimum of the whole
topology, importance sampling on small runs) integrates the same metric likelihood
:math:`m(L) = \log p(O, S \mid L)`. Where a loop closes a heading error of a few degrees the two
differ enough to move a tenth of the mass (``bench/reweighting.md``).

A particle's weight after optimal resampling is its sequential target times the product of its
resampling factors, :math:`w_i = \hat\pi(L_i) R_i`. Since :math:`\hat\pi` and the batch target
:math:`\pi` differ only in the metric part,

.. math::
    w_i' \propto w_i \exp\bigl(m(L_i) - \hat m(L_i)\bigr)

is an importance-sampling estimate of the batch posterior over topologies, with the filter as the
proposal: the filter chooses *which* topologies to keep, the batch model says *how much* each is worth.
Both carry each place's offset along the visits' headings (``odometry.sigma_offset``,
:func:`ptm_ros.model.odometry.coincidence_rows`); the batch model also integrates the separation prior
over every visit, where the filter takes a place's visits at their mean.
With every topology kept it is the batch posterior exactly (``ptm-run --method exact``). The prior
(eq. 39) and the appearance predictives (eq. 46) are the batch model's chain rule already and cancel.
Resampling keeps using the sequential weights: the reweighting changes the PTM, not the particles.

Where the reweighting applies (:func:`sampled_evidence`): only where the batch evidence is an
importance-sampling integral (eq. 18; ``odometry.n_samples`` > 0 and at most
``odometry.max_sampled_visits`` visits), i.e. converges to :math:`m(L)` itself. Beyond that the batch model
falls back on Laplace's method at the optimum, another Gaussian approximation of the same integral, with
the separation prior (eq. 15–16) evaluated at the optimum's point where the filter integrates it over the
visits' uncertainty; there the filter's own estimate is kept (the Laplace reweighting, measured on the
real runs, made a wrong merge the MAP: ``bench/reweighting.md``).

Every topology held is evaluated: the sequential weights cannot tell which ones the batch model would
weigh differently (where the EKF is far off, a topology it nearly dropped can be the batch MAP).

On in the product (``inference.reweight``): reweighted, the filter equals exact enumeration on small runs.
It was off until the batch model stopped counting a chain of aliased registrations as independent evidence:
in a ring of identical sections, a topology that closes the ring one section early is geometrically
consistent, its place coincidences bend the path until each aliased registration fits, and the batch
model preferred it by 8 nats; the heading test (:func:`ptm_ros.model.odometry.heading_aliases`) now takes
those registrations for aliases in every topology (``bench/reweighting.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ptm_ros.errors import ModelError
from ptm_ros.inference.resampling import logsumexp
from ptm_ros.model.geometry import FloatArray
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.partitions import Labels


class MetricEvidence(Protocol):
    """``log p(O, S | L)`` of a topology of the visits so far, by the batch model."""

    def __call__(self, labels: Labels, /) -> float: ...


@dataclass(frozen=True)
class Reweighted:
    """The weights of the particle set under the batch metric evidence.

    Attributes:
        log_w: normalised log weights, one per particle.
        shift: :math:`m(L_i) - \\hat m(L_i)` per particle [nats].
        seconds: the wall time it took (set by the caller that timed it; 0 otherwise).
    """

    log_w: FloatArray
    shift: FloatArray
    seconds: float = 0.0


def sampled_evidence(n_visits: int, odometry: OdometryConfig) -> bool:
    """Whether the batch metric evidence of ``n_visits`` visits is an importance-sampling integral (eq. 18),
    the condition for reweighting (module docstring); a single visit has nothing to reweigh."""
    return 2 <= n_visits <= odometry.max_sampled_visits and odometry.n_samples > 0


def reweigh(
    log_w: FloatArray, labels: tuple[Labels, ...], sequential: FloatArray, evidence: MetricEvidence
) -> Reweighted:
    r"""Multiply each weight by :math:`\exp(m(L_i) - \hat m(L_i))` (module docstring).

    Args:
        log_w: the particles' log weights (normalised or not).
        labels: their topologies.
        sequential: :math:`\hat m(L_i)`, the metric log evidence the weights carry.
        evidence: :math:`m(L)`, the batch model's.

    Raises:
        ModelError: arrays of different lengths or empty, or an evidence that is neither a finite number
            nor ``-inf``.
    """
    lw = np.asarray(log_w, dtype=float)
    seq = np.asarray(sequential, dtype=float)
    if lw.ndim != 1 or lw.shape != seq.shape or len(labels) != len(lw) or len(lw) == 0:
        sizes = f"{len(lw)}, {len(labels)}, {seq.size}"
        msg = f"reweigh needs as many weights, topologies and evidences (at least one), got {sizes}"
        raise ModelError(msg)
    batch = np.array([float(evidence(lab)) for lab in labels])
    bad = np.isnan(batch) | (batch == np.inf)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        msg = f"the batch metric evidence of {labels[k]} is {batch[k]}"
        raise ModelError(msg)
    shift = batch - seq
    cur = lw + shift
    if not np.isfinite(logsumexp(cur)):
        msg = "every topology held has zero batch metric evidence"
        raise ModelError(msg)
    return Reweighted(log_w=cur - logsumexp(cur), shift=shift)
