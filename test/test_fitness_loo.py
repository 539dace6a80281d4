"""The alias test and the pooling of ε of ``bench/bench_fitness_loo.py`` (the leave-one-run-out fit of
``OdometryConfig.registration_outlier``)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_fitness_loo import ALIAS_XY, ALIAS_YAW, SIMULATED, is_alias, pooled_outlier

TRUE = (1.0, -0.5, 2.0)


@pytest.mark.parametrize(
    ("measured", "alias"),
    [
        (TRUE, False),
        ((1.0 + 0.9 * ALIAS_XY, -0.5, 2.0), False),
        ((1.0 + 0.8 * ALIAS_XY, -0.5 - 0.8 * ALIAS_XY, 2.0), True),  # each axis within, the distance not
        ((1.0, -0.5, 2.0 - 0.9 * ALIAS_YAW), False),
        ((1.0, -0.5, 2.0 + 1.1 * ALIAS_YAW), True),
        ((1.0, -0.5, 2.0 + math.pi), True),  # the symmetric alias: turned by π
        ((1.0, -0.5, 2.0 - 2.0 * math.pi + 0.1), False),  # the heading error is wrapped
    ],
)
def test_is_alias(measured, alias):
    assert is_alias(measured, TRUE) is alias


def test_pooled_outlier_sums_the_training_runs_and_the_simulated_share():
    counts = {
        "a": {"valid": 90, "aliases": 2},
        "b": {"valid": 20, "aliases": 6},
        "c": {"valid": 10, "aliases": 1},
        SIMULATED: {"valid": 20, "aliases": 7},
    }
    loo = pooled_outlier(counts, ["a", "b"])
    assert loo == {"registration_outlier": 15 / 130, "aliases": 15, "valid": 130}
    assert pooled_outlier(counts, ["a", "b", "c"])["registration_outlier"] == 16 / 140
    del counts[SIMULATED]
    assert pooled_outlier(counts, ["b", "c"])["registration_outlier"] == 7 / 30
    with pytest.raises(ValueError, match="no valid"):
        pooled_outlier({"a": {"valid": 0, "aliases": 0}}, ["a"])
