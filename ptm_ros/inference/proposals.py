r"""Proposal kernels of the MCMC sampler over set partitions (thesis Ch. 3.2–3.4, Algorithms 2, 3 and 10,
App. C): split–merge moves drawn uniformly or driven by the odometry and the appearance, a move of one visit
(reassign, not in the thesis), and their mixture; each move returns its proposal ratio for the
Metropolis–Hastings acceptance of :mod:`ptm_ros.inference.mcmc` (settings: its ``McmcConfig``).

Split–merge proposals (Algorithm 2, 3, 10)
------------------------------------------
Every proposal here has one skeleton. From ``T`` with ``M`` blocks, ``N_S`` of them non-singletons:

* with probability ½ a *merge*: if ``M < 2`` re-propose ``T``; else pick the pair of blocks
  ``{R, S}`` with probability ``π_M(R, S | T)`` and merge them;
* with probability ½ a *split*: if ``N_S = 0`` re-propose ``T``; else pick a non-singleton block ``U``
  uniformly (``1/N_S``), then one of its ``S(|U|, 2) = 2^{|U|-1} - 1`` two-block splits ``{R, S}`` with
  probability ``π_S(R, S | U)``.

A merge and a split never produce the same ``T'`` (they change ``M`` by ∓1) and different choices give
different ``T'``, so for the merge ``T → T'`` of ``R, S`` into ``U = R ∪ S`` (``N'_S`` counted in ``T'``)

.. math::
    q(T → T') = ½\,π_M(R, S \mid T), \qquad q(T' → T) = ½\,\frac{1}{N'_S}\,π_S(R, S \mid U),

and the split is the same pair read backwards. A re-proposal has ``q(T → T) = q(T → T)``: ratio 1. The
constant ½ / ½ move choice is what makes the "impossible move → re-propose" cases harmless: the
probability of choosing a move type does not depend on the state.

* **Plain split–merge** (Algorithm 2): ``π_M = 1 / \binom{M}{2}``, ``π_S = 1 / S(|U|, 2)``, so
  ``r_merge = \binom{M}{2} / (N'_S\, S(|U|, 2))`` — the printed ``r`` of Algorithm 2 is right.
* **Odometry-driven** (Algorithm 3): ``π_M(R, S | T) ∝ \exp(-d_{RS}^2 / 2s^2)`` over all pairs, ``d_{RS}``
  the distance between the two places' optimised positions under ``T``
  (``terms(T).metric_result.place_positions``; raw odometry means when the model has no odometry term),
  ``s`` = ``McmcConfig.odometry_scale``; splits are plain. As printed, Algorithm 3 picks merges with
  probability ``N_M/(N_M+N_S)`` but then sets ``Q(T → T'_{RS}) = \exp(-D^2/σ^2)/(N_M+N_S)``, which does
  not sum to the merge probability, and its ``r`` drops the normaliser ``Σ_{R'S'} \exp(-D^2/σ^2)``; it is
  only a valid kernel when the missing mass is read as "re-propose ``T``" (a thinned uniform move). Here
  the merge distribution is normalised and the normaliser enters ``r`` (computed for ``T`` forward and
  for ``T'`` on the reverse of a split, from ``T'``'s own optimised positions).
* **Appearance-driven** (App. C, Algorithms 9–10): ``B_{ij}`` is the Bhattacharyya coefficient (eq. 91)
  between the appearance distributions of visits ``i`` and ``j`` (:func:`bhattacharyya_similarity`);
  for blocks ``R, S`` let ``inter(R, S)`` = mean ``B`` over pairs across, ``intra(R)`` = mean ``B`` over
  pairs within (1 for a singleton) and ``sep(R, S) = ½(intra(R) + intra(S)) - inter(R, S)`` (Algorithm 9's
  "intra minus inter"). Merges: ``π_M ∝ \exp(-λ\, sep)``; splits: ``π_S ∝ \exp(λ\, sep)`` over all splits
  of ``U``, enumerated for ``|U| ≤`` ``McmcConfig.max_split_enumeration`` (uniform beyond, which is
  again a function of ``U`` only, so the reverse stays exact); ``λ`` = ``McmcConfig.appearance_strength``.
  Algorithm 10's score also sums similarities to every *other* block of ``T``; it is dropped here (it makes
  ``π_S`` depend on all of ``T``) and, as in Algorithm 3, the printed ``r = \exp((D'_2-D'_1)-(D_2-D_1))``
  misses both normalisers and the ``1/N_S`` of the block choice; here they are kept.

Single-visit reassignment (not in the thesis)
---------------------------------------------
Split–merge moves whole blocks: moving one visit between two neighbouring places takes a split and a merge,
through an intermediate state that is often far less probable. The reassign kernel moves it in one step
(the Gibbs move of Dirichlet-process samplers, Neal 2000, with a data-driven conditional instead of the
posterior one). From ``T``: pick a visit ``v`` uniformly; with ``T_{-v}`` the places of the other visits,
move ``v`` to a place ``P`` of ``T_{-v}`` or to a new one with probability
``π_R(P \mid T, v) ∝ \exp(-d_{vP}^2 / 2s^2)``, ``d_{vP}`` the distance between ``v``'s and ``P``'s optimised
positions under ``T`` (a new place weighs as a place at ``McmcConfig.new_place_distance``), mixed with
uniform as below. ``T' ≠ T`` differs from ``T`` only in pairs that involve ``v``; another visit ``u`` gives
the same ``T'`` only when ``\{u, v\}`` is split from, or joined into, a two-visit place. So

.. math::
    q(T → T') = \frac{1}{N} \sum_{v ∈ V(T, T')} π_R(P'_v \mid T, v),

over the one or two movers ``V(T, T')``, and ``q(T' → T)`` the same from ``T'`` with ``T'``'s own optimum.
"auto" adds it whenever the odometry proposal is used.

Data-driven distributions are mixed with the uniform one, ``(1-ε)\,π + ε\,\mathrm{uniform}``
(ε = ``McmcConfig.proposal_mix``), so no move is ever starved by a poor optimum or scale. The
default proposal ("auto") draws each move from one of the data-driven kernels the model supports, chosen
with equal probability; the chosen kernel is part of the move (its reverse uses the same kernel), so that
kernel's own ratio applies — a mixture of π-reversible kernels is π-reversible.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from itertools import combinations
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.special import logsumexp

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.model.appearance import AppearanceModel
from ptm_ros.model.geometry import FloatArray
from ptm_ros.model.partitions import Labels, blocks, canonical, stirling2
from ptm_ros.model.posterior import PosteriorModel
from ptm_ros.model.visits import Visit

if TYPE_CHECKING:
    from ptm_ros.inference.mcmc import McmcConfig

Block = tuple[int, ...]


_LOG_HALF = math.log(0.5)


#: Kernel tables cached per topology / block before the cache is reset.
_CACHE_SIZE = 20_000


class RandomSource(Protocol):
    """Uniform random numbers: :class:`numpy.random.Generator` or the faster :class:`UniformStream`."""

    def random(self) -> float:
        """A uniform number in [0, 1)."""
        ...

    def integers(self, low: int, high: int) -> int:
        """A uniform integer in [low, high)."""
        ...


class UniformStream:
    """Buffered uniforms from a :class:`numpy.random.Generator` (scalar generator calls cost µs each).

    ``integers(low, high)`` is ``low + ⌊u (high - low)⌋`` for ranges up to 2^32 (each value has probability
    ``1/(high-low)`` within 2^-53 relative) and a direct generator draw beyond.
    """

    def __init__(self, rng: np.random.Generator, size: int = 1024) -> None:
        self.rng = rng
        self._size = size
        self._buf: list[float] = []

    def random(self) -> float:
        if not self._buf:
            self._buf = self.rng.random(self._size).tolist()
            self._buf.reverse()
        return self._buf.pop()

    def integers(self, low: int, high: int) -> int:
        span = high - low
        if span <= 1 << 32:
            return low + int(self.random() * span)
        return int(self.rng.integers(low, high))


class Move(NamedTuple):
    """One proposal draw: the proposed topology and log q of the forward and reverse moves."""

    labels: Labels
    log_forward: float
    log_reverse: float
    kind: str  # "merge" | "split" | "stay"

    @property
    def log_ratio(self) -> float:
        """``log q(T' → T) - log q(T → T')``."""
        return self.log_reverse - self.log_forward


class ProposalKernel(Protocol):
    """What the sampler needs from a proposal."""

    name: str

    def propose(self, labels: Labels, rng: RandomSource) -> Move:
        """Draw ``T'`` from ``q(T → ·)`` with both log proposal probabilities."""
        ...

    def log_prob(self, src: Labels, dst: Labels) -> float:
        """``log q(src → dst)`` in closed form (−inf when dst is not one move away)."""
        ...

    def distribution(self, labels: Labels) -> dict[Labels, float]:
        """Every topology ``q(T → ·)`` can reach with its probability, by enumerating all moves."""
        ...


