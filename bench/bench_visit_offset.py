"""Where the detector puts a visit along the robot's path, and what the posterior gains from learning it
(issue #23: the room-row splits of ``bench/calibration_4x_model.md``).

The model scatters a place's visits isotropically about it (σ_T, eq. 17). The laser-surprise detector
fires where the view changes, a distance ``δ`` before the place in the direction of travel, whichever
way the robot passes: a visit of place ``p`` at heading ``θ`` lies at ``p - δ h(θ)``,
``h(θ) = (cos θ, sin θ)``. Two visits of one place at headings ``θ_i`` and ``θ_j = θ_i + Δ`` then lie,
in the frame of visit ``i``, at

.. math::
    z_{xy} = \\delta\\,(1 - \\cos\\Delta,\\ -\\sin\\Delta),

``2δ`` apart when passed in opposite directions, ``δ√2`` at a right angle, together when passed the same
way. A valid registration of the two measures ``z`` (its translation; ``Δ`` its heading), so each
registration with ``|a| = |(1 - cos Δ, -sin Δ)| > 0.5`` gives ``δ_k = aᵀz / aᵀa``; the estimate is their
median (aliases among them are outliers). No ground truth.

For each run: the visits (``ptm-run``'s detection at the default parameters), the filter session over
them at the defaults, ``δ`` estimated from its registrations, and the session again over the visits
moved ``δ`` along their heading (pose ``⊕ (δ, 0, 0)``, the patch re-expressed in the moved frame): the
MAP against the truth both ways. ``δ`` measured with the ground truth (visit pairs of one true place,
the displacement along the first one's heading against ``a``; simulated worlds only) is reported beside.

Simulated worlds: room-row and twin-rooms (doors passed both ways) and the aliased ring (passed one
way), at the simulator's noise and at four times the model's (``bench_calibration``'s ``4x-model``),
seeds 0–3. Real runs (Intel, ACES, MIT CSAIL), when ``out/bench/real`` holds their bags, at inference
seeds 0–2 (the filter's resampling; the visits and ``δ`` hardly depend on it).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=bench:. .venv/bin/python bench/bench_visit_offset.py [--seeds 4]
        [--real-seeds 3] [--no-real]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from bench_calibration import noise_level

from ptm_ros.model.geometry import RelativePose, between, compose
from ptm_ros.model.visits import Visit

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
SHARED = REPO.parent / "shared" / "datasets"
WORLDS = ("room-row", "twin-rooms", "aliased-ring")
LEVELS = ("sim", "4x-model")
REAL = {
    "intel": "intel/intel-gt-910.txt",
    "aces": "aces/aces-gt-440.txt",
    "mit-csail": "mit-csail/mit-csail-gt-406.txt",
}
#: Registrations whose heading change gives ``|a|`` below this say little about ``δ``.
MIN_LEVER = 0.5
#: Registrations farther apart than this [m] are not two visits of one place.
MAX_SPAN = 3.0


def lever(turn: float) -> np.ndarray:
    """``a = (1 - cos Δ, -sin Δ)``: a second visit's displacement per metre of ``δ`` (module docstring)."""
    return np.array([1.0 - np.cos(turn), -np.sin(turn)])


def offset_samples(pairs: Sequence[tuple[float, np.ndarray]]) -> list[float]:
    """``δ_k = aᵀz / aᵀa`` of every ``(Δ, z_xy)`` with ``|a| > MIN_LEVER`` and ``|z| < MAX_SPAN``."""
    out = []
    for turn, z in pairs:
        a = lever(turn)
        if np.hypot(*a) > MIN_LEVER and np.hypot(*z) < MAX_SPAN:
            out.append(float(a @ z / (a @ a)))
    return out


