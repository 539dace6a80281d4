"""Priors over topologies: normalisation over all partitions, sequential form, closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import logsumexp

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.model.partitions import enumerate_partitions, num_places, stirling2
from ptm_ros.model.priors import (
    DirichletProcessPrior,
    OccupancyPrior,
    PriorConfig,
    YuleSimonPrior,
    make_prior,
)

PRIORS = [
    DirichletProcessPrior(0.7),
    DirichletProcessPrior(3.0),
    YuleSimonPrior(0.25),
    OccupancyPrior(rate=6.0, max_places=40),
    OccupancyPrior(rate=2.5, max_places=4),  # truncation below N: topologies with M > 4 get 0
]


@pytest.mark.parametrize("prior", PRIORS, ids=repr)
@pytest.mark.parametrize("n", [1, 2, 5, 8])
def test_prior_sums_to_one_over_all_partitions(prior, n):
    lp = np.array([prior.log_prob(p) for p in enumerate_partitions(n)])
    assert math.isclose(float(logsumexp(lp)), 0.0, abs_tol=1e-10)


def sequential_log_prob(prior, labels):
    total, counts = 0.0, []
    for lab in labels:
        lp = prior.log_predictive(counts)
        assert math.isclose(float(logsumexp(lp)), 0.0, abs_tol=1e-12)  # a distribution at each step
        total += lp[lab]
        if lab == len(counts):
            counts.append(0)
        counts[lab] += 1
    return total


@pytest.mark.parametrize("prior", PRIORS, ids=repr)
def test_sequential_form_multiplies_out_to_the_joint(prior):
    """Every partition of 6 visits (B_6 = 203): up to 6 places, past the truncated occupancy's 4."""
    for labels in enumerate_partitions(6):
        if prior.log_prob(labels) == -math.inf:  # truncated occupancy: more places than L_max
            try:  # either the step opening place L_max + 1 has probability 0 or a later step refuses
                assert sequential_log_prob(prior, labels) == -math.inf
            except ModelError as err:
                assert "max_places" in str(err)
            continue
        assert math.isclose(sequential_log_prob(prior, labels), prior.log_prob(labels), abs_tol=1e-9)


def test_dirichlet_closed_form_by_hand():
    # (0, 1, 0, 0): alpha^2 * 2! * 0! / (a (a+1) (a+2) (a+3))
    a = 1.5
    expected = a**2 * 2 / (a * (a + 1) * (a + 2) * (a + 3))
    assert math.isclose(math.exp(DirichletProcessPrior(a).log_prob((0, 1, 0, 0))), expected)


def test_yule_simon_by_hand():
    u = 0.2
    # (0, 1, 0, 2): new(u), revisit one of 2 ((1-u)/2), new (u)
    expected = u * (1 - u) / 2 * u
    assert math.isclose(math.exp(YuleSimonPrior(u).log_prob((0, 1, 0, 2))), expected)


def test_occupancy_matches_direct_sum_over_L():
    rate, lmax, n = 4.0, 30, 6
    prior = OccupancyPrior(rate, lmax)
    L = np.arange(1, lmax + 1)
    pois = np.array([rate**k * math.exp(-rate) / math.factorial(k) for k in L])
    pois /= pois.sum()
    for labels in [(0,) * 6, (0, 1, 2, 3, 4, 5), (0, 1, 0, 2, 1, 0)]:
        m = num_places(labels)
        direct = sum(p * math.perm(int(k), m) / float(k) ** n for k, p in zip(L, pois, strict=True) if k >= m)
        assert math.isclose(math.exp(prior.log_prob(labels)), direct, rel_tol=1e-10)
    # eq. 5: P(M) summed over topologies = C(L, M) L^-N M! S(N, M) for a point mass on L
    point = OccupancyPrior(rate=1e-9, max_places=1)  # L = 1 only
    assert math.isclose(math.exp(point.log_prob((0,) * n)), 1.0)
    assert point.log_prob((0, 1, 0, 0, 0, 0)) == -math.inf
    assert stirling2(n, 1) == 1


def test_prior_config_validation():
    with pytest.raises(ConfigError, match="one of"):
        PriorConfig(kind="uniform")
    with pytest.raises(ConfigError, match="alpha"):
        PriorConfig(kind="dirichlet", alpha=0.0)
    with pytest.raises(ConfigError, match="u must"):
        PriorConfig(kind="yule-simon", u=1.0)
    assert isinstance(make_prior(PriorConfig(kind="occupancy", rate=3.0)), OccupancyPrior)


def test_non_canonical_labels_rejected():
    with pytest.raises(ModelError, match="canonical"):
        DirichletProcessPrior().log_prob((1, 0))
    with pytest.raises(ModelError, match="counts"):
        DirichletProcessPrior().log_predictive([0, 2])