def _pair_index(a: int, b: int, m: int) -> int:
    """Row-major index of the pair ``a < b`` among the ``m(m-1)/2`` pairs (``np.triu_indices(m, 1)``)."""
    return a * (2 * m - a - 1) // 2 + (b - a - 1)


def _split_code(block: Block, other: Sequence[int]) -> int:
    """Code of the split of ``block`` whose half without ``block[0]`` is ``other``: bit j-1 ⇔ block[j]."""
    members = set(other)
    return sum(1 << (j - 1) for j in range(1, len(block)) if block[j] in members)


def _split_halves(block: Block, code: int) -> tuple[Block, Block]:
    """The halves ``(R, S)`` of split ``code`` of ``block``; ``R`` holds ``block[0]``."""
    r = [block[0]]
    s: list[int] = []
    for j in range(1, len(block)):
        (s if code >> (j - 1) & 1 else r).append(block[j])
    return tuple(r), tuple(s)


def _merge_labels(labels: Labels, parts: Sequence[Block], a: int, b: int) -> Labels:
    out = list(labels)
    for i in parts[b]:
        out[i] = a
    return canonical(out)


def _split_labels(labels: Labels, half: Block, new_label: int) -> Labels:
    out = list(labels)
    for i in half:
        out[i] = new_label
    return canonical(out)


