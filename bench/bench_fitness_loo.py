"""Leave-one-run-out check of the laser fitness densities (issue #23: no knob scored on the data it was
fitted on).

``LaserConfig.fitness_*`` (:func:`ptm_ros.laser.fitness_log_bayes`) are Beta densities of a registration's
fitness (symmetric inlier fraction) for two visits of one place and of different places, fitted by maximum
likelihood on the Intel, ACES and MIT-CSAIL runs. This script

1. collects, per real run (laser-surprise visits at the default parameters), the fitness of every
   registered pair less than 1.5 m apart in the ground truth (one place) and of up to ``--diff-pairs``
   random pairs more than 4 m apart (different places), as the defaults were fitted;
2. fits both Betas on every two runs and on all three;
3. runs ``ptm-run`` on each held-out run with the densities fitted on the other two, and with the
   defaults, over ``--seeds``; scores the MAP against the ground truth.

Writes ``bench/fitness_loo.json`` and ``bench/fitness_loo.md``. About 15 minutes on one core.

    PYTHONPATH=. .venv/bin/python bench/bench_fitness_loo.py [--seeds 0 1 2] [--work out/fitness_loo]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import io
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from run_all import DATASETS, REAL_RUNS

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
SAME_M, DIFFERENT_M = 1.5, 4.0
QUIET = ("--no-map", "--no-report", "--quiet")


def pair_fitness(bag: Path, truth_file: Path, diff_pairs: int, seed: int) -> dict[str, list[float]]:
    """Fitness of the registrable one-place and different-place pairs of a run's visits, by ground-truth
    distance; ``flat_*`` repeats those whose optimum is flat (corridor matches)."""
    from ptm_ros.config import load_config
    from ptm_ros.geometry import interpolate_poses
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_carmen_gt
    from ptm_ros.laser import FLAT_OPTIMUM, RegistrationError, register_patches
    from ptm_ros.tools.pipeline import detect_visits

    config = load_config()
    run = read_run(bag, odom_topic="/odom", scan_topic="/scan", image_topic="/panorama", require=("/odom",))
    visits = detect_visits(run, config)
    truth = load_carmen_gt(truth_file)
    xy = interpolate_poses(truth.stamps, truth.poses_corrected, np.array([v.stamp for v in visits]))[:, :2]
    n = len(visits)
    i, j = np.triu_indices(n, 1)
    d = np.hypot(*(xy[i] - xy[j]).T)
    same = np.flatnonzero(d < SAME_M)
    far = np.flatnonzero(d > DIFFERENT_M)
    far = np.random.default_rng(seed).choice(far, min(diff_pairs, len(far)), replace=False)
    out: dict[str, list[float]] = {"same": [], "different": [], "flat_same": [], "flat_different": []}
    for kind, idx in (("same", same), ("different", far)):
        for k in idx:
            a, b = visits[i[k]].patch, visits[j[k]].patch
            if a is None or b is None:
                continue
            try:
                reg = register_patches(b, a, config=config.laser)
            except RegistrationError:
                continue
            out[kind].append(float(reg.inlier_fraction))
            if reg.reason.startswith(FLAT_OPTIMUM):
                out[f"flat_{kind}"].append(float(reg.inlier_fraction))
    return out


def fit_beta(values: Sequence[float]) -> tuple[float, float]:
    """Maximum-likelihood Beta(a, b) on [0, 1] (values clipped into the open interval)."""
    from scipy.stats import beta

    x = np.clip(np.asarray(values, dtype=float), 1e-4, 1.0 - 1e-4)
    a, b, _, _ = beta.fit(x, floc=0.0, fscale=1.0)
    return float(a), float(b)


def fitted(fitness: dict[str, dict[str, list[float]]], names: Sequence[str]) -> dict[str, float]:
    """The four Beta parameters fitted on the pairs of ``names`` (``LaserConfig`` field names)."""
    same = [f for r in names for f in fitness[r]["same"]]
    diff = [f for r in names for f in fitness[r]["different"]]
    sa, sb = fit_beta(same)
    da, db = fit_beta(diff)
    return {"fitness_same_a": sa, "fitness_same_b": sb, "fitness_different_a": da, "fitness_different_b": db}


def score(bag: Path, truth: Path, laser: dict[str, float] | None, seed: int, work: Path) -> dict[str, Any]:
    """``ptm-run`` at the defaults (and ``laser`` fitness parameters), scored: MAP F1, precision, recall."""
    import yaml

    from ptm_ros.tools import run as ptm_run

    params = work / f"params-{bag.name}-{seed}-{'loo' if laser else 'default'}.yaml"
    doc: dict[str, Any] = {"inference": {"seed": seed}}
    if laser:
        doc["laser"] = laser
    params.write_text(yaml.safe_dump(doc))
    out = params.with_suffix("")
    log = io.StringIO()
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        code = ptm_run.main(
            [str(bag), "--out", str(out), "--params", str(params), "--ground-truth", str(truth), *QUIET]
        )
    if code != 0:
        return {"error": log.getvalue()[-1000:]}
    from ptm_ros.ptm import load_ptm
    from ptm_ros.tools.pipeline import score_against

    s = score_against(load_ptm(out / "ptm.json"), truth).as_dict(per_topology=False)
    return {k: s[k] for k in ("map_f1", "map_precision", "map_recall")}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--diff-pairs", type=int, default=250, help="different-place pairs per run")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "fitness_loo")
    args = parser.parse_args(argv)
    from ptm_ros.tools.convert import convert

    t0 = time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)
    bags, fitness = {}, {}
    for name, log, gt in REAL_RUNS:
        bags[name] = args.work / f"{name}.bag"
        if not bags[name].exists():
            convert(DATASETS / log, bags[name])
        fitness[name] = pair_fitness(bags[name], DATASETS / gt, args.diff_pairs, seed=0)
        print(
            f"[fitness] {name}: " + ", ".join(f"{k} {len(v)}" for k, v in fitness[name].items()), flush=True
        )
    names = [r[0] for r in REAL_RUNS]
    fits = {"all three": fitted(fitness, names)}
    rows = []
    for held in names:
        train = [r for r in names if r != held]
        fits[f"without {held}"] = loo = fitted(fitness, train)
        gt = DATASETS / {r[0]: r[2] for r in REAL_RUNS}[held]
        for seed in args.seeds:
            for label, laser in (("defaults", None), ("leave-one-out", loo)):
                rec = {
                    "run": held,
                    "seed": seed,
                    "densities": label,
                    **score(bags[held], gt, laser, seed, args.work),
                }
                print(f"[fitness] {rec}", flush=True)
                rows.append(rec)
    doc = {
        "benchmark": "fitness_loo",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "wall_s": time.perf_counter() - t0,
        "pairs": {r: {k: len(v) for k, v in f.items()} for r, f in fitness.items()},
        "flat_fitness_mean": {
            r: {k: float(np.mean(v)) if v else None for k, v in f.items() if k.startswith("flat")}
            for r, f in fitness.items()
        },
        "fits": fits,
        "runs": rows,
    }
    (BENCH / "fitness_loo.json").write_text(json.dumps(doc, indent=1))
    write_markdown(doc, BENCH / "fitness_loo.md")
    return 0


def write_markdown(doc: dict[str, Any], path: Path) -> None:
    """The fits and the held-out scores as tables."""
    from ptm_ros.laser import LaserConfig

    d = LaserConfig()
    lines = [
        "# Laser fitness densities, leave one run out (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_fitness_loo.py` ({doc['wall_s'] / 60:.0f} min). "
        "Beta densities of the registration fitness for one place (< 1.5 m apart in the ground truth) and "
        "different places (> 4 m), maximum likelihood. Pairs per run: "
        + "; ".join(
            f"{r}: {p['same']} one-place, {p['different']} different" for r, p in doc["pairs"].items()
        )
        + ".",
        "",
        "| fitted on | one place Beta(a, b) | different places Beta(a, b) |",
        "|---|---|---|",
        f"| defaults (`LaserConfig`) | ({d.fitness_same_a}, {d.fitness_same_b}) | "
        f"({d.fitness_different_a}, {d.fitness_different_b}) |",
    ]
    for name, f in doc["fits"].items():
        lines.append(
            f"| {name} | ({f['fitness_same_a']:.2f}, {f['fitness_same_b']:.2f}) | "
            f"({f['fitness_different_a']:.2f}, {f['fitness_different_b']:.2f}) |"
        )
    lines += [
        "",
        "Mean fitness of the corridor matches (flat optimum), one place against different places: "
        + "; ".join(
            f"{r}: {_fmt(m['flat_same'])} / {_fmt(m['flat_different'])}"
            for r, m in doc["flat_fitness_mean"].items()
        )
        + ".",
        "",
        "Held-out scores (`ptm-run` defaults but the fitness densities; MAP F1 and precision per seed):",
        "",
        "| run | densities | "
        + " | ".join(f"seed {s}" for s in sorted({r["seed"] for r in doc["runs"]}))
        + " | mean F1 |",
        "|---|---|" + "---|" * (len({r["seed"] for r in doc["runs"]}) + 1),
    ]
    for run in dict.fromkeys(r["run"] for r in doc["runs"]):
        for label in ("defaults", "leave-one-out"):
            rs = [r for r in doc["runs"] if r["run"] == run and r["densities"] == label]
            cells = [
                f"{r['map_f1']:.3f} (P {r['map_precision']:.3f})" if "map_f1" in r else "error" for r in rs
            ]
            f1 = [r["map_f1"] for r in rs if "map_f1" in r]
            lines.append(f"| {run} | {label} | " + " | ".join(cells) + f" | {np.mean(f1):.3f} |")
    path.write_text("\n".join(lines) + "\n")


def _fmt(x: float | None) -> str:
    return "–" if x is None else f"{x:.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
