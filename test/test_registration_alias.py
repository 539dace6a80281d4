"""Valid laser registrations that are symmetric aliases (registration_outlier, ε): the batch posterior
explains them as outliers (max-mixture), the particle filter as a two-component predictive, and both
agree; with ε = 0 one alias is enough to lose the true topology."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ptm_ros.errors import ConfigError
from ptm_ros.inference.rbpf import RbpfConfig, run_filter
from ptm_ros.io.synthetic import simulate_route
from ptm_ros.model.geometry import RelativePose, between, compose, wrap_angle
from ptm_ros.model.odometry import (
    OdometryConfig,
    heading_aliases,
    odometry_covariances,
    registration_aliases,
)
from ptm_ros.model.partitions import bell, canonical
from ptm_ros.model.posterior import (
    ModelConfig,
    PosteriorModel,
    exact_posterior,
    normalize_log,
    total_variation,
)
from ptm_ros.model.priors import PriorConfig, make_prior
from ptm_ros.model.visits import Visit

SQUARE = [(0.0, 0.0), (5.0, 0.0), (5.0, 5.0), (0.0, 5.0)]
ROUTE = [0, 1, 2, 3, 0, 1, 2]
ODO = OdometryConfig(n_samples=0, a_xy=0.15**2, area_m2=1000.0, place_prior="area")  # built on a 1000 m² A
SD = np.array([0.05, 0.05, 0.01])
ALIAS = (1, 5)  # this pair's registration is the place's 180° symmetric image, not the truth


def simulate(seed: int = 1) -> tuple[list[Visit], np.ndarray]:
    """Visits of ROUTE on SQUARE (facing the next place) with odometry drawn from ODO's noise."""
    return simulate_route(ROUTE, SQUARE, ODO, seed=seed)


def aliasing_registrar(true: np.ndarray):
    """Noisy true relative poses for pairs of one place, except ALIAS: a confident match turned by π
    (what a forward-facing laser returns for a symmetric crossing passed in opposite directions)."""

    def registrar(i, j):
        if ROUTE[i] != ROUTE[j]:
            return None
        mean = between(true[i], true[j]) + np.random.default_rng([i, j]).normal(0.0, SD)
        if (i, j) == ALIAS:
            mean = compose(np.array([0.0, 0.0, math.pi]), mean)
        return RelativePose(i, j, mean, np.diag(SD**2))

    return registrar


def model_of(visits, true, eps: float) -> PosteriorModel:
    odo = replace(ODO, registration_outlier=eps)
    cfg = ModelConfig(prior=PriorConfig(), odometry=odo, use_appearance=False)
    return PosteriorModel(visits, cfg, registrar=aliasing_registrar(true))


def test_registration_outlier_validation():
    assert 0.0 < OdometryConfig().registration_outlier < 0.5
    for bad in (-0.1, 1.0, math.nan, True, "0.1"):
        with pytest.raises(ConfigError, match="registration_outlier"):
            OdometryConfig(registration_outlier=bad)


def test_registration_aliases_flag_only_the_alias():
    visits, true = simulate()
    reg = aliasing_registrar(true)
    loops = [reg(0, 4), reg(*ALIAS), reg(2, 6)]
    truth = canonical(ROUTE)
    flags = registration_aliases(truth, visits, replace(ODO, registration_outlier=0.05), loops)
    assert flags.tolist() == [False, True, False]
    # the loops are tested together (one batch); each alone gives the same verdict
    cfg = replace(ODO, registration_outlier=0.05)
    assert [bool(registration_aliases(truth, visits, cfg, [z])[0]) for z in loops] == flags.tolist()
    assert registration_aliases(truth, visits, cfg, loops[::-1]).tolist() == flags.tolist()[::-1]
    # ε = 0 trusts every loop; no loops, no flags
    assert not registration_aliases(truth, visits, replace(ODO, registration_outlier=0.0), loops).any()
    assert not registration_aliases(truth, visits, replace(ODO, registration_outlier=0.05), []).size