def _block_position(parts: Sequence[Block], first: int) -> int:
    """Index of the block whose first visit is ``first`` (blocks are ordered by first visit)."""
    lo, hi = 0, len(parts)
    while lo < hi:
        mid = (lo + hi) // 2
        if parts[mid][0] < first:
            lo = mid + 1
        else:
            hi = mid
    return lo


def _uniform_code(k: int, rng: RandomSource) -> int:
    """A split code of a k-block drawn uniformly from 1 .. 2^{k-1}-1."""
    if k - 1 <= 62:
        return int(rng.integers(1, 1 << (k - 1)))
    while True:  # 31 bits at a time for huge blocks; all-zero codes are redrawn
        code = 0
        for start in range(0, k - 1, 31):
            width = min(31, k - 1 - start)
            code |= int(rng.integers(0, 1 << width)) << start
        if code:
            return code


def _log_num_splits(k: int) -> float:
    return math.log(stirling2(k, 2))


#: A discrete distribution: log probabilities and cumulative probabilities (lists: fast scalar access).
Table = tuple[list[float], list[float]]


def _mixed_table(log_weights: FloatArray, mix: float) -> Table:
    """``log((1-ε) softmax(w) + ε / n)`` over the finite entries and its cumulative probabilities."""
    finite = np.isfinite(log_weights)
    n = int(finite.sum())
    lp = np.full(log_weights.shape, -np.inf)
    w = log_weights[finite]
    soft = w - logsumexp(w)
    lp[finite] = soft if mix == 0.0 else np.logaddexp(math.log1p(-mix) + soft, math.log(mix / n))
    cdf = np.cumsum(np.exp(lp))
    return lp.tolist(), cdf.tolist()


def _log_sum(values: Sequence[float]) -> float:
    """``log Σ exp(values)`` of a few Python floats (no array overhead)."""
    top = max(values)
    if top == -math.inf:
        return top
    return top + math.log(math.fsum(math.exp(x - top) for x in values))


def _draw(cdf: list[float], rng: RandomSource) -> int:
    idx = bisect.bisect_right(cdf, rng.random() * cdf[-1])
    return min(idx, len(cdf) - 1)


