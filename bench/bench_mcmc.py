"""Benchmark of MCMC over topologies (ptm_ros.inference.mcmc): accuracy against enumeration and speed-ups.

Writes ``bench/mcmc.json`` (beside this script, or ``--out``) and prints a table. Three parts:

* ``accuracy``: simulated runs of N = 9 visits (a square driven twice, with and without signatures; a
  figure-eight whose two lobes look alike) against :func:`ptm_ros.model.posterior.exact_posterior` (all
  B_9 = 21 147 topologies): :func:`ptm_ros.inference.mcmc.run_mcmc` with its defaults over seeds, TV of the
  visited-set and histogram estimates to the exact posterior, wall time, sweeps, convergence.
* ``speed``: single chains side by side on the same runs, from all-singletons, each with a fresh model
  (cold posterior cache): sweeps, MH steps, posterior evaluations and wall time until the visited-set
  estimate is within TV 0.02 of the exact posterior — plain split–merge (Alg. 2) vs the odometry-driven
  proposal (Alg. 3) vs the data-driven mixture, and the mixture as one chain vs MC³ (Alg. 5) and vs
  chaining (Alg. 4). Medians over seeds; speed-ups are ratios of medians.
* ``sim33``: when ``ptm_ros.io.simulator`` is present, the ``multi-loop`` world (33 visits, odometry only,
  like thesis Fig. 39–40): ``run_mcmc`` defaults (2 chains, MC³ with β = 1, ½) with the default odometry
  model (importance sampling); convergence by sample doubling, wall time, the true topology's mass and
  rank; also the odometry proposal alone (the default mixes in single-visit reassignment), one chain
  without a heated replica, the chains in 2 worker processes, and plain split–merge (capped at 60 s).

Exact enumeration is the slow part (~10 ms per topology here); it runs in ``--processes`` worker
processes and is cached in ``--cache`` (default: a directory under the system temp dir), keyed by the
visits and model parameters. The model uses the Laplace estimate (``n_samples = 0``) and an LM tolerance
of 1e-3 nats for the N = 9 runs, the same for the sampler and the enumeration.

With ``--real`` it runs only the real-data comparison instead (issue #7) and writes ``real`` into the
JSON (other parts already there are kept):

* ``real``: Intel, ACES and MIT CSAIL (bags in ``out/bench/real``, ground truth in
  ``../shared/datasets``), one after the other. Visits are detected once per run with the default
  :class:`~ptm_ros.config.PtmConfig` (cached in ``--cache``); one cached registrar is shared by every
  estimator of a run (the RBPF runs first and pays for most registrations). The RBPF
  (``session.infer``, method rbpf, its whole particle set) against MCMC (``run_mcmc`` on the model
  ``session.infer`` builds, i.e. ``--method mcmc``, with a ``--cap`` on wall time) started (a) from
  all-singletons (``initial: singletons``, the thesis' start) and (b) from the RBPF's most probable
  topologies, one per chain (``initial: rbpf``, what the default ``auto`` does on these runs). All
  three runs have more than ``max_sampled_visits`` visits, so the batch posterior is the deterministic
  Laplace estimate and MAP differences are exact (below that, differing MAPs are re-compared over other
  importance-sampling seeds). Reported: TV between the PTMs, both MAPs'
  log posteriors under one :class:`~ptm_ros.model.posterior.PosteriorModel`, whether they are equal and why
  not, their F1 against ground truth, wall times, convergence (also on the pairs' same-place probabilities),
  the SRQ deviation of each cold chain, and the
  TV between MCMC and the RBPF's topologies re-weighted by the batch posterior (which separates "the
  filter lost a topology" from "the filter weighs its topologies differently"), the visit pairs'
  same-place marginals of the two PTMs, whether a filter with 1000 particles holds MCMC's MAPs, and,
  for the visit pairs where the two MAPs (or the two marginals) differ, which one the ground truth sides
  with (``versus_truth``).

Usage: ``PYTHONPATH=. .venv/bin/python bench/bench_mcmc.py [--quick] [--out FILE] [--processes 2]``;
``... bench/bench_mcmc.py --real [--runs intel aces mit-csail] [--cap 300]``.
"""

from __future__ import annotations

import os

# one BLAS thread: the metric likelihood solves many small dense systems, and threaded OpenBLAS on
# this busy 2-core machine made each solve ~20x slower (set before numpy is imported)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import dataclasses
import hashlib
import json
import multiprocessing as mp
import pickle
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ptm_ros.inference.mcmc import McmcConfig, McmcSampler, run_mcmc
from ptm_ros.io.synthetic import odometry_visits, true_poses
from ptm_ros.model.geometry import wrap_angle
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.partitions import canonical, enumerate_partitions
from ptm_ros.model.posterior import ModelConfig, PosteriorModel, normalize_log, total_variation
from ptm_ros.model.visits import Visit
from ptm_ros.session import compare_to_filter

THRESHOLD = 0.02
ODOMETRY = OdometryConfig(n_samples=0, tolerance=1e-3)
MODEL = ModelConfig(odometry=ODOMETRY)


# ---------------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------------


