"""Urn-model priors over topologies (thesis Ch. 1.3).

Every prior gives

* ``log_prob(labels)``: log P(T) of a whole topology, normalised over all ``B_N`` topologies of N
  visits (tests check the sum over all partitions for N ≤ 8);
* ``log_predictive(counts)``: the sequential form log P(L_n = k | L_{1:n-1}) used as the particle filter's
  proposal (eq. 39, 42), given the visit counts of the places seen so far; entry k < M is "revisit place
  k" (canonical label order), entry M is "a new place". Multiplying the predictives along a label
  sequence gives the joint (tested).

Priors (thesis notation):

* :class:`DirichletProcessPrior` — Chinese restaurant / Pólya urn (eq. 10–11):
  P(T) = α^M ∏_s (|s|−1)! / ∏_{j=1}^{N} (α + j − 1).
* :class:`YuleSimonPrior` — Yule–Simon–Zipf (eq. 12): a new place with constant probability u, otherwise
  one of the M known places uniformly. (Eq. 12 as printed indexes the cases by ``i`` and ``z(n)``
  inconsistently; the rule above is the one its text states and it sums to one.)
* :class:`OccupancyPrior` — classical occupancy with L urns (eq. 5–7), P(T | L) = L!/(L−M)! · L^{−N},
  marginalised over a Poisson(λ) on L truncated to 1 ≤ L ≤ L_max (eq. 8):
  P(T) = Σ_L Pois(L; λ)/Z · L!/(L−M)! · L^{−N}. Eq. 7's constant "k" is exactly 1:
  Σ_M S(N, M) L!/(L−M)! = L^N.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.special import gammaln, logsumexp

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.model.partitions import IntSequence, is_canonical
from ptm_ros.settings import Settings, setting


class TopologyPrior(Protocol):
    """The interface shared by all priors over topologies."""

    def log_prob(self, labels: Sequence[int]) -> float:
        """log P(T) of a canonical label sequence."""
        ...

    def log_predictive(self, counts: IntSequence) -> NDArray[np.float64]:
        """log P(next label) for each known place (by visit counts) and, last, for a new place."""
        ...


def _block_sizes(labels: Sequence[int]) -> list[int]:
    if not is_canonical(labels):
        msg = f"labels must be a canonical label sequence, got {tuple(labels)}"
        raise ModelError(msg)
    sizes: list[int] = []
    for lab in labels:
        if lab == len(sizes):
            sizes.append(0)
        sizes[lab] += 1
    return sizes


def _check_counts(counts: IntSequence) -> NDArray[np.float64]:
    c = np.asarray(counts, dtype=float).reshape(-1)
    if np.any(c < 1):
        msg = f"place visit counts must be >= 1, got {list(counts)}"
        raise ModelError(msg)
    return c


@dataclass(frozen=True)
class DirichletProcessPrior:
    """Dirichlet-process (Chinese restaurant) prior, eq. 10–11, concentration ``alpha`` > 0."""

    alpha: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            msg = f"Dirichlet process alpha must be finite and > 0, got {self.alpha}"
            raise ConfigError(msg)

    def log_prob(self, labels: Sequence[int]) -> float:
        """Eq. 11 in log form."""
        sizes = np.asarray(_block_sizes(labels), dtype=float)
        n = int(sizes.sum())
        if n == 0:
            return 0.0
        a = self.alpha
        return float(len(sizes) * math.log(a) + np.sum(gammaln(sizes)) - (gammaln(a + n) - gammaln(a)))

    def log_predictive(self, counts: IntSequence) -> NDArray[np.float64]:
        """Eq. 10: revisit ∝ visits so far, new place ∝ alpha."""
        c = _check_counts(counts)
        return np.log(np.append(c, self.alpha)) - math.log(self.alpha + c.sum())


@dataclass(frozen=True)
class YuleSimonPrior:
    """Yule–Simon–Zipf prior, eq. 12: new place with probability ``u``, else a known place uniformly."""

    u: float = 0.3

    def __post_init__(self) -> None:
        if not (0.0 < self.u < 1.0):
            msg = f"Yule-Simon new-place probability u must be in (0, 1), got {self.u}"
            raise ConfigError(msg)

    def log_prob(self, labels: Sequence[int]) -> float:
        """Product of eq. 12 along the sequence (closed form: it depends on when places were opened)."""
        if not is_canonical(labels):
            msg = f"labels must be a canonical label sequence, got {tuple(labels)}"
            raise ModelError(msg)
        total = 0.0
        m = 0
        for n, lab in enumerate(labels):
            if n == 0:
                m = 1
                continue
            if lab == m:
                total += math.log(self.u)
                m += 1
            else:
                total += math.log1p(-self.u) - math.log(m)
        return total

    def log_predictive(self, counts: IntSequence) -> NDArray[np.float64]:
        """Eq. 12 for the next visit; the first visit is always a new place."""
        c = _check_counts(counts)
        m = len(c)
        if m == 0:
            return np.zeros(1)
        out = np.full(m + 1, math.log1p(-self.u) - math.log(m))
        out[m] = math.log(self.u)
        return out


@dataclass(frozen=True)
class OccupancyPrior:
    """Classical occupancy prior with a truncated Poisson over the number of places (eq. 5–8).

    ``rate`` is λ, the expected number of places in the environment; L ranges over 1..``max_places``.
    """

    rate: float = 20.0
    max_places: int = 200

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate) and self.rate > 0):
            msg = f"occupancy prior rate (expected number of places) must be > 0, got {self.rate}"
            raise ConfigError(msg)
        if self.max_places < 1:
            msg = f"occupancy prior max_places must be >= 1, got {self.max_places}"
            raise ConfigError(msg)

    def _log_weights(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(L values, log truncated-Poisson masses of L)."""
        L = np.arange(1, self.max_places + 1, dtype=float)
        lw = L * math.log(self.rate) - self.rate - gammaln(L + 1)
        return L, lw - logsumexp(lw)

    def _log_joint_terms(self, n: int, m: int) -> NDArray[np.float64]:
        """log[Pois(L) · L!/(L−m)! · L^−n] for every L (−inf where L < m)."""
        L, lw = self._log_weights()
        out = np.full_like(L, -np.inf)
        ok = m <= L
        out[ok] = lw[ok] + gammaln(L[ok] + 1) - gammaln(L[ok] - m + 1) - n * np.log(L[ok])
        return out

    def log_prob(self, labels: Sequence[int]) -> float:
        """Eq. 8 (normalised) for a topology with N visits and M places."""
        sizes = _block_sizes(labels)
        n, m = sum(sizes), len(sizes)
        if m > self.max_places:
            return -math.inf
        return float(logsumexp(self._log_joint_terms(n, m)))

    def log_predictive(self, counts: IntSequence) -> NDArray[np.float64]:
        """P(T_{1:n}) / P(T_{1:n−1}): a known place or a new one (depends only on n−1 and M)."""
        c = _check_counts(counts)
        n, m = int(c.sum()), len(c)
        if m == 0:
            return np.zeros(1)
        if m > self.max_places:
            msg = f"{m} places exceed max_places = {self.max_places}: the history has prior probability 0"
            raise ModelError(msg)
        base = logsumexp(self._log_joint_terms(n, m))
        old = logsumexp(self._log_joint_terms(n + 1, m)) - base
        new = logsumexp(self._log_joint_terms(n + 1, m + 1)) - base if m < self.max_places else -np.inf
        out = np.full(m + 1, old)
        out[m] = new
        return out


#: The priors :func:`make_prior` builds.
PRIOR_KINDS = ("dirichlet", "yule-simon", "occupancy")


@dataclass(frozen=True)
class PriorConfig(Settings):
    """Which prior over topologies to use and its parameters (thesis Ch. 1.3)."""

    kind: str = setting(
        "dirichlet",
        choices=PRIOR_KINDS,
        doc="the prior: Dirichlet process (Ch. 1.3.1), Yule-Simon (1.3.2) or occupancy (1.3.3)",
    )
    alpha: float = setting(1.0, gt=0, doc="dirichlet: the concentration α (new places' weight)")
    u: float = setting(0.3, gt=0, lt=1, doc="yule-simon: the probability u that a visit opens a new place")
    rate: float = setting(20.0, gt=0, doc="occupancy: expected number of places")
    max_places: int = setting(200, ge=1, doc="occupancy: truncation of the Poisson number of places")


def make_prior(config: PriorConfig) -> TopologyPrior:
    """The prior object a :class:`PriorConfig` describes."""
    if config.kind == "dirichlet":
        return DirichletProcessPrior(config.alpha)
    if config.kind == "yule-simon":
        return YuleSimonPrior(config.u)
    return OccupancyPrior(config.rate, config.max_places)