@pytest.mark.parametrize("eps", [0.05, 0.132, 0.3])
def test_heading_aliases_is_the_max_mixture_decision_on_the_heading_marginal(eps):
    """A registration of visits i < j whose heading lies beyond e* of the odometry's own heading change is an
    alias, where (1 − ε) N(e*; 0, V + R) = ε / 2π (V summed here from the odometry's per-step covariances,
    independently of the module's cumulative sums); the residual is wrapped, so a full turn changes
    nothing; ε = 0 flags nothing. The batch alias test inherits the flags, whatever the optimum says."""
    visits, true = simulate()
    cfg = replace(ODO, registration_outlier=eps)
    i, j = 0, 4
    r_th = 0.01**2
    var = float(np.sum(odometry_covariances(visits[i : j + 1], cfg)[:, 2, 2])) + r_th
    bound = math.sqrt(
        var * (2.0 * math.log((1.0 - eps) * 2.0 * math.pi / eps) - math.log(2.0 * math.pi * var))
    )
    odo_turn = visits[j].pose[2] - visits[i].pose[2]
    mean = between(true[i], true[j])

    def reg(e: float) -> RelativePose:
        return RelativePose(
            i, j, np.array([mean[0], mean[1], wrap_angle(odo_turn + e)]), np.diag([1e-4, 1e-4, r_th])
        )

    cases = [
        0.0,
        0.99 * bound,
        1.01 * bound,
        -0.99 * bound,
        -1.01 * bound,
        0.99 * bound + 2 * math.pi,
        math.pi / 2,
    ]
    want = [False, False, True, False, True, False, True]
    assert heading_aliases(visits, [reg(e) for e in cases], cfg).tolist() == want
    assert not heading_aliases(visits, [reg(e) for e in cases], replace(cfg, registration_outlier=0.0)).any()
    assert heading_aliases(visits, [], cfg).shape == (0,)
    truth = canonical(ROUTE)
    assert registration_aliases(truth, visits, cfg, [reg(1.01 * bound), reg(0.0)]).tolist() == [True, False]


@pytest.mark.slow
def test_batch_posterior_explains_the_alias_as_an_outlier():
    visits, true = simulate()
    truth = canonical(ROUTE)
    strict = normalize_log(exact_posterior(model_of(visits, true, 0.0)))
    assert strict[truth] < 1e-6  # one trusted alias rules the true topology out
    model = model_of(visits, true, 0.05)
    robust = normalize_log(exact_posterior(model))
    assert max(robust, key=robust.get) == truth
    assert robust[truth] > 0.5
    terms = model.terms(truth)
    assert [(z.i, z.j) for z in terms.outliers] == [ALIAS]
    assert {(z.i, z.j) for z in terms.loops} == {(0, 4), (2, 6)}
    # the alias costs log ε against "different places" and moves no pose: the optimum is that of the
    # topology's other measurements
    reg = aliasing_registrar(true)
    clean = PosteriorModel(
        visits, model.config, registrar=lambda i, j: None if (i, j) == ALIAS else reg(i, j)
    )
    assert terms.metric_result is not None
    np.testing.assert_allclose(terms.metric_result.poses, clean.terms(truth).metric_result.poses)
    eps = model.config.odometry.registration_outlier
    assert math.isclose(terms.metric - clean.terms(truth).metric, math.log(eps), abs_tol=1e-9)


@pytest.mark.slow
def test_filter_matches_the_batch_posterior_with_an_alias():
    """All children kept: the filter's two-component predictive (state from the dominant component)
    reproduces the batch max-mixture posterior."""
    visits, true = simulate()
    model = model_of(visits, true, 0.05)
    exact = normalize_log(exact_posterior(model))
    flt = run_filter(
        visits,
        RbpfConfig(particles=bell(len(visits))),
        make_prior(PriorConfig()),
        model.config.odometry,
        registrar=aliasing_registrar(true),
    )
    assert total_variation(exact, flt.ptm_weights()) <= 0.02
    weights = flt.ptm_weights()
    assert max(weights, key=weights.get) == canonical(ROUTE)