def learned_offset(registrations: Sequence[object]) -> tuple[float, int]:
    """``δ`` from a session's registrations (median of :func:`offset_samples`; 0 without one) and how many."""
    valid = [z for z in registrations if isinstance(z, RelativePose)]
    samples = offset_samples([(float(z.mean[2]), np.asarray(z.mean[:2], dtype=float)) for z in valid])
    return (float(np.median(samples)) if samples else 0.0), len(samples)


def true_offset(true_poses: np.ndarray, places: Sequence[object]) -> tuple[float, int]:
    """``δ`` from the truth: visit pairs of one true place, the displacement of the second in the true frame
    of the first against ``a`` of their true heading change (:func:`offset_samples`)."""
    pairs = []
    for i in range(len(places)):
        for j in range(i + 1, len(places)):
            if places[i] is None or places[i] != places[j]:
                continue
            z = between(true_poses[i], true_poses[j])
            pairs.append((float(z[2]), z[:2]))
    samples = offset_samples(pairs)
    return (float(np.median(samples)) if samples else float("nan")), len(samples)


def moved(visit: Visit, delta: float) -> Visit:
    """``visit`` placed ``delta`` further along its heading, its patch re-expressed in the moved frame."""
    step = np.array([delta, 0.0, 0.0])

    def along(pose: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        return None if pose is None else tuple(float(v) for v in compose(np.asarray(pose), step))

    patch = None if visit.patch is None else visit.patch - np.array([delta, 0.0])
    return dataclasses.replace(visit, pose=along(visit.pose), odom_pose=along(visit.odom_pose), patch=patch)


def filtered(visits: Sequence[Visit], seed: int = 0) -> Any:
    """A filter session at the default parameters (inference ``seed``) over ``visits``."""
    from ptm_ros.config import load_config
    from ptm_ros.session import FilterSession, filter_visits

    session = FilterSession(load_config(overrides={"inference": {"seed": seed}}), fitted_to=list(visits))
    return filter_visits(session, list(visits))


def detected(bag: Path) -> list[Visit]:
    """``ptm-run``'s visits of a bag at the default parameters."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.tools.pipeline import detect_visits, run_extractor

    cfg = load_config()
    t = cfg.topics
    run = read_run(
        bag,
        odom_topic=t.odom,
        scan_topic=t.scan,
        image_topic=t.panorama,
        require=(t.odom,),
        appearance=cfg.model.appearance,
    )
    return detect_visits(run, cfg, {}, extractor=run_extractor(run, cfg, None))


def figures(session: Any, truth: Any) -> dict[str, Any]:
    """The MAP against the truth: ``calibration_record``'s MAP probability, whether it is right and the
    true topology's mass (simulated), ``ptm-eval``'s MAP F1 and precision (every run)."""
    from ptm_ros.tools.evaluate import calibration_record, score_against_ground_truth

    ptm = session.to_ptm()
    rec = calibration_record(ptm, truth)
    score = score_against_ground_truth(ptm, truth).as_dict(per_topology=False)
    keys = ("map_probability", "map_right", "true_topology_mass")
    return {**{k: rec[k] for k in keys}, "map_f1": score["map_f1"], "map_precision": score["map_precision"]}


def one_run(
    name: str, bag: Path, truth_file: Path, seed: int = 0, visits: list[Visit] | None = None
) -> dict[str, Any]:
    """Both passes over one bag's visits (module docstring; ``visits``: detected already), inference
    ``seed``."""
    from ptm_ros.io.groundtruth import interpolate_pose, load_ground_truth
    from ptm_ros.scoring.evaluation import EvalConfig
    from ptm_ros.tools.evaluate import true_place_ids

    truth = load_ground_truth(truth_file)
    visits = detected(bag) if visits is None else visits
    first = filtered(visits, seed)
    delta, used = learned_offset(list(first.pairs.values()))
    second = filtered([moved(v, delta) for v in visits], seed) if delta else first
    _, places = true_place_ids(first.to_ptm(), truth, config=EvalConfig())
    true_poses = interpolate_pose(truth, np.array([v.stamp for v in visits]))
    true_delta, true_pairs = true_offset(true_poses, [] if places is None else places.tolist())
    return {
        "run": name,
        "visits": len(visits),
        "learned_offset_m": delta,
        "registrations_used": used,
        "true_offset_m": true_delta,
        "true_pairs": true_pairs,
        "as_detected": figures(first, truth),
        "moved": figures(second, truth),
    }


def simulated(world: str, level: str, seed: int, work: Path) -> Path:
    """A bag of ``world`` at noise ``level`` and ``seed`` (made once under ``work``)."""
    from ptm_ros.io.simulator import SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world

    bag = work / f"{world}__{level}__s{seed}"
    if not bag.exists():
        config = SimConfig(odometry=noise_level(level))
        write_run(simulate(get_world(world), config, np.random.default_rng(seed)), bag)
    return bag


def fmt(x: Any, spec: str = ".3f") -> str:
    return "–" if x is None or (isinstance(x, float) and np.isnan(x)) else format(x, spec)


def write(rows: list[dict[str, Any]], wall: float) -> None:
    (BENCH / "visit_offset.json").write_text(
        json.dumps({"generated": time.strftime("%Y-%m-%d %H:%M:%S"), "rows": rows}, indent=1) + "\n"
    )
    lines = [
        "# Where the detector puts a visit, learned from the run (issue #23)",
        "",
        f"Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by `bench/bench_visit_offset.py` "
        f"({wall / 60:.0f} min); the method and the estimate in its docstring. *Learned δ*: from the "
        "first pass's registrations (how many); *true δ*: from the ground truth (visit pairs of one "
        "simulated place). Both passes: the filter session at the default parameters; *moved*: over the "
        "visits placed the learned δ further along their heading. MAP right / p / true mass: simulated "
        "runs (`ptm-eval --calibration`'s record); MAP F1 (precision): `ptm-eval`'s.",
        "",
        "| run | visits | learned δ (m) | true δ (m) | as detected: MAP right, p, true mass | F1 (P) | "
        "moved: MAP right, p, true mass | F1 (P) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a, b = r["as_detected"], r["moved"]
        lines.append(
            f"| {r['run']} | {r['visits']} | {r['learned_offset_m']:+.2f} ({r['registrations_used']}) | "
            f"{fmt(r['true_offset_m'], '+.2f')} ({r['true_pairs']}) | "
            f"{a['map_right']}, {a['map_probability']:.3f}, {fmt(a['true_topology_mass'])} | "
            f"{a['map_f1']:.3f} ({a['map_precision']:.3f}) | "
            f"{b['map_right']}, {b['map_probability']:.3f}, {fmt(b['true_topology_mass'])} | "
            f"{b['map_f1']:.3f} ({b['map_precision']:.3f}) |"
        )
    lines += [
        "",
        "## Command",
        "",
        "    OPENBLAS_NUM_THREADS=1 PYTHONPATH=bench:. .venv/bin/python bench/bench_visit_offset.py",
        "",
    ]
    (BENCH / "visit_offset.md").write_text("\n".join(lines))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="simulator seeds per world and level")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "visit_offset")
    parser.add_argument("--no-real", action="store_true", help="simulated worlds only")
    parser.add_argument("--real-seeds", type=int, default=3, help="inference seeds per real run")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = []
    for level in LEVELS:
        for world in WORLDS:
            for seed in range(args.seeds):
                bag = simulated(world, level, seed, args.work)
                rows.append(one_run(f"{world} {level} s{seed}", bag, bag / "ground_truth.json"))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    real = REPO / "out" / "bench" / "real"
    for name, gt in ({} if args.no_real else REAL).items():
        if (real / name).exists() and (SHARED / gt).exists():
            visits = detected(real / name)
            for seed in range(args.real_seeds):
                rows.append(one_run(f"{name} seed {seed}", real / name, SHARED / gt, seed, visits))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    write(rows, time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
