"""The laser time offset learned from a run (``laser_odometry.learn_time_offset``, issues #23/#24).

:func:`ptm_ros.perception.laser_odometry.learn_time_offset` on the first ``learn_scans`` scans of

1. simulated runs whose laser driver stamps every scan ``--delays`` s late (the true offset is minus the
   delay), over ``--worlds``, ``--seeds`` and the odometry noise levels ``--noise`` of
   ``bench_calibration.py`` (default: the simulator's own);
2. the real runs in ``../shared/datasets`` (when present; converted once under ``--work``), beside
   ``ptm-calibrate``'s choice over the same scans (:func:`ptm_ros.tools.calibrate.calibrate_run`).

Writes ``bench/time_offset.json`` and ``bench/time_offset.md``: per run the learned offset, the first
pass's estimate and the error against the truth (simulated). No ground truth is used by the estimate.

    PYTHONPATH=. .venv/bin/python bench/bench_time_offset.py [--seeds 0 1 2] [--work out/time_offset]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import itertools
import platform
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from run_all import DATASETS, REAL_RUNS, prepare_runs, write_bench

BENCH = Path(__file__).resolve().parent
WORLDS = ("aliased-loop", "twin-rooms", "room-row", "aliased-ring", "t-junction")
DELAYS = (0.0, 0.1, 0.2)


def learned(bag: Path) -> dict[str, Any]:
    """The offset learned on a bag's first ``learn_scans`` scans at the default parameters, with
    ``ptm-calibrate``'s choice over the same scans."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.maps.mapping import scan_points
    from ptm_ros.perception.laser_odometry import RunInput, learn_time_offset
    from ptm_ros.tools.calibrate import calibrate_run

    config = load_config()
    n = config.laser_odometry.learn_scans
    run = read_run(bag, require=("/odom", "/scan"))
    assert run.odometry is not None and run.scans is not None
    stamps, points = scan_points(run.scans, config.laser)
    t0 = time.perf_counter()
    est = learn_time_offset(
        RunInput.of(run.odometry.stamps, run.odometry.poses, stamps[:n], points[:n]),
        config.laser_odometry,
        config.laser,
    )
    learn_s = time.perf_counter() - t0
    calibrated = calibrate_run(run, config, max_scans=n).time_offset
    return {**est.as_dict(), "learn_s": learn_s, "ptm_calibrate": calibrated}


def simulated(
    worlds: Sequence[str], delays: Sequence[float], seeds: Sequence[int], noise: Sequence[str], work: Path
) -> list[dict]:
    from bench_calibration import NOISE_LEVELS

    from ptm_ros.io.simulator import CameraConfig, LaserConfig, SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world

    rows = []
    for level, world, delay, seed in itertools.product(noise, worlds, delays, seeds):
        cfg = SimConfig(
            odometry=NOISE_LEVELS[level],
            laser=LaserConfig(stamp_delay=delay),
            camera=CameraConfig(enabled=False),
        )
        bag = work / f"{world}-{level}-{delay}-{seed}"
        shutil.rmtree(bag, ignore_errors=True)
        write_run(simulate(get_world(world), cfg, np.random.default_rng(seed)), bag)
        row = {"run": world, "noise": level, "delay": delay, "seed": seed, **learned(bag)}
        row["error"] = row["offset"] + delay
        shutil.rmtree(bag, ignore_errors=True)
        print(f"[time_offset] {world} {level} delay {delay} seed {seed}: {row['offset']:+.3f}", flush=True)
        rows.append(row)
    return rows


def write_md(doc: dict, path: Path) -> None:
    sim, real = doc["simulated"], doc["real"]
    lines = [
        "# The laser time offset learned from the run (issues #23, #24)",
        "",
        f"Generated {doc['generated']} by `bench/bench_time_offset.py` ({doc['wall_s'] / 60:.0f} min). "
        "`learn_time_offset` on the first `learn_scans` scans at the default parameters (no ground truth); "
        "*offset*: what the extractor uses; *first*: the first pass's estimate; *ptm-calibrate*: its choice "
        "over the same scans (candidates 0 to −0.3 s by 0.05 s).",
        "",
        "## Simulated lasers stamped late",
        "",
        "Odometry noise levels: `bench_calibration.py`'s (`sim`: the simulator's own).",
        "",
        "| noise | delay (s) | runs | learned offset: min / median / max | max abs error | wrong |",
        "|---|---|---|---|---|---|",
    ]
    for level, delay in sorted({(r["noise"], r["delay"]) for r in sim}):
        rs = [r for r in sim if r["noise"] == level and r["delay"] == delay]
        off = np.array([r["offset"] for r in rs])
        wrong = sum(abs(r["error"]) > 1e-9 for r in rs)
        lines.append(
            f"| {level} | {delay} | {len(rs)} | {off.min():+.3f} / {np.median(off):+.3f} / "
            f"{off.max():+.3f} | {max(abs(r['error']) for r in rs):.3f} | {wrong} |"
        )
    head = "| world | noise | delay | seed | offset | first | ptm-calibrate |"
    lines += ["", head, "|---|---|---|---|---|---|---|"]
    lines += [
        f"| {r['run']} | {r['noise']} | {r['delay']} | {r['seed']} | {r['offset']:+.3f} | "
        f"{r['first']:+.3f} | {r['ptm_calibrate']:+.2f} |"
        for r in sim
        if abs(r["error"]) > 1e-9 or r["offset"] != 0.0
    ]
    if real:
        lines += [
            "",
            "## Real runs",
            "",
            "| run | offset | first | candidates tried | ptm-calibrate | learning (s) |",
            "|---|---|---|---|---|---|",
        ]
        for r in real:
            tried = ", ".join(f"{c['offset']:+.2f}" for c in r["scores"])
            lines.append(
                f"| {r['run']} | {r['offset']:+.3f} | {r['first']:+.3f} | {tried} | "
                f"{r['ptm_calibrate']:+.2f} | {r['learn_s']:.1f} |"
            )
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=list(WORLDS))
    parser.add_argument("--delays", type=float, nargs="+", default=list(DELAYS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--noise", nargs="+", default=["sim"], help="bench_calibration.py's noise levels")
    parser.add_argument("--work", type=Path, default=BENCH.parent / "out" / "time_offset")
    parser.add_argument("--out", type=Path, default=BENCH / "time_offset.json")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = simulated(args.worlds, args.delays, args.seeds, args.noise, args.work)
    real = []
    if DATASETS.is_dir():
        names = [name for name, _, _ in REAL_RUNS]
        for name, _, bag, _ in prepare_runs(args.work, names):
            real.append({"run": name, **learned(bag)})
            print(f"[time_offset] {name}: {real[-1]['offset']:+.3f}", flush=True)
    doc = {
        "benchmark": "time_offset",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "wall_s": time.perf_counter() - t0,
        "simulated": sim,
        "real": real,
    }
    write_bench(doc, args.out, write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
