"""MCMC over topologies: proposal probabilities by enumeration, detailed balance against the exact posterior.

The scene is a robot driving a 0.8 m square of four places and back to the first (N = 5, B_5 = 52) or one
more visit (N = 6, B_6 = 203); places are so close, and the one-component signatures so noisy, that the
posterior spreads over many topologies (entropy ≈ 2.5 nats, max ≈ 0.15 at N = 5), so a sampler with a
wrong acceptance ratio visibly misses it.

Monte Carlo bounds: a chain of n sweeps estimates π(T) with variance ≈ τ π(1-π)/n (τ = integrated
autocorrelation time). Each detailed-balance test estimates that error itself by batch means (20 batches)
and requires (i) the expected TV implied by it, ``½ Σ_T √(2/π) sd_T``, to be at most ``BOUND / 3`` — the
run is long enough for the bound to be meaningful — and (ii) the observed TV to the exact posterior to be
at most ``BOUND``. The TV is a sum of many absolute errors, so it scatters little around its mean
(observed: ±0.003 around an expected 0.006–0.013 over seeds); ``BOUND`` is then more than ten such
deviations above the expected TV and cannot be exceeded by chance, while a wrong ratio (see
``test_wrong_ratio_is_detected``: TV ≈ 0.54) misses it by far. Sweeps per kernel are chosen so that the
expected TV is ≈ 0.012 (the odometry and appearance kernels with a sharp scale mix more slowly on this
deliberately flat posterior; MC³ makes three MH steps per sweep).
"""

from __future__ import annotations

import math
from dataclasses import replace
from itertools import pairwise

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import comb, logsumexp
from scipy.stats import norm

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.inference.mcmc import (
    McmcConfig,
    McmcSampler,
    pair_marginal_change,
    run_mcmc,
    starts_from_filter,
    thesis_ladder,
)
from ptm_ros.inference.proposals import (
    AppearanceProposal,
    MixtureProposal,
    Move,
    OdometryProposal,
    ReassignProposal,
    SplitMergeProposal,
    bhattacharyya_similarity,
    make_proposal,
)
from ptm_ros.model.appearance import AppearanceConfig
from ptm_ros.model.geometry import compose
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.partitions import blocks, enumerate_partitions, random_partition
from ptm_ros.model.posterior import (
    ModelConfig,
    PosteriorModel,
    exact_posterior,
    normalize_log,
    total_variation,
)
from ptm_ros.model.priors import PriorConfig
from ptm_ros.model.visits import Visit

BOUND = 0.05


def spread_visits(route=(0, 1, 2, 3, 0), side=0.8, seed=4):
    """Visits of a small square of places with noisy odometry and one noisy signature component."""
    rng = np.random.default_rng(seed)
    pts = np.array([(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)])
    base = rng.uniform(0.5, 2.5, size=(4, 1))
    visits = []
    pose = np.array([*pts[route[0]], 0.0])
    true = pose.copy()
    for i, p in enumerate(route):
        travel = rotation = 0.0
        if i > 0:
            d = pts[p] - pts[route[i - 1]]
            heading = math.atan2(d[1], d[0])
            step = float(np.hypot(*d))
            dth = heading - true[2]
            rel = np.array([step * math.cos(dth), step * math.sin(dth), dth])
            pose = compose(pose, rel + rng.normal(0.0, [0.1, 0.1, 0.01]))
            true = np.array([*pts[p], heading])
            travel, rotation = step, abs(dth)
        sig = np.abs(base[p] + rng.normal(0.0, 0.5, 1))
        visits.append(Visit(i, float(i), tuple(float(v) for v in pose), travel, rotation, signature=sig))
    return visits


MODEL_CONFIG = ModelConfig(  # the area model and within_fraction 0.1: the posterior these tests were built on
    prior=PriorConfig(alpha=2.0),
    odometry=OdometryConfig(
        n_samples=0, penalty_max=0.0, area_m2=20.0, sigma_topology=1.0, place_prior="area"
    ),
    appearance=AppearanceConfig(within_fraction=0.1),
)


