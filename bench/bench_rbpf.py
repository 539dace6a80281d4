"""Benchmark of the RBPF over topologies (ptm_ros.inference.rbpf): speed per visit and accuracy against
enumeration.

Writes ``bench/rbpf.json`` (beside this script, or ``--out``) and prints a table. Three parts:

* ``timing``: a robot wandering a 4×4 or 6×6 grid of places 8 m apart (100 visits, 100 particles) with
  odometry only, with laser registrations, and with laser + appearance; per-visit update time (median,
  p95, and the median of each quarter of the run, to see the growth; minimum over 3 repeats), the
  posterior mass of the true topology.
* ``accuracy``: N = 8 runs against :func:`ptm_ros.model.posterior.exact_posterior` (Laplace, all 4140
  topologies): total variation of the filter keeping every child, and of 10–100 particles over seeds,
  for optimal (Fearnhead–Clifford) and top-N resampling.
* ``approximations``: N = 6 cases, every child kept, against enumeration with and without the
  separation prior (which this Laplace enumeration evaluates at its optimum, while the filter integrates
  it over its Gaussian, issue #23: with the prior the TV mixes both; ``bench_exact.py`` compares with the
  importance-sampling enumeration).
* ``linearisation``: with a large heading noise, the filter (EKF, sequential linearisation) and the
  batch Laplace estimate against importance sampling (the model's own reference, eq. 18).

Usage: ``PYTHONPATH=. .venv/bin/python bench/bench_rbpf.py [--quick] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

from ptm_ros.inference.rbpf import RbpfConfig, TopologyFilter, run_filter
from ptm_ros.io.synthetic import grid_route, simulate_route, truth_registrar
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.partitions import bell, canonical
from ptm_ros.model.posterior import (
    ModelConfig,
    PosteriorModel,
    exact_posterior,
    normalize_log,
    total_variation,
)
from ptm_ros.model.priors import PriorConfig, make_prior

PRIOR = PriorConfig()


def timing(n_visits: int, particles: int, repeats: int) -> list[dict]:
    """Per-visit update times; each visit's time is the minimum over ``repeats`` identical runs (robust to
    other processes on a shared machine), wall and CPU (``time.process_time``) alike."""
    rows = []
    for world, side, odo_name, odo in (
        ("4x4 grid", 4, "5cm/√m", OdometryConfig(n_samples=0)),
        ("4x4 grid", 4, "15cm/√m", OdometryConfig(n_samples=0, a_xy=0.15**2, a_th=0.1**2)),
        ("6x6 grid", 6, "5cm/√m", OdometryConfig(n_samples=0)),
    ):
        places, route = grid_route(n_visits, side=side)
        visits, true = simulate_route(route, places, odo, seed=3, signatures=True)
        appearance = PosteriorModel(visits, ModelConfig(odometry=odo)).appearance
        for name, kwargs in (
            ("odometry", {}),
            ("odometry+laser", {"registrar": truth_registrar(true, route)}),
            (
                "odometry+laser+appearance",
                {"registrar": truth_registrar(true, route), "appearance": appearance},
            ),
        ):
            walls, cpus = [], []
            for _ in range(repeats):
                flt = TopologyFilter(RbpfConfig(particles=particles), make_prior(PRIOR), odo, **kwargs)
                cpu = []
                for v in visits:
                    tic = time.process_time()
                    flt.update(v)
                    cpu.append(time.process_time() - tic)
                walls.append([s.update_s for s in flt.history])
                cpus.append(cpu)
            ms = np.min(walls, axis=0) * 1e3
            cpu_ms = np.min(cpus, axis=0) * 1e3
            pw = flt.ptm_weights()
            truth = canonical(route)
            rows.append(
                {
                    "world": world,
                    "odometry": odo_name,
                    "measurements": name,
                    "visits": n_visits,
                    "particles": particles,
                    "repeats": repeats,
                    "places_true": len(set(route)),
                    "places_most_split_particle": int(max(max(lab) for lab in pw) + 1),
                    "update_ms_median": float(np.median(ms)),
                    "update_ms_p95": float(np.percentile(ms, 95)),
                    "update_ms_max": float(ms.max()),
                    "update_ms_median_by_quarter": [float(np.median(q)) for q in np.array_split(ms, 4)],
                    "update_cpu_ms_median": float(np.median(cpu_ms)),
                    "update_cpu_ms_p95": float(np.percentile(cpu_ms, 95)),
                    "update_cpu_ms_median_by_quarter": [
                        float(np.median(q)) for q in np.array_split(cpu_ms, 4)
                    ],
                    "truth_mass": pw.get(truth, 0.0),
                    "map_is_truth": max(pw, key=pw.get) == truth,
                    "final_ess": flt.history[-1].ess,
                    "final_topologies": flt.history[-1].n_topologies,
                }
            )
    return rows


def accuracy(seeds: int) -> list[dict]:
    spread = OdometryConfig(n_samples=0, a_xy=0.3**2)
    cases = (  # the first is test_rbpf.py's few-particle case
        ("square 4 m, 30cm/√m, seed 4", [(0, 0), (4, 0), (4, 4), (0, 4)], spread, 4),
        ("square 4 m, 30cm/√m, seed 2", [(0, 0), (4, 0), (4, 4), (0, 4)], spread, 2),
    )
    route = [0, 1, 2, 3, 0, 1, 2, 3]
    rows = []
    for name, places, odo, vseed in cases:
        visits, _ = simulate_route(route, places, odo, seed=vseed)
        start = time.perf_counter()
        logp = exact_posterior(
            PosteriorModel(visits, ModelConfig(prior=PRIOR, odometry=odo, use_appearance=False))
        )
        exact_s = time.perf_counter() - start
        ex = normalize_log(logp)
        masses = np.sort(np.array(list(ex.values())))[::-1]
        full = run_filter(
            visits, RbpfConfig(particles=bell(len(visits))), make_prior(PRIOR), odo
        ).ptm_weights()
        row = {
            "case": name,
            "visits": len(visits),
            "exact_s": exact_s,
            "exact_map_mass": float(masses[0]),
            "tv_full_filter": total_variation(full, ex),
            "by_particles": [],
        }
        for particles in (10, 20, 50, 100):
            entry = {"particles": particles, "mass_outside_top_n": float(1.0 - masses[:particles].sum())}
            for scheme in ("optimal", "top"):
                tvs = [
                    total_variation(
                        run_filter(
                            visits,
                            RbpfConfig(particles=particles, resample=scheme),
                            make_prior(PRIOR),
                            odo,
                            seed=s,
                        ).ptm_weights(),
                        ex,
                    )
                    for s in range(seeds if scheme == "optimal" else 1)
                ]
                entry[f"tv_{scheme}_mean"] = float(np.mean(tvs))
                entry[f"tv_{scheme}_max"] = float(np.max(tvs))
            row["by_particles"].append(entry)
        rows.append(row)
    return rows


def approximations() -> list[dict]:
    """N = 6 cases where the filter (every child kept) and enumeration differ most, with and without the
    separation prior: what is linearisation and what is the prior's point value (Laplace) vs its integral
    (filter)."""
    square = [(0, 0), (5, 0), (5, 5), (0, 5)]
    close = [(0, 0), (2, 0), (2, 6), (0, 6)]  # places 0 and 1 within the penalty radius
    route = [0, 1, 2, 3, 0, 1]
    odo = OdometryConfig(n_samples=0, a_xy=0.15**2)
    rows = []
    for name, places, seed, laser in (
        ("square 5 m (test_rbpf odometry case)", square, 2, False),
        ("square 5 m, laser + appearance, seed 4", square, 4, True),
        ("places 2 m apart, seed 1", close, 1, False),
    ):
        visits, true = simulate_route(route, places, odo, seed=seed, signatures=laser, sig_noise=1.0)
        row = {"case": name}
        for tag, cfg in (("", odo), ("_no_separation_prior", dataclasses.replace(odo, penalty_max=0.0))):
            reg = truth_registrar(true, route) if laser else None
            model = PosteriorModel(
                visits, ModelConfig(prior=PRIOR, odometry=cfg, use_appearance=laser), registrar=reg
            )
            logp = exact_posterior(model)
            ex = normalize_log(logp)
            flt = run_filter(
                visits,
                RbpfConfig(particles=bell(6)),
                make_prior(PRIOR),
                cfg,
                appearance=model.appearance,
                registrar=reg,
            )
            row["exact_map_mass" + tag] = max(ex.values())
            row["tv" + tag] = total_variation(flt.ptm_weights(), ex)
            row["log_evidence_diff" + tag] = flt.log_evidence - float(logsumexp(list(logp.values())))
        rows.append(row)
    return rows


def linearisation(samples: int) -> dict:
    places = [(0, 0), (5, 0), (5, 5), (0, 5)]
    route = [0, 1, 2, 3, 0, 1]
    odo = OdometryConfig(n_samples=0, a_xy=0.15**2, a_th=0.15**2, penalty_max=0.0)
    visits, _ = simulate_route(route, places, odo, seed=2)

    def post(cfg):
        return normalize_log(
            exact_posterior(PosteriorModel(visits, ModelConfig(odometry=cfg, use_appearance=False)))
        )

    laplace = post(odo)
    sampled = post(dataclasses.replace(odo, n_samples=samples))
    full = run_filter(visits, RbpfConfig(particles=bell(len(visits))), make_prior(PRIOR), odo).ptm_weights()
    return {
        "case": "square 5 m, N = 6, 15cm/√m and 0.15 rad/√rad, no separation prior",
        "is_samples": samples,
        "tv_laplace_vs_is": total_variation(laplace, sampled),
        "tv_filter_vs_is": total_variation(full, sampled),
        "tv_filter_vs_laplace": total_variation(full, laplace),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds and samples")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "rbpf.json")
    args = parser.parse_args()
    result = {
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cpus": os.cpu_count(),
            "load_average_at_start": os.getloadavg(),
        },
        "timing": timing(100, 100, repeats=1 if args.quick else 3),
        "accuracy": accuracy(seeds=2 if args.quick else 5),
        "approximations": approximations(),
        "linearisation": linearisation(samples=300 if args.quick else 2000),
    }
    args.out.write_text(json.dumps(result, indent=1) + "\n")

    print("update per visit [ms], min of repeats: wall (median, p95, max, by quarter) | CPU (median, p95)")
    for r in result["timing"]:
        quarters = " ".join(f"{q:5.1f}" for q in r["update_ms_median_by_quarter"])
        wall = f"{r['update_ms_median']:6.1f} {r['update_ms_p95']:6.1f} {r['update_ms_max']:6.1f}  {quarters}"
        cpu = f"{r['update_cpu_ms_median']:6.1f} {r['update_cpu_ms_p95']:6.1f}"
        head = f"{r['world']} {r['places_true']:2d} places {r['odometry']:8} {r['measurements']:26}"
        print(f"{head} {wall} | {cpu}  truth mass {r['truth_mass']:.3f}")
    print()
    for r in result["accuracy"]:
        print(f"{r['case']} (N={r['visits']}, exact MAP mass {r['exact_map_mass']:.3f})")
        print(f"  TV of the filter keeping every child: {r['tv_full_filter']:.4f}")
        print(f"  {'N part':>6} {'floor':>7} {'optimal mean':>12} {'optimal max':>11} {'top':>7}")
        for e in r["by_particles"]:
            tvs = f"{e['tv_optimal_mean']:12.4f} {e['tv_optimal_max']:11.4f} {e['tv_top_mean']:7.4f}"
            print(f"  {e['particles']:6d} {e['mass_outside_top_n']:7.4f} {tvs}")
    print("\nevery child kept vs enumeration, N = 6: TV (log evidence diff), with | without separation prior")
    for r in result["approximations"]:
        with_pen = f"{r['tv']:.4f} ({r['log_evidence_diff']:+.3f})"
        without = f"{r['tv_no_separation_prior']:.4f} ({r['log_evidence_diff_no_separation_prior']:+.3f})"
        print(f"  {r['case']:40} MAP {r['exact_map_mass']:.3f}: {with_pen} | {without}")
    lin = result["linearisation"]
    print(
        f"\nlinearisation ({lin['case']}): TV Laplace–IS {lin['tv_laplace_vs_is']:.4f}, "
        f"filter–IS {lin['tv_filter_vs_is']:.4f}, filter–Laplace {lin['tv_filter_vs_laplace']:.4f}"
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