def simulate(route, places, odo, *, seed=0, signatures=None, noise=1.0, sig_noise=0.3):
    """Visits along ``route`` (place indices) with odometry noise ``noise`` × the model's own."""
    appearance = None if signatures is None else signatures[np.asarray(route)]
    return odometry_visits(
        true_poses(route, places, end_heading="ahead"),
        odo,
        np.random.default_rng(seed),
        noise=noise,
        appearance=appearance,
        sig_noise=sig_noise,
        nonnegative=True,
    )


def scenes() -> dict[str, tuple[list[Visit], tuple[int, ...]]]:
    """The N = 9 runs: name -> (visits, true labels)."""
    square = [(0.0, 0.0), (8.0, 0.0), (8.0, 8.0), (0.0, 8.0)]
    sq_route = [0, 1, 2, 3, 0, 1, 2, 3, 0]
    eight = [(0.0, 0.0), (8.0, 0.0), (8.0, 8.0), (0.0, 8.0), (-8.0, 0.0), (-8.0, -8.0), (0.0, -8.0)]
    eight_route = [0, 1, 2, 3, 0, 4, 5, 6, 0]
    sig_rng = np.random.default_rng(42)
    sq_sig = sig_rng.uniform(1.0, 3.0, size=(4, 4))
    eight_sig = sig_rng.uniform(1.0, 3.0, size=(7, 4))
    eight_sig[4:7] = eight_sig[1:4]  # the two lobes look alike (perceptual aliasing)
    return {
        "square": (simulate(sq_route, square, ODOMETRY, seed=0, noise=3.0), canonical(sq_route)),
        "square+signatures": (
            simulate(sq_route, square, ODOMETRY, seed=1, noise=4.0, signatures=sq_sig),
            canonical(sq_route),
        ),
        "figure-eight+aliasing": (
            simulate(eight_route, eight, ODOMETRY, seed=2, noise=1.0, signatures=eight_sig),
            canonical(eight_route),
        ),
    }


# ---------------------------------------------------------------------------------------------------
# Exact posterior (parallel, cached)
# ---------------------------------------------------------------------------------------------------

#: The model the enumeration workers evaluate (inherited through fork, not pickled).
_WORKER: dict[str, PosteriorModel] = {}


def _evaluate(chunk: list[tuple[int, ...]]) -> list[float]:
    model = _WORKER["model"]
    return [model.log_posterior(lab) for lab in chunk]


def _cache_key(visits, config: ModelConfig) -> str:
    h = hashlib.sha256(repr(config).encode())
    for v in visits:
        h.update(repr((v.pose, v.travel, v.rotation)).encode())
        if v.signature is not None:
            h.update(np.asarray(v.signature).tobytes())
    return h.hexdigest()[:20]


def exact_posterior_cached(visits, config: ModelConfig, processes: int, cache: Path) -> dict:
    """Normalised exact posterior of all topologies, enumerated in worker processes and cached."""
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"exact-{_cache_key(visits, config)}.pkl"
    if path.is_file():
        with path.open("rb") as f:
            return pickle.load(f)
    labels = list(enumerate_partitions(len(visits)))
    _WORKER["model"] = PosteriorModel(visits, config)
    if processes > 1:
        chunks = [labels[i : i + 500] for i in range(0, len(labels), 500)]
        with mp.get_context("fork").Pool(processes) as pool:
            values = [x for part in pool.map(_evaluate, chunks) for x in part]
    else:
        values = _evaluate(labels)
    _WORKER.clear()
    out = normalize_log(dict(zip(labels, values, strict=True)))
    with path.open("wb") as f:
        pickle.dump(out, f)
    return out


# ---------------------------------------------------------------------------------------------------
# Parts
# ---------------------------------------------------------------------------------------------------


def accuracy(runs, exact, seeds) -> list[dict[str, Any]]:
    rows = []
    for name, (visits, truth) in runs.items():
        for seed in seeds:
            model = PosteriorModel(visits, MODEL)
            res = run_mcmc(model, McmcConfig(), seed)
            d = res.diagnostics
            rows.append(
                {
                    "scene": name,
                    "seed": seed,
                    "tv_visited": total_variation(res.visited, exact[name]),
                    "tv_histogram": total_variation(res.histogram, exact[name]),
                    "wall_s": res.wall_s,
                    "sweeps": d.iterations,
                    "evaluated": d.n_evaluated,
                    "converged": d.converged,
                    "doubling_tv": d.doubling_tv,
                    "chain_tv": d.chain_tv,
                    "p_true_exact": exact[name].get(truth, 0.0),
                    "p_true_mcmc": res.probabilities.get(truth, 0.0),
                }
            )
    return rows


METHODS: dict[str, dict[str, Any]] = {
    "split-merge": {"proposal": "split-merge", "betas": (1.0,)},
    "odometry": {"proposal": "odometry", "betas": (1.0,)},
    "data-driven": {"proposal": "auto", "betas": (1.0,)},
    "data-driven+MC3": {"proposal": "auto", "betas": (1.0, 0.5)},
    "data-driven+chaining": {"proposal": "auto", "betas": (1.0,), "max_chaining": 3},
}


