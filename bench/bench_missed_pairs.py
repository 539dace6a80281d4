"""Why the MAP topology misses same-place pairs on the real runs (issue #23: the causes, pair by pair).

For each real run in ``../shared/datasets`` (converted once under ``--work``), ``ptm-run`` at the default
parameters (laser-surprise visits, seed 0), scored as ``ptm-eval`` scores it: a pair of visits less than
``same_radius`` (1.5 m) apart in the ground truth is one place. Then, with no inference involved:

1. **the registrar on the true pairs**: every one-place pair's patches registered as the filter registers
   them (:func:`ptm_ros.perception.laser.register_patches`, visit j's patch onto visit i's from the
   identity): valid, or why not (the first words of :attr:`Registration.reason`), by the two passages'
   true heading difference (same direction < π/4, opposite > 3π/4, across in between);
2. **the MAP's misses**: the one-place pairs the MAP topology puts in two places, by how far apart the MAP
   puts those two places (its place positions): closer than the separation prior's ``penalty_radius``
   (one true place split in two neighbouring places) or farther; by the pair's own registration; and how
   many lie on a chain of one-place pairs spanning more than 4 m, which no topology scores all right
   (:func:`ptm_ros.scoring.evaluation.contradictory_pairs`).

Writes ``bench/missed_pairs.json`` and ``bench/missed_pairs.md`` (``--out``). About 3 minutes.

    PYTHONPATH=. .venv/bin/python bench/bench_missed_pairs.py [--work out/missed_pairs] [--out bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from run_all import prepare_runs, ptm_run_scored, when_and_where, write_bench

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
HEADINGS = ("same direction", "across", "opposite")


def heading_class(difference: float) -> str:
    """The passages' true heading difference (rad) as one of :data:`HEADINGS`."""
    d = abs(math.remainder(difference, 2.0 * math.pi))
    return HEADINGS[0] if d < math.pi / 4 else HEADINGS[2] if d > 3 * math.pi / 4 else HEADINGS[1]


def outcome(reg: Any) -> str:
    """``valid``, ``unregistrable`` (None: a patch too small), ``too few inliers`` or the reason's first
    words (:func:`ptm_ros.perception.laser._invalid_reason`'s wording)."""
    if reg is None:
        return "unregistrable"
    if reg.valid:
        return "valid"
    if " inliers < " in reg.reason:
        return "too few inliers"
    words = reg.reason.split(":")[0].split()
    return " ".join(words[:2]) if words[0] != "ambiguous" else "ambiguous"