@pytest.fixture(scope="module")
def model5():
    return PosteriorModel(spread_visits(), MODEL_CONFIG)


@pytest.fixture(scope="module")
def exact5(model5):
    return normalize_log(exact_posterior(model5))


@pytest.fixture(scope="module")
def model6():
    return PosteriorModel(spread_visits((0, 1, 2, 3, 0, 1)), MODEL_CONFIG)


def test_scene_posterior_is_spread(exact5):
    p = np.sort(np.fromiter(exact5.values(), float))[::-1]
    assert len(p) == 52
    assert p[0] < 0.3
    assert np.sum(p > 0.01) >= 10


# ---------------------------------------------------------------------------------------------------
# Proposal probabilities
# ---------------------------------------------------------------------------------------------------


def thesis_plain_q(src, dst):
    """q(src → dst) of Algorithm 2 from its definition (merge 1/C(M,2), split 1/(N_S S(|U|,2)), ½ each)."""
    ps = [frozenset(b) for b in blocks(src)]
    pd = [frozenset(b) for b in blocks(dst)]
    m = len(ps)
    n_split = sum(len(b) > 1 for b in ps)
    if src == dst:
        return 0.5 * (m < 2) + 0.5 * (n_split == 0)
    gone, new = set(ps) - set(pd), set(pd) - set(ps)
    if len(gone) == 2 and len(new) == 1:
        return 0.5 / comb(m, 2, exact=True)
    if len(gone) == 1 and len(new) == 2:
        (u,) = gone
        return 0.5 / n_split / (2 ** (len(u) - 1) - 1)
    return 0.0


def test_plain_split_merge_matches_algorithm_2(model6):
    kernel = SplitMergeProposal()
    labels = list(enumerate_partitions(6))
    for src in labels[::7]:
        dist = kernel.distribution(src)
        assert math.fsum(dist.values()) == pytest.approx(1.0, abs=1e-12)
        for dst in labels:
            q = thesis_plain_q(src, dst)
            assert dist.get(dst, 0.0) == pytest.approx(q, rel=1e-12, abs=0.0)
            assert kernel.log_prob(src, dst) == pytest.approx(math.log(q) if q > 0 else -math.inf)


def kernels(model):
    return {
        "split-merge": SplitMergeProposal(),
        "odometry": OdometryProposal(model, scale=0.5, mix=0.0),
        "odometry-mixed": OdometryProposal(model, scale=0.5, mix=0.2),
        "appearance": AppearanceProposal(model, strength=10.0, mix=0.0),
        "appearance-small-enumeration": AppearanceProposal(model, strength=10.0, mix=0.1, max_split_size=3),
        "reassign": ReassignProposal(model, scale=0.5, mix=0.0, new_place=1.0),
        "reassign-mixed": ReassignProposal(model, scale=0.5, mix=0.2, new_place=1.0),
    }


@pytest.mark.parametrize(
    "name",
    [
        "split-merge",
        "odometry",
        "odometry-mixed",
        "appearance",
        "appearance-small-enumeration",
        "reassign",
        "reassign-mixed",
    ],
)
def test_proposal_ratio_matches_enumeration(model6, name):
    """For random T and drawn T', the move's log q forward / reverse equal the enumerated q(T→T'), q(T'→T)."""
    kernel = kernels(model6)[name]
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(25):
        src = random_partition(6, rng)
        dist = kernel.distribution(src)
        assert math.fsum(dist.values()) == pytest.approx(1.0, abs=1e-12)
        for _ in range(8):
            move = kernel.propose(src, rng)
            if move.kind == "stay":
                assert move.labels == src
                continue
            back = kernel.distribution(move.labels)
            assert move.log_forward == pytest.approx(math.log(dist[move.labels]), abs=1e-9)
            assert move.log_reverse == pytest.approx(math.log(back[src]), abs=1e-9)
            assert move.log_ratio == pytest.approx(math.log(back[src] / dist[move.labels]), abs=1e-9)
            assert kernel.log_prob(src, move.labels) == pytest.approx(move.log_forward, abs=1e-12)
            checked += 1
    assert checked > 100


