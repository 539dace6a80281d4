"""Benchmark of log P(T | Z) for one topology (odometry + appearance), issue: foundation.

Synthetic lap-after-lap loop of :mod:`bench_odometry` (eight places, 8 m apart) with a Fourier-like
appearance signature per place plus noise. For N = 33 and 100 visits it times a *fresh* evaluation of
the true topology's unnormalised log posterior (prior + metric Laplace or 200-sample importance
sampling + appearance, nothing cached), and records the importance-sampling ESS. Writes
``bench/posterior.json`` and prints a table.

    PYTHONPATH=. .venv/bin/python bench/bench_posterior.py [--repeats 30]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_odometry import N_PLACES, synthetic_loop

from ptm_ros.model.odometry import MAX_VISITS, OdometryConfig
from ptm_ros.model.posterior import ModelConfig, PosteriorModel
from ptm_ros.model.visits import Visit


def with_signatures(visits: list[Visit], rng: np.random.Generator, k: int = 8) -> list[Visit]:
    place_sig = rng.uniform(0.05, 1.0, size=(N_PLACES, k))
    return [replace(v, signature=place_sig[v.index % N_PLACES] + rng.normal(0, 0.03, k)) for v in visits]


def time_fresh(model_args: tuple, labels: tuple[int, ...], repeats: int) -> tuple[float, float, float]:
    """Median wall / CPU ms of one uncached evaluation, and the last result's ESS."""
    wall, cpu = [], []
    ess = float("nan")
    for _ in range(repeats + 1):
        model = PosteriorModel(*model_args[:1], model_args[1])  # fresh caches every time
        w0, c0 = time.perf_counter(), time.process_time()
        terms = model.terms(labels)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
        ess = terms.metric_result.ess if terms.metric_result is not None else ess
    return 1e3 * float(np.median(wall[1:])), 1e3 * float(np.median(cpu[1:])), ess


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "posterior.json")
    args = parser.parse_args()
    rows = []
    for n in (33, 100):
        rng = np.random.default_rng(n)
        visits, truth = synthetic_loop(n, OdometryConfig(n_samples=0), rng)
        visits = with_signatures(visits, rng)
        for name, n_samples in (("laplace", 0), ("is200", 200)):
            odo = OdometryConfig(n_samples=n_samples, max_sampled_visits=MAX_VISITS)  # IS at every N
            cfg = ModelConfig(odometry=odo, use_laser=False)
            # appearance model fitting (once per run) is excluded: build it outside the timed call
            wall, cpu, ess = time_fresh((visits, cfg), truth, args.repeats)
            rows.append({"n_visits": n, "metric": name, "median_ms": wall, "median_cpu_ms": cpu, "ess": ess})
    doc = {
        "benchmark": "log P(T|Z) of one topology, odometry + appearance, uncached",
        "load_average": os.getloadavg(),
        "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "rows": rows,
    }
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"{'N':>4} {'metric':>8} {'median ms':>10} {'cpu ms':>8} {'ESS':>7}")
    for r in rows:
        ms, cpu = r["median_ms"], r["median_cpu_ms"]
        print(f"{r['n_visits']:>4} {r['metric']:>8} {ms:>10.2f} {cpu:>8.2f} {r['ess']:>7.1f}")


if __name__ == "__main__":
    main()
