"""How wide is the odometry noise the metric model assumes, against the real errors (issue #23, cause F)?

For each run, the visits are detected at the default parameters (laser surprise) and the relative odometry
between consecutive visits (the model's odometry factors, :func:`ptm_ros.model.odometry.relative_odometry`) is
compared with the ground truth's relative motion. Each error component is whitened by the model's variance
(:class:`ptm_ros.model.odometry.OdometryConfig`: translation ``a_xy·ℓ + b_xy``, heading
``a_th·ρ + c_th·ℓ + b_th``). If the model were right, ``e²/σ²`` would have mean 1 and median 0.455 (χ²₁).
Reported for the laser-corrected odometry the model uses and for the raw wheel odometry, on the real runs
of ``../shared/datasets`` and on the calibration worlds (``bench_calibration.py``) at each noise level.

Writes ``bench/odometry_noise.json`` and ``bench/odometry_noise.md``. A few minutes on one core.

    PYTHONPATH=. .venv/bin/python bench/bench_odometry_noise.py [--seeds 3] [--work out/odometry_noise]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from run_all import DATASETS, REAL_RUNS

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
SIM_WORLDS = ("aliased-ring", "room-row", "twin-rooms")
CHI2_1_MEDIAN = 0.455


def whitened_errors(bag: Path, truth: Any) -> dict[str, Any]:
    """``e²/σ²`` per consecutive-visit segment, per component (x, y, heading), for the corrected and the
    wheel odometry of a bag's visits against ``truth`` (a loaded ground truth)."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.model.geometry import between, interpolate_poses, wrap_angle
    from ptm_ros.model.odometry import odometry_covariances
    from ptm_ros.tools.pipeline import detect_visits

    config = load_config()
    visits = detect_visits(read_run(bag), config)
    truth_poses = interpolate_poses(truth.stamps, truth.poses_corrected, np.array([v.stamp for v in visits]))
    var = np.diagonal(odometry_covariances(visits, config.model.odometry), axis1=1, axis2=2)
    moved = between(truth_poses[:-1], truth_poses[1:]).reshape(-1, 3)
    out: dict[str, Any] = {"segments": len(moved)}
    for name, poses in (
        ("corrected", np.array([v.pose for v in visits])),
        ("wheel", np.array([v.input_pose for v in visits])),
    ):
        e = between(poses[:-1], poses[1:]).reshape(-1, 3) - moved
        e[:, 2] = wrap_angle(e[:, 2])
        w = e**2 / var
        out[name] = {
            "xy_mean": float(w[:, :2].mean()),
            "xy_median": float(np.median(w[:, :2])),
            "heading_mean": float(w[:, 2].mean()),
            "heading_median": float(np.median(w[:, 2])),
        }
    return out


def real_rows(work: Path) -> list[dict[str, Any]]:
    from ptm_ros.io.groundtruth import load_carmen_gt
    from ptm_ros.tools.convert import convert

    rows = []
    for name, log, gt in REAL_RUNS:
        if not (DATASETS / log).is_file():
            continue
        bag = work / f"{name}.bag"
        if not bag.exists():
            convert(DATASETS / log, bag)
        rows.append({"run": name, "noise": "real", **whitened_errors(bag, load_carmen_gt(DATASETS / gt))})
        print(f"[odometry-noise] {rows[-1]}", flush=True)
    return rows


def sim_rows(work: Path, seeds: int) -> list[dict[str, Any]]:
    sys.path.insert(0, str(BENCH))
    from bench_calibration import NOISE_LEVELS

    from ptm_ros.io.groundtruth import load_sim_gt
    from ptm_ros.io.simulator import SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world

    rows = []
    for noise, level in NOISE_LEVELS.items():
        for world in SIM_WORLDS:
            for seed in range(seeds):
                bag = work / f"{world}-{noise}-{seed}"
                if bag.exists():
                    shutil.rmtree(bag)
                sim = simulate(get_world(world), SimConfig(odometry=level), np.random.default_rng(seed))
                write_run(sim, bag)
                rec = whitened_errors(bag, load_sim_gt(bag / "ground_truth.json"))
                rows.append({"run": f"{world} s{seed}", "noise": noise, **rec})
                shutil.rmtree(bag)
        print(f"[odometry-noise] {noise} done", flush=True)
    return rows


def write_markdown(doc: dict[str, Any], path: Path) -> None:
    lines = [
        "# Odometry noise: the model against the real errors (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_odometry_noise.py` ({doc['wall_s'] / 60:.1f} min). "
        "Per run, the error of the relative odometry between consecutive landmark visits against the "
        "ground truth, each component squared and divided by the model's variance (`OdometryConfig` "
        f"defaults). A right model gives mean 1 and median {CHI2_1_MEDIAN} (χ²₁); below: the model is "
        "wider than the errors, above: narrower. Simulated rows are averaged over the worlds and seeds "
        "of each noise level (`bench_calibration.NOISE_LEVELS`).",
        "",
        "| run | noise | segments | corrected xy mean / median | corrected heading mean / median "
        "| wheel xy mean / median | wheel heading mean / median |",
        "|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in doc["runs"]:
        key = (r["run"], "real") if r["noise"] == "real" else (", ".join(SIM_WORLDS), r["noise"])
        groups.setdefault(key, []).append(r)
    for (run, noise), rs in groups.items():
        cells = [run, noise, str(sum(r["segments"] for r in rs))]
        for odo in ("corrected", "wheel"):
            for comp in ("xy", "heading"):
                mean = np.mean([r[odo][f"{comp}_mean"] for r in rs])
                med = np.mean([r[odo][f"{comp}_median"] for r in rs])
                cells.append(f"{mean:.3g} / {med:.3g}")
        lines.append("| " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="simulated seeds per world and noise level")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "odometry_noise")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)
    rows = real_rows(args.work) + sim_rows(args.work, args.seeds)
    doc = {
        "benchmark": "odometry_noise",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "wall_s": time.perf_counter() - t0,
        "runs": rows,
    }
    (BENCH / "odometry_noise.json").write_text(json.dumps(doc, indent=1))
    write_markdown(doc, BENCH / "odometry_noise.md")
    print((BENCH / "odometry_noise.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
