"""The one-step predictives of the particle filter's data-driven proposal, for many particles at once
(thesis eq. 39, 42 and 46): the prior's probability of each next label, and the appearance predictive of a
new visit given the visits of each place."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import gammaln

from ptm_ros.errors import ModelError
from ptm_ros.model.appearance import AppearanceModel
from ptm_ros.model.geometry import FloatArray
from ptm_ros.model.priors import DirichletProcessPrior, OccupancyPrior, TopologyPrior, YuleSimonPrior
from ptm_ros.model.visits import Visit


def batch_log_predictive(
    prior: TopologyPrior, counts: ArrayLike, n_places: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """``log P(L_n = k | L^{n-1})`` (eq. 39, 42) for many label histories at once.

    Args:
        prior: the prior over topologies.
        counts: ``(P, cap)`` visits per place of each history (zero-padded beyond its places).
        n_places: ``(P,)`` places of each history (``M_i ≥ 1``).

    Returns:
        ``(P, cap)`` revisit terms (``-inf`` beyond ``M_i``) and ``(P,)`` new-place terms. The priors of
        :mod:`ptm_ros.model.priors` use their closed forms vectorised (equal to their ``log_predictive``); any
        other prior is asked history by history (cached by counts).
    """
    c = np.asarray(counts, dtype=np.intp)
    m = np.asarray(n_places, dtype=np.intp)
    n_hist, cap = c.shape
    valid = np.arange(cap)[None, :] < m[:, None]
    rev = np.full((n_hist, cap), -np.inf)
    if type(prior) is DirichletProcessPrior:  # revisit ∝ visits so far, new ∝ α (eq. 10)
        log_den = np.log(prior.alpha + c.sum(axis=1))
        rev[valid] = (np.log(np.where(valid, c, 1)) - log_den[:, None])[valid]
        return rev, math.log(prior.alpha) - log_den
    if type(prior) is YuleSimonPrior:  # new with probability u, else a known place uniformly (eq. 12)
        rev[valid] = np.broadcast_to(math.log1p(-prior.u) - np.log(m)[:, None], rev.shape)[valid]
        return rev, np.full(n_hist, math.log(prior.u))
    new = np.empty(n_hist)
    cache: dict[object, FloatArray] = {}
    occupancy = type(prior) is OccupancyPrior  # depends on (n, M) only
    totals = c.sum(axis=1)
    for i in range(n_hist):
        key = (totals[i], m[i]) if occupancy else c[i, : m[i]].tobytes()
        pred = cache.get(key)
        if pred is None:
            pred = np.asarray(prior.log_predictive(c[i, : m[i]]), dtype=float)
            if pred.shape != (m[i] + 1,):
                msg = f"the prior's log_predictive returned shape {pred.shape} for {m[i]} places"
                raise ModelError(msg)
            cache[key] = pred
        rev[i, : m[i]] = pred[: m[i]]
        new[i] = pred[m[i]]
    return rev, new


def block_log_predictives(
    new: int, blocks: Sequence[tuple[int, ...]], visits: Sequence[Visit], model: AppearanceModel
) -> FloatArray:
    """``log p(a_new | a_block)`` (eq. 46) for many non-empty blocks at once, ``(B,)``.

    Equal to :func:`~ptm_ros.model.appearance.appearance_log_predictive` block by block (tested), vectorised
    over the blocks with the same closed forms: the NIG Student-t predictive (eq. 25–28 corrected, see
    :func:`~ptm_ros.model.appearance.log_predictive_nig`) and the Pólya predictive of word counts (eq. 54–57,
    :func:`~ptm_ros.model.appearance.log_predictive_dcm`). Block sufficient statistics come from one
    ``np.add.reduceat`` over the concatenated blocks; visits without a measurement (missing) add
    nothing, and a visit ``new`` without one gets 0. The measurements of visit ``new`` must have been
    validated (e.g. by ``appearance_log_predictive(new, (), …)``); earlier visits' were when they arrived.
    """
    if not blocks:
        return np.zeros(0)
    sizes = np.array([len(b) for b in blocks], dtype=np.intp)
    if np.any(sizes == 0):
        msg = "block_log_predictives needs non-empty blocks (a new place: appearance_log_predictive)"
        raise ModelError(msg)
    flat = np.fromiter((i for b in blocks for i in b), dtype=np.intp, count=int(sizes.sum()))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    out = np.zeros(len(blocks))
    if model.nig is not None and visits[new].signature is not None:
        prior = model.nig
        have = np.array([visits[i].signature is not None for i in flat])
        zero = np.zeros(prior.dim)
        sigs = [visits[i].signature for i in flat]
        rows = np.array([zero if g is None else np.asarray(g, dtype=float) for g in sigs])
        rows = rows.reshape(len(flat), -1)
        a = np.asarray(visits[new].signature, dtype=float)
        total = np.add.reduceat(rows, starts, axis=0)
        total_sq = np.add.reduceat(rows * rows, starts, axis=0)
        cnt = np.add.reduceat(have.astype(float), starts)[:, None]  # visits with a signature per block
        kappa_n = prior.kappa + cnt
        alpha_n = prior.alpha + 0.5 * cnt
        mean = np.divide(total, cnt, out=np.zeros_like(total), where=cnt > 0)
        scatter = np.maximum(total_sq - total * mean, 0.0)
        beta_n = prior.beta + 0.5 * (scatter + prior.kappa * cnt / kappa_n * np.square(mean - prior.mu))
        mu_n = (prior.kappa * prior.mu + total) / kappa_n
        nu = 2.0 * alpha_n
        scale_sq = beta_n * (kappa_n + 1.0) / (alpha_n * kappa_n)
        out += np.sum(
            gammaln(0.5 * (nu + 1.0))
            - gammaln(0.5 * nu)
            - 0.5 * np.log(nu * np.pi * scale_sq)
            - 0.5 * (nu + 1.0) * np.log1p(np.square(a - mu_n) / (nu * scale_sq)),
            axis=1,
        )
    if model.dcm_alpha is not None and visits[new].words is not None:
        alpha = model.dcm_alpha
        x = np.asarray(visits[new].words, dtype=float)
        none = np.zeros(alpha.size)
        words = np.array(
            [none if visits[i].words is None else np.asarray(visits[i].words, dtype=float) for i in flat]
        ).reshape(len(flat), -1)
        post = alpha + np.add.reduceat(words, starts, axis=0)  # (B, V)
        nz = x > 0
        m = float(x.sum())
        a_sum = post.sum(axis=1)
        out += (
            gammaln(m + 1.0)
            - float(np.sum(gammaln(x[nz] + 1.0)))
            + gammaln(a_sum)
            - gammaln(m + a_sum)
            + np.sum(gammaln(x[nz] + post[:, nz]) - gammaln(post[:, nz]), axis=1)
        )
    return out