@pytest.mark.parametrize("name", ["split-merge", "odometry", "appearance", "reassign"])
@pytest.mark.slow
def test_proposal_draws_follow_the_enumerated_distribution(model6, name):
    kernel = kernels(model6)[name]
    src = (0, 1, 0, 2, 0, 1)
    dist = kernel.distribution(src)
    rng = np.random.default_rng(2)
    n = 40_000
    counts: dict = {}
    for _ in range(n):
        lab = kernel.propose(src, rng).labels
        counts[lab] = counts.get(lab, 0) + 1
    freq = {k: v / n for k, v in counts.items()}
    # E TV ≤ ½ Σ √(p/n) ≤ ½ √(K/n) with K ≤ 20 reachable topologies: 0.011; bound ≈ 4 E, > 10 sd
    assert len(dist) <= 20
    assert total_variation(freq, dist) < 0.04
    assert set(freq) <= set(dist)


def test_huge_block_splits_stay_exact():
    kernel = SplitMergeProposal()
    labels = (0,) * 70
    rng = np.random.default_rng(0)
    move = kernel.propose(labels, rng)
    while move.kind == "stay":
        move = kernel.propose(labels, rng)
    assert move.kind == "split"
    assert move.log_forward == pytest.approx(math.log(0.5) - math.log(2.0**69 - 1.0))
    assert kernel.log_prob(labels, move.labels) == pytest.approx(move.log_forward)
    assert kernel.log_prob(move.labels, labels) == pytest.approx(move.log_reverse)
    assert move.log_reverse == pytest.approx(math.log(0.5))  # one merge possible from two blocks


def test_bhattacharyya_similarity_matches_integration():
    visits = spread_visits()
    model = PosteriorModel(visits, MODEL_CONFIG)
    sim = bhattacharyya_similarity(visits, model.appearance)
    nig = model.appearance.nig
    sd = math.sqrt(nig.beta[0] / (nig.alpha[0] - 1.0))
    a, b = float(visits[0].signature[0]), float(visits[2].signature[0])
    bc, _ = quad(lambda x: math.sqrt(norm.pdf(x, a, sd) * norm.pdf(x, b, sd)), -50, 50, points=[a, b])
    assert sim[0, 2] == pytest.approx(bc, rel=1e-6)
    assert np.allclose(sim, sim.T) and np.all(np.diag(sim) == 1.0) and np.all((sim > 0) & (sim <= 1))


def test_bhattacharyya_similarity_of_word_histograms():
    words = [np.array([5, 0, 1]), np.array([4, 1, 0]), np.array([0, 0, 0])]
    visits = [Visit(i, float(i), (float(i), 0.0, 0.0), words=w) for i, w in enumerate(words)]
    cfg = ModelConfig(appearance=AppearanceConfig(models=("words",), dcm_alpha=0.5))
    model = PosteriorModel(visits, cfg)
    sim = bhattacharyya_similarity(visits, model.appearance)
    p = [(w + 0.5) / (w.sum() + 1.5) for w in words]
    for i in range(3):
        for j in range(3):
            expected = 1.0 if i == j else float(np.sum(np.sqrt(p[i] * p[j])))
            assert sim[i, j] == pytest.approx(expected, rel=1e-12)


# ---------------------------------------------------------------------------------------------------
# Detailed balance: the chains sample the exact posterior
# ---------------------------------------------------------------------------------------------------


