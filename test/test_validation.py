"""ptm_ros.io.validation: the message checks shared by the bag reader and the nodes."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest

from ptm_ros.io.validation import header_stamp_ns, scan_payload, stamp_order


def earliest_longest_increasing(stamps: list[int]) -> list[int]:
    """Brute force: the indices of the longest strictly increasing subsequence, the lexicographically
    smallest of equally long ones (combinations come in lexicographic order)."""
    for size in range(len(stamps), 0, -1):
        for pick in itertools.combinations(range(len(stamps)), size):
            if all(stamps[a] < stamps[b] for a, b in itertools.pairwise(pick)):
                return list(pick)
    return []


def test_stamp_order_keeps_the_earliest_longest_increasing_run_against_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(300):
        n = int(rng.integers(0, 10))
        stamps = [int(v) for v in rng.integers(0, 6, size=n)]
        kept, reasons = stamp_order(stamps)
        assert kept == earliest_longest_increasing(stamps)
        assert len(reasons) == n - len(kept)
        dropped = [i for i in range(n) if i not in set(kept)]
        for i, reason in zip(dropped, reasons, strict=True):
            before = [stamps[k] for k in kept if k < i]
            after = [stamps[k] for k in kept if k > i]
            if before and stamps[i] == before[-1]:
                assert reason == "duplicate"
            elif before and stamps[i] < before[-1]:
                assert reason == "stamp-backwards"
            else:
                assert reason == "outlier" and after and stamps[i] >= after[0]


def test_stamp_order_on_the_issue_cases():
    clean = list(range(100))
    back = clean[:50] + [s - 40 for s in clean[50:60]] + clean[60:]  # ten stamped back
    kept, reasons = stamp_order(back)
    assert len(kept) == 90 and reasons == ["stamp-backwards"] * 10
    dup = [*clean[:30], 29, *clean[30:]]
    kept, reasons = stamp_order(dup)
    assert [dup[k] for k in kept] == clean and reasons == ["duplicate"]
    ahead = [*clean[:30], 10_000, *clean[30:]]  # a lone message far ahead costs itself only
    kept, reasons = stamp_order(ahead)
    assert [ahead[k] for k in kept] == clean and reasons == ["outlier"]
    early = [*clean[:30], 25, *clean[30:]]  # one stamped a little back: it goes, not its predecessor
    kept, reasons = stamp_order(early)
    assert [early[k] for k in kept] == clean and reasons == ["stamp-backwards"]


def scan(ranges, amin=0.0, ainc=0.1, rmin=0.0, rmax=10.0):
    r = np.asarray(ranges, dtype=np.float32)
    return SimpleNamespace(
        ranges=r, angle_min=amin, angle_max=amin + (r.size - 1) * ainc, angle_increment=ainc,
        range_min=rmin, range_max=rmax,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("ranges", "reason"),
    [
        ([], "scan-empty"),
        ([math.nan] * 5, "scan-non-finite"),
        ([math.inf] * 5, "scan-non-finite"),
        ([math.nan, -math.inf, math.inf], "scan-non-finite"),
    ],
)
def test_empty_and_non_finite_scans_are_rejected(ranges, reason):
    payload, rejected = scan_payload(scan(ranges))
    assert payload is None and rejected[0] == reason


def test_a_scan_with_one_finite_range_is_used():
    payload, rejected = scan_payload(scan([math.nan, 2.0, math.inf]))
    assert rejected is None and payload[0].tolist()[1] == 2.0


@pytest.mark.parametrize(
    ("sec", "nanosec", "ns"), [(0, 0, 0), (3, 5, 3_000_000_005), (-1, 0, None), (1, 10**9, None)]
)
def test_header_stamp_ns(sec, nanosec, ns):
    header = SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec))
    assert header_stamp_ns(header) == ns
