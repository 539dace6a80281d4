"""Benchmark of the metric likelihood :func:`ptm_ros.model.odometry.metric_log_likelihood`.

A synthetic loop: eight landmarks on a 16 m square (corners and side midpoints, 8 m apart) visited lap
after lap, with odometry noise drawn from the model of the default :class:`OdometryConfig`. For
N = 10, 33 and 100 visits it times the Laplace path (``n_samples = 0``) and importance sampling with
200 samples, for the true topology (visit i is place i mod 8) and for all-distinct places, and records
the effective sample size of both proposals. Writes ``bench/odometry.json`` and prints a table.

    .venv/bin/python bench/bench_odometry.py [--repeats 30] [--out bench/odometry.json]

Timings are medians over repeats of one call, wall and CPU time; on a busy machine OpenBLAS threads
contend, so ``OPENBLAS_NUM_THREADS=1`` gives steadier numbers (recorded in the JSON with the load).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ptm_ros.io.synthetic import odometry_visits
from ptm_ros.model.odometry import MAX_VISITS, OdometryConfig, metric_log_likelihood
from ptm_ros.model.visits import Visit

SIZES = (10, 33, 100)
N_PLACES = 8
SIDE = 16.0


def landmark_poses() -> np.ndarray:
    """Poses (x, y, heading of travel) of the eight landmarks, counter-clockwise from the origin."""
    half = SIDE / 2
    xy = [(0, 0), (half, 0), (SIDE, 0), (SIDE, half), (SIDE, SIDE), (half, SIDE), (0, SIDE), (0, half)]
    heading = [0, 0, np.pi / 2, np.pi / 2, np.pi, np.pi, -np.pi / 2, -np.pi / 2]
    return np.array([(x, y, h) for (x, y), h in zip(xy, heading, strict=True)], dtype=float)


def synthetic_loop(
    n: int, cfg: OdometryConfig, rng: np.random.Generator
) -> tuple[list[Visit], tuple[int, ...]]:
    """``n`` visits of the lap-after-lap loop with noisy odometry, and the true topology."""
    visits = odometry_visits(landmark_poses()[np.arange(n) % N_PLACES], cfg, rng)
    return visits, tuple(int(i) for i in np.arange(n) % N_PLACES)


def median_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall and CPU time of ``fn()`` in milliseconds (after one warm-up call).

    CPU time (``time.process_time``) is the steadier figure when other processes share the cores.
    """
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def run(repeats: int, seed: int) -> list[dict[str, object]]:
    laplace = OdometryConfig(n_samples=0)
    # importance sampling at every N, also beyond the model's default cut-over to Laplace
    sampled = OdometryConfig(n_samples=200, max_sampled_visits=MAX_VISITS)
    absolute = OdometryConfig(n_samples=200, proposal="absolute", max_sampled_visits=MAX_VISITS)
    rows: list[dict[str, object]] = []
    for n in SIZES:
        visits, truth = synthetic_loop(n, laplace, np.random.default_rng(seed))
        for name, labels in (("true", truth), ("distinct", tuple(range(n)))):
            lap = metric_log_likelihood(labels, visits, laplace)
            res = metric_log_likelihood(labels, visits, sampled, rng=np.random.default_rng(seed))
            res_abs = metric_log_likelihood(labels, visits, absolute, rng=np.random.default_rng(seed))
            rng = np.random.default_rng(seed)
            lap_wall, lap_cpu = median_ms(
                lambda v=visits, t=labels: metric_log_likelihood(t, v, laplace), repeats
            )
            is_wall, is_cpu = median_ms(
                lambda v=visits, t=labels, g=rng: metric_log_likelihood(t, v, sampled, rng=g), repeats
            )
            rows.append(
                {
                    "n_visits": n,
                    "topology": name,
                    "places": len(set(labels)),
                    "laplace_ms": lap_wall,
                    "laplace_cpu_ms": lap_cpu,
                    "is200_ms": is_wall,
                    "is200_cpu_ms": is_cpu,
                    "iterations": lap.iterations,
                    "log_laplace": lap.log_laplace,
                    "log_is200": res.log_likelihood,
                    "ess_relative": res.ess,
                    "ess_absolute": res_abs.ess,
                }
            )
    return rows


def print_table(rows: Sequence[dict[str, object]]) -> None:
    print(
        f"{'N':>4} {'topology':>9} {'M':>3} {'it':>3} {'Laplace ms':>10} {'(cpu)':>6} {'IS200 ms':>9} "
        f"{'(cpu)':>6} {'log Laplace':>12} {'log IS':>10} {'ESS rel':>8} {'ESS abs':>8}"
    )
    for r in rows:
        print(
            f"{r['n_visits']:>4} {r['topology']:>9} {r['places']:>3} {r['iterations']:>3} "
            f"{r['laplace_ms']:>10.2f} {r['laplace_cpu_ms']:>6.2f} {r['is200_ms']:>9.2f} "
            f"{r['is200_cpu_ms']:>6.2f} {r['log_laplace']:>12.3f} {r['log_is200']:>10.3f} "
            f"{r['ess_relative']:>8.1f} {r['ess_absolute']:>8.1f}"
        )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30, help="timed calls per case (median reported)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "odometry.json")
    args = parser.parse_args(argv)
    rows = run(args.repeats, args.seed)
    print_table(rows)
    record = {
        "benchmark": "ptm_ros.model.odometry.metric_log_likelihood on a synthetic 8-place loop",
        "config": OdometryConfig().__dict__,
        "repeats": args.repeats,
        "seed": args.seed,
        "environment": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "load_average_1min": os.getloadavg()[0],
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        },
        "rows": rows,
    }
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
