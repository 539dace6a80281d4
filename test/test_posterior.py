"""The posterior over topologies: composition of terms, caching, exact enumeration."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import logsumexp

from ptm_ros.errors import ModelError
from ptm_ros.model.appearance import AppearanceConfig, appearance_log_likelihood
from ptm_ros.model.geometry import compose
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.partitions import bell, enumerate_partitions
from ptm_ros.model.posterior import (
    ModelConfig,
    PosteriorModel,
    exact_posterior,
    normalize_log,
    same_place_probabilities,
    top_k,
    total_variation,
)
from ptm_ros.model.priors import DirichletProcessPrior, PriorConfig
from ptm_ros.model.visits import Visit


def square_loop_visits(n_laps_visits: int = 5, side: float = 6.0, noise: float = 0.02, seed: int = 0):
    """Visits at the corners of a square driven counter-clockwise; visit 4 is back at visit 0."""
    rng = np.random.default_rng(seed)
    step = np.array([side, 0.0, math.pi / 2])
    pose = np.zeros(3)
    visits = []
    for i in range(n_laps_visits):
        sig = np.array([1.0 + (i % 4), 2.0, 0.5 * (i % 4)]) + rng.normal(0, 0.05, 3)
        visits.append(
            Visit(
                i,
                float(i),
                tuple(pose),
                travel=0.0 if i == 0 else side,
                rotation=0.0 if i == 0 else 1.57,
                signature=sig,
            )
        )
        noisy = step + rng.normal(0, [noise, noise, noise / 5])
        pose = compose(pose, noisy)
    return visits


FAST = ModelConfig(odometry=OdometryConfig(n_samples=0))


def test_prior_only_posterior_is_the_prior():
    visits = square_loop_visits()
    cfg = ModelConfig(use_odometry=False, use_appearance=False, prior=PriorConfig(alpha=2.0))
    model = PosteriorModel(visits, cfg)
    post = normalize_log(exact_posterior(model))
    prior = DirichletProcessPrior(2.0)
    for labels in enumerate_partitions(5):
        assert math.isclose(post[labels], math.exp(prior.log_prob(labels)), rel_tol=1e-9)


def test_terms_add_up_and_are_cached():
    model = PosteriorModel(square_loop_visits(), FAST)
    t = model.terms((0, 1, 2, 3, 0))
    assert t.total == pytest.approx(t.prior + t.metric + t.appearance)
    assert t.appearance != 0.0 and t.metric != 0.0
    assert model.terms((0, 1, 2, 3, 0)) is t
    # the appearance term is a product over blocks: recomputing without the cache gives the same value
    fresh = PosteriorModel(square_loop_visits(), FAST)
    fresh._block_cache.clear()
    assert fresh.terms((0, 1, 2, 3, 0)).appearance == pytest.approx(t.appearance, rel=1e-12)


def test_exact_posterior_prefers_the_true_loop_closure():
    model = PosteriorModel(square_loop_visits(), FAST)
    logp = exact_posterior(model)
    assert len(logp) == bell(5)
    post = normalize_log(logp)
    assert math.isclose(sum(post.values()), 1.0, rel_tol=1e-12)
    (best, p_best), _ = top_k(post, 2)
    assert best == (0, 1, 2, 3, 0)
    assert p_best > 0.9


def test_importance_sampled_posterior_close_to_laplace():
    """Under the area model the open loop, whose fifth place sits on the first, is 1e-4 likely: Laplace's
    penalty at the mode (3.3 nats below the samples' average) cannot move the posterior. Under the step
    prior the open loop holds 0.005 (Laplace) and the same 3.3 nats move 0.11 of the mass (the filter and
    ``ptm-run`` integrate the penalty)."""
    visits = square_loop_visits()
    area = OdometryConfig(n_samples=0, place_prior="area")
    lap = normalize_log(exact_posterior(PosteriorModel(visits, ModelConfig(odometry=area))))
    cfg = ModelConfig(odometry=replace(area, n_samples=200))
    is_ = normalize_log(exact_posterior(PosteriorModel(visits, cfg, seed=3)))
    assert total_variation(lap, is_) < 0.05
    again = normalize_log(exact_posterior(PosteriorModel(visits, cfg, seed=3)))
    assert again == is_  # deterministic under the seed, independent of evaluation order


def test_a_missing_signature_is_left_out_of_the_appearance_term():
    visits = square_loop_visits()
    full = PosteriorModel(visits, FAST)
    visits[2] = Visit(2, 2.0, visits[2].pose, travel=6.0, rotation=1.57)  # no panorama at visit 2
    model = PosteriorModel(visits, FAST)
    assert model.appearance is not None
    kept = [v for v in visits if v.index != 2]
    for labels in ((0, 1, 2, 3, 0), (0, 1, 1, 2, 0)):
        without = tuple(lab for i, lab in enumerate(labels) if i != 2)
        want = appearance_log_likelihood(without, kept, model.appearance)
        assert model.terms(labels).appearance == pytest.approx(want, rel=1e-12)
    assert full.terms((0, 1, 2, 3, 0)).appearance != model.terms((0, 1, 2, 3, 0)).appearance
    lone = [v if v.index == 0 else Visit(v.index, v.stamp, v.pose, v.travel, v.rotation) for v in visits]
    assert PosteriorModel(lone, FAST).appearance is None  # one signature: no prior to fit
    words_cfg = ModelConfig(
        appearance=AppearanceConfig(models=("words",)), odometry=OdometryConfig(n_samples=0)
    )
    assert PosteriorModel(square_loop_visits(), words_cfg).appearance is None


def test_registrar_called_once_per_chained_pair():
    calls = []

    def registrar(i, j):
        calls.append((i, j))

    model = PosteriorModel(square_loop_visits(), FAST, registrar=registrar)
    model.log_posterior((0, 1, 0, 1, 0))
    model.log_posterior((0, 1, 2, 1, 0))
    # chains within places: {0,2,4}, {1,3}; then {0,4}, {1,3} (cached), {2}
    assert sorted(calls) == [(0, 2), (0, 4), (1, 3), (2, 4)]


def test_bad_labels_rejected():
    model = PosteriorModel(square_loop_visits(), FAST)
    with pytest.raises(ModelError, match="canonical"):
        model.log_posterior((0, 2, 1, 0, 0))
    with pytest.raises(ModelError, match="5 visits"):
        model.log_posterior((0, 1))
    with pytest.raises(ModelError, match="at least one visit"):
        PosteriorModel([])


def test_same_place_probabilities_by_hand():
    """Σ_T P(T) [T_i = T_j] for a three-topology ensemble of 3 visits, written out pair by pair."""
    probs = {(0, 0, 1): 0.5, (0, 1, 0): 0.3, (0, 1, 2): 0.2}
    same = same_place_probabilities(probs, 3)
    expected = np.array([[1.0, 0.5, 0.3], [0.5, 1.0, 0.0], [0.3, 0.0, 1.0]])
    np.testing.assert_allclose(same, expected, atol=1e-12)
    # all B_7 = 877 topologies of 7 visits with random weights (several chunks), against a plain loop
    w = np.random.default_rng(0).random(877)
    many = dict(zip(enumerate_partitions(7), (w / w.sum()).tolist(), strict=True))
    loop = sum(p * (np.array(lab)[:, None] == np.array(lab)[None, :]) for lab, p in many.items())
    np.testing.assert_allclose(same_place_probabilities(many, 7), loop, atol=1e-12)


def test_total_variation_and_normalisation():
    p = normalize_log({(0, 0): 0.0, (0, 1): math.log(3.0)})
    assert p[(0, 1)] == pytest.approx(0.75)
    assert total_variation(p, {(0, 0): 1.0}) == pytest.approx(0.75)
    assert float(logsumexp([0.0])) == 0.0
