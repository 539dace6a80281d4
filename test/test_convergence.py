"""Tests of ptm_ros.inference.convergence: SRQ points against hand-computed cases and the renewal theory."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.stats import kstwobign

from ptm_ros.errors import DataError
from ptm_ros.inference.convergence import most_visited, regeneration_times, srq_deviation, srq_points

# P(sup |Brownian bridge| > LAMBDA) = 1e-6 (Kolmogorov distribution).
LAMBDA = float(kstwobign.isf(1e-6))


def markov_chain(P: NDArray[np.float64], n: int, rng: np.random.Generator, start: int = 0) -> list[int]:
    """``n`` states of the chain with transition matrix ``P`` after ``start``."""
    cdf = np.cumsum(P, axis=1)
    cdf[:, -1] = 1.0
    u = rng.random(n)
    out = []
    s = start
    for t in range(n):
        s = int(np.searchsorted(cdf[s], u[t], side="right"))
        out.append(s)
    return out


def return_time_moments(P: NDArray[np.float64], atom: int) -> tuple[float, float]:
    """``E[τ]`` and ``E[τ²]`` of the return time ``τ`` to ``atom`` (first-step analysis).

    Hitting times ``H_i`` of the atom (``H_atom = 0``): ``h = E H`` solves ``h_i = 1 + Σ_j P_ij h_j`` and
    ``g = E H²`` solves ``g_i = 1 + 2 Σ_j P_ij h_j + Σ_j P_ij g_j`` over ``i ≠ atom``; ``τ = 1 + H_J``,
    ``J ~ P(atom, ·)``.
    """
    k = P.shape[0]
    rest = [i for i in range(k) if i != atom]
    A = np.eye(len(rest)) - P[np.ix_(rest, rest)]
    h = np.zeros(k)
    h[rest] = np.linalg.solve(A, np.ones(len(rest)))
    g = np.zeros(k)
    g[rest] = np.linalg.solve(A, 1.0 + 2.0 * P[rest] @ h)
    return 1.0 + P[atom] @ h, 1.0 + 2.0 * P[atom] @ h + P[atom] @ g


def srq_bound(cv: float, r: int) -> float:
    """Deviation a stationary chain exceeds with probability ~1e-6: ``λ·CV/√R`` (module docstring) plus
    ``2/R`` for the discreteness and the first tour (from the start, not from the atom)."""
    return LAMBDA * cv / math.sqrt(r) + 2.0 / r


def test_hand_computed_points() -> None:
    states = ["a", "b", "a", "a", "c", "a"]
    assert most_visited(states) == "a"
    assert regeneration_times(states, "a").tolist() == [1, 3, 4, 6]
    x, y = srq_points(states)
    assert x.tolist() == [0.25, 0.5, 0.75, 1.0]
    assert y == pytest.approx([1 / 6, 3 / 6, 4 / 6, 1.0])
    assert srq_deviation(x, y) == pytest.approx(0.25 - 1 / 6)
    x, y = srq_points(states, atom="b")  # one regeneration: the single point (1, 1)
    assert x.tolist() == [1.0] and y.tolist() == [1.0]
    # label tuples as states; a late first visit (burn-in away from the atom) is a first vertical jump
    topo = [(0, 1, 2), (0, 1, 2), (0, 1, 2), (0, 0, 1), (0, 1, 0), (0, 0, 1), (0, 0, 1), (0, 0, 1)]
    assert most_visited(topo) == (0, 0, 1)  # 4 visits against 3
    x, y = srq_points(topo)
    assert x.tolist() == [0.25, 0.5, 0.75, 1.0]
    assert y == pytest.approx([4 / 8, 6 / 8, 7 / 8, 1.0])
    assert srq_deviation(x, y) == pytest.approx(0.25)


def test_ties_and_brute_force_times() -> None:
    assert most_visited(["b", "a", "b", "a"]) == "b"  # equal counts: the first reached
    assert most_visited([3, 1, 1, 3]) == 3
    rng = np.random.default_rng(5)
    seq = rng.integers(0, 4, 500)
    atom = most_visited(seq.tolist())
    counts = np.bincount(seq, minlength=4)
    assert counts[atom] == counts.max()
    times = np.flatnonzero(seq == atom) + 1
    assert regeneration_times(seq.tolist(), atom).tolist() == times.tolist()
    x, y = srq_points(seq.tolist())
    assert x == pytest.approx(np.arange(1, len(times) + 1) / len(times))
    assert y == pytest.approx(times / times[-1])
    assert np.all(np.diff(y) > 0.0) and y[-1] == 1.0


def test_iid_sequence_stays_near_the_diagonal() -> None:
    p = np.array([0.5, 0.3, 0.2])
    seq = np.random.default_rng(1).choice(3, size=20000, p=p).tolist()
    x, y = srq_points(seq)
    assert most_visited(seq) == 0
    # tours are geometric(p0): CV = sqrt(1 - p0)
    bound = srq_bound(math.sqrt(1.0 - p[0]), len(x))
    assert bound < 0.025
    assert srq_deviation(x, y) < bound


def test_well_mixing_markov_chain_stays_near_the_diagonal() -> None:
    P = np.array([[0.6, 0.25, 0.15], [0.4, 0.4, 0.2], [0.3, 0.3, 0.4]])
    w, v = np.linalg.eig(P.T)
    pi = np.real(v[:, np.argmax(np.real(w))])
    pi /= pi.sum()
    assert np.argmax(pi) == 0 and pi[0] > pi[1] + 0.1  # a clear mode: the default atom is state 0
    m1, m2 = return_time_moments(P, 0)
    assert m1 == pytest.approx(1.0 / pi[0])  # Kac's formula checks the first-step analysis
    cv = math.sqrt(m2 - m1**2) / m1
    seq = markov_chain(P, 20000, np.random.default_rng(2))
    assert most_visited(seq) == 0
    x, y = srq_points(seq)
    tours = np.diff(regeneration_times(seq, 0))
    assert tours.mean() == pytest.approx(m1, abs=5.0 * math.sqrt(m2 - m1**2) / math.sqrt(tours.size))
    bound = srq_bound(cv, len(x))
    assert bound < 0.04
    assert srq_deviation(x, y) < bound


def test_chain_stuck_in_half_the_space_deviates() -> None:
    # first half in {0, 1, 2} only, second half over {0, ..., 5}
    n = 40000
    rng = np.random.default_rng(3)
    seq = np.concatenate([rng.integers(0, 3, n // 2), rng.integers(0, 6, n // 2)]).tolist()
    atom = most_visited(seq)
    assert atom in (0, 1, 2)
    x, y = srq_points(seq)
    # the atom is visited at rate 1/3, then 1/6: at the end of the first half x ≈ 2/3, y ≈ 1/2
    # (binomial spread of x there ≈ 0.005; the SRQ of a mixing chain stays within ~0.02)
    assert srq_deviation(x, y) > 0.14
    # an atom of the other half: first visit after n/2, so y_1 > 1/2 while x_1 = 1/R
    x, y = srq_points(seq, atom=3)
    assert y[0] > 0.5 and x[0] < 0.001
    assert srq_deviation(x, y) > 0.49


def test_errors() -> None:
    with pytest.raises(DataError, match="no states"):
        srq_points([])
    with pytest.raises(DataError, match="never visits the atom"):
        srq_points([1, 2, 1], atom=7)
    with pytest.raises(DataError, match="hashable"):
        srq_points([[0, 1], [0, 0]])
    with pytest.raises(DataError, match="cannot compare"):
        regeneration_times([np.zeros(2), np.ones(2)], np.zeros(2))
    with pytest.raises(DataError, match="equal non-empty"):
        srq_deviation([0.5, 1.0], [1.0])
    with pytest.raises(DataError, match="equal non-empty"):
        srq_deviation([], [])
