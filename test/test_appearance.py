"""Appearance likelihoods: Fourier signatures, NIG and Pólya marginals against brute force."""

from __future__ import annotations

import math
from itertools import product

import numpy as np
import pytest
from scipy import integrate, optimize, stats
from scipy.special import beta as beta_fn

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.model.appearance import (
    MAX_WITHIN_FRACTION,
    AppearanceConfig,
    AppearanceModel,
    NigPrior,
    NigStats,
    appearance_log_likelihood,
    appearance_log_predictive,
    block_log_likelihood,
    estimate_dcm_alpha,
    fit_appearance_model,
    fourier_signature,
    log_marginal_dcm,
    log_marginal_nig,
    log_marginal_nig_stats,
    log_predictive_dcm,
    log_predictive_nig,
    nig_prior_from_data,
    panorama_signature,
)
from ptm_ros.model.partitions import blocks, enumerate_partitions
from ptm_ros.model.visits import Visit

PRIOR_1D = NigPrior(mu=np.array([0.3]), kappa=0.5, alpha=2.5, beta=0.8)
DATA_1D = np.array([0.1, 0.9, 0.5])


# --------------------------------------------------------------------------------- Fourier signatures


def _texture(rng: np.random.Generator, h: int = 48, w: int = 256) -> np.ndarray:
    img = np.full((h, w), 0.5)
    for _ in range(30):
        x0, y0 = rng.integers(0, w), rng.integers(0, h)
        img[y0 : y0 + rng.integers(3, 20), x0 : x0 + rng.integers(3, 40)] = rng.random()
    return (np.clip(img + 0.02 * rng.standard_normal((h, w)), 0, 1) * 255).astype(np.uint8)


