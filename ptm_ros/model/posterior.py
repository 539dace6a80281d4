"""The posterior over topologies, log P(T | Z) = log P(T) + log P(O, S | T) + log P(A | T) (eq. 1–4).

:class:`PosteriorModel` binds a visit sequence to the models of a :class:`ModelConfig` and evaluates
the unnormalised log posterior of any topology:

* prior: :mod:`ptm_ros.model.priors` (Ch. 1.3);
* metric likelihood of odometry and laser registrations: :mod:`ptm_ros.model.odometry` (eq. 14–18, 47–49);
  laser registrations enter for pairs of visits placed at one place (each visit against the previous
  visit of its place), computed lazily by a *registrar* and cached per pair. The data are the outcomes
  of all pairs; a pair the topology does not chain has an uninformative outcome density 1/V_reg, so up
  to a constant each chained valid registration contributes log N(z; ·) + log V_reg (a likelihood
  ratio), and pairs never registered need not be computed; every chained registration (valid or not)
  also contributes the likelihood ratio of its fitness, one place vs different places
  (:func:`ptm_ros.perception.laser.fitness_log_bayes`). A valid registration is a true match with probability
  1 − ε and a symmetric alias (uniform over V_reg) with probability ε (``registration_outlier``); the
  loops the odometry and topology predict worse than an alias
  (:func:`ptm_ros.model.odometry.registration_aliases`: at the topology's optimum without registrations,
  or on the heading alone, :func:`ptm_ros.model.odometry.heading_aliases`) contribute log ε and no pose
  constraint, the others log(1 − ε) besides their Gaussian (a max-mixture);
* appearance likelihood: :mod:`ptm_ros.model.appearance` (eq. 22–28, 54–57), a product over blocks cached
  per block, because a topology's blocks recur across MCMC moves and particles; a visit without a
  panorama is a missing measurement and simply left out.

Whole-topology results are cached too. Importance sampling inside the metric likelihood draws from a
generator seeded by ``(seed, labels)``, so a topology's value does not depend on evaluation order.

:func:`exact_posterior` enumerates all ``B_N`` topologies (N ≤ 12): the yardstick for every sampler.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray
from scipy.special import logsumexp

from ptm_ros.errors import ModelError
from ptm_ros.model.appearance import (
    AppearanceConfig,
    AppearanceModel,
    appearance_log_likelihood,
    fit_appearance_model,
)
from ptm_ros.model.geometry import NoMatch, Registrar, RelativePose
from ptm_ros.model.odometry import AliasTest, MetricResult, OdometryConfig, alias_test, metric_log_likelihood
from ptm_ros.model.partitions import MAX_ENUMERATION, Labels, blocks, enumerate_partitions, is_canonical
from ptm_ros.model.priors import PriorConfig, make_prior
from ptm_ros.model.visits import Visit
from ptm_ros.settings import Settings, setting


@dataclass(frozen=True)
class ModelConfig(Settings):
    """Which measurements enter the posterior, and their models' parameters."""

    prior: PriorConfig = setting(factory=PriorConfig, doc="the prior P(T) over topologies (Ch. 1.3).")
    odometry: OdometryConfig = setting(
        factory=OdometryConfig,
        doc="the metric likelihood P(O, S | T) of odometry and laser registrations (Ch. 2.2–2.4).",
    )
    appearance: AppearanceConfig = setting(
        factory=AppearanceConfig, doc="the appearance likelihood P(A | T) (Ch. 2.5)."
    )
    use_odometry: bool = setting(
        True,
        doc=(
            "multiply in the metric likelihood of odometry and laser registrations; off: the posterior is "
            "the prior times the appearance likelihood."
        ),
    )
    use_appearance: bool = setting(
        True,
        doc=(
            "multiply in the appearance likelihood; it enters only when at least two visits carry each "
            "configured appearance measurement (``appearance.models``)."
        ),
    )
    use_laser: bool = setting(
        True,
        doc=(
            "use the laser scans: registrations between visits of one place enter the metric likelihood "
            "(only when a registrar is given), visits carry laser patches and the default detector is "
            "laser surprise; off: neither registrations nor patches."
        ),
    )


@dataclass(frozen=True)
class PosteriorTerms:
    """The parts of log P(T | Z) for one topology (unnormalised)."""

    prior: float
    metric: float
    appearance: float
    metric_result: MetricResult | None = None
    loops: tuple[RelativePose, ...] = ()  # the laser loops used as true matches
    outliers: tuple[RelativePose, ...] = ()  # the valid registrations explained as aliases

    @property
    def total(self) -> float:
        return self.prior + self.metric + self.appearance


