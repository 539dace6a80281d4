r"""Mixing diagnostics of an MCMC chain: the scaled regeneration quantile (SRQ) plot (thesis Ch. 3.6).

A Markov chain *regenerates* each time it is in an atom state ``a``: the future after such a time is
independent of the past and distributed alike, so the stretches between regenerations (*tours*) are
i.i.d. (Mykland, Tierney & Yu 1995, "Regeneration in Markov chain samplers", JASA 90). For a discrete
state space such as topologies any single state is an atom. Let ``T_1 < … < T_R`` be the regeneration
times of a run (the 1-based positions ``t`` with ``X_t = a``). The SRQ plot shows

.. math::
    \Big(\frac{i}{R},\ \frac{T_i}{T_R}\Big), \qquad i = 1, …, R,

the visit times against the visit count, both scaled to unity (thesis Ch. 3.6, Fig. 42). With i.i.d.
tours of mean ``μ`` and standard deviation ``σ``, ``T_i ≈ iμ + σ W_i`` and

.. math::
    \frac{T_i}{T_R} - \frac{i}{R} \approx \frac{σ}{μ \sqrt{R}}\, B\Big(\frac{i}{R}\Big),

``B`` a Brownian bridge: a chain at stationarity gives points within ``O(σ/(μ\sqrt R))`` of the
diagonal. Long tours away from the atom (the chain trapped elsewhere) show as vertical segments, long
stays near the atom as horizontal ones; :func:`srq_deviation` is the largest distance ``max |y - x|``.

Choices (the thesis gives only the verbal definition above, which this follows):

* every time index at the atom counts, a repeat of the atom (a rejected move) included: each is a
  regeneration of the sampled chain, and a thinned chain (every ``k``-th state) is again a Markov chain
  with the same atom, so thinning keeps the plot valid;
* times are counted from the start of the run (``T_1`` may be large: a burn-in away from the atom shows
  as a first vertical segment); the part after the last regeneration is not shown (``T_R`` scales);
* the default atom is the most visited state (ties: the one reached first), the "high probability"
  state the thesis recommends so that ``R`` is large.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import DataError
from ptm_ros.model.geometry import FloatArray

__all__ = ["most_visited", "regeneration_times", "srq_deviation", "srq_points"]


def most_visited(states: Sequence[Hashable]) -> Hashable:
    """The most frequent state of a chain (ties: the one that occurs first)."""
    if len(states) == 0:
        msg = "the chain has no states"
        raise DataError(msg)
    try:
        counts = Counter(states)
    except TypeError as err:
        msg = f"chain states must be hashable (e.g. label tuples, not lists or arrays): {err}"
        raise DataError(msg) from err
    return counts.most_common(1)[0][0]  # equal counts keep the order first encountered


def regeneration_times(states: Sequence[Hashable], atom: Hashable) -> NDArray[np.int64]:
    """``(R,)`` regeneration times ``T_i``: the 1-based positions ``t`` with ``states[t-1] == atom``."""
    try:
        hits = [t for t, s in enumerate(states, start=1) if s == atom]
    except (TypeError, ValueError) as err:
        msg = f"cannot compare chain states with the atom {atom!r}: {err}"
        raise DataError(msg) from err
    return np.asarray(hits, dtype=np.int64)


def srq_points(states: Sequence[Hashable], atom: Hashable | None = None) -> tuple[FloatArray, FloatArray]:
    """SRQ plot points ``x = i/R``, ``y = T_i/T_R`` (``i = 1..R``) of a chain's state sequence.

    ``atom`` defaults to :func:`most_visited` (pass it explicitly to compare several chains at one
    state; ``None`` itself cannot be an atom).

    Raises:
        DataError: an empty chain, unhashable states, or an atom the chain never visits.
    """
    if atom is None:
        atom = most_visited(states)
    times = regeneration_times(states, atom)
    if times.size == 0:
        msg = f"the chain ({len(states)} states) never visits the atom {atom!r}"
        raise DataError(msg)
    r = times.size
    x = np.arange(1, r + 1, dtype=float) / r
    y = times.astype(float) / float(times[-1])
    return x, y


def srq_deviation(x: ArrayLike, y: ArrayLike) -> float:
    """Largest distance ``max_i |y_i - x_i|`` of SRQ points from the unit-slope line."""
    xa, ya = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if xa.shape != ya.shape or xa.ndim != 1 or xa.size == 0:
        msg = f"SRQ points need equal non-empty 1-D x and y, got shapes {xa.shape} and {ya.shape}"
        raise DataError(msg)
    return float(np.max(np.abs(ya - xa)))