def sample_and_check(model, exact, config, sweeps, proposal=None, seed=0):
    """Run one chain for ``sweeps`` sweeps; return (TV to exact, batch-means expected TV)."""
    cfg = McmcConfig(
        chains=1,
        estimate="histogram",
        burn_in=0.0,
        min_iterations=sweeps,
        max_iterations=sweeps,
        max_seconds=600.0,
        **{"betas": (1.0,), **config},
    )
    with McmcSampler(model, cfg, seed, proposal=proposal) as sampler:
        sampler.advance(sweeps)
        batches = 20
        size = sweeps // batches
        cum = [sampler.estimate("histogram", stop=size * b) for b in range(1, batches + 1)]
    keys = list(exact)
    counts = np.array([[c.get(k, 0.0) * size * (b + 1) for k in keys] for b, c in enumerate(cum)])
    per_batch = np.diff(np.vstack([np.zeros(len(keys)), counts]), axis=0) / size
    sd = per_batch.std(axis=0, ddof=1) / math.sqrt(batches)
    expected_tv = 0.5 * math.sqrt(2.0 / math.pi) * float(sd.sum())
    return total_variation(cum[-1], exact), expected_tv


@pytest.mark.parametrize(
    ("config", "sweeps"),
    [
        ({"proposal": "split-merge"}, 100_000),
        ({"proposal": "odometry", "odometry_scale": 0.5, "proposal_mix": 0.0}, 150_000),
        ({"proposal": "appearance", "appearance_strength": 10.0, "proposal_mix": 0.0}, 150_000),
        (
            {"proposal": "reassign", "odometry_scale": 0.5, "new_place_distance": 1.0, "proposal_mix": 0.0},
            150_000,
        ),
        ({"proposal": "auto", "odometry_scale": 0.5, "max_chaining": 3}, 100_000),
        ({"proposal": "split-merge", "betas": thesis_ladder(3, 2.0)}, 50_000),
    ],
    ids=["split-merge", "odometry", "appearance", "reassign", "chained-mixture", "mc3-cold-chain"],
)
@pytest.mark.slow
def test_chain_samples_the_exact_posterior(model5, exact5, config, sweeps):
    tv, expected = sample_and_check(model5, exact5, config, sweeps)
    assert expected <= BOUND / 3
    assert tv <= BOUND


class IgnoresReverse(SplitMergeProposal):
    """A deliberately wrong kernel: reports q(T'→T) = q(T→T') (the proposal ratio dropped)."""

    def propose(self, labels, rng):
        move = super().propose(labels, rng)
        return Move(move.labels, move.log_forward, move.log_forward, move.kind)


def test_wrong_ratio_is_detected(model5, exact5):
    tv, expected = sample_and_check(model5, exact5, {"proposal": "split-merge"}, 20_000, IgnoresReverse())
    assert expected <= BOUND / 3
    assert tv > 5 * BOUND


def test_mc3_swaps_and_acceptance_are_reported(model5):
    cfg = McmcConfig(
        proposal="split-merge", betas=(1.0, 0.5, 0.25), chains=1, min_iterations=2000, max_iterations=2000
    )
    res = run_mcmc(model5, cfg, 0)
    acc = res.diagnostics.acceptance
    assert set(acc) >= {"merge", "split", "swap 0-1", "swap 1-2"}
    assert all(0.0 < v < 1.0 for v in acc.values())
    assert res.diagnostics.proposals["swap 0-1"] == 2000


# ---------------------------------------------------------------------------------------------------
# Estimates, convergence, determinism, errors
# ---------------------------------------------------------------------------------------------------


def test_visited_estimate_is_the_posterior_renormalised(model6):
    cfg = McmcConfig(chains=2, min_iterations=200, max_iterations=200)
    res = run_mcmc(model6, cfg, 5)
    lp = res.log_posteriors
    z = logsumexp(list(lp.values()))
    for lab, p in res.visited.items():
        assert p == pytest.approx(math.exp(lp[lab] - z), rel=1e-9)
        assert lp[lab] == pytest.approx(model6.log_posterior(lab), abs=1e-12)
    exact = normalize_log(exact_posterior(model6))
    covered = math.fsum(exact[lab] for lab in res.visited)
    assert total_variation(res.visited, exact) == pytest.approx(1.0 - covered, abs=1e-9)
    assert math.fsum(res.histogram.values()) == pytest.approx(1.0)
    assert res.samples == 400
    assert list(res.probabilities.values()) == sorted(res.probabilities.values(), reverse=True)


