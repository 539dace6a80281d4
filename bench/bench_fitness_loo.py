"""Leave-one-run-out check of the constants fitted on the real runs: laser fitness densities and ε.

Issue #23: no knob scored on the data it was fitted on.

``LaserConfig.fitness_*`` (:func:`ptm_ros.perception.laser.fitness_log_bayes`) are Beta densities of a
registration's fitness (symmetric inlier fraction) for two visits of one place and of different places, fitted
by maximum likelihood on the Intel, ACES and MIT-CSAIL runs. ``OdometryConfig.registration_outlier`` (ε) is
the fraction of the valid registrations of one-place pairs that are off the true relative pose by more than
``ALIAS_XY`` m or ``ALIAS_YAW`` rad (aliases), pooled over those runs and the simulated worlds
(``run_all.SIM_WORLDS``, a fixed share not fitted on the real runs). This script

1. collects, per real run (laser-surprise visits at the default parameters), the fitness of every
   registered pair less than 1.5 m apart in the ground truth (one place) and of up to ``--diff-pairs``
   random pairs more than 4 m apart (different places), as the defaults were fitted, and counts the valid
   one-place registrations and their aliases; the same counts on the simulated worlds;
2. fits both Betas and ε on every two runs and on all three;
3. runs ``ptm-run`` on each held-out run at the defaults, with the densities fitted on the other two, and
   with those densities and ε, over ``--seeds``; scores the MAP against the ground truth.

Writes ``bench/fitness_loo.json`` and ``bench/fitness_loo.md`` (``--out``). About 20 minutes on one core.

    PYTHONPATH=. .venv/bin/python bench/bench_fitness_loo.py [--seeds 0 1 2] [--diff-pairs 250] \\
        [--work out/fitness_loo] [--out bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from run_all import LOO_HEADERS, SIMULATED, outlier_table, prepare_runs, ptm_run_scored

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
SAME_M, DIFFERENT_M = 1.5, 4.0
ALIAS_XY, ALIAS_YAW = 0.5, 0.3  # a valid registration this far off the true relative pose is an alias
LOO, LOO_EPS = "leave-one-out", "leave-one-out (densities + ε)"
QUIET = ("--no-map", "--no-report", "--quiet")


def is_alias(measured: ArrayLike, true: ArrayLike) -> bool:
    """Whether a registration ``(x, y, yaw)`` is off the true relative pose by more than ``ALIAS_XY`` m or
    ``ALIAS_YAW`` rad."""
    from ptm_ros.model.geometry import wrap_angle

    e = np.asarray(measured, dtype=float) - np.asarray(true, dtype=float)
    return bool(np.hypot(e[0], e[1]) > ALIAS_XY or abs(float(wrap_angle(e[2]))) > ALIAS_YAW)


def collect_pairs(
    bag: Path, truth_file: Path, diff_pairs: int, seed: int
) -> tuple[dict[str, list[float]], dict[str, int]]:
    """Fitness of the registrable one-place and different-place pairs of a run's visits, by ground-truth
    distance (``flat_*`` repeats those whose optimum is flat: corridor matches), and the count of the valid
    one-place registrations and of their aliases (:func:`is_alias`)."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.geometry import between, interpolate_poses
    from ptm_ros.perception.laser import FLAT_OPTIMUM, RegistrationError, register_patches
    from ptm_ros.tools.pipeline import detect_visits

    config = load_config()
    run = read_run(bag, odom_topic="/odom", scan_topic="/scan", image_topic="/panorama", require=("/odom",))
    visits = detect_visits(run, config)
    truth = load_ground_truth(truth_file)
    poses = interpolate_poses(truth.stamps, truth.poses_corrected, np.array([v.stamp for v in visits]))
    n = len(visits)
    i, j = np.triu_indices(n, 1)
    d = np.hypot(*(poses[i, :2] - poses[j, :2]).T)
    same = np.flatnonzero(d < SAME_M)
    far = np.flatnonzero(d > DIFFERENT_M)
    far = np.random.default_rng(seed).choice(far, min(diff_pairs, len(far)), replace=False)
    out: dict[str, list[float]] = {"same": [], "different": [], "flat_same": [], "flat_different": []}
    counts = {"valid": 0, "aliases": 0}
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
            if kind == "same" and reg.valid:
                counts["valid"] += 1
                counts["aliases"] += is_alias(reg.mean, between(poses[i[k]], poses[j[k]]))
    return out, counts


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


def pooled_outlier(counts: Mapping[str, Mapping[str, int]], names: Sequence[str]) -> dict[str, float]:
    """ε fitted on the runs ``names`` (and the simulated worlds' counts when ``counts`` has them): their
    aliases over their valid one-place registrations, with both sums."""
    keys = [*names, SIMULATED] if SIMULATED in counts else list(names)
    aliases = sum(counts[k]["aliases"] for k in keys)
    valid = sum(counts[k]["valid"] for k in keys)
    if not valid:
        msg = f"no valid one-place registration in {', '.join(keys)}"
        raise ValueError(msg)
    return {"registration_outlier": aliases / valid, "aliases": aliases, "valid": valid}


