"""The real runs made unlike themselves: a slower laser, worse wheels (issue #23: held-out data).

The shared runs are the data every default was chosen on, and the issue's held-out runs came from other
robots and loggers. This benchmark makes each CARMEN log of ``../shared/datasets`` into logs its robot
could have recorded, then runs ``ptm-run`` on them at the default parameters with the run's ground truth
(matched by stamp, so it still applies):

* ``every 2nd scan``, ``every 3rd scan``: only every second / third ``FLASER`` record kept (a laser logged
  at a half / a third of the rate; the odometry of the kept records is unchanged);
* ``drift``: the odometry re-integrated from its own increments with a heading bias of ``DRIFT_RAD_PER_M``
  per metre travelled and the travel scaled by ``DRIFT_SCALE`` (worse wheels: a systematic turn and a
  wrong wheel radius), in every record that carries an odometry pose (``FLASER``, ``ODOM``).

Per run and log: MAP F1 (precision, recall), the MAP probability and the mass on topologies with no scored
pair wrong, the smoothed MAP trajectory's and the odometry's ATE, the visits, the laser odometry's matched
and rejected scans and its ATE at the visits (:func:`laser_odometry_ate`), the learned heading-noise scale
and the registrations (valid / made); and the pair calibration (``ptm-eval``'s ``pair_calibration``),
pooled over seeds, runs and logs in the last table.

Over inference seeds ``--seeds`` (0, 1, 2). Writes ``bench/perturbed_runs.json`` and
``bench/perturbed_runs.md`` (``--out``). About 12 minutes.

    PYTHONPATH=. .venv/bin/python bench/bench_perturbed_runs.py [--seeds 0 1 2] [--work out/perturbed] \\
        [--out bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import gzip
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from run_all import (
    DATASETS,
    REAL_RUNS,
    pair_calibration_section,
    ptm_run_scored,
    shared_data_ready,
    when_and_where,
    write_bench,
)

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
DRIFT_RAD_PER_M = 0.01
DRIFT_SCALE = 1.02


def _pose_slice(tokens: Sequence[str]) -> slice | None:
    """Where a CARMEN record keeps its odometry pose ``x y θ``: ``FLASER`` its second pose triple,
    ``ODOM`` its first three values; None for any other line."""
    if not tokens:
        return None
    if tokens[0] == "FLASER":
        n = int(tokens[1])
        return slice(2 + n + 3, 2 + n + 6)
    if tokens[0] == "ODOM":
        return slice(1, 4)
    return None


def every_nth_scan(lines: Iterable[str], n: int) -> list[str]:
    """The log with only every ``n``-th ``FLASER`` record (the first kept), every other line as it is."""
    out, k = [], 0
    for line in lines:
        if line.split(maxsplit=1)[:1] == ["FLASER"]:
            k += 1
            if (k - 1) % n:
                continue
        out.append(line)
    return out


def drifted(lines: Iterable[str], bias: float, scale: float) -> list[str]:
    """The log with its odometry poses re-integrated, in file order, from their own increments: each
    increment's translation (in the previous pose's frame) times ``scale``, its rotation plus ``bias``
    rad per metre of its (unscaled) translation. A ``FLASER`` record's laser pose is set to its new
    odometry pose. ``bias`` 0 and ``scale`` 1 give the poses back (to the printed precision)."""
    out: list[str] = []
    prev: tuple[float, float, float] | None = None
    cur = (0.0, 0.0, 0.0)
    for line in lines:
        tokens = line.split()
        where = _pose_slice(tokens)
        if where is None:
            out.append(line)
            continue
        x, y, th = (float(v) for v in tokens[where])
        if prev is None:
            cur = (x, y, th)
        else:
            c, s = math.cos(prev[2]), math.sin(prev[2])
            dx, dy = x - prev[0], y - prev[1]
            lx, ly = c * dx + s * dy, -s * dx + c * dy
            turn = math.remainder(th - prev[2], 2.0 * math.pi)
            cc, cs = math.cos(cur[2]), math.sin(cur[2])
            cur = (
                cur[0] + scale * (cc * lx - cs * ly),
                cur[1] + scale * (cs * lx + cc * ly),
                math.remainder(cur[2] + turn + bias * math.hypot(lx, ly), 2.0 * math.pi),
            )
        prev = (x, y, th)
        tokens[where] = [f"{v:.6f}" for v in cur]
        if tokens[0] == "FLASER":
            laser = slice(where.start - 3, where.start)
            tokens[laser] = tokens[where]
        out.append(" ".join(tokens))
    return out


PERTURBATIONS: dict[str, Callable[[list[str]], list[str]]] = {
    "as logged": list,
    "every 2nd scan": lambda lines: every_nth_scan(lines, 2),
    "every 3rd scan": lambda lines: every_nth_scan(lines, 3),
    "drift": lambda lines: drifted(lines, DRIFT_RAD_PER_M, DRIFT_SCALE),
}


def perturbed_bag(log: Path, name: str, work: Path) -> Path:
    """The bag of ``log`` under perturbation ``name``, made once under ``work`` (a changed perturbation
    needs a fresh ``work``)."""
    from ptm_ros.tools.convert import convert

    tag = name.replace(" ", "-")
    bag = work / f"{log.name.split('.')[0]}-{tag}.bag"
    if not bag.exists():
        with gzip.open(log, "rt") as f:
            lines = f.read().splitlines()
        text = work / f"{log.name.split('.')[0]}-{tag}.clf.gz"
        with gzip.open(text, "wt") as f:
            f.write("\n".join(PERTURBATIONS[name](lines)) + "\n")
        convert(text, bag)
    return bag


def perturbed_logs(work: Path) -> Iterator[tuple[str, str, Path, Path]]:
    """Every shared real run under every perturbation, as ``(run, perturbation, bag, ground truth file)``
    (the bags made once under ``work``, :func:`perturbed_bag`)."""
    for name, log, gt in REAL_RUNS:
        for label in PERTURBATIONS:
            yield name, label, perturbed_bag(DATASETS / log, label, work), DATASETS / gt


def score(bag: Path, truth: Path, out: Path, seed: int, *options: str) -> dict[str, Any]:
    """``ptm-run`` at the defaults but the inference ``seed`` and ``options`` (``--force``: a drifted
    odometry no longer moves as the ground truth's raw one), its figures."""
    import json

    res = ptm_run_scored(bag, truth, out, "--seed", str(seed), "--force", "--no-report", "--no-map", *options)
    if isinstance(res, str):
        return {"error": res}
    _, s = res
    doc = json.loads((out / "ptm.json").read_text())
    diag, ate = doc["diagnostics"], doc.get("trajectory_error") or {}
    lo = diag.get("laser_odometry", {})
    return {
        **{k: s[k] for k in ("map_f1", "map_precision", "map_recall", "consistent_mass")},
        "map_probability": doc["topologies"][0]["probability"],
        "visits": len(doc["landmarks"]),
        "ate_smoothed_m": ate.get("ate_smoothed_m"),
        "ate_odometry_m": ate.get("ate_odometry_m"),
        "ate_laser_odometry_m": laser_odometry_ate(doc["landmarks"], truth),
        "laser_matched": lo.get("matched"),
        "laser_rejected": lo.get("rejected"),
        "heading_scale": doc["inference"].get("heading_noise", {}).get("scale", math.nan),
        "translation_noise": doc["inference"].get("translation_noise"),
        "registrations": diag.get("registrations"),
        "registrations_valid": diag.get("registrations_valid"),
        "pair_calibration": s["pair_calibration"],
    }


def laser_odometry_ate(landmarks: Sequence[dict[str, Any]], truth: Path) -> float:
    """ATE (m, after the best rigid 2-D alignment) of the visits' laser-corrected odometry poses
    (``ptm.json``'s ``corrected_pose``) against the ground truth at their stamps, over the visits inside
    its time span: how well the laser odometry held the run together before any loop was closed."""
    import numpy as np

    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.geometry import interpolate_poses
    from ptm_ros.scoring.evaluation import absolute_trajectory_error

    gt = load_ground_truth(truth)
    stamps = np.array([v["stamp"] for v in landmarks])
    inside = (stamps >= gt.stamps[0]) & (stamps <= gt.stamps[-1])
    est = np.array([v["corrected_pose"][:2] for v in landmarks])[inside]
    true = interpolate_poses(gt.stamps, gt.poses_corrected, stamps[inside])[:, :2]
    return absolute_trajectory_error(est, true)


def write_md(doc: dict[str, Any], path: Path) -> None:
    """The markdown of :func:`main`'s record."""
    lines = [
        "# The real runs made unlike themselves (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_perturbed_runs.py` ({doc['minutes']:.0f} min). Each "
        "CARMEN log as logged, with only every 2nd or 3rd scan (a laser at a half or a third of the rate) "
        "and with its "
        f"odometry drifted ({doc['drift_rad_per_m']} rad of heading per metre, travel × "
        f"{doc['drift_scale']}); `ptm-run` at the default parameters, scored against the run's ground truth.",
        "",
        "Per inference seed (the filter's resampling; the visits and the laser odometry do not depend on "
        f"it), seeds {', '.join(str(x) for x in doc['seeds'])}:",
        "",
        "| run | log | visits | MAP F1 (precision) | MAP p | ATE smoothed (m) | heading scale "
        "| registrations valid / made | laser odometry matched / rejected | ATE at the visits, laser "
        "odometry (m) | odometry ATE (m) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in doc["rows"]:
        groups.setdefault((r["run"], r["log"]), []).append(r)
    for (run, log), rows in groups.items():
        failed = [r["error"][-120:] for r in rows if "error" in r]
        if failed:
            lines.append(f"| {run} | {log} | failed: {failed!r} |||||||||")
        ok = [r for r in rows if "error" not in r]
        if ok:
            lines.append(_seeds_row(run, log, ok))
    lines += pair_calibration_lines(doc["rows"])
    lines += ["", "## Commands", "", "    PYTHONPATH=. .venv/bin/python bench/bench_perturbed_runs.py", ""]
    path.write_text("\n".join(lines))


def pair_calibration_lines(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The markdown section of the pair calibration, pooled over the seeds and runs of each log, over the
    logs of each run, and over everything (:func:`run_all.pair_calibration_section`)."""
    ok = [r for r in rows if r.get("pair_calibration")]
    groups: dict[str, list[dict[str, Any]]] = {"all": ok} if ok else {}
    for key in ("log", "run"):
        for r in ok:
            groups.setdefault(f"{key}: {r[key]}", []).append(r)
    return pair_calibration_section(groups, "pooled over seeds, runs and logs")


def _seeds_row(run: str, log: str, rows: Sequence[dict[str, Any]]) -> str:
    """One markdown row of a run and log over its seeds (per-seed figures joined by ``/``)."""

    def each(fmt: str, *keys: str) -> str:
        return " / ".join(fmt.format(*(r[k] for k in keys)) for r in rows)

    first = rows[0]
    cells = [
        run,
        log,
        str(first["visits"]),
        each("{:.3f} ({:.2f})", "map_f1", "map_precision"),
        each("{:.2f}", "map_probability"),
        each("{:.2f}", "ate_smoothed_m"),
        each("{:.3g}", "heading_scale"),
        each("{}/{}", "registrations_valid", "registrations"),
        f"{first['laser_matched']} / {first['laser_rejected']}",
        f"{first['ate_laser_odometry_m']:.2f}",
        f"{first['ate_odometry_m']:.2f}",
    ]
    return "| " + " | ".join(cells) + " |"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "out" / "perturbed")
    parser.add_argument("--out", type=Path, default=BENCH, help="where perturbed_runs.{json,md} are written")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="inference seeds")
    args = parser.parse_args(argv)
    if not shared_data_ready("perturbed", args.work, args.out):
        return 0
    t0 = time.perf_counter()
    rows = []
    for name, label, bag, truth in perturbed_logs(args.work):
        for seed in args.seeds:
            out = args.work / f"{name}-{label.replace(' ', '-')}-{seed}"
            rows.append({"run": name, "log": label, "seed": seed, **score(bag, truth, out, seed)})
            print(f"[perturbed] {rows[-1]}", flush=True)
    doc = {
        **when_and_where(t0),
        "drift_rad_per_m": DRIFT_RAD_PER_M,
        "drift_scale": DRIFT_SCALE,
        "seeds": args.seeds,
        "rows": rows,
    }
    write_bench(doc, args.out / "perturbed_runs.json", write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