def test_converges_and_stops_on_its_own(model6):
    exact = normalize_log(exact_posterior(model6))
    cfg = McmcConfig(tolerance=0.01, min_iterations=100, max_iterations=100_000)
    res = run_mcmc(model6, cfg, 0)
    diag = res.diagnostics
    assert diag.converged and diag.stop_reason == "converged"
    assert diag.iterations < cfg.max_iterations
    assert diag.doubling_tv <= 0.01 and diag.chain_tv is not None and diag.chain_tv <= 0.01
    assert [h.iterations for h in diag.history] == [100 * 2**k for k in range(len(diag.history))]
    assert total_variation(res.probabilities, exact) <= 0.01
    assert max(res.probabilities, key=res.probabilities.get) == max(exact, key=exact.get)
    # a pair's same-place probability is the probability of an event: it moves by at most the TV
    for h in diag.history:
        assert 0.0 <= h.doubling_pair <= h.doubling_tv + 1e-5
        assert h.chain_pair is not None and 0.0 <= h.chain_pair <= h.chain_tv + 1e-5
    last = diag.history[-1]
    assert (diag.doubling_pair, diag.chain_pair) == (last.doubling_pair, last.chain_pair)


def test_pair_marginal_change_is_the_largest_same_place_probability_difference():
    p = {(0, 0, 1): 0.5, (0, 1, 2): 0.5}  # P(0~1) = 0.5, P(1~2) = 0, P(0~2) = 0
    q = {(0, 1, 1): 0.8, (0, 0, 0): 0.2}  # P(0~1) = 0.2, P(1~2) = 1, P(0~2) = 0.2
    assert pair_marginal_change(p, q, 3) == pytest.approx(1.0)
    assert pair_marginal_change(p, {(0, 0, 1): 0.2, (0, 1, 2): 0.8}, 3) == pytest.approx(0.3)
    assert pair_marginal_change(p, p, 3) == 0.0
    assert pair_marginal_change({(0,): 1.0}, {(0,): 1.0}, 1) == 0.0
    # two PTMs with disjoint support (TV 1) can agree on every pair: P(0~1) = P(2~3) = 0.5 in both
    a = {(0, 0, 1, 2): 0.5, (0, 1, 2, 2): 0.5}
    b = {(0, 0, 1, 1): 0.5, (0, 1, 2, 3): 0.5}
    assert total_variation(a, b) == pytest.approx(1.0)
    assert pair_marginal_change(a, b, 4) == pytest.approx(0.0)
    # the least probable topologies holding 1e-6 of the mass are left out
    assert pair_marginal_change(a, {**a, (0, 1, 0, 1): 1e-7}, 4) == 0.0


def test_caps_stop_an_unconverged_run(model5):
    capped = run_mcmc(
        model5, McmcConfig(estimate="histogram", tolerance=1e-6, min_iterations=50, max_iterations=400), 0
    )
    assert capped.diagnostics.stop_reason == "max_iterations"
    assert not capped.diagnostics.converged
    assert capped.diagnostics.iterations == 400
    timed = run_mcmc(
        model5,
        McmcConfig(estimate="histogram", tolerance=1e-6, max_iterations=10**9, max_seconds=0.3),
        0,
    )
    assert timed.diagnostics.stop_reason == "max_seconds"
    assert timed.diagnostics.iterations < 10**9