class SplitMergeProposal:
    """Algorithm 2: uniform merges of two blocks and uniform two-block splits of a non-singleton block.

    Subclasses change ``π_M`` (:meth:`merge_log_weights`) and ``π_S`` (:meth:`split_log_weights`); the
    move skeleton, the closed-form probabilities and the enumeration are shared.
    """

    name = "split-merge"

    def __init__(self, mix: float = 0.0) -> None:
        if not 0.0 <= mix < 1.0:
            msg = f"proposal mix must be in [0, 1), got {mix}"
            raise ConfigError(msg)
        self.mix = float(mix)
        self._merge_cache: dict[Labels, Table | None] = {}
        self._split_cache: dict[Block, Table | None] = {}
        self._triu: dict[int, tuple[list[int], list[int]]] = {}
        self._parts: dict[Labels, tuple[list[Block], list[Block]]] = {}
        # (labels, a, b) / (labels, first visit of the block, code) -> (new labels, log q of the reverse)
        self._moves: dict[tuple[Labels, int, int], tuple[Labels, float]] = {}

    # -- hooks --------------------------------------------------------------------------------------
    def merge_log_weights(self, labels: Labels, parts: Sequence[Block]) -> FloatArray | None:
        """Unnormalised log weights of merging each pair of blocks (triu order); None = uniform."""
        return None

    def split_log_weights(self, block: Block) -> FloatArray | None:
        """Unnormalised log weights of each split code of ``block`` (entry 0 = −inf); None = uniform."""
        return None

    # -- tables -------------------------------------------------------------------------------------
    def _merge_table(self, labels: Labels, parts: Sequence[Block]) -> Table | None:
        if labels in self._merge_cache:
            return self._merge_cache[labels]
        w = self.merge_log_weights(labels, parts)
        table = None if w is None else _mixed_table(np.asarray(w, dtype=float), self.mix)
        if len(self._merge_cache) >= _CACHE_SIZE:
            self._merge_cache.clear()
        self._merge_cache[labels] = table
        return table

    def _split_table(self, block: Block) -> Table | None:
        if block in self._split_cache:
            return self._split_cache[block]
        w = self.split_log_weights(block)
        table = None if w is None else _mixed_table(np.asarray(w, dtype=float), self.mix)
        if len(self._split_cache) >= _CACHE_SIZE:
            self._split_cache.clear()
        self._split_cache[block] = table
        return table

    def _blocks(self, labels: Labels) -> tuple[list[Block], list[Block]]:
        """The blocks of ``labels`` and its non-singleton blocks (cached)."""
        out = self._parts.get(labels)
        if out is None:
            parts = blocks(labels)
            out = (parts, [p for p in parts if len(p) > 1])
            if len(self._parts) >= _CACHE_SIZE:
                self._parts.clear()
            self._parts[labels] = out
        return out

    def _pairs(self, m: int) -> tuple[list[int], list[int]]:
        """Rows and columns of the pairs ``a < b`` of m blocks, in ``np.triu_indices`` order."""
        pairs = self._triu.get(m)
        if pairs is None:
            rows, cols = np.triu_indices(m, 1)
            pairs = (rows.tolist(), cols.tolist())
            self._triu[m] = pairs
        return pairs

    def _remember(self, key: tuple[Labels, int, int], value: tuple[Labels, float]) -> None:
        if len(self._moves) >= _CACHE_SIZE:
            self._moves.clear()
        self._moves[key] = value

    def log_merge(self, labels: Labels, parts: Sequence[Block], a: int, b: int) -> float:
        """``log q`` of merging blocks ``a < b`` of ``labels`` (blocks ``parts``)."""
        m = len(parts)
        table = self._merge_table(labels, parts)
        if table is None:
            return _LOG_HALF - math.log(m * (m - 1) / 2)
        return _LOG_HALF + table[0][_pair_index(a, b, m)]

    def log_split(self, labels: Labels, block: Block, code: int) -> float:
        """``log q`` of splitting ``block`` (a block of ``labels``) by ``code``."""
        n_split = len(self._blocks(labels)[1])
        table = self._split_table(block)
        lp = -_log_num_splits(len(block)) if table is None else table[0][code]
        return _LOG_HALF - math.log(n_split) + lp

    def _log_stay(self, parts: Sequence[Block]) -> float:
        p = 0.5 * (len(parts) < 2) + 0.5 * all(len(b) == 1 for b in parts)
        return math.log(p) if p > 0.0 else -math.inf

    # -- the kernel ---------------------------------------------------------------------------------
    def propose(self, labels: Labels, rng: RandomSource) -> Move:
        """Draw a merge or a split (½ each); an impossible move re-proposes ``labels``."""
        parts, splittable = self._blocks(labels)
        m = len(parts)
        if rng.random() < 0.5:
            if m < 2:
                return Move(labels, _LOG_HALF, _LOG_HALF, "stay")
            table = self._merge_table(labels, parts)
            if table is None:
                a = int(rng.integers(0, m))
                b = int(rng.integers(0, m - 1))
                b += b >= a
                a, b = min(a, b), max(a, b)
                log_f = _LOG_HALF - math.log(m * (m - 1) / 2)
            else:
                idx = _draw(table[1], rng)
                rows, cols = self._pairs(m)
                a, b = rows[idx], cols[idx]
                log_f = _LOG_HALF + table[0][idx]
            key = (labels, a, b)
            known = self._moves.get(key)
            if known is None:
                new = _merge_labels(labels, parts, a, b)
                union = tuple(sorted(parts[a] + parts[b]))
                known = (new, self.log_split(new, union, _split_code(union, parts[b])))
                self._remember(key, known)
            return Move(known[0], log_f, known[1], "merge")
        if not splittable:
            return Move(labels, _LOG_HALF, _LOG_HALF, "stay")
        block = splittable[int(rng.integers(0, len(splittable)))]
        table = self._split_table(block)
        if table is None:
            code = _uniform_code(len(block), rng)
            lp = -_log_num_splits(len(block))
        else:
            code = _draw(table[1], rng)
            lp = table[0][code]
        log_f = _LOG_HALF - math.log(len(splittable)) + lp
        key = (labels, -1 - block[0], code)  # negative: never equal to a merge key
        known = self._moves.get(key)
        if known is None:
            half_r, half_s = _split_halves(block, code)
            new = _split_labels(labels, half_s, m)
            new_parts = self._blocks(new)[0]
            a = _block_position(new_parts, half_r[0])
            b = _block_position(new_parts, half_s[0])
            known = (new, self.log_merge(new, new_parts, a, b))
            self._remember(key, known)
        return Move(known[0], log_f, known[1], "split")

    def log_prob(self, src: Labels, dst: Labels) -> float:
        """``log q(src → dst)`` in closed form: identify the merge or split that turns src into dst."""
        ps, pd = blocks(src), blocks(dst)
        if src == dst:
            return self._log_stay(ps)
        set_s, set_d = set(ps), set(pd)
        gone = [b for b in ps if b not in set_d]
        new = [b for b in pd if b not in set_s]
        if len(gone) == 2 and len(new) == 1 and set(gone[0]) | set(gone[1]) == set(new[0]):
            a, b = ps.index(gone[0]), ps.index(gone[1])
            return self.log_merge(src, ps, min(a, b), max(a, b))
        if len(gone) == 1 and len(new) == 2 and set(new[0]) | set(new[1]) == set(gone[0]):
            block = gone[0]
            other = new[1] if block[0] in new[0] else new[0]
            return self.log_split(src, block, _split_code(block, other))
        return -math.inf

    def distribution(self, labels: Labels) -> dict[Labels, float]:
        """``q(labels → ·)`` by enumerating every merge and every split (small N only)."""
        parts = blocks(labels)
        m = len(parts)
        out: dict[Labels, float] = {}
        stay = self._log_stay(parts)
        if stay > -math.inf:
            out[labels] = math.exp(stay)
        if m >= 2:
            table = self._merge_table(labels, parts)
            for idx, (a, b) in enumerate(combinations(range(m), 2)):
                lp = -math.log(m * (m - 1) / 2) if table is None else table[0][idx]
                new = _merge_labels(labels, parts, a, b)
                out[new] = out.get(new, 0.0) + 0.5 * math.exp(lp)
        splittable = [p for p in parts if len(p) > 1]
        for block in splittable:
            table = self._split_table(block)
            for code in range(1, 1 << (len(block) - 1)):
                lp = -_log_num_splits(len(block)) if table is None else table[0][code]
                new = _split_labels(labels, _split_halves(block, code)[1], m)
                out[new] = out.get(new, 0.0) + 0.5 / len(splittable) * math.exp(lp)
        return out