def test_signature_invariant_to_circular_column_shift():
    rng = np.random.default_rng(0)
    img = _texture(rng)
    rgb = np.stack([img, np.roll(img, 3, axis=0), img // 2], axis=2)
    for image, kwargs in [
        (img, {}),
        (rgb, {"bands": 3, "include_dc": True}),
        (img, {"gain_invariant": True}),
    ]:
        ref = fourier_signature(image, 6, **kwargs)
        for shift in (1, 17, 128, 255):
            np.testing.assert_allclose(
                fourier_signature(np.roll(image, shift, axis=1), 6, **kwargs), ref, rtol=1e-12
            )


def test_signature_values_match_direct_dft():
    rng = np.random.default_rng(1)
    img = rng.random((10, 40))
    profile = img.mean(axis=0)
    c = np.arange(40)
    direct = [abs(np.sum(profile * np.exp(-2j * np.pi * k * c / 40))) / 40 for k in range(6)]
    np.testing.assert_allclose(fourier_signature(img, 5), direct[1:6], rtol=1e-12)
    np.testing.assert_allclose(fourier_signature(img, 5, include_dc=True), direct[0:5], rtol=1e-12)
    assert fourier_signature(img, 5, include_dc=True)[0] == pytest.approx(img.mean(), rel=1e-12)
    # bands: top rows then bottom rows; uint8 scaled by 255; gain invariance divides by band brightness
    two = fourier_signature(img, 3, bands=2)
    np.testing.assert_allclose(two[:3], fourier_signature(img[:5], 3), rtol=1e-12)
    np.testing.assert_allclose(two[3:], fourier_signature(img[5:], 3), rtol=1e-12)
    u8 = (img * 255).round().astype(np.uint8)
    np.testing.assert_allclose(fourier_signature(u8, 3), fourier_signature(u8 / 255.0, 3), rtol=1e-12)
    np.testing.assert_allclose(
        fourier_signature(0.5 * img, 3, gain_invariant=True), fourier_signature(img, 3, gain_invariant=True)
    )


def _area_sampled_scene(shift_px: float, w: int = 512, h: int = 8) -> np.ndarray:
    """A piecewise-constant 360° scene imaged by box-filter pixels, turned by ``shift_px`` columns."""
    edges = np.array([0.0, 0.11, 0.19, 0.42, 0.47, 0.71, 0.9]) * w  # step positions (columns)
    levels = np.array([0.2, 0.9, 0.4, 0.7, 0.1, 0.6, 0.3])
    left = np.arange(w) + shift_px

    def integral(x: np.ndarray) -> np.ndarray:  # ∫_0^x scene over one period, x in columns, periodic
        periods, rem = np.divmod(x, w)
        seg = np.diff(np.append(edges, w))
        full = np.sum(seg * levels)
        idx = np.searchsorted(edges, rem, side="right") - 1
        before = np.concatenate([[0.0], np.cumsum(seg * levels)])[idx]
        return periods * full + before + (rem - edges[idx]) * levels[idx]

    row = integral(left + 1.0) - integral(left)
    return np.tile(row, (h, 1))


def test_signature_nearly_invariant_to_subpixel_turn():
    ref = fourier_signature(_area_sampled_scene(0.0), 8)
    # a whole-pixel turn of the scene is a column roll: exact
    np.testing.assert_allclose(fourier_signature(_area_sampled_scene(5.0), 8), ref, rtol=1e-10)
    worst = 0.0
    for shift in (0.25, 0.5, 0.73):
        sig = fourier_signature(_area_sampled_scene(shift), 8)
        worst = max(worst, float(np.linalg.norm(sig - ref) / np.linalg.norm(ref)))
    assert 0.0 < worst < 1e-3  # measured ≈ 2e-4 (aliasing of the scene's sharp edges)
    # far smaller than the difference to another scene
    other = fourier_signature(_area_sampled_scene(0.0)[:, ::-1] ** 2, 8)
    assert np.linalg.norm(other - ref) / np.linalg.norm(ref) > 0.1


def test_different_panoramas_give_different_signatures():
    rng = np.random.default_rng(2)
    a, b = _texture(rng), _texture(rng)
    sa, sb = fourier_signature(a, 8), fourier_signature(b, 8)
    assert np.linalg.norm(sa - sb) > 0.2 * np.linalg.norm(sa)
    sig = panorama_signature(a, AppearanceConfig(n_coeffs=4, bands=2))
    assert sig.shape == (8,)


@pytest.mark.parametrize(
    ("image", "kwargs", "match"),
    [
        (np.zeros((4, 4, 4, 1)), {}, "shape"),
        (np.zeros((4, 20), dtype=bool), {}, "dtype"),
        (np.zeros((4, 20), dtype=complex), {}, "dtype"),
        (np.full((4, 20), np.nan), {}, "non-finite"),
        (np.zeros((4, 15)), {"n_coeffs": 8}, "too small"),
        (np.zeros((2, 40)), {"bands": 3}, "bands"),
        (np.zeros((4, 40)), {"gain_invariant": True}, "zero mean brightness"),
        (np.zeros((4, 40)), {"n_coeffs": 0}, "n_coeffs"),
    ],
)
def test_signature_rejects_bad_input(image, kwargs, match):
    with pytest.raises(ModelError, match=match):
        fourier_signature(image, **kwargs)


# ------------------------------------------------------------------------------------------ NIG model


def _normal_pdf(x: float, mean: float, var: float) -> float:
    return math.exp(-0.5 * (x - mean) ** 2 / var) / math.sqrt(2.0 * math.pi * var)


def _inv_gamma_pdf(s2: float, alpha: float, beta: float) -> float:
    return math.exp(alpha * math.log(beta) - math.lgamma(alpha) - (alpha + 1.0) * math.log(s2) - beta / s2)


def _nig_marginal_by_quadrature(a: np.ndarray, mu: float, kappa: float, alpha: float, beta: float) -> float:
    """∫∫ IG(σ²; α, β) N(y; μ, σ²/κ) Π N(a_i; y, σ²) dy dσ², over y and log σ² (2-D quadrature)."""
    n = a.size
    centre = (kappa * mu + a.sum()) / (kappa + n)  # where the y-integrand peaks; only sets the limits
    obs = [float(v) for v in a]

    def inner(log_s2: float) -> float:
        s2 = math.exp(log_s2)
        half = 14.0 * math.sqrt(s2 / (kappa + n))

        def f(y: float) -> float:
            return _normal_pdf(y, mu, s2 / kappa) * math.prod(_normal_pdf(v, y, s2) for v in obs)

        val, _ = integrate.quad(f, centre - half, centre + half, epsabs=0.0, epsrel=1e-11, limit=200)
        return val * _inv_gamma_pdf(s2, alpha, beta) * s2

    val, _ = integrate.quad(inner, math.log(1e-6), math.log(1e6), epsabs=0.0, epsrel=1e-10, limit=400)
    return math.log(val)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_nig_marginal_matches_2d_quadrature(n):
    a = DATA_1D[:n]
    expected = _nig_marginal_by_quadrature(a, 0.3, 0.5, 2.5, 0.8)
    got = log_marginal_nig(a[:, None], PRIOR_1D)
    assert np.exp(got) == pytest.approx(np.exp(expected), rel=1e-6)


def test_nig_marginal_matches_quadrature_for_peaked_prior():
    # a strong prior on a small within-place variance (the regime of nig_prior_from_data)
    a = np.array([1.02, 0.98])
    expected = _nig_marginal_by_quadrature(a, 1.3, 0.2, 20.0, 0.05)
    prior = NigPrior(mu=np.array([1.3]), kappa=0.2, alpha=20.0, beta=0.05)
    assert np.exp(log_marginal_nig(a[:, None], prior)) == pytest.approx(np.exp(expected), rel=1e-6)


def test_nig_marginal_factorises_over_components_and_is_exchangeable():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 3))
    prior = NigPrior(mu=np.array([0.1, -0.2, 0.4]), kappa=0.7, alpha=np.array([2.0, 3.0, 4.0]), beta=0.6)
    parts = [
        log_marginal_nig(a[:, [k]], NigPrior(prior.mu[[k]], prior.kappa, prior.alpha[k], prior.beta[k]))
        for k in range(3)
    ]
    assert log_marginal_nig(a, prior) == pytest.approx(sum(parts), rel=1e-12)
    assert log_marginal_nig(a[::-1], prior) == pytest.approx(log_marginal_nig(a, prior), rel=1e-12)
    assert log_marginal_nig(np.zeros((0, 3)), prior) == 0.0