@pytest.mark.parametrize("processes", [1, 2])
def test_the_time_cap_is_checked_after_every_sweep(model5, monkeypatch, processes):
    """A long run's sweep can take a second (its registrations computed on first use): the cap must not
    wait for a whole chunk of sweeps. Counted in sweeps, so a slow machine cannot fail it."""
    import time

    import ptm_ros.inference.mcmc as mcmc_module

    sweep = mcmc_module._Ladder.sweep

    def slow_sweep(self):
        time.sleep(0.05)
        sweep(self)

    monkeypatch.setattr(mcmc_module._Ladder, "sweep", slow_sweep)  # inherited by forked workers
    cfg = McmcConfig(chains=2, processes=processes, tolerance=1e-9, min_iterations=500, max_seconds=0.3)
    with McmcSampler(model5, cfg, 0) as sampler:
        reached = sampler.advance(cfg.min_iterations, cfg.max_seconds)
        sweeps = [rec.iteration for rec in sampler.records]
    assert 1 <= reached < 500
    assert max(sweeps) <= 0.3 / 0.05 + 2  # the deadline, plus the sweep that crosses it


def test_deterministic_under_a_seed(model6):
    cfg = McmcConfig(min_iterations=300, max_iterations=300, max_chaining=2, betas=(1.0, 0.6))
    a = run_mcmc(model6, cfg, 11)
    b = run_mcmc(model6, cfg, 11)
    c = run_mcmc(model6, cfg, 12)
    assert a.histogram == b.histogram and a.visited == b.visited
    assert a.diagnostics.acceptance == b.diagnostics.acceptance
    assert a.histogram != c.histogram
    gen = run_mcmc(model6, cfg, np.random.default_rng(11))
    assert gen.histogram == run_mcmc(model6, cfg, np.random.default_rng(11)).histogram


def test_progress_hears_of_the_sweeps_and_changes_nothing(model6):
    """``run_mcmc(progress=...)`` (ptm-run's bar) advances the chains in tenths of a round: the same
    result as without, the sweeps reported rising to each round's target (rounds double)."""
    cfg = McmcConfig(min_iterations=100, max_iterations=400, tolerance=1e-9, chains=2)
    heard: list[tuple[int, int]] = []
    with_bar = run_mcmc(model6, cfg, 7, progress=lambda done, target: heard.append((done, target)))
    plain = run_mcmc(model6, cfg, 7)
    assert with_bar.histogram == plain.histogram and with_bar.visited == plain.visited
    assert with_bar.cold_states == plain.cold_states
    assert with_bar.diagnostics.proposals == plain.diagnostics.proposals
    assert [d for d, _ in heard] == sorted(d for d, _ in heard) and heard[-1] == (400, 400)
    assert {t for _, t in heard} == {100, 200, 400} and heard[:2] == [(10, 100), (20, 100)]


def test_worker_processes_give_the_same_result(model6):
    cfg = McmcConfig(min_iterations=300, max_iterations=300, chains=2)
    inline = run_mcmc(model6, cfg, 7)
    forked = run_mcmc(model6, replace(cfg, processes=2), 7)
    assert forked.histogram == inline.histogram
    assert forked.visited == pytest.approx(inline.visited)
    assert forked.diagnostics.proposals == inline.diagnostics.proposals


def test_single_visit_and_initial_states(model6):
    one = PosteriorModel(spread_visits((0,)), MODEL_CONFIG)
    res = run_mcmc(one, McmcConfig(min_iterations=10, max_iterations=10), 0)
    assert res.probabilities == {(0,): 1.0}
    start = (0, 1, 0, 1, 0, 1)
    with McmcSampler(model6, McmcConfig(chains=1), 0, initial=start) as sampler:
        assert sampler.estimate("histogram") == {start: 1.0}  # before any sweep: the initial state
    for initial in ("one-place", "random"):
        out = run_mcmc(model6, McmcConfig(initial=initial, min_iterations=50, max_iterations=50), 0)
        assert out.samples == 100