def time_to_threshold(visits, exact, method, *, seed, cap_sweeps, cap_s, step=5) -> dict[str, Any]:
    """One chain from all-singletons until TV(visited estimate, exact) <= THRESHOLD (or the caps)."""
    cfg = McmcConfig(chains=1, max_iterations=cap_sweeps, max_seconds=cap_s, **METHODS[method])
    model = PosteriorModel(visits, MODEL)
    with McmcSampler(model, cfg, seed) as sampler:
        tv = total_variation(sampler.estimate("visited"), exact)
        while tv > THRESHOLD and sampler.iterations < cap_sweeps and sampler.wall_s < cap_s:
            sampler.advance(sampler.iterations + step)
            tv = total_variation(sampler.estimate("visited"), exact)
        evaluated = sampler.check("visited").n_evaluated
        return {
            "method": method,
            "seed": seed,
            "reached": tv <= THRESHOLD,
            "tv": tv,
            "sweeps": sampler.iterations,
            "mh_steps": sampler.iterations * len(cfg.betas),
            "evaluated": evaluated,
            "wall_s": sampler.wall_s,
        }


def _ratio(summary: dict[str, dict[str, float]], a: str, b: str, key: str) -> float:
    """How many times more ``key`` method a needed than method b."""
    return summary[a][key] / max(summary[b][key], 1e-9)


PAIRS = {
    "odometry vs split-merge": ("split-merge", "odometry"),
    "data-driven vs split-merge": ("split-merge", "data-driven"),
    "MC3 vs single chain": ("data-driven", "data-driven+MC3"),
    "chaining vs single proposal": ("data-driven", "data-driven+chaining"),
}


def speed(runs, exact, seeds, cap_sweeps, cap_s) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, (visits, _) in runs.items():
        rows = [
            time_to_threshold(visits, exact[name], method, seed=seed, cap_sweeps=cap_sweeps, cap_s=cap_s)
            for method in METHODS
            for seed in seeds
        ]
        summary = {}
        for method in METHODS:
            mine = [r for r in rows if r["method"] == method]
            summary[method] = {
                "reached": sum(r["reached"] for r in mine),
                "runs": len(mine),
                "median_sweeps": statistics.median(r["sweeps"] for r in mine),
                "median_mh_steps": statistics.median(r["mh_steps"] for r in mine),
                "median_evaluated": statistics.median(r["evaluated"] for r in mine),
                "median_wall_s": statistics.median(r["wall_s"] for r in mine),
            }

        out[name] = {
            "runs": rows,
            "summary": summary,
            "speedup_wall": {k: _ratio(summary, a, b, "median_wall_s") for k, (a, b) in PAIRS.items()},
            "speedup_sweeps": {k: _ratio(summary, a, b, "median_sweeps") for k, (a, b) in PAIRS.items()},
        }
    return out


def sim33_visits(seed: int):
    """33 visits of the simulator's multi-loop world (odometry at the passages), and the true labels."""
    from ptm_ros.io.simulator import CameraConfig, SimConfig, simulate
    from ptm_ros.io.worlds import get_world

    run = simulate(
        get_world("multi-loop"), SimConfig(camera=CameraConfig(enabled=False)), np.random.default_rng(seed)
    )
    stamps, odom = run.odom_stamps, run.odom_poses
    dist = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(odom[:, :2], axis=0).T))])
    turn = np.concatenate([[0.0], np.cumsum(np.abs(wrap_angle(np.diff(odom[:, 2]))))])
    visits, prev = [], None
    for n, passage in enumerate(run.passages):
        k = int(np.argmin(np.abs(stamps - passage.stamp)))
        travel = 0.0 if prev is None else float(dist[k] - dist[prev])
        rotation = 0.0 if prev is None else float(turn[k] - turn[prev])
        visits.append(Visit(n, float(stamps[k]), tuple(float(v) for v in odom[k]), travel, rotation))
        prev = k
    return visits, canonical([p.place for p in run.passages])


def sim33(seeds, methods) -> list[dict[str, Any]] | None:
    try:
        import ptm_ros.io.simulator  # noqa: F401
    except ImportError:
        return None
    rows = []
    for seed in seeds:
        visits, truth = sim33_visits(seed)
        for method, cfg in methods.items():
            model = PosteriorModel(visits, ModelConfig())
            res = run_mcmc(model, cfg, seed)
            d = res.diagnostics
            ranked = list(res.probabilities)
            rows.append(
                {
                    "seed": seed,
                    "method": method,
                    "visits": len(visits),
                    "converged": d.converged,
                    "stop_reason": d.stop_reason,
                    "doubling_tv": d.doubling_tv,
                    "chain_tv": d.chain_tv,
                    "wall_s": res.wall_s,
                    "sweeps": d.iterations,
                    "evaluated": d.n_evaluated,
                    "acceptance": d.acceptance,
                    "p_true": res.probabilities.get(truth, 0.0),
                    "rank_true": ranked.index(truth) + 1 if truth in res.probabilities else None,
                    "top4": [p for _, p in list(res.probabilities.items())[:4]],
                    "places_true": max(truth) + 1,
                    "places_map": max(ranked[0]) + 1,
                }
            )
    return rows


