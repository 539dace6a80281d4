"""The odometry check on the real runs made unlike themselves, and what the learned scale does when used
(issue #23).

``ptm-run`` reports the translation-noise scale its laser registrations suggest
(``inference.translation_noise``, :mod:`ptm_ros.model.translation_noise`). This benchmark runs it at the
default parameters on every log of ``bench_perturbed_runs`` (each shared CARMEN run as logged, with every
2nd or 3rd scan, with drifting wheels; inference seed 0) and records the scale beside the MAP's score and
the pair calibration. Then, where the scale is not 1, it runs the log again with the scale put into the
model (``a_xy`` and ``b_xy`` multiplied by it): is the posterior better with the run's own noise?

Writes ``bench/translation_noise.json`` and ``bench/translation_noise.md`` (``--out``). About 20 minutes.

    PYTHONPATH=. .venv/bin/python bench/bench_translation_noise.py [--work out/perturbed] [--out bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench_perturbed_runs import perturbed_logs, score
from run_all import shared_data_ready, when_and_where, write_bench

from ptm_ros.model.odometry import OdometryConfig

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent


def scored(bag: Path, truth: Path, out: Path, *options: str) -> dict[str, Any]:
    """``ptm-run`` at seed 0 with ``options`` (:func:`bench_perturbed_runs.score`): the MAP's score, the
    pair calibration's summary and the odometry check."""
    res = score(bag, truth, out, 0, *options)
    if "error" in res:
        return res
    pairs = res["pair_calibration"]
    return {
        **{k: res[k] for k in ("map_f1", "map_precision", "map_recall")},
        **{
            k: pairs[k]
            for k in ("doubtful_pairs", "doubtful_gap", "confident_false_merges", "confident_misses")
        },
        **{k: res[k] for k in ("translation_noise", "heading_scale")},
    }


def used_params(scale: float, path: Path) -> Path:
    """A parameter file with the translation noise multiplied by ``scale``."""
    cfg = OdometryConfig()
    path.write_text(f"model:\n  odometry:\n    a_xy: {cfg.a_xy * scale!r}\n    b_xy: {cfg.b_xy * scale!r}\n")
    return path


def write_md(doc: dict[str, Any], path: Path) -> None:
    def score(r: dict[str, Any]) -> str:
        if "error" in r:
            return "failed"
        gap = "–" if r["doubtful_gap"] is None else f"{r['doubtful_gap']:.2f}"  # no doubtful pair
        return (
            f"{r['map_f1']:.3f} ({r['map_precision']:.2f}) | {r['confident_false_merges']} / "
            f"{r['confident_misses']} | {r['doubtful_pairs']}, {gap}"
        )

    lines = [
        "# The odometry check: the translation noise the registrations suggest (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_translation_noise.py` ({doc['minutes']:.0f} min). "
        "Every log of `bench/perturbed_runs.md`, `ptm-run` at the default parameters (seed 0): the "
        "translation-noise scale its valid registrations suggest (`inference.translation_noise`: 1 as "
        "modelled, 2 or more: the odometry is worse than its model and the summary warns), from how many "
        "registrations, the learned heading scale; the MAP F1 (precision), the pair calibration's confident "
        "false merges / confident misses and its doubtful pairs with their gap (`ptm-eval`'s "
        "`pair_calibration`). *Used*: the same run with `a_xy` and `b_xy` multiplied by the scale (where it "
        "is not 1).",
        "",
        "| run | log | scale | registrations | heading scale | MAP F1 (P) | false merges / misses "
        "| doubtful, gap | used: MAP F1 (P) | false merges / misses | doubtful, gap |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    nan = float("nan")
    for r in doc["rows"]:
        d = r["default"]
        noise = d.get("translation_noise") or {}
        used = r.get("used")
        cells = [
            r["run"],
            r["log"],
            f"{noise.get('scale', nan):.3g}",
            str(noise.get("registrations", 0)),
            f"{d.get('heading_scale') or nan:.3g}",
            score(d),
            score(used) if used else "– | – | –",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## Commands", "", "    PYTHONPATH=. .venv/bin/python bench/bench_translation_noise.py", ""]
    path.write_text("\n".join(lines))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "out" / "perturbed")
    parser.add_argument(
        "--out", type=Path, default=BENCH, help="where translation_noise.{json,md} are written"
    )
    args = parser.parse_args(argv)
    if not shared_data_ready("translation-noise", args.work, args.out):
        return 0
    t0 = time.perf_counter()
    rows = []
    for name, label, bag, truth in perturbed_logs(args.work):
        tag = f"{name}-{label.replace(' ', '-')}"
        row: dict[str, Any] = {"run": name, "log": label}
        row["default"] = scored(bag, truth, args.work / f"{tag}-noise")
        scale = (row["default"].get("translation_noise") or {}).get("scale", 1.0)
        if scale != 1.0:
            params = used_params(scale, args.work / f"{tag}-noise-used.yaml")
            row["used"] = scored(bag, truth, args.work / f"{tag}-noise-used", "--params", str(params))
        rows.append(row)
        print(f"[translation-noise] {json.dumps(row)}", flush=True)
    write_bench({**when_and_where(t0), "rows": rows}, args.out / "translation_noise.json", write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
