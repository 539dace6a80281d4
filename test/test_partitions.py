"""Set partitions: counts against known sequences, enumeration, uniform sampling."""

from __future__ import annotations

from collections import Counter
from itertools import product

import numpy as np
import pytest
from scipy.stats import chi2

from ptm_ros.errors import ModelError
from ptm_ros.model.partitions import (
    bell,
    blocks,
    canonical,
    enumerate_partitions,
    from_blocks,
    is_canonical,
    num_places,
    random_partition,
    stirling2,
)

# OEIS A000110 and rows of A008277
BELL = [1, 1, 2, 5, 15, 52, 203, 877, 4140, 21147, 115975, 678570, 4213597]


def test_bell_numbers_match_known_sequence():
    assert [bell(n) for n in range(13)] == BELL
    assert bell(20) == 51724158235372  # quoted in thesis Ch. 1.4


def test_stirling_rows_and_recursion():
    assert [stirling2(5, k) for k in range(6)] == [0, 1, 15, 25, 10, 1]
    assert [stirling2(7, k) for k in range(1, 8)] == [1, 63, 301, 350, 140, 21, 1]
    for n in range(1, 25):
        for k in range(1, n + 1):
            assert stirling2(n, k) == stirling2(n - 1, k - 1) + k * stirling2(n - 1, k)
    # exact big integers, no float overflow
    assert stirling2(100, 50) == stirling2(99, 49) + 50 * stirling2(99, 50)
    assert stirling2(100, 50) > 10**100


def brute_force_partitions(n):
    """All canonical forms of all n^n label assignments (independent of the recursive enumerator)."""
    return {canonical(a) for a in product(range(n), repeat=n)}


@pytest.mark.parametrize("n", range(7))
def test_enumeration_is_complete_unique_and_canonical(n):
    parts = list(enumerate_partitions(n))
    assert len(parts) == BELL[n] == len(set(parts))
    assert all(is_canonical(p) for p in parts)
    assert set(parts) == (brute_force_partitions(n) if n else {()})


def test_enumeration_counts_by_places_equal_stirling():
    counts = Counter(num_places(p) for p in enumerate_partitions(9))
    assert counts == {k: stirling2(9, k) for k in range(1, 10)}


def test_enumeration_limit():
    with pytest.raises(ModelError, match="limited"):
        next(enumerate_partitions(13))


def test_canonical_blocks_round_trip():
    assert canonical([5, 3, 5, 9, 3]) == (0, 1, 0, 2, 1)
    assert not is_canonical((1, 0))
    assert not is_canonical((0, 2))
    lab = (0, 1, 0, 2, 1)
    assert blocks(lab) == [(0, 2), (1, 4), (3,)]
    assert from_blocks(blocks(lab), 5) == lab
    with pytest.raises(ModelError, match="cover"):
        from_blocks([(0,), (2,)], 3)
    with pytest.raises(ModelError, match="partition"):
        from_blocks([(0, 1), (1, 2)], 3)


def test_random_partition_is_uniform():
    """Chi-square goodness of fit over all 52 partitions of 5 items (p-value threshold 1e-4)."""
    rng = np.random.default_rng(7)
    draws = 52 * 400
    counts = Counter(random_partition(5, rng) for _ in range(draws))
    parts = list(enumerate_partitions(5))
    assert set(counts) == set(parts)
    obs = np.array([counts[p] for p in parts])
    stat = float(np.sum((obs - 400) ** 2 / 400))
    assert chi2.sf(stat, df=51) > 1e-4


def test_random_partition_large_n_is_valid_and_seeded():
    a = random_partition(200, np.random.default_rng(1))
    b = random_partition(200, np.random.default_rng(1))
    assert a == b and is_canonical(a) and len(a) == 200
    # typical number of blocks of a uniform partition of 200 items is near 200/log(200) ≈ 38–60
    assert 25 < num_places(a) < 80