# ---------------------------------------------------------------------------------------------------
# Real runs: MCMC against the RBPF (issue #7)
# ---------------------------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]
REAL_BAGS = REPO / "out" / "bench" / "real"
DATASETS = REPO.parent / "shared" / "datasets"
#: run -> ground-truth file under ``DATASETS / run``
REAL_RUNS = {"intel": "intel-gt-910.txt", "aces": "aces-gt-440.txt", "mit-csail": "mit-csail-gt-406.txt"}


def real_visits(name: str, bag: Path, config, cache: Path) -> tuple[list[Visit], float]:
    """The run's visits (``pipeline.detect_visits``), pickled in ``cache`` keyed by bag, config and the
    package's source (the detector code changes as others work on it)."""
    from ptm_ros.io.bag import read_run
    from ptm_ros.tools.pipeline import detect_visits

    h = hashlib.sha256(repr(config).encode())
    h.update(source_hash().encode())
    for f in sorted(bag.iterdir()):
        h.update(f"{f.name}:{f.stat().st_size}:{f.stat().st_mtime_ns}".encode())
    path = cache / f"visits-{name}-{h.hexdigest()[:16]}.pkl"
    if path.is_file():
        with path.open("rb") as f:
            return pickle.load(f), 0.0
    t0 = time.perf_counter()
    visits = detect_visits(read_run(bag), config)
    wall = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump(visits, f)
    return visits, wall