def test_nig_stats_and_predictive_chain_rule():
    rng = np.random.default_rng(4)
    a = 0.5 + 0.1 * rng.normal(size=(6, 2))
    prior = NigPrior(mu=np.array([0.4, 0.6]), kappa=0.3, alpha=3.0, beta=np.array([0.02, 0.05]))
    stats_ = NigStats.empty(2)
    chain = 0.0
    for i in range(len(a)):
        pred = log_predictive_nig(a[i], stats_, prior)
        diff = log_marginal_nig(a[: i + 1], prior) - log_marginal_nig(a[:i], prior)
        assert pred == pytest.approx(diff, rel=1e-10, abs=1e-10)
        chain += pred
        stats_ = stats_.add(a[i])
    assert chain == pytest.approx(log_marginal_nig(a, prior), rel=1e-10)
    assert stats_.n == 6
    np.testing.assert_allclose(stats_.total, NigStats.from_signatures(a).total)
    assert log_marginal_nig_stats(stats_, prior) == pytest.approx(log_marginal_nig(a, prior), rel=1e-10)


def test_nig_predictive_is_a_density():
    stats_ = NigStats.from_signatures(DATA_1D[:2, None])
    total, _ = integrate.quad(
        lambda x: np.exp(log_predictive_nig(np.array([x]), stats_, PRIOR_1D)), -np.inf, np.inf, epsabs=1e-13
    )
    assert total == pytest.approx(1.0, abs=1e-9)


