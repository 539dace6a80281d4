r"""The spread of the visits' offset along their headings, learned from the run's laser registrations
(issue #23; the thesis leaves the model's parameters to future work, Ch. 6.3).

The place model (:func:`ptm_ros.model.odometry.coincidence_rows`) puts visit ``i`` of place ``s`` at
:math:`p_s + \delta_s h_i + \epsilon_i`, ``h_i`` the unit vector of its heading,
:math:`\epsilon_i \sim \mathcal N(0, \sigma_T^2 I)` and :math:`\delta_s \sim \mathcal N(0, \sigma_\delta^2)`.
How far from its place the detector fires depends on the detector and the building: 0.4–0.85 m before the
simulator's doorways (``bench/visit_offset.md``), about nothing on the shared real runs. So ``σ_δ`` is
learned from each run.

Model
-----
A valid registration ``z`` of visits ``i < j`` of one place measures their relative pose; its translation,
in the frame of visit ``i``, is

.. math::
    z_{xy} = -\delta_s\, a(\Delta) + e, \qquad a(\Delta) = (1 - \cos\Delta,\ -\sin\Delta), \qquad
    e \sim \mathcal N(0, 2\sigma_T^2 I)

with ``Δ`` its heading change (``h_j`` seen from ``i``): the offset moves the second visit along ``a`` only.
Projected on ``â = a/|a|`` and on its normal ``n̂``, :math:`E[(\hat a^\top z)^2] = \sigma_\delta^2 |a|^2 +
2\sigma_T^2` and :math:`E[(\hat n^\top z)^2] = 2\sigma_T^2`, so the moment equation

.. math::
    \sum_k \big((\hat a_k^\top z_k)^2 - (\hat n_k^\top z_k)^2\big) = \sigma_\delta^2 \sum_k |a_k|^2

holds without knowing ``σ_T``; and a registration between two different places that still matched (an alias),
whose translation has no preferred direction, adds as much to both sums on average: the estimate needs no
outlier model. A weak prior, :data:`PRIOR_WEIGHT` registrations at the configured ``sigma_offset`` with
``|a|² = 1``, keeps a run with few turned registrations near the configured value:

.. math::
    \hat\sigma_\delta^2 = \max\Big(0,\ \frac{\sum_k (\ldots) + w\,\sigma_0^2}{\sum_k |a_k|^2 + w}\Big).

Only registrations with a lever (``|a|`` > :data:`MIN_LEVER`, a heading change above about 29°) and a
translation a place can hold (``|z_xy|`` < :data:`MAX_SPAN`) count. The estimate is kept on a lattice of
:data:`STEP_M` so that :class:`ptm_ros.session.FilterSession` replays the filter only when it moves.

Approximation: the sums treat the registrations as independent, but the registrations of one place share its
``δ_s``; a run whose turned registrations are all of one place learns that place's offset.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ptm_ros.model.geometry import RelativePose

#: Registrations whose heading changes by less give no lever on the offset (``|a| = 2 sin(Δ/2)``: 29°).
MIN_LEVER = 0.5
#: A registration's translation beyond this [m] is not two visits of one place.
MAX_SPAN = 3.0
#: The prior's weight, in registrations with ``|a|² = 1`` at the configured ``sigma_offset``.
PRIOR_WEIGHT = 4.0
#: The lattice of learned values [m].
STEP_M = 0.125


@dataclass(frozen=True)
class OffsetSpread:
    """A learned ``σ_δ``.

    Attributes:
        sigma: ``σ_δ`` [m], on the lattice (``step * STEP_M``).
        step: its lattice step.
        samples: the registrations with a lever it was learned from.
        registrations: the valid registrations seen when it was learned.
    """

    sigma: float
    step: int
    samples: int
    registrations: int

    @classmethod
    def prior(cls, sigma: float) -> OffsetSpread:
        """The value before any registration: the configured one, on the lattice."""
        step = round(sigma / STEP_M)
        return cls(step * STEP_M, step, 0, 0)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> OffsetSpread:
        """Inverse of :meth:`as_dict`."""
        return cls(float(d["sigma"]), int(d["step"]), int(d["samples"]), int(d["registrations"]))

    def as_dict(self) -> dict[str, float | int]:
        """Plain values (ptm.json's ``inference.visit_offset``)."""
        keys = ("sigma", "step", "samples", "registrations")
        return {k: getattr(self, k) for k in keys}


def offset_moments(registrations: Iterable[RelativePose]) -> tuple[float, float, int]:
    """``Σ ((âᵀz)² - (n̂ᵀz)²)``, ``Σ |a|²`` and their count over the registrations with a lever (module
    docstring)."""
    z = np.array([np.asarray(r.mean, dtype=float) for r in registrations]).reshape(-1, 3)
    a = np.stack([1.0 - np.cos(z[:, 2]), -np.sin(z[:, 2])], axis=1)
    norm = np.hypot(a[:, 0], a[:, 1])
    keep = (norm > MIN_LEVER) & (np.hypot(z[:, 0], z[:, 1]) < MAX_SPAN)
    a_hat = a[keep] / norm[keep, None]
    along = np.sum(a_hat * z[keep, :2], axis=1)
    normal = a_hat[:, 0] * z[keep, 1] - a_hat[:, 1] * z[keep, 0]
    return float(np.sum(along**2 - normal**2)), float(np.sum(norm[keep] ** 2)), int(np.count_nonzero(keep))


def offset_spread(registrations: Iterable[RelativePose], prior_sigma: float) -> OffsetSpread:
    """``σ_δ`` learned from valid registrations under the prior at ``prior_sigma`` (module docstring)."""
    regs = list(registrations)
    excess, leverage, samples = offset_moments(regs)
    variance = max(0.0, (excess + PRIOR_WEIGHT * prior_sigma**2) / (leverage + PRIOR_WEIGHT))
    step = round(math.sqrt(variance) / STEP_M)
    return OffsetSpread(step * STEP_M, step, samples, len(regs))
