"""Topologies as set partitions (thesis Ch. 1.1, 1.4).

A topology of ``N`` landmark visits is a set partition of ``{0, …, N-1}``: visits in one block are
visits of one place. We represent it by its *canonical label sequence* (a restricted growth string):
visit 0 has label 0 and every visit either repeats an earlier label or takes the next unused integer,
e.g. ``(0, 1, 2, 0)`` = ``{{0, 3}, {1}, {2}}``. Two label sequences describe the same topology exactly
when their canonical forms are equal.

The number of partitions of ``n`` visits into ``k`` places is the Stirling number of the second kind
``S(n, k) = S(n-1, k-1) + k S(n-1, k)`` and their total is the Bell number ``B_n = Σ_k S(n, k)``
(thesis Ch. 1.4); both are exact Python integers here.
"""

from __future__ import annotations

import random
from collections.abc import Iterator, Sequence
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import ModelError

Labels = tuple[int, ...]
#: Integers as the functions over labels or visit counts take them: a Python sequence or an integer array.
IntSequence = Sequence[int] | NDArray[np.integer[Any]]

#: Largest N for which :func:`enumerate_partitions` is allowed (B_12 = 4 213 597).
MAX_ENUMERATION = 12


def canonical(labels: Sequence[int]) -> Labels:
    """Relabel a label sequence to its canonical restricted-growth form (first appearance order)."""
    mapping: dict[int, int] = {}
    out = []
    for label in labels:
        if label not in mapping:
            mapping[label] = len(mapping)
        out.append(mapping[label])
    return tuple(out)


def is_canonical(labels: Sequence[int]) -> bool:
    """True when ``labels`` is a restricted growth string (``labels[0] == 0``, each new label = max+1)."""
    top = -1
    for label in labels:
        if label < 0 or label > top + 1:
            return False
        top = max(top, label)
    return True


def num_places(labels: Sequence[int]) -> int:
    """Number of distinct places (blocks) in a topology."""
    return len(set(labels))


def blocks(labels: Sequence[int]) -> list[tuple[int, ...]]:
    """The blocks of a topology as sorted tuples of visit indices, ordered by first visit."""
    out: dict[int, list[int]] = {}
    for i, label in enumerate(labels):
        out.setdefault(label, []).append(i)
    return [tuple(b) for b in out.values()]


def from_blocks(parts: Sequence[Sequence[int]], n: int) -> Labels:
    """Canonical labels of the partition given by ``parts`` (which must cover ``0..n-1`` exactly once)."""
    labels = [-1] * n
    for j, part in enumerate(parts):
        for i in part:
            if not 0 <= i < n or labels[i] != -1:
                msg = f"blocks do not form a partition of {n} visits (index {i})"
                raise ModelError(msg)
            labels[i] = j
    if -1 in labels:
        msg = f"blocks do not cover visit {labels.index(-1)} of {n}"
        raise ModelError(msg)
    return canonical(labels)


@cache
def stirling2(n: int, k: int) -> int:
    """Stirling number of the second kind ``S(n, k)``: partitions of n items into k non-empty blocks."""
    if n < 0 or k < 0:
        msg = f"stirling2 needs n, k >= 0, got ({n}, {k})"
        raise ModelError(msg)
    if n == k:
        return 1
    if k == 0 or k > n:
        return 0
    # iterative row build avoids deep recursion for large n
    row = [1] + [0] * k  # S(0, j)
    for m in range(1, n + 1):
        new = [0] * (k + 1)
        for j in range(1, min(m, k) + 1):
            new[j] = row[j - 1] + j * row[j]
        row = new
    return row[k]


@cache
def bell(n: int) -> int:
    """Bell number ``B_n``: the number of topologies of n visits (B_0 = 1)."""
    if n < 0:
        msg = f"bell needs n >= 0, got {n}"
        raise ModelError(msg)
    return sum(stirling2(n, k) for k in range(n + 1))


def enumerate_partitions(n: int) -> Iterator[Labels]:
    """Yield every topology of ``n`` visits once, as canonical label sequences, in lexicographic order.

    Restricted to ``n <= MAX_ENUMERATION`` (B_12 ≈ 4.2 million); the count equals :func:`bell`.
    """
    if n < 0 or n > MAX_ENUMERATION:
        msg = f"enumeration is limited to 0 <= N <= {MAX_ENUMERATION}, got N = {n}"
        raise ModelError(msg)
    if n == 0:
        yield ()
        return
    labels = [0] * n
    maxes = [0] * n  # maxes[i] = max(labels[:i+1])

    def rec(i: int) -> Iterator[Labels]:
        if i == n:
            yield tuple(labels)
            return
        top = maxes[i - 1]
        for lab in range(top + 2):
            labels[i] = lab
            maxes[i] = max(top, lab)
            yield from rec(i + 1)

    yield from rec(1)


def random_partition(n: int, rng: np.random.Generator) -> Labels:
    """A topology of ``n`` visits drawn uniformly from all ``B_n`` of them.

    Built backwards from the recursion ``S(m, k) = S(m-1, k-1) + k S(m-1, k)``: the number of blocks k
    is drawn with probability ``S(n, k) / B_n``; then, from the last item down, item m opens a block of
    its own with probability ``S(m-1, k-1) / S(m, k)`` or joins one of the k blocks of the rest.
    """
    if n < 0:
        msg = f"random_partition needs n >= 0, got {n}"
        raise ModelError(msg)
    if n == 0:
        return ()
    exact = random.Random(int(rng.integers(0, 2**63)))  # exact big-integer draws, seeded from rng
    u = exact.randrange(bell(n))
    k = 1
    acc = stirling2(n, 1)
    while u >= acc:
        k += 1
        acc += stirling2(n, k)
    assign = [0] * n  # block id per item (not yet canonical)
    for m in range(n, 0, -1):
        # item m-1 among the first m items, which form k blocks
        num = stirling2(m - 1, k - 1)
        den = stirling2(m, k)
        if exact.randrange(den) < num:
            assign[m - 1] = k - 1  # singleton block of its own among the first m items
            k -= 1
        else:
            assign[m - 1] = exact.randrange(k)  # joins one of the k blocks of the first m-1
    return canonical(assign)