def test_within_place_variance_is_learned_from_the_spreads():
    # visits drawn from the model of eq. 25 with a known within-place variance; each visit's spread is
    # ½ (a - a')² against a second draw of its place: E[spread] = σ², so the learned share is σ²/v
    rng = np.random.default_rng(11)
    sigma2 = np.array([0.01, 0.09])
    places = rng.normal([1.0, 2.0], [0.5, 0.2], size=(400, 2))
    a = places + rng.normal(size=(400, 2)) * np.sqrt(sigma2)
    twin = places + rng.normal(size=(400, 2)) * np.sqrt(sigma2)
    spreads = 0.5 * (a - twin) ** 2
    v = a.var(axis=0, ddof=1)
    prior = nig_prior_from_data(a, within_fraction=0.3, alpha=5.0, spreads=spreads, prior_visits=0.0)
    learned = prior.beta / (prior.alpha - 1.0)
    np.testing.assert_allclose(learned, spreads.mean(axis=0), rtol=1e-12)  # the rule, exactly
    np.testing.assert_allclose(learned, sigma2, rtol=0.15)  # … which recovers the truth
    rho = learned / v
    assert prior.kappa == pytest.approx(rho.mean() / (1.0 - rho.mean()))
    # shrinkage: n0 visits at the prior guess ρ0 v
    shrunk = nig_prior_from_data(a, within_fraction=0.3, alpha=5.0, spreads=spreads[:2], prior_visits=2.0)
    np.testing.assert_allclose(shrunk.beta / 4.0, (spreads[:2].sum(axis=0) + 2.0 * 0.3 * v) / 4.0, rtol=1e-12)
    # an all-alike run: the share is capped below 1 (κ finite)
    capped = nig_prior_from_data(a, spreads=10.0 * spreads, prior_visits=0.0)
    assert np.all(capped.beta / (capped.alpha - 1.0) <= MAX_WITHIN_FRACTION * v * (1 + 1e-12))
    assert np.isfinite(capped.kappa)
    with pytest.raises(ModelError, match="spreads"):
        nig_prior_from_data(a, spreads=-spreads)
    with pytest.raises(ModelError, match="spreads"):
        nig_prior_from_data(a, spreads=spreads[:, :1])
    with pytest.raises(ConfigError, match="prior_visits"):
        nig_prior_from_data(a, spreads=spreads, prior_visits=-1.0)


def test_fit_uses_the_visits_spreads_unless_told_not_to():
    rng = np.random.default_rng(12)
    sig = np.abs(rng.normal(1.0, 0.3, size=(6, 3)))
    spread = np.full(3, 0.5 * 0.3**2)
    visits = [
        Visit(i, float(i), (float(i), 0.0, 0.0), signature=sig[i], signature_spread=spread) for i in range(6)
    ]
    v = sig.var(axis=0, ddof=1)
    cfg = AppearanceConfig(within_fraction=0.3, within_prior_visits=2.0)
    learned = fit_appearance_model(visits, cfg).nig
    expect = np.minimum((6 * spread + 2.0 * 0.3 * v) / 8.0 / v, MAX_WITHIN_FRACTION) * v
    np.testing.assert_allclose(learned.beta / (cfg.nig_alpha - 1.0), expect, rtol=1e-12)
    fixed = fit_appearance_model(visits, AppearanceConfig(within_fraction=0.3, within_learned=False)).nig
    np.testing.assert_allclose(fixed.beta / (cfg.nig_alpha - 1.0), 0.3 * v, rtol=1e-12)
    plain = [Visit(i, float(i), (float(i), 0.0, 0.0), signature=sig[i]) for i in range(6)]
    np.testing.assert_allclose(fit_appearance_model(plain, cfg).nig.beta, fixed.beta, rtol=1e-12)
    with pytest.raises(ModelError, match="signature_spread"):
        Visit(0, 0.0, (0.0, 0.0, 0.0), signature=sig[0], signature_spread=spread[:2])
    with pytest.raises(ModelError, match="signature_spread"):
        Visit(0, 0.0, (0.0, 0.0, 0.0), signature=sig[0], signature_spread=-spread)