def _has_appearance(visits: Sequence[Visit], config: AppearanceConfig) -> bool:
    """Whether at least two visits carry each configured appearance measurement (visits without one are
    missing measurements, left out of the appearance likelihood)."""
    need_sig = "fourier" in config.models
    need_words = "words" in config.models
    sigs = sum(v.signature is not None for v in visits)
    words = sum(v.words is not None for v in visits)
    return (not need_sig or sigs >= 2) and (not need_words or words >= 2)


def chained_outcomes(
    labels: Sequence[int], registration: Callable[[int, int], RelativePose | NoMatch | None]
) -> list[RelativePose | NoMatch | None]:
    """The laser outcomes a topology looks at (eq. 47–49): each visit against the previous visit of its
    place (``registration(i, j)``, i < j), in block order."""
    return [registration(a, b) for block in blocks(labels) for a, b in pairwise(block)]


def chained_registrations(
    labels: Sequence[int], registration: Callable[[int, int], RelativePose | NoMatch | None]
) -> tuple[RelativePose, ...]:
    """The valid registrations among a topology's :func:`chained_outcomes` (failed or missing left out)."""
    return tuple(z for z in chained_outcomes(labels, registration) if isinstance(z, RelativePose))


def split_aliases(
    labels: Sequence[int], visits: Sequence[Visit], config: OdometryConfig, measured: Sequence[RelativePose]
) -> tuple[tuple[RelativePose, ...], tuple[RelativePose, ...]]:
    """``(loops, outliers)``: a topology's valid registrations ``measured`` split into the ones used as pose
    constraints and the ones explained as symmetric aliases (:func:`ptm_ros.model.odometry.alias_test`,
    the max-mixture of ``registration_outlier``). The batch posterior, the smoothing of ``ptm-run`` and the
    map publisher's online map all take a topology's loops from here."""
    return _split(measured, alias_test(labels, visits, config, measured))


def _split(
    measured: Sequence[RelativePose], test: AliasTest
) -> tuple[tuple[RelativePose, ...], tuple[RelativePose, ...]]:
    loops = tuple(z for z, a in zip(measured, test.aliases, strict=True) if not a)
    outliers = tuple(z for z, a in zip(measured, test.aliases, strict=True) if a)
    return loops, outliers


class PosteriorModel:
    """log P(T | Z) for topologies of a fixed visit sequence, with caching (see module docstring)."""

    def __init__(
        self,
        visits: Sequence[Visit],
        config: ModelConfig | None = None,
        *,
        registrar: Registrar | None = None,
        seed: int = 0,
    ) -> None:
        if not visits:
            msg = "the posterior needs at least one visit"
            raise ModelError(msg)
        self.visits = tuple(visits)
        self.config = config or ModelConfig()
        self.seed = int(seed)
        self.prior = make_prior(self.config.prior)
        self.appearance: AppearanceModel | None = None
        if self.config.use_appearance and _has_appearance(self.visits, self.config.appearance):
            self.appearance = fit_appearance_model(self.visits, self.config.appearance)
        self.registrar = registrar if self.config.use_laser else None
        self._block_cache: dict[tuple[int, ...], float] = {}
        self._pair_cache: dict[tuple[int, int], RelativePose | NoMatch | None] = {}
        self._terms_cache: dict[Labels, PosteriorTerms] = {}

    @property
    def n(self) -> int:
        return len(self.visits)

    def _check(self, labels: Sequence[int]) -> Labels:
        lab = tuple(int(v) for v in labels)
        if len(lab) != self.n or not is_canonical(lab):
            msg = f"expected a canonical label sequence of {self.n} visits, got {lab}"
            raise ModelError(msg)
        return lab

    def registration(self, i: int, j: int) -> RelativePose | NoMatch | None:
        """The cached laser outcome between visits i < j (None: no registrar or no information)."""
        if self.registrar is None:
            return None
        key = (i, j)
        if key not in self._pair_cache:
            self._pair_cache[key] = self.registrar(i, j)
        return self._pair_cache[key]

    def loops(self, labels: Labels) -> tuple[RelativePose, ...]:
        """Laser measurements used by a topology: each visit against the previous visit of its place."""
        return chained_registrations(labels, self.registration)

    def laser_evidence(self, labels: Labels) -> float:
        """Σ of the fitness evidence (``log_bayes``) of the laser outcomes of the chained pairs."""
        return float(sum(z.log_bayes for z in self._chained(labels) if z is not None))

    def _chained(self, labels: Labels) -> list[RelativePose | NoMatch | None]:
        return chained_outcomes(labels, self.registration)

    def terms(self, labels: Sequence[int]) -> PosteriorTerms:
        """All parts of the unnormalised log posterior of a topology (cached)."""
        lab = self._check(labels)
        cached = self._terms_cache.get(lab)
        if cached is not None:
            return cached
        prior = self.prior.log_prob(lab)
        metric, result = 0.0, None
        loops: tuple[RelativePose, ...] = ()
        outliers: tuple[RelativePose, ...] = ()
        if self.config.use_odometry and self.n > 1:
            cfg = self.config.odometry
            measured = self.loops(lab)
            test = alias_test(lab, self.visits, cfg, measured)
            loops, outliers = _split(measured, test)
            rng = np.random.default_rng([self.seed, *lab])
            # optimised from the optimum without laser loops (the alias test's), not from the odometry:
            # the loops kept agree with it, so a few iterations suffice (the same optimum, to tolerance)
            result = metric_log_likelihood(lab, self.visits, cfg, loops, rng=rng, initial=test.poses)
            # likelihood ratio of each used registration against "not the same place" (uniform over
            # V_reg), so that every topology explains the same data (see the module docstring)
            metric = result.log_likelihood + len(loops) * math.log(cfg.registration_volume)
            if cfg.registration_outlier > 0.0:
                metric += len(loops) * math.log1p(-cfg.registration_outlier)
                metric += len(outliers) * math.log(cfg.registration_outlier)
            metric += self.laser_evidence(lab)
        app = 0.0
        if self.appearance is not None:
            app = appearance_log_likelihood(lab, self.visits, self.appearance, cache=self._block_cache)
        out = PosteriorTerms(
            prior=prior,
            metric=metric,
            appearance=app,
            metric_result=result,
            loops=loops,
            outliers=outliers,
        )
        self._terms_cache[lab] = out
        return out

    def log_posterior(self, labels: Sequence[int]) -> float:
        """Unnormalised log P(T | Z)."""
        return self.terms(labels).total

    def clear_cache(self) -> None:
        """Forget cached topologies (block and pair caches stay valid and are kept)."""
        self._terms_cache.clear()