def analyse(name: str, bag: Path, truth_file: Path, work: Path) -> dict[str, Any]:
    """Both parts of the module docstring for one run."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.geometry import interpolate_poses
    from ptm_ros.perception.laser import RegistrationError, register_patches
    from ptm_ros.scoring.evaluation import EvalConfig, contradictory_pairs, pair_truth
    from ptm_ros.tools.evaluate import true_positions_for
    from ptm_ros.tools.pipeline import detect_visits

    config = load_config()
    res = ptm_run_scored(bag, truth_file, work / name, "--no-report", "--no-map", "--quiet")
    if isinstance(res, str):
        msg = f"ptm-run failed on {bag}: {res}"
        raise RuntimeError(msg)
    ptm, s = res
    run = read_run(bag, odom_topic="/odom", scan_topic="/scan", image_topic="/panorama", require=("/odom",))
    visits = detect_visits(run, config)
    if [v.stamp for v in visits] != [lm.stamp for lm in ptm.landmarks]:
        msg = f"{name}: the visits detected here are not ptm-run's"
        raise RuntimeError(msg)
    truth = load_ground_truth(truth_file)
    xy = true_positions_for(ptm, truth)
    heading = interpolate_poses(truth.stamps, truth.poses_corrected, np.array([v.stamp for v in visits]))[
        :, 2
    ]
    ii, jj, same = pair_truth(xy, EvalConfig())
    chained = contradictory_pairs(xy, ii, jj, EvalConfig())
    top = ptm.topologies[0]
    labels = np.asarray(top.labels)
    places = np.asarray(top.positions, dtype=float)[:, :2]
    radius = config.model.odometry.penalty_radius
    registered: Counter[tuple[str, str]] = Counter()
    missed: Counter[tuple[str, str]] = Counter()
    spans: list[float] = []
    unavoidable = 0
    for i, j, chain in zip(ii[same], jj[same], chained[same], strict=True):
        a, b = visits[i].patch, visits[j].patch
        try:
            reg = None if a is None or b is None else register_patches(b, a, config=config.laser)
        except RegistrationError:
            reg = None
        how = outcome(reg)
        registered[(heading_class(float(heading[j] - heading[i])), how)] += 1
        if labels[i] != labels[j]:
            gap = float(np.hypot(*(places[labels[i]] - places[labels[j]])))
            spans.append(gap)
            unavoidable += int(chain)
            missed[("split" if gap < radius else "apart", how)] += 1
    return {
        "run": name,
        "visits": len(visits),
        "map_f1": s["map_f1"],
        "map_precision": s["map_precision"],
        "map_recall": s["map_recall"],
        "map_probability": top.probability,
        "penalty_radius_m": radius,
        "same_pairs": int(np.sum(same)),
        "registered": [[h, o, c] for (h, o), c in sorted(registered.items())],
        "missed": [[k, o, c] for (k, o), c in sorted(missed.items())],
        "missed_on_contradictory_chains": unavoidable,
        "missed_place_gaps_m": sorted(spans),
    }


def write_md(doc: dict[str, Any], path: Path) -> None:
    """The markdown of :func:`main`'s record."""
    lines = [
        "# Why the MAP misses same-place pairs on the real runs (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_missed_pairs.py` ({doc['minutes']:.0f} min). "
        "`ptm-run` at the default parameters (seed 0), scored as `ptm-eval` scores it: visits less than "
        "1.5 m apart in the ground truth are one place. *Registrar*: every such pair's patches registered "
        "as the filter registers them, by the passages' true heading difference; *misses*: the pairs the MAP "
        "puts in two places, by how far apart it puts those places (closer than the separation prior's "
        "`penalty_radius`: one true place split in two neighbouring places); *unavoidable*: missed pairs "
        "on a chain of one-place pairs spanning more than 4 m, which no topology scores all right.",
        "",
        "| run | visits | MAP F1 (P, R) | one-place pairs | registered valid: same direction / across / "
        "opposite | missed | unavoidable | split (< D) | missed and registered valid "
        "| gaps between the MAP places (m) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        valid = []
        for h in HEADINGS:
            n = sum(c for hh, _, c in r["registered"] if hh == h)
            v = sum(c for hh, o, c in r["registered"] if hh == h and o == "valid")
            valid.append(f"{v}/{n}")
        n_missed = sum(c for _, _, c in r["missed"])
        split = sum(c for k, _, c in r["missed"] if k == "split")
        valid_missed = sum(c for _, o, c in r["missed"] if o == "valid")
        gaps = r["missed_place_gaps_m"]
        gap = f"{gaps[0]:.1f}–{gaps[-1]:.1f}" if gaps else "–"
        lines.append(
            f"| {r['run']} | {r['visits']} | {r['map_f1']:.3f} "
            f"({r['map_precision']:.3f}, {r['map_recall']:.3f}) | {r['same_pairs']} | {' / '.join(valid)} "
            f"| {n_missed} | {r['missed_on_contradictory_chains']} | {split} | {valid_missed} | {gap} |"
        )
    lines += ["", "Why the registrar fails on one-place pairs (all headings):", ""]
    lines += ["| run | " + " | ".join(doc["reasons"]) + " |", "|---|" + "---|" * len(doc["reasons"])]
    for r in doc["runs"]:
        counts = Counter()
        for _, o, c in r["registered"]:
            counts[o] += c
        lines.append(f"| {r['run']} | " + " | ".join(str(counts[k]) for k in doc["reasons"]) + " |")
    lines += ["", "## Commands", "", "    PYTHONPATH=. .venv/bin/python bench/bench_missed_pairs.py", ""]
    path.write_text("\n".join(lines))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "out" / "missed_pairs")
    parser.add_argument("--out", type=Path, default=BENCH, help="where missed_pairs.{json,md} are written")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)
    runs = [
        analyse(name, bag, gt, args.work)
        for name, kind, bag, gt in prepare_runs(args.work, None)
        if kind == "real"
    ]
    reasons = sorted({o for r in runs for _, o, _ in r["registered"]}, key=lambda o: (o != "valid", o))
    doc = {
        **when_and_where(t0),
        "reasons": reasons,
        "runs": runs,
    }
    write_bench(doc, args.out / "missed_pairs.json", write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