def test_empirical_bayes_prior_reproduces_observed_variance():
    rng = np.random.default_rng(5)
    sigs = np.abs(rng.normal([1.0, 0.3], [0.2, 0.05], size=(40, 2)))
    prior = nig_prior_from_data(sigs, within_fraction=0.2, alpha=4.0)
    np.testing.assert_allclose(prior.mu, sigs.mean(axis=0))
    assert prior.kappa == pytest.approx(0.25)
    # IG mean = β/(α-1) = ρ v
    np.testing.assert_allclose(prior.beta / (prior.alpha - 1), 0.2 * sigs.var(axis=0, ddof=1))
    # the one-visit prior predictive has the observed mean and variance (numerical moments per component)
    for k in range(2):
        marginal = NigPrior(prior.mu[[k]], prior.kappa, prior.alpha[k], prior.beta[k])

        def moment(x, p, marginal=marginal):
            return x**p * np.exp(log_predictive_nig(np.array([x]), NigStats.empty(1), marginal))

        m1 = integrate.quad(moment, -np.inf, np.inf, args=(1,))[0]
        m2 = integrate.quad(moment, -np.inf, np.inf, args=(2,))[0]
        assert m1 == pytest.approx(sigs[:, k].mean(), rel=1e-7)
        assert m2 - m1**2 == pytest.approx(sigs[:, k].var(ddof=1), rel=1e-6)


def test_nig_errors():
    with pytest.raises(ConfigError, match="kappa"):
        NigPrior(mu=np.zeros(2), kappa=0.0, alpha=2.0, beta=1.0)
    with pytest.raises(ConfigError, match="beta"):
        NigPrior(mu=np.zeros(2), kappa=1.0, alpha=2.0, beta=np.ones(3))
    with pytest.raises(ConfigError, match="alpha"):
        NigPrior(mu=np.zeros(2), kappa=1.0, alpha=-1.0, beta=1.0)
    with pytest.raises(ModelError, match="components"):
        log_marginal_nig(np.zeros((2, 3)), NigPrior(mu=np.zeros(2), kappa=1.0, alpha=2.0, beta=1.0))
    with pytest.raises(ModelError, match="finite"):
        log_marginal_nig(np.array([[np.inf]]), PRIOR_1D)
    with pytest.raises(ModelError, match=r"\(1,\)"):
        NigStats.empty(1).add(np.zeros(2))
    with pytest.raises(ConfigError, match="within_fraction"):
        nig_prior_from_data(np.ones((3, 2)), within_fraction=1.0)
    with pytest.raises(ConfigError, match="alpha"):
        nig_prior_from_data(np.ones((3, 2)), alpha=1.0)


# ------------------------------------------------------------------------------------- Pólya / DCM


def test_dcm_v2_matches_beta_binomial_quadrature():
    alpha = np.array([0.4, 0.7])  # < 1: endpoint singularities, integrated with quad's algebraic weight
    for block in ([[3, 5]], [[3, 5], [0, 4]], [[2, 0], [1, 6], [4, 4]]):
        x = np.array(block)

        def f(t, x=x):
            return np.prod([stats.binom.pmf(row[0], row.sum(), t) for row in x])

        val, _ = integrate.quad(
            f, 0, 1, weight="alg", wvar=(alpha[0] - 1, alpha[1] - 1), epsabs=0, epsrel=1e-12
        )
        expected = np.log(val / beta_fn(*alpha))
        assert log_marginal_dcm(x, alpha) == pytest.approx(expected, rel=1e-9)


def test_dcm_v3_matches_dirichlet_quadrature():
    alpha = np.array([1.5, 2.0, 1.2])
    x = np.array([[2, 1, 0], [1, 3, 1]])
    log_dir_norm = math.lgamma(alpha.sum()) - sum(math.lgamma(a) for a in alpha)
    log_coeff = sum(math.lgamma(row.sum() + 1) - sum(math.lgamma(c + 1) for c in row) for row in x)
    power = x.sum(axis=0) + alpha - 1.0  # Dirichlet density times the multinomials, in θ

    def f(t2: float, t1: float) -> float:
        t3 = 1.0 - t1 - t2
        if t3 <= 0.0:
            return 0.0
        return math.exp(log_dir_norm + log_coeff) * t1 ** power[0] * t2 ** power[1] * t3 ** power[2]

    val, _ = integrate.dblquad(f, 0, 1, 0, lambda t1: 1 - t1, epsabs=0, epsrel=1e-10)
    assert log_marginal_dcm(x, alpha) == pytest.approx(np.log(val), rel=1e-7)