def source_hash() -> str:
    """SHA-256 prefix of every ``ptm_ros/**/*.py`` file (which code produced the visits)."""
    h = hashlib.sha256()
    for f in sorted((REPO / "ptm_ros").rglob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def pair_disagreements(a: tuple[int, ...], b: tuple[int, ...]) -> int:
    """Visit pairs that one topology puts at one place and the other does not."""
    x, y = np.asarray(a), np.asarray(b)
    same_a = x[:, None] == x[None, :]
    same_b = y[:, None] == y[None, :]
    return int(np.sum(np.triu(same_a != same_b, 1)))


def topology_row(model: PosteriorModel, labels: tuple[int, ...]) -> dict[str, Any]:
    """A topology's batch log posterior and its parts under ``model``."""
    terms = model.terms(labels)
    res = terms.metric_result
    return {
        "places": max(labels) + 1,
        "log_posterior": terms.total,
        "prior": terms.prior,
        "metric": terms.metric,
        "laser_evidence": model.laser_evidence(labels),
        "metric_is_ess": None if res is None else res.ess,
    }


def ptm_score(visits, probs: dict, gt: Path) -> dict[str, Any]:
    """MAP and posterior F1 of a PTM against the CARMEN ground truth (``ptm-eval``'s figures)."""
    from ptm_ros.model.ptm import Landmark, make_ptm
    from ptm_ros.tools.evaluate import score_against_ground_truth

    landmarks = [Landmark(v.index, v.stamp, v.pose) for v in visits]
    s = score_against_ground_truth(make_ptm(landmarks, probs), gt).as_dict(per_topology=False)
    keys = ("map_f1", "map_precision", "map_recall", "posterior_f1", "consistent_mass", "n_scored_pairs")
    return {k: s[k] for k in keys}


def truth_of_pairs(visits, gt: Path) -> np.ndarray:
    """``(n, n)`` ground truth of every visit pair: 1 one place, 0 different, NaN unscored (the grey zone,
    or a visit outside the ground truth's span): ``ptm-eval``'s
    :func:`~ptm_ros.scoring.evaluation.pair_truth`."""
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.ptm import Landmark, make_ptm
    from ptm_ros.scoring.evaluation import pair_truth
    from ptm_ros.tools.evaluate import true_positions_for

    n = len(visits)
    ptm = make_ptm([Landmark.from_visit(v) for v in visits], {tuple(range(n)): 1.0})
    i, j, same = pair_truth(true_positions_for(ptm, load_ground_truth(gt), max_extrapolation=0.5))
    out = np.full((n, n), np.nan)
    out[i, j] = out[j, i] = same
    return out


def differences_vs_truth(
    truth: np.ndarray, mcmc: dict, rbpf: dict, mcmc_map: tuple[int, ...], rbpf_map: tuple[int, ...]
) -> dict[str, Any]:
    """Where the two estimates differ, which one the ground truth sides with.

    ``map_pairs``: visit pairs the two MAPs disagree on (one puts them at one place, the other not),
    split into those the ground truth scores right for MCMC's MAP, for the RBPF's, and unscored (grey
    zone). ``marginal_pairs``: the same for the pairs whose same-place marginals differ by more than 0.1,
    a PTM being "right" when its marginal is nearer the truth; ``abs_error_*`` sums ``|p - truth|`` over
    those scored pairs."""
    from ptm_ros.model.posterior import same_place_probabilities

    n = truth.shape[0]
    iu = np.triu_indices(n, 1)
    t = truth[iu]
    scored = ~np.isnan(t)

    def split(mask: np.ndarray, right_m: np.ndarray, right_r: np.ndarray) -> dict[str, int]:
        return {
            "pairs": int(mask.sum()),
            "mcmc_right": int((mask & scored & right_m).sum()),
            "rbpf_right": int((mask & scored & right_r).sum()),
            "unscored": int((mask & ~scored).sum()),
        }

    a, b = np.asarray(mcmc_map), np.asarray(rbpf_map)
    same_m, same_r = (a[:, None] == a[None, :])[iu], (b[:, None] == b[None, :])[iu]
    tt = np.nan_to_num(t, nan=-1.0)  # never equal to 0 or 1
    map_pairs = split(same_m != same_r, same_m == tt, same_r == tt)
    p_m, p_r = (same_place_probabilities(d, n)[iu] for d in (mcmc, rbpf))
    err_m, err_r = np.abs(p_m - t), np.abs(p_r - t)
    differ = np.abs(p_m - p_r) > 0.1
    marg = split(differ, err_m < err_r, err_r < err_m)  # False on unscored pairs (NaN errors)
    marg["abs_error_mcmc"] = float(np.nansum(err_m[differ]))
    marg["abs_error_rbpf"] = float(np.nansum(err_r[differ]))
    return {"map_pairs": map_pairs, "marginal_pairs": marg}


def srq_deviations(res) -> list[float | None]:
    """SRQ deviation (:func:`ptm_ros.inference.convergence.srq_deviation`) of each cold chain at one shared
    atom."""
    from ptm_ros.inference.convergence import most_visited, srq_deviation, srq_points

    if not any(res.cold_states):
        return [None] * len(res.cold_states)
    atom = most_visited([i for chain in res.cold_states for i in chain])
    out: list[float | None] = []
    for chain in res.cold_states:
        out.append(srq_deviation(*srq_points(chain, atom)) if atom in chain else None)
    return out


#: Other importance-sampling seeds of the batch model on which differing MAPs are re-compared.
NOISE_SEEDS = tuple(range(1, 9))


def map_difference_noise(model: PosteriorModel, a: tuple[int, ...], b: tuple[int, ...]) -> dict[str, Any]:
    """``log π(a) - log π(b)`` under other importance-sampling seeds and under the Laplace estimate.

    The metric term is an importance-sampling estimate with common random numbers per (seed, labels); on
    the real runs its effective sample size is often 1–20 of 200, so a MAP found by maximising over
    thousands of topologies may owe part of its lead to a lucky estimate. Re-drawing the samples (other
    seeds) and the deterministic Laplace estimate (``n_samples = 0``) show whether the lead is real.
    """
    by_seed = []
    for seed in NOISE_SEEDS:
        other = PosteriorModel(model.visits, model.config, registrar=model.registrar, seed=seed)
        by_seed.append(other.log_posterior(a) - other.log_posterior(b))
    odo = dataclasses.replace(model.config.odometry, n_samples=0)
    laplace = PosteriorModel(
        model.visits, dataclasses.replace(model.config, odometry=odo), registrar=model.registrar
    )
    return {
        "seed0": model.log_posterior(a) - model.log_posterior(b),
        "by_seed": by_seed,
        "mean": statistics.fmean(by_seed),
        "sd": statistics.stdev(by_seed),
        "laplace": laplace.log_posterior(a) - laplace.log_posterior(b),
    }


def compare(
    model: PosteriorModel, rbpf: dict, rbpf_map: tuple[int, ...], res, truth: np.ndarray
) -> dict[str, Any]:
    """MCMC result ``res`` against the RBPF's PTM: TVs, MAPs under one model, why they differ, and which
    one the ground truth ``truth`` (:func:`truth_of_pairs`) sides with where they do."""
    probs = res.probabilities
    mcmc_map = next(iter(probs))
    lp_r = model.log_posterior(rbpf_map)
    lp_m = model.log_posterior(mcmc_map)
    d = res.diagnostics
    if mcmc_map == rbpf_map:
        why = "equal"
    elif lp_m > lp_r:
        held = mcmc_map in rbpf
        why = f"MCMC's MAP is {lp_m - lp_r:.2f} nats more probable under the batch posterior; " + (
            f"the RBPF holds it with mass {rbpf[mcmc_map]:.3g} (its EKF weights rank it lower)"
            if held
            else "the RBPF lost it (not among its particles)"
        )
    else:
        why = (
            f"MCMC's MAP is {lp_r - lp_m:.2f} nats less probable than the RBPF's, which MCMC never evaluated:"
            f" MCMC did not converge{'' if not d.converged else ' (although its own diagnostics said so)'}"
        )
    ranked = list(probs)
    noise = None
    if mcmc_map != rbpf_map and model.n <= model.config.odometry.max_sampled_visits:
        noise = map_difference_noise(model, mcmc_map, rbpf_map)
        why += (
            f" [MCMC MAP - RBPF MAP over {len(NOISE_SEEDS)} other importance-sampling seeds: "
            f"{noise['mean']:+.2f} ± {noise['sd']:.2f} nats; Laplace: {noise['laplace']:+.2f}]"
        )
    versus = compare_to_filter(model, probs, rbpf)  # what ptm-run --method mcmc reports (initial: rbpf)
    return {
        "map_labels": list(mcmc_map),
        "map_difference_noise": noise,
        "tv_to_rbpf": versus["tv"],
        "tv_to_rbpf_reweighted": versus["tv_reweighted"],
        "map_equal": versus["map_equal"],
        "map_log_posterior": lp_m,
        "map_minus_rbpf_map_nats": versus["map_gain_nats"],
        "pairs_in_play": versus["pairs_in_play"],
        "pair_max_diff": versus["pair_max_diff"],
        "pair_mean_diff": versus["pair_mean_diff"],
        "pairs_differing": versus["pairs_differing"],
        "map": topology_row(model, mcmc_map),
        "map_pair_disagreements_with_rbpf_map": pair_disagreements(mcmc_map, rbpf_map),
        "rbpf_map_mass_in_mcmc": probs.get(rbpf_map, 0.0),
        "rbpf_map_rank_in_mcmc": ranked.index(rbpf_map) + 1 if rbpf_map in probs else None,
        "mcmc_map_mass_in_rbpf": rbpf.get(mcmc_map, 0.0),
        "explanation": why,
        "versus_truth": differences_vs_truth(truth, probs, rbpf, mcmc_map, rbpf_map),
        "wall_s": res.wall_s,
        "converged": d.converged,
        "stop_reason": d.stop_reason,
        "sweeps": d.iterations,
        "doubling_tv": d.doubling_tv,
        "chain_tv": d.chain_tv,
        "doubling_pair": d.doubling_pair,
        "chain_pair": d.chain_pair,
        "evaluated": d.n_evaluated,
        "acceptance": d.acceptance,
        "history": [dataclasses.asdict(h) for h in d.history],
        "srq_deviation": srq_deviations(res),
        "chain_last_log_posterior": [res.log_posteriors[res.state_labels[c[-1]]] for c in res.cold_states],
        "chain_best_log_posterior": [
            max(res.log_posteriors[res.state_labels[i]] for i in set(c)) for c in res.cold_states
        ],
        "cold_thin": res.cold_thin,
        "top5": [p for _, p in list(probs.items())[:5]],
    }


#: Particles of the second, larger filter that checks whether MCMC's MAPs are within a filter's reach.
BIG_FILTER_PARTICLES = 1000


def real_run(name: str, cap_s: float, cache: Path) -> dict[str, Any]:
    """RBPF and MCMC (from singletons, from the RBPF's MAP) on one real run (module docstring)."""
    from ptm_ros import factories, session
    from ptm_ros.config import PtmConfig

    bag = REAL_BAGS / name
    gt = DATASETS / name / REAL_RUNS[name]
    load = {"before": os.getloadavg()}
    base = PtmConfig()
    visits, detect_s = real_visits(name, bag, base, cache)
    inf = dataclasses.replace(
        base.inference, top=10**9, mcmc=dataclasses.replace(base.inference.mcmc, max_seconds=cap_s)
    )
    config = dataclasses.replace(base, inference=inf)
    registrar = factories.cached(factories.make_registrar(visits, config))

    t0 = time.perf_counter()
    rb = session.infer(
        visits,
        dataclasses.replace(config, inference=dataclasses.replace(inf, method="rbpf")),
        registrar=registrar,
    )
    rbpf_wall = time.perf_counter() - t0
    rbpf = dict(rb.probabilities)
    rbpf_map = next(iter(rbpf))

    # the model ``session.infer`` builds for ``--method mcmc``; its values depend only on (seed, labels)
    model = PosteriorModel(visits, config.model, registrar=registrar, seed=inf.seed)
    rbpf_batch = normalize_log({lab: model.log_posterior(lab) for lab in rbpf})
    truth = truth_of_pairs(visits, gt)
    row: dict[str, Any] = {
        "run": name,
        "visits": len(visits),
        "detect_s": detect_s,
        "rbpf": {
            "particles": inf.particles,
            "wall_s": rbpf_wall,
            "topologies": len(rbpf),
            "map": topology_row(model, rbpf_map),
            "map_labels": list(rbpf_map),
            "map_probability": rbpf[rbpf_map],
            "top5": [p for _, p in list(rbpf.items())[:5]],
            "batch_map_among_particles": list(rbpf_batch).index(max(rbpf_batch, key=rbpf_batch.get)),
            "score": ptm_score(visits, rbpf, gt),
        },
    }
    for start, initial in (("singletons", None), ("rbpf", list(rbpf)[: inf.mcmc.chains])):
        res = run_mcmc(model, dataclasses.replace(inf.mcmc, initial=start), inf.seed, initial=initial)
        out = compare(model, rbpf, rbpf_map, res, truth)
        out["score"] = ptm_score(visits, res.probabilities, gt)
        row[f"mcmc_{start}"] = out
        print(
            f"  {name} mcmc from {start}: {out['wall_s']:.0f} s, {out['sweeps']} sweeps, "
            f"{out['stop_reason']}; {out['explanation']}",
            flush=True,
        )
    # does a filter with 10x the particles hold the MAPs MCMC found (why the 100-particle filter missed them)
    big = BIG_FILTER_PARTICLES
    t0 = time.perf_counter()
    more = session.infer(
        visits,
        dataclasses.replace(config, inference=dataclasses.replace(inf, method="rbpf", particles=big)),
        registrar=registrar,
    )
    ranked = list(more.probabilities)
    row[f"rbpf_{big}"] = {
        "wall_s": time.perf_counter() - t0,
        "topologies": len(ranked),
        "map_equal_to_rbpf_map": ranked[0] == rbpf_map,
        "score": ptm_score(visits, more.probabilities, gt),
    }
    for start in ("singletons", "rbpf"):
        lab = tuple(row[f"mcmc_{start}"]["map_labels"])
        row[f"mcmc_{start}"][f"map_rank_in_rbpf_{big}"] = (
            ranked.index(lab) + 1 if lab in more.probabilities else None
        )
        row[f"mcmc_{start}"][f"map_mass_in_rbpf_{big}"] = more.probabilities.get(lab, 0.0)
    load["after"] = os.getloadavg()
    row["load_average"] = load
    return row


def print_real(rows: list[dict[str, Any]]) -> None:
    print("\nReal runs: MCMC vs RBPF (log posteriors under one PosteriorModel; F1 = MAP / posterior)")
    print(
        f"  {'run':10s} {'N':>4s} {'start':10s} {'TV':>6s} {'TVrw':>6s} {'MAP=':>5s} {'lp RBPF':>9s} "
        f"{'lp MCMC':>9s} {'F1 RBPF':>11s} {'F1 MCMC':>11s} {'wall R':>7s} {'wall M':>7s} {'conv':>5s}"
    )
    for r in rows:
        rb = r["rbpf"]
        for start in ("singletons", "rbpf"):
            m = r[f"mcmc_{start}"]
            print(
                f"  {r['run']:10s} {r['visits']:4d} {start:10s} {m['tv_to_rbpf']:6.3f} "
                f"{m['tv_to_rbpf_reweighted']:6.3f} {m['map_equal']!s:>5s} "
                f"{rb['map']['log_posterior']:9.2f} {m['map_log_posterior']:9.2f} "
                f"{rb['score']['map_f1']:5.3f}/{rb['score']['posterior_f1']:5.3f} "
                f"{m['score']['map_f1']:5.3f}/{m['score']['posterior_f1']:5.3f} {rb['wall_s']:7.1f} "
                f"{m['wall_s']:7.1f} {m['converged']!s:>5s}"
            )
    print("  TVrw: TV between MCMC and the RBPF's topologies re-weighted by the batch posterior")
    big = BIG_FILTER_PARTICLES
    for r in rows:
        for start in ("singletons", "rbpf"):
            m = r[f"mcmc_{start}"]
            print(
                f"  {r['run']} from {start}: {m['explanation']}; same-place marginals of "
                f"{m['pairs_in_play']} pairs: max |diff| {m['pair_max_diff']:.3f}, "
                f"mean {m['pair_mean_diff']:.4f}, {m['pairs_differing']} differ by > 0.1; "
                f"MCMC's MAP in a {big}-particle filter: rank "
                f"{m[f'map_rank_in_rbpf_{big}']}, mass {m[f'map_mass_in_rbpf_{big}']:.3g}"
            )
            print(
                f"    convergence: doubling TV {m['doubling_tv']:.3f}, chain TV {m['chain_tv']:.3f}; "
                f"same-place probabilities: doubling {m['doubling_pair']:.3f}, chains {m['chain_pair']:.3f}"
            )
            for key, what in (("map_pairs", "the MAPs"), ("marginal_pairs", "the marginals (> 0.1)")):
                v = m["versus_truth"][key]
                print(
                    f"    pairs where {what} differ: {v['pairs']}; ground truth sides with MCMC on "
                    f"{v['mcmc_right']}, with the RBPF on {v['rbpf_right']}, {v['unscored']} unscored"
                )


# ---------------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds")
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("mcmc.json"))
    parser.add_argument("--processes", type=int, default=2, help="workers for exact enumeration")
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "ptm_ros_bench_mcmc")
    parser.add_argument("--skip", nargs="*", default=[], choices=["accuracy", "speed", "sim33"])
    parser.add_argument("--real", action="store_true", help="only the real-run comparison with the RBPF")
    parser.add_argument("--runs", nargs="*", default=list(REAL_RUNS), choices=list(REAL_RUNS))
    parser.add_argument("--cap", type=float, default=300.0, help="MCMC wall-time cap per run (s)")
    args = parser.parse_args()
    if args.real:
        main_real(args)
        return
    seeds = range(2 if args.quick else 5)

    t0 = time.monotonic()
    runs = scenes()
    exact = {}
    for name, (visits, _) in runs.items():
        t = time.monotonic()
        exact[name] = exact_posterior_cached(visits, MODEL, args.processes, args.cache)
        print(f"exact posterior {name}: {len(exact[name])} topologies, {time.monotonic() - t:.1f} s")

    report: dict[str, Any] = {
        "machine": {
            "python": platform.python_version(),
            "processor": platform.processor(),
            "cpus": mp.cpu_count(),
        },
        "threshold": THRESHOLD,
        "model": dataclasses.asdict(MODEL),
        "mcmc_defaults": dataclasses.asdict(McmcConfig()),
        "scenes": {
            name: {
                "visits": len(v),
                "truth": list(truth),
                "p_truth": exact[name].get(truth, 0.0),
                "p_max": max(exact[name].values()),
                "topologies_above_1e-3": sum(p > 1e-3 for p in exact[name].values()),
            }
            for name, (v, truth) in runs.items()
        },
    }
    if "accuracy" not in args.skip:
        report["accuracy"] = accuracy(runs, exact, seeds)
    if "speed" not in args.skip:
        report["speed"] = speed(runs, exact, seeds, cap_sweeps=20_000, cap_s=120.0)
    if "sim33" not in args.skip:
        report["sim33"] = sim33(
            range(1 if args.quick else 3),
            {
                "default": McmcConfig(),
                "no-reassign": McmcConfig(proposal="odometry"),
                "single-chain": McmcConfig(betas=(1.0,)),
                "2-processes": McmcConfig(processes=2),
                "split-merge": McmcConfig(proposal="split-merge", max_seconds=60.0),
            },
        )
    report["total_wall_s"] = time.monotonic() - t0
    args.out.write_text(json.dumps(report, indent=1, default=float) + "\n")
    print_tables(report)
    print(f"wrote {args.out} ({report['total_wall_s']:.0f} s)")