def _geometry(
    model: PosteriorModel, labels: Labels, odometry_xy: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``(M, 2)`` place and ``(N, 2)`` visit positions of a topology: at its optimum when the model has a
    metric term, else the raw odometry (places at their visits' mean)."""
    result = model.terms(labels).metric_result
    if result is not None:
        return np.asarray(result.place_positions, dtype=float), np.asarray(result.poses, dtype=float)[:, :2]
    lab = np.asarray(labels)
    m = int(lab.max()) + 1
    counts = np.bincount(lab, minlength=m)[:, None]
    sums = np.stack([np.bincount(lab, weights=odometry_xy[:, k], minlength=m) for k in (0, 1)], 1)
    return sums / counts, odometry_xy


class OdometryProposal(SplitMergeProposal):
    """Algorithm 3: merges weighted by ``exp(-d²/2s²)`` between optimised place positions; plain splits."""

    name = "odometry"

    def __init__(self, model: PosteriorModel, scale: float = 1.0, mix: float = 0.05) -> None:
        super().__init__(mix)
        if not (math.isfinite(scale) and scale > 0.0):
            msg = f"odometry proposal scale must be finite and > 0, got {scale}"
            raise ConfigError(msg)
        self.model = model
        self.scale = float(scale)
        self._odometry_xy = np.array([v.pose[:2] for v in model.visits], dtype=float)

    def place_positions(self, labels: Labels) -> FloatArray:
        """``(M, 2)`` place positions of a topology: optimised (metric term) or raw odometry means."""
        return _geometry(self.model, labels, self._odometry_xy)[0]

    def merge_log_weights(self, labels: Labels, parts: Sequence[Block]) -> FloatArray:
        pos = self.place_positions(labels)
        rows, cols = self._pairs(len(parts))
        d2 = np.sum(np.square(pos[rows] - pos[cols]), axis=1)
        return -0.5 * d2 / self.scale**2


def _neutral_missing(log_bc: FloatArray, have: NDArray[np.bool_]) -> FloatArray:
    """Pairs with a visit lacking the measurement (a missing panorama) get the mean log coefficient of
    the measured pairs: no evidence either way for the proposal."""
    both = have[:, None] & have[None, :]
    np.fill_diagonal(both, False)
    fill = float(np.mean(log_bc[both])) if np.any(both) else 0.0
    return np.where(have[:, None] & have[None, :], log_bc, fill)


def bhattacharyya_similarity(visits: Sequence[Visit], model: AppearanceModel) -> FloatArray:
    """``(N, N)`` Bhattacharyya coefficients (eq. 91) between the visits' appearance distributions.

    * Fourier signatures: visit ``i`` is ``N(a_i, diag σ²)`` with the fitted NIG prior's expected
      within-place variance ``σ_k² = β_k / (α_k - 1)``; per component
      ``BC = exp(-(a_ik - a_jk)² / 8σ_k²)``, geometrically averaged over the ``K`` components (so the scale
      does not depend on the signature length).
    * Word histograms: ``p_i = (x_i + α) / (m_i + α_·)``, the Dirichlet posterior mean of the visit's word
      distribution (defined for empty histograms too); ``BC = Σ_w √(p_iw p_jw)``.

    With both, their geometric mean. 1 on the diagonal. Visits without a measurement (missing
    panoramas) get the mean coefficient of the measured pairs.
    """
    logs = []
    if model.nig is not None:
        have = np.array([v.signature is not None for v in visits])
        zero = np.zeros(model.nig.dim)
        sig = np.array(
            [zero if v.signature is None else np.asarray(v.signature, float).ravel() for v in visits]
        )
        var = model.nig.beta / (model.nig.alpha - 1.0)
        diff = sig[:, None, :] - sig[None, :, :]
        logs.append(_neutral_missing(-np.mean(np.square(diff) / var, axis=2) / 8.0, have))
    if model.dcm_alpha is not None:
        alpha = model.dcm_alpha
        have = np.array([v.words is not None for v in visits])
        x = np.array(
            [np.zeros(alpha.size) if v.words is None else np.asarray(v.words, float).ravel() for v in visits]
        )
        p = (x + alpha) / (x.sum(axis=1, keepdims=True) + alpha.sum())
        root = np.sqrt(p)
        logs.append(_neutral_missing(np.log(np.clip(root @ root.T, 1e-300, 1.0)), have))
    if not logs:
        msg = "the appearance model has neither signatures nor word histograms"
        raise ModelError(msg)
    sim = np.exp(np.mean(logs, axis=0))
    np.fill_diagonal(sim, 1.0)
    return sim


class AppearanceProposal(SplitMergeProposal):
    """App. C, Algorithm 10: merges ``∝ exp(-λ sep)``, splits ``∝ exp(λ sep)`` (Bhattacharyya scores)."""

    name = "appearance"

    def __init__(
        self, model: PosteriorModel, strength: float = 10.0, mix: float = 0.05, max_split_size: int = 12
    ) -> None:
        super().__init__(mix)
        if model.appearance is None:
            msg = "the appearance proposal needs a model with an appearance term (signatures or words)"
            raise ModelError(msg)
        if not (math.isfinite(strength) and strength >= 0.0) or not 2 <= max_split_size <= 20:
            msg = f"appearance proposal needs strength >= 0 and 2 <= max_split_size <= 20, got {strength}"
            raise ConfigError(msg)
        self.strength = float(strength)
        self.max_split_size = int(max_split_size)
        self.similarity = bhattacharyya_similarity(model.visits, model.appearance)
        self._codes: dict[int, NDArray[np.bool_]] = {}

    def merge_log_weights(self, labels: Labels, parts: Sequence[Block]) -> FloatArray:
        m, n = len(parts), len(labels)
        z = np.zeros((m, n))
        z[np.asarray(labels), np.arange(n)] = 1.0
        c = z @ self.similarity @ z.T
        size = z.sum(axis=1)
        intra = np.ones(m)
        big = size > 1
        intra[big] = (np.diag(c)[big] - size[big]) / (size[big] * (size[big] - 1))
        rows, cols = self._pairs(m)
        inter = c[rows, cols] / (size[rows] * size[cols])
        sep = 0.5 * (intra[rows] + intra[cols]) - inter
        return -self.strength * sep

    def split_log_weights(self, block: Block) -> FloatArray | None:
        k = len(block)
        if k > self.max_split_size:
            return None
        members = self._codes.get(k)
        if members is None:  # (2^{k-1}, k): True = in the half without block[0]
            codes = np.arange(1 << (k - 1))
            members = np.zeros((codes.size, k), dtype=bool)
            members[:, 1:] = (codes[:, None] >> np.arange(k - 1)) & 1
            self._codes[k] = members
        s = members[1:].astype(float)
        r = 1.0 - s
        sim = self.similarity[np.ix_(block, block)]
        off = sim - np.eye(k)
        n_s, n_r = s.sum(1), r.sum(1)
        ss = np.einsum("ck,kl,cl->c", s, off, s)
        rr = np.einsum("ck,kl,cl->c", r, off, r)
        rs = np.einsum("ck,kl,cl->c", r, sim, s)
        intra_s = np.where(n_s > 1, ss / np.maximum(n_s * (n_s - 1), 1.0), 1.0)
        intra_r = np.where(n_r > 1, rr / np.maximum(n_r * (n_r - 1), 1.0), 1.0)
        sep = 0.5 * (intra_r + intra_s) - rs / (n_r * n_s)
        return np.concatenate([[-np.inf], self.strength * sep])


class ReassignProposal:
    """One visit moved to another place or to a new one, data-driven by odometry (module docstring).

    Split–merge moves whole blocks; a visit joined to the wrong one of two neighbouring places needs a
    split and a merge, the intermediate state often far less probable. This kernel moves it in one step.
    """

    name = "reassign"

    def __init__(
        self, model: PosteriorModel, scale: float = 1.0, mix: float = 0.05, new_place: float = 2.0
    ) -> None:
        if not (math.isfinite(scale) and scale > 0.0 and 0.0 <= mix < 1.0):
            msg = f"reassign proposal needs scale > 0 and mix in [0, 1), got {scale}, {mix}"
            raise ConfigError(msg)
        if not (math.isfinite(new_place) and new_place > 0.0):
            msg = f"reassign proposal needs new_place > 0 (m), got {new_place}"
            raise ConfigError(msg)
        self.model = model
        self.n = model.n
        self.scale = float(scale)
        self.mix = float(mix)
        self.new_place_log_weight = -0.5 * (new_place / self.scale) ** 2
        self._odometry_xy = np.array([v.pose[:2] for v in model.visits], dtype=float).reshape(-1, 2)
        self._tables: dict[tuple[Labels, int], tuple[list[int], list[float], list[float]]] = {}

    def options(self, labels: Labels, v: int) -> tuple[list[int], list[float]]:
        """The places visit ``v`` may join (labels of the other visits' places; a new place last) and
        their log probabilities ``log π_R(P | T, v)``."""
        rest, lp, _ = self._table(labels, v)
        return rest, lp

    def _table(self, labels: Labels, v: int) -> tuple[list[int], list[float], list[float]]:
        key = (labels, v)
        out = self._tables.get(key)
        if out is None:
            place_xy, visit_xy = _geometry(self.model, labels, self._odometry_xy)
            rest = sorted(set(labels[:v]) | set(labels[v + 1 :]))
            w = np.empty(len(rest) + 1)
            diff = place_xy[rest] - visit_xy[v]
            w[:-1] = np.sum(diff * diff, axis=1) * (-0.5 / self.scale**2)
            w[-1] = self.new_place_log_weight
            out = (rest, *_mixed_table(w, self.mix))
            if len(self._tables) >= _CACHE_SIZE:
                self._tables.clear()
            self._tables[key] = out
        return out

    def _log_q(self, src: Labels, dst: Labels, v: int) -> float:
        """``log q`` of moving ``v`` of ``src`` to its place in ``dst`` (the rest must agree)."""
        rest, lp = self.options(src, v)
        mate = next((u for u in range(self.n) if u != v and dst[u] == dst[v]), None)
        k = len(rest) if mate is None else rest.index(src[mate])
        return lp[k] - math.log(self.n)

    def log_prob(self, src: Labels, dst: Labels) -> float:
        """``log q(src → dst)``: summed over the visits whose move turns ``src`` into ``dst`` (two when a
        pair of visits is split or joined, one otherwise)."""
        if src == dst:
            return _log_sum([self._log_q(src, src, v) for v in range(self.n)])
        s, d = np.asarray(src), np.asarray(dst)
        differ = (s[:, None] == s[None, :]) != (d[:, None] == d[None, :])
        degree = differ.sum(axis=1)
        movers = np.flatnonzero(degree == degree.sum() // 2)
        if not len(movers):
            return -math.inf
        return _log_sum([self._log_q(src, dst, int(v)) for v in movers])

    def propose(self, labels: Labels, rng: RandomSource) -> Move:
        """Pick a visit uniformly and a place for it from :meth:`options`."""
        v = int(rng.integers(0, self.n))
        rest, _, cdf = self._table(labels, v)
        k = _draw(cdf, rng)
        out = list(labels)
        out[v] = rest[k] if k < len(rest) else max(labels) + 1
        new = canonical(out)
        if new == labels:
            return Move(labels, 0.0, 0.0, "stay")
        return Move(new, self.log_prob(labels, new), self.log_prob(new, labels), "reassign")

    def distribution(self, labels: Labels) -> dict[Labels, float]:
        """``q(labels → ·)`` by enumerating every visit and every place it may join."""
        out: dict[Labels, float] = {}
        for v in range(self.n):
            rest, lp = self.options(labels, v)
            for k, target in enumerate([*rest, max(labels) + 1]):
                new = canonical([*labels[:v], target, *labels[v + 1 :]])
                out[new] = out.get(new, 0.0) + math.exp(lp[k]) / self.n
        return out


class MixtureProposal:
    """An equal mixture of proposal kernels: each draw uses one kernel, chosen uniformly.

    The chosen kernel is part of the move (the reverse uses the same kernel), so the acceptance uses that
    kernel's own ratio; :meth:`log_prob` and :meth:`distribution` give the marginal mixture.
    """

    def __init__(self, kernels: Sequence[ProposalKernel]) -> None:
        if not kernels:
            msg = "a mixture proposal needs at least one kernel"
            raise ConfigError(msg)
        self.kernels = tuple(kernels)
        self.name = "+".join(k.name for k in self.kernels)

    def propose(self, labels: Labels, rng: RandomSource) -> Move:
        kernel = (
            self.kernels[int(rng.integers(0, len(self.kernels)))]
            if len(self.kernels) > 1
            else self.kernels[0]
        )
        return kernel.propose(labels, rng)

    def log_prob(self, src: Labels, dst: Labels) -> float:
        return float(logsumexp([k.log_prob(src, dst) for k in self.kernels])) - math.log(len(self.kernels))

    def distribution(self, labels: Labels) -> dict[Labels, float]:
        out: dict[Labels, float] = {}
        for kernel in self.kernels:
            for lab, p in kernel.distribution(labels).items():
                out[lab] = out.get(lab, 0.0) + p / len(self.kernels)
        return out


def make_proposal(model: PosteriorModel, config: McmcConfig) -> ProposalKernel:
    """The proposal kernel ``config.proposal`` describes for ``model``."""
    odometry = config.proposal == "odometry" or (
        config.proposal == "auto" and model.config.use_odometry and model.n > 1
    )
    appearance = config.proposal == "appearance" or (
        config.proposal == "auto" and model.appearance is not None
    )
    reassign = config.proposal == "reassign" or (odometry and config.proposal == "auto")
    kernels: list[ProposalKernel] = []
    if odometry:
        kernels.append(OdometryProposal(model, config.odometry_scale, config.proposal_mix))
    if appearance:
        kernels.append(
            AppearanceProposal(
                model, config.appearance_strength, config.proposal_mix, config.max_split_enumeration
            )
        )
    if reassign and model.n > 1:
        kernels.append(
            ReassignProposal(model, config.odometry_scale, config.proposal_mix, config.new_place_distance)
        )
    if not kernels:
        return SplitMergeProposal()
    return kernels[0] if len(kernels) == 1 else MixtureProposal(kernels)