def test_dcm_pmf_sums_to_one_over_all_count_vectors():
    alpha = np.array([0.3, 1.7, 0.9])
    n = 7
    vectors = [np.array([a, b, n - a - b]) for a in range(n + 1) for b in range(n + 1 - a)]
    total = sum(np.exp(log_marginal_dcm(v[None], alpha)) for v in vectors)
    assert total == pytest.approx(1.0, abs=1e-12)
    # two visits of one place: the joint pmf over both histograms (totals 3 and 2) sums to one too
    first = [np.array([a, b, 3 - a - b]) for a in range(4) for b in range(4 - a)]
    second = [np.array([a, b, 2 - a - b]) for a in range(3) for b in range(3 - a)]
    joint = sum(np.exp(log_marginal_dcm(np.stack([u, v]), alpha)) for u, v in product(first, second))
    assert joint == pytest.approx(1.0, abs=1e-12)
    # matches scipy's independent implementation
    for v in vectors[:5]:
        assert log_marginal_dcm(v[None], alpha) == pytest.approx(
            stats.dirichlet_multinomial.logpmf(v, alpha, n), rel=1e-12
        )


def test_dcm_predictive_is_marginal_difference_and_normalised():
    rng = np.random.default_rng(6)
    alpha = np.array([0.5, 1.0, 2.0, 0.25])
    block = rng.integers(0, 6, size=(3, 4))
    new = np.array([1, 0, 4, 2])
    pred = log_predictive_dcm(new, block.sum(axis=0), alpha)
    diff = log_marginal_dcm(np.vstack([block, new]), alpha) - log_marginal_dcm(block, alpha)
    assert pred == pytest.approx(diff, rel=1e-12)
    assert log_predictive_dcm(new, np.zeros(4, int), alpha) == pytest.approx(
        log_marginal_dcm(new[None], alpha)
    )
    m = 4
    vectors = [np.array(v) for v in product(range(m + 1), repeat=4) if sum(v) == m]
    total = sum(np.exp(log_predictive_dcm(v, block.sum(axis=0), alpha)) for v in vectors)
    assert total == pytest.approx(1.0, abs=1e-12)


def _sample_dcm(rng: np.random.Generator, alpha: np.ndarray, docs: int) -> np.ndarray:
    return rng.multinomial(rng.integers(20, 61, size=docs), rng.dirichlet(alpha, size=docs))


def test_minka_fixed_point_matches_generic_optimizer():
    rng = np.random.default_rng(7)
    x = _sample_dcm(rng, np.array([0.6, 1.5, 3.0, 0.9]), 150)

    def nll(log_alpha):  # scipy's own DCM pmf, independent of the code under test
        return -np.sum(stats.dirichlet_multinomial.logpmf(x, np.exp(log_alpha), x.sum(axis=1)))

    res = optimize.minimize(nll, np.zeros(4), method="L-BFGS-B", options={"gtol": 1e-10, "ftol": 1e-15})
    assert res.success
    np.testing.assert_allclose(estimate_dcm_alpha(x), np.exp(res.x), rtol=1e-4)


def test_minka_fixed_point_recovers_alpha_and_handles_edge_cases():
    rng = np.random.default_rng(8)
    true = np.array([0.5, 1.0, 2.0, 0.3])
    est = estimate_dcm_alpha(_sample_dcm(rng, true, 3000))
    np.testing.assert_allclose(est, true, rtol=0.1)
    # an unseen word goes to the floor; empty histograms are ignored
    x = np.hstack([_sample_dcm(rng, true[:3], 200), np.zeros((200, 1), int)])
    x = np.vstack([x, np.zeros((5, 4), int)])
    est = estimate_dcm_alpha(x, min_alpha=1e-6)
    assert est[3] == 1e-6
    # under-dispersed histograms (likelihood growing towards a multinomial): precision held at the cap,
    # proportions = pooled frequencies
    x = np.tile([10, 15, 25], (40, 1)) + np.array([[1, -1, 0], [-1, 1, 0]] * 20)
    est = estimate_dcm_alpha(x, max_precision=1e6)
    assert est.sum() == pytest.approx(1e6, rel=1e-9)
    np.testing.assert_allclose(est / est.sum(), [0.2, 0.3, 0.5], rtol=1e-5)


