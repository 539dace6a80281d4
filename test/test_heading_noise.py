"""The heading noise learned from the run's registrations (:mod:`ptm_ros.model.heading_noise`) and the filter
session that learns it (:class:`ptm_ros.session.FilterSession`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from ptm_ros.config import PtmConfig, load_config
from ptm_ros.io.synthetic import grid_route, simulate_route, truth_registrar
from ptm_ros.model.geometry import RelativePose
from ptm_ros.model.heading_noise import (
    OUTLIER_FRACTIONS,
    SCALE_STEPS,
    HeadingResiduals,
    NoiseScale,
    heading_residuals,
    heading_scale,
    profiled_outlier,
    scaled_heading_noise,
)
from ptm_ros.model.odometry import OdometryConfig, path_heading_variances
from ptm_ros.model.visits import Visit
from ptm_ros.session import HEADING_KEY, FilterSession, filter_visits


def _draw(rng: np.random.Generator, scale: float, n: int, outliers: float) -> HeadingResiduals:
    v = rng.uniform(0.001, 0.05, n)
    r = np.full(n, 1e-4)
    e = rng.normal(0.0, np.sqrt(scale * v + r))
    out = rng.random(n) < outliers
    e[out] = rng.uniform(-math.pi, math.pi, out.sum())
    return HeadingResiduals(e, v, r)


def test_residuals_compare_the_registration_with_the_odometry_heading_change():
    cfg = OdometryConfig()
    visits = [
        Visit(0, 0.0, (0.0, 0.0, 3.0)),
        Visit(1, 1.0, (4.0, 0.0, -3.0), travel=4.0, rotation=0.3),
        Visit(2, 2.0, (4.0, 3.0, -2.5), travel=3.0, rotation=0.5),
    ]
    z = RelativePose(0, 2, np.array([1.0, 2.0, 0.9]), np.diag([0.01, 0.01, 0.002]))
    res = heading_residuals(visits, [z, replace(z, i=1, j=5)], cfg)  # the second is beyond the visits
    assert len(res) == 1
    # odometry heading change -2.5 - 3.0 = -5.5 ≡ 0.7832 rad; the registration says 0.9
    assert res.error[0] == pytest.approx(0.9 - (-5.5 + 2 * math.pi))
    expected_v = sum(cfg.a_th * v.rotation + cfg.c_th * v.travel + cfg.b_th for v in visits[1:])
    assert res.path_variance[0] == pytest.approx(expected_v)
    assert res.registration_variance[0] == pytest.approx(0.002)
    assert np.allclose(
        np.diff(path_heading_variances(visits, cfg)),
        [0.0025 * 0.3 + 0.0004 * 4 + 1e-4, 0.0025 * 0.5 + 0.0004 * 3 + 1e-4],
    )


def test_the_estimate_is_the_lattice_posterior_mode_computed_by_brute_force():
    res = _draw(np.random.default_rng(3), 0.2, 60, 0.2)
    got = heading_scale(res, prior_sd=1.0)
    best = (-np.inf, None, None)
    for m in SCALE_STEPS:
        k = 2.0 ** (m / 2)
        for eps in OUTLIER_FRACTIONS:
            inlier = stats.norm.pdf(
                res.error, scale=np.sqrt(k * res.path_variance + res.registration_variance)
            )
            lp = np.sum(np.log((1 - eps) * inlier + eps / (2 * math.pi))) + stats.norm.logpdf(math.log(k))
            if lp > best[0]:
                best = (lp, m, eps)
    assert (got.step, got.outlier_fraction) == (best[1], best[2])
    assert got.scale == pytest.approx(2.0 ** (best[1] / 2)) and got.registrations == 60


@pytest.mark.parametrize("true_scale", [0.05, 0.25, 1.0, 4.0])
def test_the_scale_is_recovered_through_aliases(true_scale):
    for seed in range(5):
        got = heading_scale(_draw(np.random.default_rng(seed), true_scale, 300, 0.3), prior_sd=1.0)
        assert abs(math.log2(got.scale) - math.log2(true_scale)) <= 1.0, (seed, got)
        assert 0.1 <= got.outlier_fraction <= 0.5


def test_without_registrations_the_model_is_kept_and_few_move_it_little():
    empty = HeadingResiduals(np.zeros(0), np.zeros(0), np.zeros(0))
    assert heading_scale(empty, 1.0) == NoiseScale(1.0, 0, OUTLIER_FRACTIONS[0], 0)
    one = HeadingResiduals(np.array([0.0]), np.array([0.04]), np.array([1e-4]))
    assert heading_scale(one, 1.0).scale >= 0.25  # one perfect match: not a collapse of the model
    assert heading_scale(one, 0.1).scale == 1.0  # a confident prior keeps it


def test_scaling_touches_the_heading_terms_only():
    cfg = OdometryConfig()
    out = scaled_heading_noise(cfg, 0.25)
    assert (out.a_th, out.b_th, out.c_th) == pytest.approx((cfg.a_th / 4, cfg.b_th / 4, cfg.c_th / 4))
    assert (out.a_xy, out.b_xy, out.sigma_topology) == (cfg.a_xy, cfg.b_xy, cfg.sigma_topology)
    assert scaled_heading_noise(cfg, 1.0) is cfg
    with pytest.raises(Exception, match="learn_heading"):
        OdometryConfig(learn_heading="yes")  # type: ignore[arg-type]


def _run(heading_factor: float, seed: int = 0):
    """A 40-visit grid walk whose odometry heading noise is ``heading_factor`` times the model's, with
    registrations of every same-place pair."""
    places, route = grid_route(40, seed=seed)
    model = OdometryConfig()
    truth = scaled_heading_noise(model, heading_factor)
    visits, true = simulate_route(route, places, truth, seed)
    return visits, truth_registrar(true, route)


def _config(**odometry) -> PtmConfig:
    return load_config(None, {"model": {"odometry": odometry}, "inference": {"particles": 30}})


@pytest.mark.parametrize(("factor", "low", "high"), [(0.05, 0.01, 0.3), (6.0, 2.0, 16.0)])
@pytest.mark.slow
def test_the_session_learns_the_runs_heading_noise_and_replays(factor, low, high):
    visits, registrar = _run(factor)
    session = filter_visits(FilterSession(_config(), registrar=registrar), visits)
    assert low <= session.heading.scale <= high, session.heading
    assert session.replays > 0
    assert session.odometry_config().a_th == pytest.approx(OdometryConfig().a_th * session.heading.scale)
    details = session.inference().details[HEADING_KEY]
    assert details == session.heading.as_dict()
    off = filter_visits(FilterSession(_config(learn_heading=False), registrar=registrar), visits)
    assert off.heading.scale == 1.0 and HEADING_KEY not in off.inference().details


@pytest.mark.slow
def test_learning_is_the_same_streamed_offline_and_resumed(tmp_path):
    from ptm_ros.inference.persistence import load_filter_state, save_filter_state

    visits, registrar = _run(0.05, seed=1)
    config = _config()
    online = filter_visits(FilterSession(config, registrar=registrar), visits)
    offline = filter_visits(FilterSession(config, fitted_to=visits, registrar=registrar), visits)
    assert online.heading == offline.heading
    assert online.inference().probabilities == offline.inference().probabilities
    half = filter_visits(FilterSession(config, registrar=registrar), visits[:25])
    assert half.heading.scale < 1.0  # learned before the checkpoint
    save_filter_state(tmp_path / "s.npz", half.state_dict(), meta={})
    resumed = FilterSession(config, registrar=registrar)
    resumed.load_state(load_filter_state(tmp_path / "s.npz")[0])
    assert resumed.heading == half.heading
    filter_visits(resumed, visits)
    assert resumed.heading == online.heading
    assert resumed.inference().probabilities == online.inference().probabilities


def test_the_batch_estimators_use_the_heading_noise_the_filter_learns():
    """6 visits (B_6 = 203 topologies enumerated), two places revisited: the filter learns a scale of 0.35
    and the exact MAP's log posterior under it is 1.6 nats from the unlearned model's."""
    from ptm_ros.model.posterior import PosteriorModel
    from ptm_ros.session import infer

    places, route = grid_route(6, side=2, seed=0)
    visits, true = simulate_route(route, places, scaled_heading_noise(OdometryConfig(), 0.05), 0)
    registrar = truth_registrar(true, route)
    exact = _config()
    exact = replace(exact, inference=replace(exact.inference, method="exact"))
    filtered = filter_visits(FilterSession(_config(), registrar=registrar), visits)
    assert filtered.heading.scale < 1.0
    result = infer(visits, exact, registrar=registrar)
    assert result.details[HEADING_KEY] == filtered.heading.as_dict()
    model = PosteriorModel(
        visits, replace(exact.model, odometry=filtered.odometry_config()), registrar=registrar
    )
    best = max(result.probabilities, key=result.probabilities.__getitem__)
    assert result.log_posteriors[best] == pytest.approx(model.log_posterior(best))
    unlearned = PosteriorModel(visits, exact.model, registrar=registrar)
    assert result.log_posteriors[best] != pytest.approx(unlearned.log_posterior(best))


@pytest.mark.slow
def test_a_live_stream_freezes_the_scale_with_the_priors_and_an_offline_run_does_not():
    visits, registrar = _run(0.05, seed=1)
    config = _config()
    early = filter_visits(FilterSession(config, registrar=registrar), visits[:12]).heading
    live = filter_visits(FilterSession(config, refit_max_visits=12, registrar=registrar), visits)
    assert live.heading.step == early.step
    offline = filter_visits(FilterSession(config, fitted_to=visits, registrar=registrar), visits)
    never = filter_visits(FilterSession(config, refit_max_visits=0, registrar=registrar), visits)
    assert offline.heading == never.heading and offline.heading.step != early.step


def test_the_profiled_outlier_fraction_at_the_scale_in_use_counts_the_aliases():
    """A ring of rotated, identical sides: registrations of different sides match a quarter turn off the
    odometry's own heading change (the calibration bench's aliased ring: 7 of its 8 valid registrations).
    At the scale in use the heading model takes them for aliases, whether or not the scale moves; clean
    residuals keep the smallest fraction."""
    path = np.full(8, 0.01)  # rad², the model's heading variance of each registration's path
    reg = np.full(8, 1e-4)
    aliased = HeadingResiduals(np.array([0.0, 1.57, -1.57, 3.14, 1.56, -1.55, 1.58, 1.59]), path, reg)
    clean = HeadingResiduals(np.array([0.02, -0.05, 0.1, -0.08, 0.0, 0.06, -0.12, 0.04]), path, reg)
    assert profiled_outlier(aliased, 0) == 0.9
    assert profiled_outlier(clean, 0) == OUTLIER_FRACTIONS[0]
    none = HeadingResiduals(np.zeros(0), np.zeros(0), np.zeros(0))
    assert profiled_outlier(none, 0) == OUTLIER_FRACTIONS[0]
    learned = heading_scale(clean, 1.0)
    assert learned.outlier_fraction == profiled_outlier(clean, learned.step)