def normalize_log(weights: Mapping[Labels, float]) -> dict[Labels, float]:
    """Probabilities from unnormalised log weights (log-sum-exp; −inf entries get 0)."""
    keys = list(weights)
    lw = np.array([weights[k] for k in keys], dtype=float)
    if not np.any(np.isfinite(lw)):
        msg = "every topology has zero posterior probability"
        raise ModelError(msg)
    p = np.exp(lw - logsumexp(lw))
    return dict(zip(keys, p.tolist(), strict=True))


def exact_posterior(
    model: PosteriorModel, *, progress: Callable[[Iterable[Labels], int], Iterable[Labels]] | None = None
) -> dict[Labels, float]:
    """Unnormalised log posterior of every topology of the model's visits (N ≤ 12).

    ``progress`` may wrap the enumeration (e.g. a tqdm bar); it receives the iterator and its length.
    """
    if model.n > MAX_ENUMERATION:
        msg = f"exact enumeration needs N <= {MAX_ENUMERATION} visits, got {model.n}"
        raise ModelError(msg)
    from ptm_ros.model.partitions import bell

    parts: Iterable[Labels] = enumerate_partitions(model.n)
    if progress is not None:
        parts = progress(parts, bell(model.n))
    out = {lab: model.log_posterior(lab) for lab in parts}
    model.clear_cache()  # B_N topologies: do not keep them all twice
    return out


def total_variation(p: Mapping[Labels, float], q: Mapping[Labels, float]) -> float:
    """Total-variation distance ½ Σ |p − q| between two distributions over topologies."""
    keys = set(p) | set(q)
    return 0.5 * math.fsum(abs(p.get(k, 0.0) - q.get(k, 0.0)) for k in keys)


def same_place_probabilities(probabilities: Mapping[Labels, float], n: int) -> NDArray[np.float64]:
    """``(n, n)`` marginal probability that visits i and j are one place, ``Σ_T P(T) [T_i = T_j]`` over
    a distribution of topologies of ``n`` visits (1 on the diagonal for a normalised distribution)."""
    out = np.zeros((n, n))
    items = [(lab, p) for lab, p in probabilities.items() if p > 0.0]
    for start in range(0, len(items), 256):  # (chunk, n, n) booleans at a time
        chunk = items[start : start + 256]
        lab = np.array([lab for lab, _ in chunk], dtype=np.int64).reshape(len(chunk), n)
        w = np.array([p for _, p in chunk], dtype=float)
        out += np.einsum("t,tij->ij", w, lab[:, :, None] == lab[:, None, :])
    return out


def top_k(probabilities: Mapping[Labels, float], k: int) -> list[tuple[Labels, float]]:
    """The k most probable topologies, most probable first (ties broken by labels)."""
    return sorted(probabilities.items(), key=lambda kv: (-kv[1], kv[0]))[:k]


def as_array(labels: Labels) -> NDArray[np.int64]:
    """Labels as an integer array (for vectorised scoring)."""
    return np.asarray(labels, dtype=np.int64)