def test_dcm_errors():
    with pytest.raises(ModelError, match="whole numbers"):
        log_marginal_dcm(np.array([[1.5, 2.0]]), np.ones(2))
    with pytest.raises(ModelError, match=">= 0"):
        log_marginal_dcm(np.array([[-1, 2]]), np.ones(2))
    with pytest.raises(ModelError, match="positive"):
        log_marginal_dcm(np.array([[1, 2]]), np.array([1.0, 0.0]))
    with pytest.raises(ModelError, match="shape"):
        log_predictive_dcm(np.array([1, 2]), np.array([1, 2, 3]), np.ones(2))
    with pytest.raises(ModelError, match="non-empty"):
        estimate_dcm_alpha(np.zeros((3, 2), int))
    with pytest.raises(ModelError, match="converge"):
        estimate_dcm_alpha(_sample_dcm(np.random.default_rng(0), np.ones(3), 50), max_iter=2, tol=1e-300)


# ------------------------------------------------------------------------------ topology likelihood


def _visits(sigs, words=None):
    return [
        Visit(
            index=i,
            stamp=float(i),
            pose=(0.0, 0.0, 0.0),
            signature=s,
            words=None if words is None else words[i],
        )
        for i, s in enumerate(sigs)
    ]


def _place_data(seed: int = 9):
    rng = np.random.default_rng(seed)
    truth = (0, 1, 2, 0, 1, 0, 2)
    centres = rng.uniform(0.2, 1.0, size=(3, 4))
    sigs = np.array([centres[p] + 0.02 * rng.normal(size=4) for p in truth])
    thetas = rng.dirichlet(np.full(30, 0.3), size=3)
    words = np.array([rng.multinomial(80, thetas[p]) for p in truth])
    return truth, sigs, words


def test_topology_likelihood_is_sum_of_block_marginals_and_uses_cache():
    _, sigs, words = _place_data()
    visits = _visits(sigs, words)
    model = fit_appearance_model(visits, AppearanceConfig(models=("fourier", "words")))
    labels = (0, 1, 0, 2, 1, 1, 0)
    expected = sum(
        log_marginal_nig(sigs[list(b)], model.nig) + log_marginal_dcm(words[list(b)], model.dcm_alpha)
        for b in blocks(labels)
    )
    assert appearance_log_likelihood(labels, visits, model) == pytest.approx(expected, rel=1e-12)
    cache: dict[tuple[int, ...], float] = {}
    assert appearance_log_likelihood(labels, visits, model, cache) == pytest.approx(expected, rel=1e-12)
    assert set(cache) == set(blocks(labels))
    cache[(1, 4, 5)] = cache[(1, 4, 5)] + 10.0  # a cached block is reused, not recomputed
    assert appearance_log_likelihood(labels, visits, model, cache) == pytest.approx(expected + 10.0)


def test_predictive_of_a_visit_is_the_block_likelihood_difference():
    _, sigs, words = _place_data()
    visits = _visits(sigs, words)
    model = fit_appearance_model(visits, AppearanceConfig(models=("fourier", "words")))
    for block, new in [((0, 3), 5), ((), 2), ((1,), 6)]:
        diff = block_log_likelihood((*block, new), visits, model) - (
            block_log_likelihood(block, visits, model) if block else 0.0
        )
        assert appearance_log_predictive(new, block, visits, model) == pytest.approx(diff, rel=1e-10)


