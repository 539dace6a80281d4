"""Benchmark of the Bayesian-surprise landmark detectors (:mod:`ptm_ros.perception.laser_surprise`,
:mod:`ptm_ros.perception.appearance_surprise` over :mod:`ptm_ros.perception.surprise`, thesis Ch. 4.6–4.8).

1. Throughput: the laser detector on a simulated run (scans/s, target >= 200) and the SIFT bag-of-words
   appearance detector on 64 x 512 panoramas (SIFT + words + EDCM surprise, panoramas/s, target >= 10).
2. Laser detector on the simulated worlds (``ptm_ros.io.worlds``), every per-scan statistic at the
   default settings: a decision-point passage is *found* when a detection lies within 2 m of the place
   while the robot passes it (one detection per passage); every other detection is a false positive.
3. Robustness of the default laser detector to speed, laser noise, a 360° scanner and a 5 Hz laser,
   beside the same detector without forgetting per metre of travel.
4. Appearance detectors (words with a 256-word vocabulary built from a different run; Fourier) on the
   same worlds, with the chance level: as many detections at random panoramas, scored the same way.
5. Real logs in ``../shared/datasets`` (when present): laser detections per 10 m of odometry (these
   logs have no decision-point ground truth).

Writes ``bench/surprise.json`` and prints tables.

    PYTHONPATH=. .venv/bin/python bench/bench_surprise.py [--seeds 3] [--out bench/surprise.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

from ptm_ros.io.simulator import CameraConfig, LaserConfig, SimConfig, SimRun, simulate
from ptm_ros.io.worlds import WORLDS, get_world
from ptm_ros.model.vocabulary import Vocabulary, sift_descriptors
from ptm_ros.perception.appearance_surprise import AppearanceSurpriseConfig, AppearanceSurpriseDetector
from ptm_ros.perception.laser_surprise import STATISTICS, LaserSurpriseConfig, LaserSurpriseDetector

BENCH = Path(__file__).resolve().parent
DATASETS = BENCH.parent.parent / "shared" / "datasets"
RADIUS = 2.0
NO_CAMERA = CameraConfig(enabled=False)
VARIANTS = {
    "default": SimConfig(camera=NO_CAMERA),
    "speed 0.3 m/s": SimConfig(speed=0.3, camera=NO_CAMERA),
    "speed 1.0 m/s": SimConfig(speed=1.0, camera=NO_CAMERA),
    "laser noise 5 cm": SimConfig(laser=LaserConfig(noise=0.05), camera=NO_CAMERA),
    "360° laser": SimConfig(laser=LaserConfig(fov=2 * math.pi, beams=360), camera=NO_CAMERA),
    "laser 5 Hz": SimConfig(laser=LaserConfig(rate=5.0), camera=NO_CAMERA),
}
REAL_LOGS = {
    "intel": "intel/intel-raw-910.clf.gz",
    "aces": "aces/aces-raw-440.clf.gz",
    "mit-csail": "mit-csail/mit-csail.clf.gz",
}


# ------------------------------------------------------------------------------------------- scoring


def match(run: SimRun, stamps: list[float], radius: float = RADIUS) -> dict:
    """Passages found (a detection within ``radius`` m of the place during the passage) and false
    positives (detections matched to no passage, duplicates included)."""
    t, poses = run.odom_stamps, run.true_poses
    s = np.asarray(stamps, dtype=float)
    xy = np.column_stack([np.interp(s, t, poses[:, 0]), np.interp(s, t, poses[:, 1])]).reshape(-1, 2)
    used = np.zeros(len(s), dtype=bool)
    found = 0
    for passage in run.passages:
        place = run.world.place(passage.place)
        near = np.hypot(poses[:, 0] - place.x, poses[:, 1] - place.y) <= radius
        lo = hi = int(np.argmin(np.abs(t - passage.stamp)))
        while lo > 0 and near[lo - 1]:
            lo -= 1
        while hi < len(t) - 1 and near[hi + 1]:
            hi += 1
        ok = (
            ~used & (s >= t[lo]) & (s <= t[hi]) & (np.hypot(xy[:, 0] - place.x, xy[:, 1] - place.y) <= radius)
        )
        if ok.any():
            used[np.flatnonzero(ok)[0]] = True
            found += 1
    n = len(run.passages)
    return {
        "passages": n,
        "found": found,
        "recall": found / n,
        "false_positives": int((~used).sum()),
        "detections": len(s),
    }


# --------------------------------------------------------------------------------------------- laser


def laser_detections(run: SimRun, config: LaserSurpriseConfig) -> tuple[list[float], float]:
    """Landmark stamps of the laser detector fed the run's odometry and scans in time order, and the
    wall time spent in the detector."""
    laser = run.config.laser
    detector = LaserSurpriseDetector(config)
    found = []
    t0 = time.perf_counter()
    for stamp, kind, i in run.events(images=False):
        if kind == 0:
            detector.on_odometry(stamp, run.odom_poses[i])
        elif detector.on_scan(
            stamp,
            run.scan_ranges[i],
            angle_min=laser.angle_min,
            angle_increment=laser.angle_increment,
            range_min=laser.range_min,
            range_max=laser.range_max,
        ):
            found.append(float(detector.last_landmark_stamp))  # type: ignore[arg-type]
    return found, time.perf_counter() - t0


def bench_laser(seeds: int) -> list[dict]:
    rows = []
    for world in WORLDS:
        for seed in range(seeds):
            run = simulate(get_world(world), VARIANTS["default"], np.random.default_rng(seed))
            for statistic in STATISTICS:
                stamps, _ = laser_detections(run, LaserSurpriseConfig(statistic=statistic))
                rows.append({"world": world, "seed": seed, "statistic": statistic, **match(run, stamps)})
    return rows


def bench_variants(seeds: int) -> list[dict]:
    configs = {
        "default": LaserSurpriseConfig(),
        "no forgetting per metre": LaserSurpriseConfig(memory_distance=math.inf),
    }
    rows = []
    for variant, sim_config in VARIANTS.items():
        for world in ("aliased-loop", "two-loop", "multi-loop"):
            for seed in range(seeds):
                run = simulate(get_world(world), sim_config, np.random.default_rng(100 + seed))
                for name, config in configs.items():
                    stamps, _ = laser_detections(run, config)
                    rows.append(
                        {
                            "variant": variant,
                            "detector": name,
                            "world": world,
                            "seed": 100 + seed,
                            **match(run, stamps),
                        }
                    )
    return rows


# ---------------------------------------------------------------------------------------- appearance


def build_vocabulary(size: int) -> Vocabulary:
    """A vocabulary from the panoramas of a run not used for scoring (two-loop, seed 1000)."""
    train = simulate(get_world("two-loop"), SimConfig(), np.random.default_rng(1000))
    descriptors = np.vstack([sift_descriptors(image) for image in train.images])
    return Vocabulary.build(descriptors, size, np.random.default_rng(0))


def appearance_detections(
    run: SimRun, config: AppearanceSurpriseConfig, vocabulary: Vocabulary | None
) -> tuple[list[float], float]:
    detector = AppearanceSurpriseDetector(config, vocabulary)
    found = []
    t0 = time.perf_counter()
    for stamp, kind, i in run.events(scans=False):
        if kind == 0:
            detector.on_odometry(stamp, run.odom_poses[i])
        elif detector.on_image(stamp, run.images[i]):
            found.append(float(detector.last_landmark_stamp))  # type: ignore[arg-type]
    return found, time.perf_counter() - t0


def chance(run: SimRun, count: int, rng: np.random.Generator, draws: int = 50) -> dict:
    """Mean recall and false positives of ``count`` detections at random panoramas."""
    scores = [
        match(
            run, sorted(rng.choice(run.image_stamps, size=min(count, len(run.image_stamps)), replace=False))
        )
        for _ in range(draws)
    ]
    return {
        "recall": float(np.mean([s["recall"] for s in scores])),
        "false_positives": float(np.mean([s["false_positives"] for s in scores])),
    }


def bench_appearance(seeds: int, vocabulary: Vocabulary) -> tuple[list[dict], dict]:
    rows = []
    timing = {"panoramas": 0, "words_s": 0.0}
    rng = np.random.default_rng(7)
    for world in WORLDS:
        for seed in range(seeds):
            run = simulate(get_world(world), SimConfig(), np.random.default_rng(seed))
            for model in ("words", "fourier"):
                stamps, wall = appearance_detections(run, AppearanceSurpriseConfig(model=model), vocabulary)
                if model == "words":
                    timing["panoramas"] += len(run.image_stamps)
                    timing["words_s"] += wall
                score = match(run, stamps)
                rows.append(
                    {
                        "world": world,
                        "seed": seed,
                        "model": model,
                        **score,
                        "chance": chance(run, len(stamps), rng),
                    }
                )
    return rows, timing


# ------------------------------------------------------------------------------------------ throughput


def bench_throughput(vocabulary_256: Vocabulary, vocabulary_1024: Vocabulary) -> dict:
    run = simulate(get_world("multi-loop"), SimConfig(), np.random.default_rng(0))
    cpu0 = time.process_time()
    _, wall = laser_detections(run, LaserSurpriseConfig())
    cpu = time.process_time() - cpu0
    out = {
        "laser": {
            "scans": len(run.scan_stamps),
            "wall_s": wall,
            "scans_per_s": len(run.scan_stamps) / wall,
            "scans_per_cpu_s": len(run.scan_stamps) / cpu,
        }
    }
    images = run.images[:60]
    for name, vocabulary in (("words_v256", vocabulary_256), ("words_v1024", vocabulary_1024)):
        detector = AppearanceSurpriseDetector(AppearanceSurpriseConfig(), vocabulary)
        t0 = time.perf_counter()
        descriptors = [sift_descriptors(image) for image in images]
        t1 = time.perf_counter()
        histograms = [vocabulary.words(d) for d in descriptors]
        t2 = time.perf_counter()
        for k, h in enumerate(histograms):
            detector.on_measurement(float(k), h)
        t3 = time.perf_counter()
        n = len(images)
        out[name] = {
            "panoramas": n,
            "shape": list(images.shape[1:]),
            "sift_ms": 1e3 * (t1 - t0) / n,
            "words_ms": 1e3 * (t2 - t1) / n,
            "surprise_ms": 1e3 * (t3 - t2) / n,
            "panoramas_per_s": n / (t3 - t0),
        }
    detector = AppearanceSurpriseDetector(AppearanceSurpriseConfig(model="fourier"))
    t0 = time.perf_counter()
    for k, image in enumerate(images):
        detector.on_image(float(k), image)
    out["fourier"] = {"panoramas": len(images), "panoramas_per_s": len(images) / (time.perf_counter() - t0)}
    return out


# ------------------------------------------------------------------------------------------ real logs


def bench_real() -> list[dict]:
    if not (DATASETS / "README.md").is_file():
        return []
    from ptm_ros.io.carmen import read_log

    rows = []
    for name, rel in REAL_LOGS.items():
        log = read_log(DATASETS / rel)
        detector = LaserSurpriseDetector()
        count, travel, last, skipped, last_stamp = 0, 0.0, None, 0, -math.inf
        for record in log.lasers:
            if record.logger_timestamp < last_stamp:  # as the pipeline does: skip stamps going back
                skipped += 1
                continue
            last_stamp = record.logger_timestamp
            pose = np.asarray(record.odom_pose, dtype=float)
            if last is not None:
                travel += float(np.hypot(*(pose[:2] - last[:2])))
            last = pose
            detector.on_odometry(record.logger_timestamp, pose)
            count += detector.on_scan(
                record.logger_timestamp,
                record.ranges,
                angle_min=record.angle_min,
                angle_increment=record.angle_increment,
                range_min=0.0,
                range_max=record.max_range or 80.0,
            )
        rows.append(
            {
                "log": name,
                "scans": len(log.lasers),
                "skipped_stamp_backwards": skipped,
                "odometry_m": travel,
                "m_per_scan": travel / max(len(log.lasers) - 1, 1),
                "detections": count,
                "per_10m": 10.0 * count / travel,
            }
        )
    return rows


# ----------------------------------------------------------------------------------------------- main


def summarise(rows: list[dict], keys: tuple[str, ...]) -> list[dict]:
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    out = []
    for key, rs in groups.items():
        passages = sum(r["passages"] for r in rs)
        out.append(
            {
                **dict(zip(keys, key, strict=True)),
                "passages": passages,
                "recall": sum(r["found"] for r in rs) / passages,
                "worst_recall": min(r["recall"] for r in rs),
                "false_positives": sum(r["false_positives"] for r in rs),
                "max_fp_per_passage": max(r["false_positives"] / r["passages"] for r in rs),
            }
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="simulator seeds per world")
    parser.add_argument("--out", type=Path, default=BENCH / "surprise.json")
    args = parser.parse_args()
    t_start = time.perf_counter()

    vocabulary_256, vocabulary_1024 = build_vocabulary(256), build_vocabulary(1024)
    throughput = bench_throughput(vocabulary_256, vocabulary_1024)
    laser = bench_laser(args.seeds)
    variants = bench_variants(max(1, args.seeds - 1))
    appearance, _ = bench_appearance(args.seeds, vocabulary_256)
    real = bench_real()

    result = {
        "schema": "ptm_ros.bench.surprise/1",
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()),
            "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        },
        "match_radius_m": RADIUS,
        "config": {
            "laser": dataclasses.asdict(LaserSurpriseConfig()),
            "appearance": dataclasses.asdict(AppearanceSurpriseConfig()),
        },
        "throughput": throughput,
        "laser_summary": summarise(laser, ("statistic",)),
        "laser_per_world": summarise(laser, ("statistic", "world")),
        "laser": laser,
        "laser_variants_summary": summarise(variants, ("variant", "detector")),
        "laser_variants": variants,
        "appearance_summary": summarise(appearance, ("model", "world")),
        "appearance": appearance,
        "real_logs": real,
        "wall_s": time.perf_counter() - t_start,
    }
    args.out.write_text(json.dumps(result, indent=1, default=float))
    print_tables(result)
    print(f"wrote {args.out} in {result['wall_s']:.0f} s")


def print_tables(result: dict) -> None:
    tp = result["throughput"]
    print(f"\nthroughput: laser {tp['laser']['scans_per_s']:.0f} scans/s (target 200)", end="")
    for name in ("words_v256", "words_v1024"):
        t = tp[name]
        print(
            f"; {name} {t['panoramas_per_s']:.1f} panoramas/s (SIFT {t['sift_ms']:.0f} ms, words "
            f"{t['words_ms']:.1f} ms, surprise {t['surprise_ms']:.1f} ms; target 10)",
            end="",
        )
    print(f"; fourier {tp['fourier']['panoramas_per_s']:.0f} panoramas/s")
    print(f"\nlaser detector, recall within {RADIUS} m / false positives per world (all seeds):")
    print(f"{'statistic':16s}" + "".join(f"{w:>22s}" for w in WORLDS) + f"{'all':>18s}")
    for statistic in STATISTICS:
        cells = [r for r in result["laser_per_world"] if r["statistic"] == statistic]
        total = next(r for r in result["laser_summary"] if r["statistic"] == statistic)
        line = "".join(f"{c['recall']:>10.2f} {c['false_positives']:>4d}/{c['passages']:<6d}" for c in cells)
        print(
            f"{statistic:16s}{line}{total['recall']:>8.2f} {total['false_positives']:>4d}/{total['passages']}"
        )
    print("\nlaser robustness (aliased-loop, two-loop, multi-loop): recall / false positives / passages")
    for r in result["laser_variants_summary"]:
        print(
            f"  {r['variant']:18s} {r['detector']:24s} {r['recall']:.2f} "
            f"{r['false_positives']:4d} / {r['passages']}"
        )
    print("\nappearance detectors (chance = as many detections at random panoramas):")
    for r in result["appearance_summary"]:
        rows = [a for a in result["appearance"] if a["model"] == r["model"] and a["world"] == r["world"]]
        chance_recall = np.mean([a["chance"]["recall"] for a in rows])
        chance_fp = np.sum([a["chance"]["false_positives"] for a in rows])
        print(
            f"  {r['model']:8s} {r['world']:13s} recall {r['recall']:.2f} fp {r['false_positives']:4d} / "
            f"{r['passages']:4d}   chance: recall {chance_recall:.2f} fp {chance_fp:6.1f}"
        )
    if result["real_logs"]:
        print("\nreal logs (no decision-point ground truth): laser detections")
        for r in result["real_logs"]:
            print(
                f"  {r['log']:10s} {r['scans']:5d} scans, {r['odometry_m']:6.0f} m "
                f"({r['m_per_scan']:.2f} m/scan): {r['detections']:4d} detections, "
                f"{r['per_10m']:.2f} per 10 m"
            )


if __name__ == "__main__":
    main()
