"""The heading noise learned from a run (``model.odometry.learn_heading``, issue #23) against the truth.

For each real run in ``../shared/datasets`` (converted once under ``--work``) and each simulated world of
``--worlds`` at the odometry noise levels ``--noise`` of ``bench_calibration.py`` (seed 0):

* **measured**: the laser-corrected odometry's heading error against the ground truth over consecutive
  stretches of ``--window`` m of true travel, its mean square divided by the mean heading variance the
  default model gives the same stretches (``a_th ρ + c_th ℓ``): the scale a perfect estimator would learn;
* **learned**: the scale the filter session learns from the run's own laser registrations, no ground truth
  (:mod:`ptm_ros.model.heading_noise`, as ``ptm-run`` at the default parameters), with the registrations and
  the outlier fraction behind it.

Writes ``bench/heading_noise.json`` and ``bench/heading_noise.md``.

    PYTHONPATH=. .venv/bin/python bench/bench_heading_noise.py [--work out/heading_noise]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from run_all import DATASETS, REAL_RUNS, prepare_runs, write_bench

BENCH = Path(__file__).resolve().parent
WORLDS = ("aliased-loop", "twin-rooms", "room-row", "aliased-ring")
NOISE = ("sim", "model", "twice-model")


def measured_ratio(stamps: np.ndarray, corrected: np.ndarray, truth: Any, window: float) -> dict[str, float]:
    """Mean square heading error of ``corrected`` (poses at ``stamps``) over ``window`` m stretches of the
    truth's travel, against the default model's mean heading variance of the same stretches."""
    from ptm_ros.model.geometry import between, interpolate_poses, wrap_angle
    from ptm_ros.model.odometry import OdometryConfig

    inside = (truth.stamps >= stamps[0]) & (truth.stamps <= stamps[-1])
    t, g = truth.stamps[inside], truth.poses_corrected[inside]
    c = interpolate_poses(stamps, corrected, t)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g[:, :2], axis=0).T))])
    turned = np.concatenate([[0.0], np.cumsum(np.abs(wrap_angle(np.diff(g[:, 2]))))])
    cfg = OdometryConfig()
    err, var, i = [], [], 0
    while (j := int(np.searchsorted(travel, travel[i] + window))) < len(t):
        err.append(float(wrap_angle(between(c[i], c[j])[2] - between(g[i], g[j])[2])) ** 2)
        var.append(cfg.a_th * (turned[j] - turned[i]) + cfg.c_th * (travel[j] - travel[i]))
        i = j
    if not err:
        return {"stretches": 0}
    return {
        "stretches": len(err),
        "mean_square": float(np.mean(err)),
        "ratio": float(np.mean(err) / np.mean(var)),
    }


def one_run(bag: Path, truth_path: Path, window: float) -> dict[str, Any]:
    """Measured and learned scale of one bag at the default parameters (laser-surprise visits)."""
    from ptm_ros.config import PtmConfig
    from ptm_ros.factories import with_detector_kind
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.session import FilterSession, filter_visits
    from ptm_ros.tools.outputs import run_odometry
    from ptm_ros.tools.pipeline import corrected_odometry, detect_visits, run_extractor, run_sensors

    run = read_run(bag)
    config = with_detector_kind(PtmConfig(), **run_sensors(run))
    extractor = run_extractor(run, config)
    visits = detect_visits(run, config, extractor=extractor)
    odom = run_odometry(run)
    out: dict[str, Any] = {"visits": len(visits)}
    out["measured"] = measured_ratio(
        np.asarray(odom.stamps), corrected_odometry(run, extractor), load_ground_truth(truth_path), window
    )
    t0 = time.perf_counter()
    session = filter_visits(FilterSession(config, fitted_to=visits), visits)
    out["learned"] = session.heading.as_dict()
    out["filter_s"] = time.perf_counter() - t0
    out["replays"] = session.replays
    return out


def write_md(doc: dict[str, Any], path: Path) -> None:
    lines = [
        "# The heading noise learned from the run (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_heading_noise.py` ({doc['wall_s'] / 60:.0f} min). "
        f"*Measured*: the laser-corrected odometry's heading error against the ground truth over "
        f"{doc['window_m']:.0f} m stretches of true travel, its mean square over the default model's heading "
        "variance of the same stretches (what a perfect estimator would learn). *Learned*: the scale "
        "`ptm-run` learns at the default parameters from the run's own laser registrations, no ground truth "
        "(`ptm_ros.model.heading_noise`; lattice 2^(m/2), prior log k ~ N(0, 1)). Laser-surprise visits.",
        "",
        "| run | noise | visits | stretches | measured ratio | learned scale | registrations | outliers "
        "| filter s (replays) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        m, lr = r["measured"], r["learned"]
        ratio = f"{m['ratio']:.3f}" if "ratio" in m else "–"
        lines.append(
            f"| {r['run']} | {r.get('noise', 'real')} | {r['visits']} | {m['stretches']} | {ratio} | "
            f"{lr['scale']:.3g} | {lr['registrations']} | {lr['outlier_fraction']:.2f} | "
            f"{r['filter_s']:.1f} ({r['replays']}) |"
        )
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=list(WORLDS))
    parser.add_argument("--noise", nargs="+", default=list(NOISE), help="bench_calibration.py's noise levels")
    parser.add_argument("--window", type=float, default=30.0, help="stretch of true travel (m)")
    parser.add_argument("--work", type=Path, default=BENCH.parent / "out" / "heading_noise")
    parser.add_argument("--out", type=Path, default=BENCH / "heading_noise.json")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(BENCH))
    from bench_calibration import NOISE_LEVELS

    from ptm_ros.io.simulator import SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world

    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs = []
    if DATASETS.is_dir():
        for name, _, bag, gt in prepare_runs(args.work, [name for name, _, _ in REAL_RUNS]):
            runs.append({"run": name, **one_run(bag, gt, args.window)})
            print(f"[heading] {name}: {runs[-1]}", flush=True)
    for world in args.worlds:
        for noise in args.noise:
            bag = args.work / "sim" / f"{world}-{noise}"
            if not bag.exists():
                sim = simulate(
                    get_world(world), SimConfig(odometry=NOISE_LEVELS[noise]), np.random.default_rng(0)
                )
                write_run(sim, bag)
            runs.append(
                {"run": world, "noise": noise, **one_run(bag, bag / "ground_truth.json", args.window)}
            )
            print(f"[heading] {world} {noise}: {runs[-1]}", flush=True)
    doc = {
        "benchmark": "heading_noise",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "wall_s": time.perf_counter() - t0,
        "window_m": args.window,
        "runs": runs,
    }
    write_bench(doc, args.out, write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
