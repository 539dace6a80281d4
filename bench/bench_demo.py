"""Is ``make demo``'s run a lucky pick? The demo world over many seeds of the sensor noise (issue #25).

``bags/demo`` is ``ptm-sim bags/demo --world twin-junctions --seed 0``. For each seed the same world is
simulated (``ptm-sim``'s configuration), run through ``ptm-run``'s pipeline at the defaults plus
``config/demo.yaml`` (no map, no report), and the filter's timeline (``ptm.json``'s
``inference.timeline``) is scored against the truth of the visits so far
(:func:`ptm_ros.scoring.evaluation.timeline_masses`), beside the greedy baseline's answer (``ptm.json``'s
``greedy``). The mass is *split* at a visit when the truth holds between 0.1 and 0.9 of it; a seed
*behaves like the demo* when the mass is split at two consecutive visits or more, the truth holds more
than 0.9 at the end and the greedy answer is wrong.

Writes ``bench/demo_seeds.json`` and ``bench/demo_seeds.md``. About 15 s per seed on one core.

    PYTHONPATH=. .venv/bin/python bench/bench_demo.py [--seeds 20] [--work out/demo_seeds]
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

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
WORLD = "twin-junctions"
PARAMS = REPO / "config" / "demo.yaml"
HIGH = 0.9  # the truth's mass above HIGH at the end
SPLIT = (0.1, 0.9)  # a visit where the truth holds a share in this range: the mass is split


def seed_row(seed: int, work: Path) -> dict[str, Any]:
    """One seed: simulate, run the pipeline, score the timeline and the greedy answer."""
    from ptm_ros.io.simulator import SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world
    from ptm_ros.model.ptm import ptm_greedy, ptm_timeline
    from ptm_ros.scoring.evaluation import first_wrong_visit, timeline_masses
    from ptm_ros.tools.bringup import load_parameters
    from ptm_ros.tools.pipeline import run_offline

    bag = work / f"seed{seed}"
    if bag.exists():
        shutil.rmtree(bag)
    write_run(simulate(get_world(WORLD), SimConfig(), np.random.default_rng(seed)), bag)
    t0 = time.perf_counter()
    result = run_offline(
        bag, work / f"out{seed}", load_parameters(PARAMS)[0], write_report=False, write_map=False
    )
    wall = time.perf_counter() - t0
    truth = result.score.true_labels if result.score is not None else None
    row: dict[str, Any] = {"seed": seed, "visits": len(result.ptm.landmarks), "wall_s": wall}
    if truth is None:
        return {**row, "truth": None}
    masses = [0.0 if m is None else m for m in timeline_masses(ptm_timeline(result.ptm), truth)]
    greedy = ptm_greedy(result.ptm)
    split = [k for k, m in enumerate(masses) if SPLIT[0] <= m <= SPLIT[1]]
    row.update(
        truth=list(truth),
        truth_mass=masses,
        min_truth_mass=min(masses),
        end_truth_mass=masses[-1],
        split_visits=split,
        greedy=None if greedy is None else list(greedy),
        greedy_wrong_at=None if greedy is None else first_wrong_visit(greedy, truth),
    )
    row["like_the_demo"] = bool(
        len(split) >= 2
        and split == list(range(split[0], split[-1] + 1))
        and row["end_truth_mass"] > HIGH
        and row["greedy_wrong_at"] is not None
    )
    return row


def write_md(rows: Sequence[dict[str, Any]], path: Path) -> None:
    like = sum(bool(r.get("like_the_demo")) for r in rows)
    lines = [
        f"# `make demo`'s world over {len(rows)} seeds ({WORLD}, defaults + config/demo.yaml)",
        "",
        f"Like the demo (the mass split, the truth holding {SPLIT[0]}–{SPLIT[1]}, at two consecutive visits "
        f"or more; the truth above {HIGH} at the end; the greedy answer wrong): **{like} of {len(rows)}** "
        "seeds.",
        "",
        "| seed | visits | truth's mass per visit | min | end | split at visits | greedy wrong from | s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r.get("truth") is None:
            lines.append(f"| {r['seed']} | {r['visits']} | no exact truth | | | | | {r['wall_s']:.1f} |")
            continue
        masses = " ".join(f"{m:.2f}" for m in r["truth_mass"])
        wrong = "right" if r["greedy_wrong_at"] is None else f"visit {r['greedy_wrong_at']}"
        split = ", ".join(map(str, r["split_visits"])) or "none"
        low, end = r["min_truth_mass"], r["end_truth_mass"]
        lines.append(
            f"| {r['seed']} | {r['visits']} | {masses} | {low:.3f} | {end:.3f} | {split} | {wrong} "
            f"| {r['wall_s']:.1f} |"
        )
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=20, help="seeds 0..N-1 (default: %(default)s)")
    p.add_argument("--work", type=Path, default=REPO / "out" / "demo_seeds", help="bags and outputs")
    args = p.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in range(args.seeds):
        rows.append(seed_row(seed, args.work))
        r = rows[-1]
        print(
            f"[demo] seed {seed}: like the demo {r.get('like_the_demo')}, truth "
            f"{' '.join(f'{m:.2f}' for m in r.get('truth_mass') or [])}, greedy wrong from "
            f"{r.get('greedy_wrong_at')}",
            flush=True,
        )
    doc = {"generated": time.strftime("%Y-%m-%d %H:%M:%S"), "world": WORLD, "rows": rows}
    (BENCH / "demo_seeds.json").write_text(json.dumps(doc, indent=1) + "\n")
    write_md(rows, BENCH / "demo_seeds.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