def test_make_proposal_picks_the_supported_kernels(model6):
    assert isinstance(make_proposal(model6, McmcConfig()), MixtureProposal)
    assert make_proposal(model6, McmcConfig()).name == "odometry+appearance+reassign"
    no_app = PosteriorModel(
        spread_visits(), ModelConfig(use_appearance=False, odometry=MODEL_CONFIG.odometry)
    )
    assert make_proposal(no_app, McmcConfig()).name == "odometry+reassign"
    assert isinstance(make_proposal(no_app, McmcConfig(proposal="odometry")), OdometryProposal)
    assert isinstance(make_proposal(no_app, McmcConfig(proposal="reassign")), ReassignProposal)
    bare = PosteriorModel(spread_visits(), ModelConfig(use_appearance=False, use_odometry=False))
    assert type(make_proposal(bare, McmcConfig())) is SplitMergeProposal
    with pytest.raises(ModelError, match="appearance term"):
        make_proposal(bare, McmcConfig(proposal="appearance"))
    # the odometry kernel falls back to raw odometry positions without a metric term
    pos = OdometryProposal(bare).place_positions((0, 1, 2, 3, 0))
    u = np.array([v.pose[:2] for v in bare.visits])
    assert np.allclose(pos[0], (u[0] + u[4]) / 2) and np.allclose(pos[1:], u[1:4])


