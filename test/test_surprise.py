"""Tests of landmark detection by Bayesian surprise (thesis Ch. 4.6–4.8): every closed-form KL against
numerical integration, enumeration or Monte Carlo; the predicted-surprise band against quadrature; the
detectors' behaviour on repeated, stepped and stationary measurements and on the simulated worlds."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from scipy import integrate, optimize, stats
from scipy.special import digamma, gammaln

from ptm_ros.errors import ConfigError, DataError, ModelError
from ptm_ros.perception.appearance_surprise import AppearanceSurpriseConfig, AppearanceSurpriseDetector
from ptm_ros.perception.laser_surprise import LaserSurpriseConfig, LaserSurpriseDetector, scan_statistic
from ptm_ros.perception.surprise import (
    BandTrigger,
    EdcmPrior,
    EdcmStats,
    GaussianStats,
    Niw,
    NormalGamma,
    SurpriseStep,
    edcm_kl,
    edcm_log_pmf,
    edcm_surprise_step,
    fit_edcm,
    gamma_kl,
    gaussian_kl,
    gaussian_surprise_step,
    limit_surprise_trace,
    niw_kl,
    niw_posterior,
    niw_surprise,
    normal_gamma_kl,
    surprise_trace,
    trace_from_dict,
    trace_to_dict,
)

# ----------------------------------------------------------------------------------------- Gaussian KLs


def printed_eq67(mp: float, vp: float, mq: float, vq: float) -> float:
    """Eq. 67 exactly as printed in the thesis."""
    return 0.5 * math.log(vp / vq) + (mq**2 + mp**2 + vp - 2 * mp * mq) / (2 * vp) - 0.5


@pytest.mark.parametrize(
    ("mp", "vp", "mq", "vq"), [(0.0, 1.0, 0.0, 1.0), (0.3, 0.5, -1.0, 2.0), (2.0, 3.0, 1.5, 0.2)]
)
def test_gaussian_kl_matches_numerical_integration(mp: float, vp: float, mq: float, vq: float) -> None:
    p, q = stats.norm(mp, math.sqrt(vp)), stats.norm(mq, math.sqrt(vq))
    brute = integrate.quad(lambda x: p.pdf(x) * (p.logpdf(x) - q.logpdf(x)), -40, 40, limit=200)[0]
    assert float(gaussian_kl(mp, vp, mq, vq)) == pytest.approx(brute, rel=1e-7, abs=1e-10)


def test_printed_eq67_is_wrong_when_the_variances_differ() -> None:
    exact = float(gaussian_kl(0.3, 0.5, -1.0, 2.0))
    assert exact == pytest.approx(math.log(2.0) + (0.5 + 1.69) / 4.0 - 0.5, rel=1e-12)
    assert printed_eq67(0.3, 0.5, -1.0, 2.0) == pytest.approx(-math.log(2.0) + 2.19 - 0.5, rel=1e-12)  # 0.997
    assert printed_eq67(0.0, 1.0, 0.0, 2.0) == pytest.approx(-0.5 * math.log(2.0))  # a negative "divergence"
    assert float(gaussian_kl(0.0, 1.0, 0.0, 2.0)) == pytest.approx(0.5 * math.log(2.0) - 0.25)


def test_gaussian_kl_rejects_non_positive_variance() -> None:
    with pytest.raises(ModelError, match="positive variances"):
        gaussian_kl(0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize(("ap", "bp", "aq", "bq"), [(2.0, 1.0, 3.0, 0.5), (0.7, 2.0, 5.0, 4.0)])
def test_gamma_kl_matches_numerical_integration(ap: float, bp: float, aq: float, bq: float) -> None:
    p, q = stats.gamma(ap, scale=1 / bp), stats.gamma(aq, scale=1 / bq)
    brute = integrate.quad(lambda x: p.pdf(x) * (p.logpdf(x) - q.logpdf(x)), 0, np.inf, limit=200)[0]
    assert float(gamma_kl(ap, bp, aq, bq)) == pytest.approx(brute, rel=1e-6)


def test_normal_gamma_kl_matches_double_integral() -> None:
    p = NormalGamma([0.4], [2.0], [3.0], [1.5])
    q = NormalGamma([-0.2], [0.5], [2.0], [0.8])
    # Simpson's rule on a grid over (log λ, u), μ = m_p + u / sqrt(κ_p λ): ±12 sd of μ | λ, and λ over
    # [1e-6, 60] (p puts 2e-10 of its mass outside it).
    log_lam = np.linspace(math.log(1e-6), math.log(60.0), 1501)
    u = np.linspace(-12.0, 12.0, 1201)
    lam = np.exp(log_lam)[:, None]
    mu = 0.4 + u[None, :] / np.sqrt(2.0 * lam)

    def log_density(ng: NormalGamma) -> np.ndarray:
        return stats.gamma.logpdf(lam, ng.shape[0], scale=1 / ng.rate[0]) + stats.norm.logpdf(
            mu, ng.mean[0], 1 / np.sqrt(ng.kappa[0] * lam)
        )

    lp = log_density(p)
    jacobian = lam / np.sqrt(2.0 * lam)  # dλ = λ d(log λ), dμ = du / sqrt(κ_p λ)
    integrand = np.exp(lp) * (lp - log_density(q)) * jacobian
    brute = integrate.simpson(integrate.simpson(integrand, x=u, axis=1), x=log_lam)
    assert normal_gamma_kl(p, q) == pytest.approx(brute, rel=1e-6)


def test_niw_kl_in_one_dimension_is_the_normal_gamma_kl() -> None:
    # μ|λ ~ N(m, 1/(κλ)), λ ~ Ga(a, b)  <=>  NIW(m, κ, ν = 2a, Ψ = 2b).
    p = NormalGamma([0.3], [2.0], [3.0], [1.5])
    q = NormalGamma([-0.1], [1.0], [2.0], [0.7])
    assert niw_kl(Niw([0.3], 2.0, 6.0, [[3.0]]), Niw([-0.1], 1.0, 4.0, [[1.4]])) == pytest.approx(
        normal_gamma_kl(p, q), rel=1e-12
    )


def random_niw(rng: np.random.Generator, d: int, dof_extra: float) -> Niw:
    a = rng.normal(size=(d, d))
    return Niw(rng.normal(size=d), rng.uniform(0.5, 3.0), d + 1.0 + dof_extra, a @ a.T + d * np.eye(d))


@pytest.mark.parametrize("d", [2, 3])
def test_niw_kl_matches_monte_carlo(d: int) -> None:
    rng = np.random.default_rng(d)
    p, q = random_niw(rng, d, 6.0), random_niw(rng, d, 4.0)
    n = 20_000
    sigmas = stats.invwishart(df=p.dof, scale=p.scale).rvs(size=n, random_state=rng)
    chol = np.linalg.cholesky(sigmas / p.kappa)
    mus = p.mean + np.einsum("nij,nj->ni", chol, rng.standard_normal((n, d)))

    def log_density(niw: Niw) -> np.ndarray:
        log_iw = stats.invwishart(df=niw.dof, scale=niw.scale).logpdf(np.moveaxis(sigmas, 0, -1))
        diff = mus - niw.mean
        maha = np.einsum("ni,ni->n", diff, np.linalg.solve(sigmas / niw.kappa, diff[..., None])[..., 0])
        _, logdet = np.linalg.slogdet(sigmas / niw.kappa)
        return log_iw - 0.5 * (maha + logdet + d * math.log(2 * math.pi))

    ratio = log_density(p) - log_density(q)
    # 5 standard errors: a false failure has probability ~6e-7 (and the seed is fixed).
    assert abs(niw_kl(p, q) - ratio.mean()) < 5 * ratio.std() / math.sqrt(n)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_niw_surprise_is_the_kl_of_the_rank_one_update(d: int) -> None:
    rng = np.random.default_rng(10 + d)
    before = random_niw(rng, d, 2.5)
    for _ in range(5):
        z = before.mean + rng.normal(size=d) * 3
        stats_after = GaussianStats(0.0, np.zeros(d), np.zeros((d, d))).add(z)
        after = niw_posterior(before, stats_after)  # the NIW posterior is its own conjugate prior
        e = z - before.mean
        q = float(e @ np.linalg.solve(before.scale, e))
        assert float(niw_surprise(before, q)) == pytest.approx(niw_kl(after, before), rel=1e-10)


def test_niw_posterior_matches_the_batch_formula() -> None:
    rng = np.random.default_rng(3)
    prior = random_niw(rng, 2, 3.0)
    z = rng.normal(size=(7, 2))
    post = niw_posterior(
        prior, GaussianStats.empty(2).add(z[0]).add(z[1]).add(z[2]).add(z[3]).add(z[4]).add(z[5]).add(z[6])
    )
    zbar = z.mean(axis=0)
    scatter = (z - zbar).T @ (z - zbar)
    expected = (
        prior.scale
        + scatter
        + prior.kappa * 7 / (prior.kappa + 7) * np.outer(zbar - prior.mean, zbar - prior.mean)
    )
    assert post.scale == pytest.approx(expected, rel=1e-10)
    assert post.mean == pytest.approx((prior.kappa * prior.mean + 7 * zbar) / (prior.kappa + 7), rel=1e-12)


@pytest.mark.parametrize("d", [1, 3])
def test_predicted_surprise_matches_quadrature_and_real_predictive_draws(d: int) -> None:
    rng = np.random.default_rng(20 + d)
    prior = random_niw(rng, d, 2.0)
    data = GaussianStats.empty(d)
    for z in rng.normal(size=(12, d)):
        data = data.add(z)
    post = niw_posterior(prior, data)
    dof = post.dof - d + 1.0

    # Exact moments of the predicted surprise: x = κq/(κ+1) ~ (d/dof) F(d, dof).
    def f(x: float) -> float:
        return float(niw_surprise(post, x * (post.kappa + 1.0) / post.kappa))

    def dens(x: float) -> float:
        return float(stats.f.pdf(x * dof / d, d, dof) * dof / d)

    moment = [integrate.quad(lambda x, k=k: f(x) ** k * dens(x), 0, np.inf, limit=200)[0] for k in (1, 2, 4)]
    mean, var = moment[0], moment[1] - moment[0] ** 2
    central4 = integrate.quad(lambda x: (f(x) - mean) ** 4 * dens(x), 0, np.inf, limit=200)[0]

    # Brute force: draw measurements z from the predictive multivariate t, update, take the NIW KL.
    n = 3000
    shape = post.scale * (post.kappa + 1.0) / (post.kappa * dof)
    zs = stats.multivariate_t(loc=post.mean, shape=shape, df=dof).rvs(size=n, random_state=rng).reshape(n, d)
    kls = np.array([niw_kl(niw_posterior(post, GaussianStats.empty(d).add(z)), post) for z in zs])
    assert abs(kls.mean() - mean) < 5 * math.sqrt(var / n)
    assert abs(kls.var() - var) < 5 * math.sqrt((central4 - var**2) / n)

    m = 200_000
    step = gaussian_surprise_step(prior, data, post.mean, rng, m)
    assert abs(step.predicted_mean - mean) < 5 * math.sqrt(var / m)
    assert abs(step.predicted_std**2 - var) < 5 * math.sqrt((central4 - var**2) / m)
    assert step.surprise == pytest.approx(f(0.0), rel=1e-12)  # z at the posterior mean: q = 0


def test_diagonal_model_is_the_sum_of_one_dimensional_ones() -> None:
    rng = np.random.default_rng(4)
    prior = NormalGamma([0.1, -0.3], [0.5, 2.0], [2.0, 3.0], [0.2, 0.6])
    data = GaussianStats.empty(2)
    for z in rng.normal(size=(5, 2)):
        data = data.add(z)
    z = np.array([0.7, -1.2])
    total = gaussian_surprise_step(prior, data, z, rng, 10).surprise
    parts = 0.0
    for k in range(2):
        niw_k = Niw([prior.mean[k]], prior.kappa[k], 2 * prior.shape[k], [[2 * prior.rate[k]]])
        one = GaussianStats(data.n, data.total[k : k + 1], data.outer[k : k + 1, k : k + 1])
        parts += gaussian_surprise_step(niw_k, one, z[k : k + 1], rng, 10).surprise
    assert total == pytest.approx(parts, rel=1e-10)


# ------------------------------------------------------------------------------------------------- EDCM


def compositions(words: int, n: int) -> np.ndarray:
    """All histograms of ``n`` words over ``words`` words."""
    out = []
    for cut in itertools.combinations(range(n + words - 1), words - 1):
        b = (-1, *cut, n + words - 1)
        out.append([b[i + 1] - b[i] - 1 for i in range(words)])
    return np.array(out)


def polya_log_pmf(x: np.ndarray, alpha: np.ndarray) -> float:
    n, a = x.sum(), alpha.sum()
    return float(
        gammaln(n + 1)
        - gammaln(x + 1).sum()
        + gammaln(a)
        - gammaln(n + a)
        + (gammaln(x + alpha) - gammaln(alpha)).sum()
    )


def printed_eq66(bp: np.ndarray, bq: np.ndarray, n: int) -> float:
    sp, sq = bp.sum(), bq.sum()
    return float(
        gammaln(sq + n)
        - gammaln(sp + n)
        - gammaln(sq)
        + gammaln(sp)
        - (digamma(sq + n) - digamma(sq)) * np.sum(bq * np.log(bq / bp))
    )


def test_edcm_kl_is_exact_for_one_word_histograms() -> None:
    # For n = 1 the EDCM is the categorical distribution β/s exactly, whatever the size of β.
    rng = np.random.default_rng(5)
    bp, bq = rng.uniform(0.2, 3.0, 6), rng.uniform(0.2, 3.0, 6)
    xs = compositions(6, 1)
    lp = np.array([edcm_log_pmf(x, bp) for x in xs])
    lq = np.array([edcm_log_pmf(x, bq) for x in xs])
    assert np.exp(lp).sum() == pytest.approx(1.0, rel=1e-12)
    brute = float(np.sum(np.exp(lp) * (lp - lq)))
    assert edcm_kl(bp, bq, 1) == pytest.approx(brute, rel=1e-10)
    assert abs(printed_eq66(bp, bq, 1) - brute) > 0.1 * brute  # eq. 66 as printed is not the KL


@pytest.mark.parametrize("n", [3, 6])
def test_edcm_kl_approximates_the_polya_kl_for_small_parameters(n: int) -> None:
    # Eq. 60: the surprise is the KL between the Pólya models; the EDCM replaces Γ(x+β)/Γ(β) by Γ(x)β,
    # exact to first order in β, so the relative error is O(s). With s ≈ 0.035: under 5 %.
    rng = np.random.default_rng(6)
    bp, bq = rng.uniform(0.3, 1.0, 5) * 0.01, rng.uniform(0.3, 1.0, 5) * 0.01
    xs = compositions(5, n)
    lp = np.array([polya_log_pmf(x, bp) for x in xs])
    lq = np.array([polya_log_pmf(x, bq) for x in xs])
    brute = float(np.sum(np.exp(lp) * (lp - lq)))
    assert edcm_kl(bp, bq, n) == pytest.approx(brute, rel=0.05)
    norm = np.exp([edcm_log_pmf(x, bp) for x in xs]).sum()
    assert 1.0 - 0.05 < norm < 1.0  # the EDCM loses O(s) of its mass


def test_edcm_kl_is_zero_for_equal_models_and_infinite_for_a_missing_word() -> None:
    b = np.array([0.1, 0.2, 0.05])
    assert edcm_kl(b, b, 50) == pytest.approx(0.0, abs=1e-12)
    assert edcm_kl(b, np.array([0.1, 0.2, 0.0]), 5) == math.inf
    with pytest.raises(ModelError, match="positive sum"):
        edcm_kl(np.zeros(3), b, 5)


def weighted_edcm_log_posterior(
    log_beta: np.ndarray, docs: np.ndarray, weights: np.ndarray, prior: EdcmPrior
) -> float:
    beta = np.exp(log_beta)
    s = beta.sum()
    lengths = docs.sum(axis=1)
    present = docs > 0
    lik = np.sum(weights * (gammaln(s) - gammaln(s + lengths) + present @ log_beta))
    lam, tau = prior.strength, prior.strength / prior.precision
    return float(lik + np.sum(lam * prior.background * log_beta - tau * beta))


def test_fit_edcm_is_the_map_of_the_weighted_histograms() -> None:
    rng = np.random.default_rng(7)
    words = 8
    docs = np.array(
        [rng.multinomial(int(rng.integers(3, 15)), rng.dirichlet(np.full(words, 0.3))) for _ in range(6)]
    )
    prior = EdcmPrior(words, strength=2.0, precision=3.0)
    data = EdcmStats.empty(words)
    for doc in docs:
        data = data.decay(0.8).add(doc)
    weights = 0.8 ** np.arange(len(docs) - 1, -1, -1)
    beta = fit_edcm(data, prior)
    best = optimize.minimize(
        lambda lb: -weighted_edcm_log_posterior(lb, docs, weights, prior),
        np.zeros(words),
        method="BFGS",
        options={"gtol": 1e-10},
    )
    assert beta == pytest.approx(np.exp(best.x), rel=1e-4)
    assert weighted_edcm_log_posterior(np.log(beta), docs, weights, prior) >= -best.fun - 1e-9


def test_fit_edcm_without_prior_weight_solves_printed_eq64_65() -> None:
    docs = np.array([[3, 0, 1, 0], [0, 2, 2, 1], [1, 1, 0, 4]])
    data = EdcmStats.empty(4)
    for doc in docs:
        data = data.add(doc)
    beta = fit_edcm(data, EdcmPrior(4, strength=1e-12, precision=1.0))
    present = (docs > 0).sum(axis=0)
    lengths = docs.sum(axis=1)
    s = 1.0
    for _ in range(2000):  # eq. 64 as printed, iterated
        s = present.sum() / np.sum(digamma(s + lengths) - digamma(s))
    assert beta == pytest.approx(present / np.sum(digamma(s + lengths) - digamma(s)), rel=1e-6)  # eq. 65


def test_polya_urn_draws_have_the_polya_word_presence() -> None:
    from ptm_ros.perception.surprise import _polya_presence

    alpha = np.array([0.05, 0.3, 1.0, 0.02, 0.6])
    n, m = 12, 40_000
    presence = _polya_presence(alpha, n, m, np.random.default_rng(8))
    s = alpha.sum()
    # P(x_w = 0) under the Pólya model: Γ(s)Γ(s - α_w + n) / (Γ(s - α_w)Γ(s + n)).
    absent = np.exp(gammaln(s) + gammaln(s - alpha + n) - gammaln(s - alpha) - gammaln(s + n))
    p = 1.0 - absent
    assert np.all(np.abs(presence.mean(axis=0) - p) < 5 * np.sqrt(p * (1 - p) / m))


# -------------------------------------------------------------------------------------------- trigger


def step(surprise: float) -> SurpriseStep:
    return SurpriseStep(surprise, 1.0, 0.1)  # band edge 1.0 + k·0.1


def test_band_trigger_fires_once_per_excursion_at_its_first_maximum() -> None:
    trigger = BandTrigger(band_sigmas=2.0, warmup=2, min_travel=0.0)
    values = [5.0, 0.5, 0.9, 1.5, 2.5, 2.0, 3.0, 1.0, 0.8, 1.6, 0.7]
    fired = [trigger.step(float(t), step(v), None) for t, v in enumerate(values)]
    # 5.0 is in the warm-up; the excursion 1.5, 2.5, 2.0, 3.0 fires once at its first maximum (t=4),
    # confirmed at t=5; the single-sample excursion at t=9 fires at t=10.
    assert fired == [None, None, None, None, None, 4.0, None, None, None, None, 9.0]


def test_band_trigger_spaces_landmarks_by_travel() -> None:
    trigger = BandTrigger(band_sigmas=2.0, warmup=0, min_travel=2.0)
    values = [2.0, 0.5, 2.0, 0.5, 2.0, 0.5]
    travel = [0.0, 0.1, 1.5, 1.6, 2.5, 2.6]
    fired = [trigger.step(float(t), step(v), d) for t, (v, d) in enumerate(zip(values, travel, strict=True))]
    assert fired == [None, 0.0, None, None, None, 4.0]  # t=2 is only 1.5 m after t=0


# ---------------------------------------------------------------------------------------- laser detector


def feed(detector: LaserSurpriseDetector, zs: np.ndarray) -> list[int]:
    return [i for i, z in enumerate(zs) if detector.on_statistic(0.1 * i, z)]


@pytest.mark.parametrize("kind", ["log-area", "sectors"])
def test_repeated_measurement_stops_being_surprising(kind: str) -> None:
    d = 1 if kind == "log-area" else 3
    z = np.full((300, d), 0.7)
    never_forget = LaserSurpriseDetector(LaserSurpriseConfig(statistic=kind, memory=1e12))
    assert feed(never_forget, z) == []
    s = never_forget.trace.surprise
    assert np.all(np.diff(s) < 0.0)
    # -> 0 like d/(4ν) (Fig. 58): the mean term vanishes (z = m) and the IW term is ~ d/(4ν) for large ν.
    nu = d + 1.0 + 2.0 + 299.0
    assert s[-1] == pytest.approx(d / (4.0 * nu), rel=0.02)

    cfg = LaserSurpriseConfig(statistic=kind)
    forgetful = LaserSurpriseDetector(cfg)
    assert feed(forgetful, z) == []
    s = forgetful.trace.surprise
    assert np.all(np.diff(s) <= 1e-15)
    # The floor: the steady state before each update holds n = γ/(1-γ) measurements, all equal to z.
    gamma = math.exp(-1.0 / cfg.memory)
    n = gamma / (1.0 - gamma)
    steady = niw_posterior(cfg.prior(z[0]), GaussianStats(n, n * z[0], n * np.outer(z[0], z[0])))
    assert s[-1] == pytest.approx(float(niw_surprise(steady, 0.0)), rel=1e-6)


@pytest.mark.parametrize(("kind", "seed"), [("log-area", 0), ("log-area", 1), ("sectors", 0), ("sectors", 1)])
def test_a_step_fires_exactly_once_at_the_change(kind: str, seed: int) -> None:
    d = 1 if kind == "log-area" else 3
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 0.01, (600, d))
    z[300:] += 0.2
    detector = LaserSurpriseDetector(LaserSurpriseConfig(statistic=kind))
    assert feed(detector, z) == [301]  # declared one scan after the change ...
    assert detector.trace.landmarks.tolist() == [pytest.approx(30.0)]  # ... at the scan of the change
    assert detector.last_landmark_stamp == pytest.approx(30.0)


def exceedance(cfg: LaserSurpriseConfig, d: int) -> float:
    """P(predicted surprise > mean + k·std) at the steady state of the forgetting (quadrature)."""
    n = 1.0 / (1.0 - math.exp(-1.0 / cfg.memory))
    post = Niw(np.zeros(d), cfg.prior_kappa + n, d + 1.0 + cfg.prior_strength + n, np.eye(d))
    dof = post.dof - d + 1.0

    def f(x: float) -> float:
        return float(niw_surprise(post, x * (post.kappa + 1.0) / post.kappa))

    def dens(x: float) -> float:
        return float(stats.f.pdf(x * dof / d, d, dof) * dof / d)

    mean = integrate.quad(lambda x: f(x) * dens(x), 0, np.inf)[0]
    std = math.sqrt(integrate.quad(lambda x: (f(x) - mean) ** 2 * dens(x), 0, np.inf)[0])
    edge = optimize.brentq(lambda x: f(x) - (mean + cfg.band_sigmas * std), 1e-9, 1e6)
    return float(stats.f.sf(edge * dof / d, d, dof))


def test_stationary_noise_below_the_prior_floor_does_not_fire() -> None:
    z = np.random.default_rng(9).normal(0.0, 0.01, (5000, 3))  # prior_std = 0.03
    assert len(feed(LaserSurpriseDetector(), z)) <= 2  # observed: 0; a rate below 4e-4


def test_stationary_noise_fires_no_more_than_the_band_promises() -> None:
    # Noise well above the prior floor: the model is data-driven, and its false alarms are bounded by how
    # often its own predictive exceeds the band (k = 5: 0.6 % for d = 3). Bound: twice that.
    cfg = LaserSurpriseConfig()
    p = exceedance(cfg, 3)
    assert 0.003 < p < 0.01
    n = 5000
    fires = len(feed(LaserSurpriseDetector(cfg), np.random.default_rng(10).normal(0.0, 0.1, (n, 3))))
    assert fires < 2 * p * n


def test_laser_detector_reads_scans_and_validates_them() -> None:
    detector = LaserSurpriseDetector()
    ranges = np.full(181, 2.0)
    geometry = {
        "angle_min": -math.pi / 2,
        "angle_increment": math.pi / 180,
        "range_min": 0.1,
        "range_max": 20.0,
    }
    assert detector.on_scan(1.0, ranges, **geometry) is False
    with pytest.raises(DataError, match="went backwards"):
        detector.on_scan(0.5, ranges, **geometry)
    with pytest.raises(DataError, match="no valid beam"):
        detector.on_scan(2.0, np.full(181, np.nan), **geometry)
    assert detector.on_odometry(2.0, np.zeros(3)) is False
    assert detector.trace.stamps.tolist() == [1.0]


# ------------------------------------------------------------------------------------------- statistics


def test_log_area_is_the_area_of_the_scan_polygon() -> None:
    rng = np.random.default_rng(11)
    angle_min, inc = -math.pi / 2, math.pi / 180
    r = rng.uniform(0.5, 8.0, 181)
    r[[10, 11, 50]] = np.nan  # dropped: the fan joins the neighbouring valid beams
    keep = ~np.isnan(r)
    theta = angle_min + inc * np.arange(181)
    x, y = np.r_[0.0, (r * np.cos(theta))[keep]], np.r_[0.0, (r * np.sin(theta))[keep]]
    shoelace = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    value = scan_statistic(r, angle_min, inc, 0.1, 20.0, kind="log-area")
    assert value == pytest.approx([math.log(shoelace)], rel=1e-12)


def test_sector_statistics_average_log_ranges_and_treat_inf_as_open() -> None:
    n = 360
    angle_min, inc = -math.pi, 2 * math.pi / n
    theta = angle_min + inc * np.arange(n)
    r = np.full(n, 1.0)
    r[np.abs(theta - math.pi / 2) <= 0.25] = np.inf  # left: no return -> range_max
    r[np.abs(theta) <= 0.25] = 4.0
    r[np.abs(theta + math.pi / 2) <= 0.25] = np.where(np.arange(n) % 2 == 0, 2.0, 0.01)[
        np.abs(theta + math.pi / 2) <= 0.25
    ]
    sectors = scan_statistic(r, angle_min, inc, 0.05, 10.0)  # 0.01 < range_min: dropped
    assert sectors == pytest.approx([math.log(10.0), math.log(4.0), math.log(2.0)], rel=1e-12)
    assert scan_statistic(r, angle_min, inc, 0.05, 10.0, kind="sides") == pytest.approx(sectors[[0, 2]])
    with pytest.raises(ModelError, match="unknown scan statistic"):
        scan_statistic(r, angle_min, inc, 0.05, 10.0, kind="volume")


# ------------------------------------------------------------------------------------ appearance detector


def test_repeated_histogram_stops_being_surprising() -> None:
    prior = EdcmPrior(50, strength=10.0, precision=10.0)
    x = np.bincount(np.random.default_rng(12).integers(0, 50, 80), minlength=50)
    data = EdcmStats.empty(50)
    values = []
    for _ in range(60):
        values.append(edcm_surprise_step(prior, data, x, np.random.default_rng(0), 4).surprise)
        data = data.add(x)
    assert np.all(np.diff(values) < 0.0)
    assert values[-1] < 0.01 * values[0]


class Words:
    """A stand-in vocabulary: :class:`AppearanceSurpriseDetector` only needs ``size`` for measurements."""

    size = 64


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_change_of_word_distribution_fires_once(seed: int) -> None:
    rng = np.random.default_rng(seed)
    place_a, place_b = rng.dirichlet(np.full(64, 0.2)), rng.dirichlet(np.full(64, 0.2))
    detector = AppearanceSurpriseDetector(AppearanceSurpriseConfig(), vocabulary=Words(), rng=rng)  # type: ignore[arg-type]
    fired = [
        i
        for i in range(60)
        if detector.on_measurement(
            float(i), rng.multinomial(120, rng.dirichlet(100 * (place_a if i < 30 else place_b)))
        )
    ]
    assert fired == [31]
    assert detector.last_landmark_stamp == 30.0


def test_appearance_detector_on_panoramas() -> None:
    pytest.importorskip("cv2")
    from ptm_ros.model.vocabulary import Vocabulary, sift_descriptors

    rng = np.random.default_rng(13)

    def texture(seed: int) -> np.ndarray:
        blocks = np.random.default_rng(seed).uniform(0, 255, (8, 64))
        return np.kron(blocks, np.ones((8, 8)))

    scenes = [texture(1), texture(2)]
    images = [
        np.clip(scenes[i >= 12] + rng.normal(0, 3, (64, 512)), 0, 255).astype(np.uint8) for i in range(24)
    ]
    # 256 words: the EDCM sees only which words are present, and with ~300 features per panorama a small
    # vocabulary has every word present in every image.
    vocabulary = Vocabulary.build(np.vstack([sift_descriptors(im) for im in images[::3]]), 256, rng)
    detector = AppearanceSurpriseDetector(AppearanceSurpriseConfig(), vocabulary=vocabulary, rng=rng)
    fired = [i for i, im in enumerate(images) if detector.on_image(float(i), im)]
    assert fired == [13]
    fourier = AppearanceSurpriseDetector(AppearanceSurpriseConfig(model="fourier", prior_std=0.1), rng=rng)
    assert [i for i, im in enumerate(images) if fourier.on_image(float(i), im)] == [13]


# --------------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("statistic", "volume", "statistic must be one of"),
        ("side_half_angle", 2.0, r"side_half_angle must be a finite number in \(0, 1\.5708\)"),
        ("memory", 0.0, "memory must be a finite number > 0"),
        ("memory_distance", -1.0, "memory_distance must be a number > 0"),
        ("prior_std", 0.0, "prior_std must be a finite number > 0"),
        ("band_sigmas", math.nan, "band_sigmas must be a finite number > 0"),
        ("samples", 1, "samples must be an integer >= 2"),
        ("warmup", 1.5, "warmup must be an integer >= 1"),
        ("min_travel", -0.1, "min_travel must be a finite number >= 0"),
    ],
)
def test_laser_config_rejects_bad_values(field: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        LaserSurpriseConfig(**{field: value})  # type: ignore[arg-type]


def test_appearance_config_and_detector_reject_bad_values() -> None:
    with pytest.raises(ConfigError, match=r"model must be one of \('words', 'fourier'\)"):
        AppearanceSurpriseConfig(model="colour")
    with pytest.raises(ConfigError, match="edcm_strength must be a finite number > 0"):
        AppearanceSurpriseConfig(edcm_strength=0.0)
    with pytest.raises(ConfigError, match="needs a Vocabulary"):
        AppearanceSurpriseDetector(AppearanceSurpriseConfig(model="words"))
    detector = AppearanceSurpriseDetector(AppearanceSurpriseConfig(), vocabulary=Words())  # type: ignore[arg-type]
    with pytest.raises(DataError, match="histogram has 3 words, the model 64"):
        detector.on_measurement(0.0, np.array([1, 2, 3]))


def test_model_types_reject_bad_parameters() -> None:
    with pytest.raises(ModelError, match="dof > d - 1"):
        Niw([0.0, 0.0], 1.0, 0.5, np.eye(2))
    with pytest.raises(ModelError, match="not positive definite"):
        Niw([0.0, 0.0], 1.0, 4.0, [[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(ModelError, match="rate must be finite and > 0"):
        NormalGamma([0.0], [1.0], [1.0], [0.0])
    with pytest.raises(ModelError, match="background must be a positive"):
        EdcmPrior(3, background=np.array([1.0, 0.0, 1.0]))


# ------------------------------------------------------------------------------------- simulated worlds


def detections(run: object, config: LaserSurpriseConfig) -> list[float]:
    laser = run.config.laser  # type: ignore[attr-defined]
    detector = LaserSurpriseDetector(config)
    found = []
    for stamp, kind, i in run.events(images=False):  # type: ignore[attr-defined]
        if kind == 0:
            detector.on_odometry(stamp, run.odom_poses[i])  # type: ignore[attr-defined]
        elif detector.on_scan(
            stamp,
            run.scan_ranges[i],  # type: ignore[attr-defined]
            angle_min=laser.angle_min,
            angle_increment=laser.angle_increment,
            range_min=laser.range_min,
            range_max=laser.range_max,
        ):
            found.append(detector.last_landmark_stamp)
    return found


def match_passages(run: object, stamps: list[float], radius: float = 2.0) -> tuple[int, int]:
    """(passages with a detection within ``radius`` m of the place during that passage, false positives).

    Each passage takes at most one detection: extra detections at a place count as false positives.
    """
    t, poses = run.odom_stamps, run.true_poses  # type: ignore[attr-defined]
    xy = np.column_stack([np.interp(stamps, t, poses[:, 0]), np.interp(stamps, t, poses[:, 1])]).reshape(
        -1, 2
    )
    used = np.zeros(len(stamps), dtype=bool)
    hits = 0
    for passage in run.passages:  # type: ignore[attr-defined]
        place = run.world.place(passage.place)  # type: ignore[attr-defined]
        near = np.hypot(poses[:, 0] - place.x, poses[:, 1] - place.y) <= radius
        k = int(np.argmin(np.abs(t - passage.stamp)))
        lo, hi = k, k
        while lo > 0 and near[lo - 1]:
            lo -= 1
        while hi < len(t) - 1 and near[hi + 1]:
            hi += 1
        ok = (~used) & (np.asarray(stamps) >= t[lo]) & (np.asarray(stamps) <= t[hi])
        ok &= np.hypot(xy[:, 0] - place.x, xy[:, 1] - place.y) <= radius
        if ok.any():
            used[np.flatnonzero(ok)[0]] = True
            hits += 1
    return hits, int((~used).sum())


@pytest.mark.parametrize("world", ["aliased-loop", "t-junction", "multi-loop"])
@pytest.mark.slow
def test_laser_surprise_finds_the_decision_points_of_simulated_worlds(world: str) -> None:
    sim = pytest.importorskip("ptm_ros.io.simulator")
    worlds = pytest.importorskip("ptm_ros.io.worlds")
    config = sim.SimConfig(camera=sim.CameraConfig(enabled=False))
    run = sim.simulate(worlds.get_world(world), config, np.random.default_rng(0))
    hits, false_positives = match_passages(run, detections(run, LaserSurpriseConfig()))
    passages = len(run.passages)
    assert hits >= 0.95 * passages
    assert false_positives <= passages


def test_on_scan_equals_on_statistic_with_the_sides_openness() -> None:
    """:meth:`LaserSurpriseDetector.on_scan` takes the openness (mean ``sides`` statistic) from the
    ``sectors`` statistic it already has: the same numbers as computing ``sides`` separately, so the trace
    and the localised landmarks are identical, bit for bit."""
    sim = pytest.importorskip("ptm_ros.io.simulator")
    worlds = pytest.importorskip("ptm_ros.io.worlds")
    config = sim.SimConfig(camera=sim.CameraConfig(enabled=False))
    run = sim.simulate(worlds.get_world("t-junction"), config, np.random.default_rng(4), visits=3)
    lc = run.config.laser
    geometry = (lc.angle_min, lc.angle_increment, lc.range_min, lc.range_max)
    cfg = LaserSurpriseConfig()
    direct, manual = LaserSurpriseDetector(cfg), LaserSurpriseDetector(cfg)
    fired = [[], []]
    for t, kind, k in run.events(images=False):
        if kind == 0:
            direct.on_odometry(t, run.odom_poses[k])
            manual.on_odometry(t, run.odom_poses[k])
            continue
        r = run.scan_ranges[k]
        if direct.on_scan(
            t,
            r,
            angle_min=geometry[0],
            angle_increment=geometry[1],
            range_min=geometry[2],
            range_max=geometry[3],
        ):
            fired[0].append(direct.last_landmark_stamp)
        z = scan_statistic(r, *geometry, kind="sectors")
        sides = scan_statistic(r, *geometry, kind="sides")
        if manual.on_statistic(t, z, openness=float(np.mean(sides))):
            fired[1].append(manual.last_landmark_stamp)
    assert len(fired[0]) >= 2 and fired[0] == fired[1]
    assert np.array_equal(direct.trace.surprise, manual.trace.surprise)


def test_limit_trace_keeps_the_latest_rows_and_detects_the_same():
    """A bounded trace (the node's memory bound) keeps the latest measurements and changes no decision."""
    rng = np.random.default_rng(5)
    z = np.concatenate([rng.normal(0.0, 0.05, (60, 3)), rng.normal(2.0, 0.05, (40, 3))])
    full = LaserSurpriseDetector(LaserSurpriseConfig(localize_distance=0.0))
    bounded = LaserSurpriseDetector(LaserSurpriseConfig(localize_distance=0.0))
    bounded.limit_trace(7)
    fired = [(full.on_statistic(float(t), v), bounded.on_statistic(float(t), v)) for t, v in enumerate(z)]
    assert [a for a, _ in fired] == [b for _, b in fired] and any(a for a, _ in fired)
    tail = full.trace
    short = bounded.trace
    assert len(short.stamps) == 7
    np.testing.assert_array_equal(short.stamps, tail.stamps[-7:])
    np.testing.assert_array_equal(short.surprise, tail.surprise[-7:])
    np.testing.assert_array_equal(short.landmarks, tail.landmarks[-7:])
    with pytest.raises(ConfigError, match="trace rows"):
        bounded.limit_trace(-1)


def test_a_trace_crosses_json_exactly_and_bad_documents_are_refused():
    """The detector node's ``~/surprise_trace`` answer: the trace of a surprise detector through JSON, bit for
    bit; other detectors have none (and nothing to bound)."""
    from ptm_ros.perception.detectors import EquidistantDetector

    rng = np.random.default_rng(3)
    det = LaserSurpriseDetector(LaserSurpriseConfig(localize_distance=0.0))
    z = np.concatenate([rng.normal(0.0, 0.05, (50, 3)), rng.normal(2.0, 0.05, (30, 3))])
    for t, v in enumerate(z):
        det.on_statistic(1000.0 + 0.1 * t, v)
    trace = surprise_trace(det)
    assert trace is not None and len(trace.stamps) == len(z) and len(trace.landmarks) >= 1
    back = trace_from_dict(json.loads(json.dumps(trace_to_dict(trace))))
    for name in ("stamps", "surprise", "predicted_mean", "predicted_std", "upper", "landmarks"):
        np.testing.assert_array_equal(getattr(back, name), getattr(trace, name))
    limit_surprise_trace(det, 5)
    assert len(surprise_trace(det).stamps) == 5
    plain = EquidistantDetector()
    limit_surprise_trace(plain, 5)  # no trace: nothing to do
    assert surprise_trace(plain) is None
    doc = trace_to_dict(trace)
    with pytest.raises(DataError, match="not a surprise trace"):
        trace_from_dict({**doc, "schema": "other/1"})
    with pytest.raises(DataError, match="missing or non-numeric 'upper'"):
        trace_from_dict({k: v for k, v in doc.items() if k != "upper"})
    with pytest.raises(DataError, match="unequal lengths"):
        trace_from_dict({**doc, "surprise": doc["surprise"][1:]})