def score(
    bag: Path, truth: Path, params: Mapping[str, Any], *, tag: str, seed: int, work: Path
) -> dict[str, Any]:
    """``ptm-run`` at the defaults but ``params`` (a parameter file's sections), scored: MAP F1, precision,
    recall; ``tag`` names its files under ``work``."""
    import yaml

    path = work / f"params-{bag.name}-{seed}-{tag}.yaml"
    path.write_text(yaml.safe_dump({"inference": {"seed": seed}, **params}))
    res = ptm_run_scored(bag, truth, path.with_suffix(""), "--params", str(path), *QUIET)
    if isinstance(res, str):
        return {"error": res}
    _, s = res
    return {k: s[k] for k in ("map_f1", "map_precision", "map_recall")}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--diff-pairs", type=int, default=250, help="different-place pairs per run")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "fitness_loo")
    parser.add_argument("--out", type=Path, default=BENCH, help="where fitness_loo.{json,md} are written")
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)
    runs = prepare_runs(args.work, None)
    bags = {name: (bag, gt) for name, kind, bag, gt in runs if kind == "real"}
    fitness, counts = {}, {SIMULATED: {"valid": 0, "aliases": 0}}
    for name, kind, bag, gt in runs:
        pairs, found = collect_pairs(bag, gt, args.diff_pairs if kind == "real" else 0, seed=0)
        if kind == "real":
            fitness[name], counts[name] = pairs, found
        else:
            counts[SIMULATED] = {k: counts[SIMULATED][k] + v for k, v in found.items()}
        report = ", ".join(f"{k} {len(v)}" for k, v in pairs.items())
        print(f"[fitness] {name}: {report}; one-place registrations {found}", flush=True)
    names = list(bags)
    fits = {"all three": fitted(fitness, names)}
    outlier_fits = {"all three": pooled_outlier(counts, names)}
    rows = []
    for held in names:
        train = [r for r in names if r != held]
        fits[f"without {held}"] = loo = fitted(fitness, train)
        outlier_fits[f"without {held}"] = eps = pooled_outlier(counts, train)
        odometry = {"registration_outlier": eps["registration_outlier"]}
        variants = (
            ("defaults", "default", {}),
            (LOO, "loo", {"laser": loo}),
            (LOO_EPS, "loo-eps", {"laser": loo, "model": {"odometry": odometry}}),
        )
        for seed in args.seeds:
            for label, tag, params in variants:
                rec = {
                    "run": held,
                    "seed": seed,
                    "densities": label,
                    **score(*bags[held], params, tag=tag, seed=seed, work=args.work),
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
        "alias": {"max_xy_m": ALIAS_XY, "max_yaw_rad": ALIAS_YAW},
        "simulated_worlds": [name for name, kind, _, _ in runs if kind == "simulated"],
        "outlier_counts": counts,
        "outlier_fits": outlier_fits,
        "runs": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fitness_loo.json").write_text(json.dumps(doc, indent=1))
    write_markdown(doc, args.out / "fitness_loo.md")
    return 0


def write_markdown(doc: dict[str, Any], path: Path) -> None:
    """The fits and the held-out scores as tables."""
    from ptm_ros.perception.laser import LaserConfig

    d = LaserConfig()
    lines = [
        "# Constants fitted on the real runs, leave one run out (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_fitness_loo.py` ({doc['wall_s'] / 60:.0f} min).",
        "",
        "## Laser fitness densities",
        "",
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
        *outlier_lines(doc),
        "",
        "## Held-out scores",
        "",
        "`ptm-run` at the defaults but the fitness densities (and ε) fitted without the run; MAP F1 and "
        "precision per seed:",
        "",
        "| run | parameters | "
        + " | ".join(f"seed {s}" for s in sorted({r["seed"] for r in doc["runs"]}))
        + " | mean F1 |",
        "|---|---|" + "---|" * (len({r["seed"] for r in doc["runs"]}) + 1),
    ]
    for run in dict.fromkeys(r["run"] for r in doc["runs"]):
        for label in dict.fromkeys(r["densities"] for r in doc["runs"]):
            rs = [r for r in doc["runs"] if r["run"] == run and r["densities"] == label]
            cells = [
                f"{r['map_f1']:.3f} (P {r['map_precision']:.3f})" if "map_f1" in r else "error" for r in rs
            ]
            f1 = [r["map_f1"] for r in rs if "map_f1" in r]
            lines.append(
                f"| {run} | {LOO_HEADERS.get(label, label)} | "
                + " | ".join(cells)
                + f" | {np.mean(f1):.3f} |"
            )
    path.write_text("\n".join(lines) + "\n")


def outlier_lines(doc: Mapping[str, Any]) -> list[str]:
    """The ε section: the alias counts per run and ε per fitting set."""
    alias, counts = doc["alias"], doc["outlier_counts"]
    sim = counts[SIMULATED]
    return [
        "",
        "## Registration outlier probability ε",
        "",
        "Valid registrations of one-place pairs (the laser-surprise visits above) and their aliases, off "
        f"the true relative pose by > {alias['max_xy_m']} m or > {alias['max_yaw_rad']} rad: "
        + "; ".join(f"{r}: {c['aliases']}/{c['valid']}" for r, c in counts.items() if r != SIMULATED)
        + f"; simulated worlds ({', '.join(doc['simulated_worlds'])}, a fixed share of every fit): "
        f"{sim['aliases']}/{sim['valid']}.",
        "",
        *outlier_table(doc),
    ]


def _fmt(x: float | None) -> str:
    return "–" if x is None else f"{x:.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