def test_thesis_ladder():
    assert thesis_ladder(3, 0.5) == pytest.approx((1.0, 1 / 1.5, 0.5))
    assert all(a > b for a, b in pairwise(thesis_ladder(5, 10.0)))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"proposal": "gibbs"}, "proposal must be one of"),
        ({"estimate": "mode"}, "estimate must be one of"),
        ({"betas": (0.5, 0.25)}, "betas must start at 1.0"),
        ({"betas": (1.0, 0.5, 0.5)}, "decrease strictly"),
        ({"tolerance": 0.0}, r"tolerance must be a finite number in \(0, 1\)"),
        ({"proposal_mix": 1.0}, r"proposal_mix must be a finite number in \[0, 1\)"),
        ({"max_chaining": 0}, "max_chaining must be an integer >= 1"),
        ({"min_iterations": 10, "max_iterations": 5}, "max_iterations"),
        ({"max_split_enumeration": 30}, r"max_split_enumeration must be an integer in \[2, 20\]"),
        ({"new_place_distance": 0.0}, "new_place_distance must be a finite number > 0"),
        ({"initial": "filter"}, "initial must be one of"),
        ({"auto_filter_visits": 0}, "auto_filter_visits must be an integer >= 1"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        McmcConfig(**kwargs)


def test_bad_initial_topology(model5):
    with pytest.raises(ModelError, match="canonical label sequence of 5 visits"):
        McmcSampler(model5, McmcConfig(), 0, initial=(1, 0, 0, 0, 0))
    with pytest.raises(ModelError, match="canonical label sequence of 5 visits"):
        McmcSampler(model5, McmcConfig(), 0, initial=[(0, 0, 0, 0, 0), (0, 1)])
    with pytest.raises(ConfigError, match="rbpf"):
        McmcSampler(model5, McmcConfig(initial="rbpf"), 0)


def test_auto_start_is_singletons_on_short_runs_and_the_filter_on_long_ones(model5):
    """``initial: auto`` (the default): from singletons up to ``auto_filter_visits`` visits; beyond, the
    chains need the filter's topologies, which only the caller (``pipeline.infer``) can supply."""
    auto = McmcConfig()
    assert auto.initial == "auto"
    by_threshold = [starts_from_filter(replace(auto, auto_filter_visits=k), 5) for k in (4, 5, 6)]
    assert by_threshold == [True, False, False]
    assert starts_from_filter(McmcConfig(initial="rbpf"), 1) is True
    assert starts_from_filter(McmcConfig(initial="singletons", auto_filter_visits=1), 5) is False
    with McmcSampler(model5, auto, 0) as sampler:
        assert [next(iter(rec.visited)) for rec in sampler.records] == [(0, 1, 2, 3, 4)] * auto.chains
    with pytest.raises(ConfigError, match=r"'auto' over 5 visits needs the filter's topologies"):
        McmcSampler(model5, replace(auto, auto_filter_visits=4), 0)
    given = (0, 0, 1, 1, 0)
    with McmcSampler(model5, replace(auto, auto_filter_visits=4), 0, initial=given) as sampler:
        assert next(iter(sampler.records[0].visited)) == given


def test_each_chain_starts_from_its_given_topology(model6):
    """A sequence of topologies: chain c starts from the c-th (cycled); "rbpf" takes them from the caller."""
    starts = [(0, 1, 0, 1, 0, 1), (0, 0, 0, 0, 0, 0)]
    config = McmcConfig(chains=3, initial="rbpf", betas=(1.0,))
    with McmcSampler(model6, config, 0, initial=starts) as sampler:
        first = [next(iter(rec.visited)) for rec in sampler.records]
    assert first == [starts[0], starts[1], starts[0]]
    res = run_mcmc(model6, replace(config, min_iterations=50, max_iterations=50), 0, initial=starts)
    assert res.samples == 150
    with pytest.raises(ConfigError, match="ladder"):
        thesis_ladder(0, 1.0)


# ---------------------------------------------------------------------------------------------------
# Cold-chain trace (SRQ plots)
# ---------------------------------------------------------------------------------------------------


def test_cold_trace_reproduces_the_histogram(model6):
    cfg = McmcConfig(estimate="histogram", burn_in=0.0, min_iterations=300, max_iterations=300, chains=2)
    res = run_mcmc(model6, cfg, 3)
    assert res.cold_thin == 1
    assert [len(s) for s in res.cold_states] == [300, 300]
    ids = {i for s in res.cold_states for i in s}
    assert ids == set(range(len(res.state_labels)))  # dense ids, only states that occur
    assert len(set(res.state_labels)) == len(res.state_labels)  # one id per topology, shared by chains
    counts: dict = {}
    for s in res.cold_states:
        for i in s:
            lab = res.state_labels[i]
            counts[lab] = counts.get(lab, 0) + 1
    assert {lab: c / 600 for lab, c in counts.items()} == pytest.approx(res.histogram, abs=1e-12)
    # chains start apart (singletons) and move: the first state of each chain is one merge or split away
    for s in res.cold_states:
        first = res.state_labels[s[0]]
        assert first == tuple(range(6)) or abs(max(first) - 5) == 1


def test_cold_trace_is_thinned_by_one_stride(model6):
    cfg = McmcConfig(min_iterations=300, max_iterations=300, chains=2)
    full = run_mcmc(model6, replace(cfg, trace_samples=4000), 9)
    thin = run_mcmc(model6, replace(cfg, trace_samples=7), 9)
    assert thin.cold_thin == 43  # ⌈300 / 7⌉
    for a, b in zip(full.cold_states, thin.cold_states, strict=True):
        assert len(b) == 7  # sweeps 0, 43, …, 258
        assert [thin.state_labels[i] for i in b] == [full.state_labels[i] for i in a[::43]]
    one = run_mcmc(model6, replace(cfg, trace_samples=1), 9)
    assert one.cold_thin == 300 and [len(s) for s in one.cold_states] == [1, 1]
    forked = run_mcmc(model6, replace(cfg, trace_samples=7, processes=2), 9)
    assert forked.cold_states == thin.cold_states and forked.state_labels == thin.state_labels


def test_cold_trace_config_errors(model5):
    with pytest.raises(ConfigError, match="trace_samples must be an integer >= 1"):
        McmcConfig(trace_samples=0)
    with McmcSampler(model5, McmcConfig(chains=1), 0) as sampler:
        assert sampler.cold_chain(10) == (((),), (), 1)  # no sweep yet
        with pytest.raises(ConfigError, match="max_samples must be >= 1"):
            sampler.cold_chain(0)
