"""Resampling of the particle filter's children (thesis Ch. 3.7, step 3 of :mod:`ptm_ros.inference.rbpf`):
Fearnhead and Clifford's optimal resampling for discrete states, which thins a set of distinct children
to at most ``N`` with unbiased weights, and the deterministic beam it is compared with.

Weights are handled in log space throughout (:func:`logsumexp`); the random generator is passed in.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ModelError
from ptm_ros.model.geometry import FloatArray

#: Indices into the children (and the filter's index arrays).
IntArray = NDArray[np.intp]

#: Resampling schemes: ``optimal`` (Fearnhead–Clifford, unbiased) or ``top`` (keep the heaviest children,
#: a deterministic beam; biased, a baseline).
RESAMPLE_METHODS = ("optimal", "top")


def logsumexp(a: ArrayLike) -> float:
    """``log Σ exp(a)`` of a 1-D array, stable (max subtracted); ``-inf`` when every entry is ``-inf``.

    A lean stand-in for :func:`scipy.special.logsumexp`, whose per-call overhead (~0.1 ms) would be a
    noticeable share of a filter step.
    """
    x = np.asarray(a, dtype=float)
    top = float(np.max(x))
    if not math.isfinite(top):
        return top
    return top + math.log(float(np.sum(np.exp(x - top))))


def _fc_threshold(w_sorted: FloatArray, n: int) -> tuple[int, float]:
    """``(A, c)`` with ``Σ min(w/c, 1) = n``: the ``A`` largest weights are ``≥ c`` (weights sorted
    descending, all > 0, more than ``n`` of them)."""
    tail = np.cumsum(w_sorted[::-1])[::-1]  # tail[a] = Σ_{i ≥ a} w_i
    a = np.arange(n)
    c = tail[:n] / (n - a)
    below = np.flatnonzero(w_sorted[:n] < c)
    # at a = n-1, c = tail > w_{n-1} in exact arithmetic; when the rest is below rounding, a = n-1 anyway
    first = int(below[0]) if len(below) else n - 1
    return first, float(c[first])


def optimal_resample(log_weights: ArrayLike, n: int, rng: np.random.Generator) -> tuple[IntArray, FloatArray]:
    """Fearnhead–Clifford optimal resampling of distinct discrete states (JRSS B 65, 2003).

    With normalised weights ``w`` (from ``log_weights``, ``(K,)``) and ``K > n`` states of positive
    weight, ``c`` solves ``Σ_i min(w_i / c, 1) = n``. States with ``w_i ≥ c`` are kept with their weight;
    the others are resampled systematically (one uniform ``u ~ U[0, c)``, points ``u + j c``) so that
    each is kept with probability ``w_i / c`` (its interval is shorter than ``c``: at most one point
    falls in it, hence no duplicates) and then carries weight ``c``. So ``E[new weight_i] = w_i``
    (unbiased) and the new weights sum to exactly 1. With ``K ≤ n`` every state of positive weight is kept.

    Returns:
        ``(indices, log_new_weights)``: kept indices into ``log_weights`` (ascending) and their
        normalised log weights.

    Raises:
        ModelError: ``n < 1``, NaN or ``+inf`` weights, or no weight > 0.
    """
    lw = _check_log_weights(log_weights, n)
    lw = lw - logsumexp(lw)
    w = np.exp(lw)
    live = np.flatnonzero(w > 0.0)
    if len(live) <= n:
        return live, lw[live]
    order = live[np.argsort(-w[live], kind="stable")]
    kept_count, _ = _fc_threshold(w[order], n)
    kept = order[:kept_count]
    rest = np.sort(order[kept_count:])
    m = n - kept_count
    cum = np.cumsum(w[rest])
    c = float(cum[-1]) / m  # the threshold, recomputed from the same sums the grid walks
    points = rng.uniform(0.0, c) + c * np.arange(m)
    pos = np.minimum(np.searchsorted(cum, points, side="right"), len(rest) - 1)
    chosen = rest[np.unique(pos)]
    idx = np.concatenate([kept, chosen])
    new_lw = np.concatenate([lw[kept], np.full(len(chosen), math.log(c))])
    order_out = np.argsort(idx)
    return idx[order_out], new_lw[order_out]


def thinned_mass(log_weights: ArrayLike, n: int) -> float:
    """The share of the probability that :func:`optimal_resample` keeping ``n`` of ``log_weights`` thins at
    random: the states below its threshold ``c``, each kept with probability ``w / c`` only; 0 when ``n``
    keeps every state of positive weight."""
    return _thinned(_sorted_weights(_check_log_weights(log_weights, n)), n)


def particle_count(log_weights: ArrayLike, n_min: int, n_max: int, max_thinned: float) -> int:
    """How many states :func:`optimal_resample` should keep: the smallest ``n`` in ``[n_min, n_max]``
    whose :func:`thinned_mass` is at most ``max_thinned``, else ``n_max`` (``n_min`` when ``n_max`` is
    below it). The thinned mass falls as ``n`` grows (the threshold ``c`` falls, so more states clear it),
    which makes the smallest such ``n`` a bisection's."""
    if n_max <= n_min:
        return n_min
    w = _sorted_weights(_check_log_weights(log_weights, n_min))
    lo, hi = n_min, min(n_max, len(w))
    if hi <= lo or _thinned(w, lo) <= max_thinned:
        return n_min
    while hi - lo > 1:  # thinned(lo) > max_thinned; thinned(hi) <= max_thinned unless hi is the cap
        mid = (lo + hi) // 2
        if _thinned(w, mid) <= max_thinned:
            hi = mid
        else:
            lo = mid
    return hi


def _sorted_weights(lw: FloatArray) -> FloatArray:
    """The normalised weights of positive value, in descending order."""
    w = np.exp(lw - logsumexp(lw))
    return np.sort(w[w > 0.0])[::-1]


def _thinned(w_sorted: FloatArray, n: int) -> float:
    """:func:`thinned_mass` of normalised weights in descending order."""
    if len(w_sorted) <= n:
        return 0.0
    first, _ = _fc_threshold(w_sorted, n)
    return float(np.sum(w_sorted[first:]))


def top_resample(log_weights: ArrayLike, n: int) -> tuple[IntArray, FloatArray]:
    """Keep the ``n`` heaviest states (ties by index), renormalised: a deterministic, biased beam."""
    lw = _check_log_weights(log_weights, n)
    live = np.flatnonzero(lw > -np.inf)
    idx = np.sort(live[np.argsort(-lw[live], kind="stable")[:n]])
    return idx, lw[idx] - logsumexp(lw[idx])


def _check_log_weights(log_weights: ArrayLike, n: int) -> FloatArray:
    lw = np.asarray(log_weights, dtype=float)
    if lw.ndim != 1 or lw.size == 0:
        msg = f"log weights must be a non-empty 1-D array, got shape {lw.shape}"
        raise ModelError(msg)
    if np.any(np.isnan(lw)) or np.any(lw == np.inf):
        msg = "log weights must not be NaN or +inf"
        raise ModelError(msg)
    if not np.any(np.isfinite(lw)):
        msg = "every state has weight 0"
        raise ModelError(msg)
    if isinstance(n, bool) or n < 1:
        msg = f"the number of states to keep must be >= 1, got {n}"
        raise ModelError(msg)
    return lw