@pytest.mark.parametrize("models", [("fourier",), ("words",), ("fourier", "words")])
def test_true_topology_is_the_most_likely_among_all_partitions(models):
    truth, sigs, words = _place_data()
    visits = _visits(sigs, words)
    model = fit_appearance_model(visits, AppearanceConfig(models=models))
    cache: dict[tuple[int, ...], float] = {}
    scores = {lab: appearance_log_likelihood(lab, visits, model, cache) for lab in enumerate_partitions(7)}
    ranked = sorted(scores, key=scores.get, reverse=True)
    assert ranked[0] == truth
    # the all-distinct and all-same topologies are far less likely than the truth
    assert scores[truth] - scores[(0,) * 7] > 5.0
    assert scores[truth] - scores[tuple(range(7))] > 5.0


def test_fixed_dirichlet_and_missing_measurements():
    _, sigs, words = _place_data()
    model = fit_appearance_model(_visits(sigs, words), AppearanceConfig(models=("words",), dcm_alpha=0.5))
    np.testing.assert_array_equal(model.dcm_alpha, np.full(30, 0.5))
    assert model.nig is None
    expected = log_marginal_dcm(words, np.full(30, 0.5))
    assert appearance_log_likelihood((0,) * 7, _visits(sigs, words), model) == pytest.approx(expected)
    with pytest.raises(ModelError, match="only 0 visits carry a bag-of-words"):
        fit_appearance_model(_visits(sigs), AppearanceConfig(models=("words",)))
    visits = _visits(sigs)
    model = fit_appearance_model(visits, AppearanceConfig())
    with pytest.raises(ModelError, match="labels cover 3"):
        appearance_log_likelihood((0, 1, 0), visits, model)
    with pytest.raises(ModelError, match="not a new visit"):
        appearance_log_predictive(0, (0, 1), visits, model)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"models": ()}, "models"),
        ({"models": ("laser",)}, "models"),
        ({"models": ("fourier", "fourier")}, "models"),
        ({"n_coeffs": 0}, "n_coeffs"),
        ({"within_fraction": 0.0}, "within_fraction"),
        ({"nig_alpha": 1.0}, "nig_alpha"),
        ({"nig_kappa": -1.0}, "nig_kappa"),
        ({"dcm_alpha": float("nan")}, "dcm_alpha"),
        ({"dcm_tol": 0.0}, "dcm_tol"),
    ],
)
def test_config_validation(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        AppearanceConfig(**kwargs)


def test_model_needs_a_prior():
    with pytest.raises(ConfigError, match="needs a NIG prior"):
        AppearanceModel()


def test_missing_measurements_are_left_out():
    """A visit without a signature (no panorama near it) is a missing measurement: block likelihoods and
    predictives equal those of the visits that have one; the prior is fitted on those."""
    from dataclasses import replace

    from ptm_ros.model.appearance import (
        AppearanceConfig,
        appearance_log_predictive,
        block_log_likelihood,
        fit_appearance_model,
    )

    rng = np.random.default_rng(4)
    full = [Visit(i, float(i), (0.0, 0.0, 0.0), signature=rng.normal(1.0, 0.3, 4)) for i in range(6)]
    holes = [replace(v, signature=None) if v.index in (1, 4) else v for v in full]
    model = fit_appearance_model(holes, AppearanceConfig())
    kept = [v for v in full if v.index not in (1, 4)]
    assert math.isclose(
        block_log_likelihood((0, 1, 2, 4), holes, model),
        block_log_likelihood((0, 1), kept, model),
        rel_tol=1e-12,
    )
    assert block_log_likelihood((1, 4), holes, model) == 0.0
    assert appearance_log_predictive(4, (0, 2), holes, model) == 0.0
    assert math.isclose(
        appearance_log_predictive(5, (0, 1, 2), holes, model),
        appearance_log_predictive(3, (0, 1), kept, model),
        rel_tol=1e-12,
    )
    with pytest.raises(ModelError, match="only 1 visits"):
        fit_appearance_model([full[0], *[replace(v, signature=None) for v in full[1:]]], AppearanceConfig())