def main_real(args: argparse.Namespace) -> None:
    """``--real``: the runs one after the other (the machine is shared); merged into ``args.out``."""
    if not (DATASETS / "README.md").is_file() or not REAL_BAGS.is_dir():
        raise SystemExit(f"--real needs {DATASETS} and the bags in {REAL_BAGS} (make bench converts them)")
    t0 = time.monotonic()
    rows = []
    for name in args.runs:
        print(f"[real] {name} (load average {os.getloadavg()[0]:.1f})", flush=True)
        rows.append(real_run(name, args.cap, args.cache))
    report = json.loads(args.out.read_text()) if args.out.is_file() else {}
    report["real"] = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "cpus": mp.cpu_count(),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "source_hash": source_hash(),
        "mcmc_cap_s": args.cap,
        "mcmc_config": dataclasses.asdict(dataclasses.replace(McmcConfig(), max_seconds=args.cap)),
        "runs": rows,
        "wall_s": time.monotonic() - t0,
    }
    args.out.write_text(json.dumps(report, indent=1, default=float) + "\n")
    print_real(rows)
    print(f"wrote {args.out} ({report['real']['wall_s']:.0f} s)")


def print_tables(report: dict[str, Any]) -> None:
    print("\nScenes (exact posterior):")
    for name, s in report["scenes"].items():
        print(f"  {name:24s} N={s['visits']}  P(truth)={s['p_truth']:.3f}  max={s['p_max']:.3f}")
    if "accuracy" in report:
        print(f"\nAccuracy of run_mcmc defaults (TV to exact; target <= {THRESHOLD}):")
        print(
            f"  {'scene':24s} {'TV visited':>10s} {'TV hist':>8s} {'wall s':>7s} {'sweeps':>7s} {'conv':>5s}"
        )
        for name in report["scenes"]:
            rows = [r for r in report["accuracy"] if r["scene"] == name]
            print(
                f"  {name:24s} {max(r['tv_visited'] for r in rows):10.4f} "
                f"{statistics.median(r['tv_histogram'] for r in rows):8.4f} "
                f"{statistics.median(r['wall_s'] for r in rows):7.2f} "
                f"{statistics.median(r['sweeps'] for r in rows):7.0f} "
                f"{sum(r['converged'] for r in rows)}/{len(rows)}"
            )
        print("  (TV visited: worst seed; the others: medians)")
    if "speed" in report:
        print(f"\nTime to TV <= {THRESHOLD} from all-singletons, one chain (medians over seeds):")
        print(f"  {'scene':24s} {'method':22s} {'reached':>7s} {'sweeps':>7s} {'evals':>6s} {'wall s':>7s}")
        for name, part in report["speed"].items():
            for method, s in part["summary"].items():
                print(
                    f"  {name:24s} {method:22s} {s['reached']:>3d}/{s['runs']:<3d} {s['median_sweeps']:7.0f} "
                    f"{s['median_evaluated']:6.0f} {s['median_wall_s']:7.2f}"
                )
            sw = part["speedup_wall"]
            print("  " + "; ".join(f"{k}: ×{v:.2f}" for k, v in sw.items()) + " (wall)")
    if report.get("sim33"):
        print("\nmulti-loop simulator run (33 visits, odometry only):")
        print(
            f"  {'seed':>4s} {'method':12s} {'conv':>5s} {'doubling':>8s} {'chains':>7s} {'wall s':>7s} "
            f"{'sweeps':>7s} {'evals':>6s} {'P(true)':>8s} {'rank':>5s}"
        )
        for r in report["sim33"]:
            chain = "-" if r["chain_tv"] is None else f"{r['chain_tv']:.4f}"
            print(
                f"  {r['seed']:4d} {r['method']:12s} {r['converged']!s:>5s} {r['doubling_tv']:8.4f} "
                f"{chain:>7s} {r['wall_s']:7.2f} {r['sweeps']:7d} {r['evaluated']:6d} {r['p_true']:8.3f} "
                f"{r['rank_true']!s:>5s}"
            )


if __name__ == "__main__":
    main()
