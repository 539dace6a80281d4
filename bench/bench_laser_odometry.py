"""The laser odometry alone against the ground truth, scan by scan (issue #23: the front end).

The topology posterior is only as good as the odometry it is fed: on Intel at half the scan rate the MAP
that merged a whole corridor system onto a parallel one was the batch model's own best answer, because
the laser odometry had drifted 7 m (``bench/perturbed_runs.md``). This benchmark measures the front end
without the posterior's coin flips: on each real run, as logged and made unlike itself as
``bench/bench_perturbed_runs.py`` makes it, :class:`~ptm_ros.perception.laser_odometry.LaserOdometry` runs at
the defaults over every scan (:func:`~ptm_ros.maps.mapping.scan_points`; the time offset learned from the
first ``learn_scans`` scans by :func:`~ptm_ros.perception.laser_odometry.learn_time_offset`; ``ptm-run``'s
visit extractor feeds it its own way, and its counts can differ by a few scans) and each scan's corrected
pose is compared with the ground truth at its stamp:

* ``ate_m``: the RMS position error over all scans inside the ground truth's span, after the best rigid
  2-D alignment;
* per scan step (consecutive scans): the heading error of the corrected relative motion against the
  ground truth's, its RMS and its sum (the net drift), the sum split by the step's status (``matched``,
  ``rejected``: the match failed and the step kept the wheels' motion, ``kept``: gated or too few
  points); and the wheels' own heading error sum.

Writes ``bench/laser_odometry.{json,md}`` (``--out``). About a minute.

    PYTHONPATH=. .venv/bin/python bench/bench_laser_odometry.py [--work out/perturbed] [--out bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from bench_perturbed_runs import perturbed_logs
from numpy.typing import NDArray
from run_all import DATASETS, when_and_where, write_bench

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
STATUSES = ("matched", "rejected", "kept")


@dataclass(frozen=True)
class ScanPass:
    """One laser-odometry pass: per scan its stamp, wheel pose and corrected pose (``(S, 3)``) and status
    (:data:`STATUSES`), at the learned ``time_offset`` (s)."""

    stamps: NDArray[np.float64]
    wheel: NDArray[np.float64]
    corrected: NDArray[np.float64]
    status: tuple[str, ...]
    time_offset: float


def laser_odometry_pass(bag: Path) -> ScanPass:
    """The default laser odometry over all scans of ``bag``, the time offset learned from the first
    ``learn_scans`` scans."""
    from ptm_ros.config import PtmConfig
    from ptm_ros.io.bag import read_run
    from ptm_ros.maps.mapping import scan_points
    from ptm_ros.model.geometry import interpolate_poses
    from ptm_ros.perception.laser_odometry import LaserOdometry, RunInput, learn_time_offset

    cfg = PtmConfig()
    run = read_run(bag, odom_topic=cfg.topics.odom, scan_topic=cfg.topics.scan, image_topic=None)
    assert run.odometry is not None and run.scans is not None
    t, poses = run.odometry.stamps, run.odometry.poses
    stamps, points = scan_points(run.scans, cfg.laser)
    first = cfg.laser_odometry.learn_scans
    offset = learn_time_offset(
        RunInput.of(t, poses, stamps[:first], points[:first]), cfg.laser_odometry, cfg.laser
    ).offset
    keep = np.flatnonzero((stamps + offset >= t[0]) & (stamps + offset <= t[-1]))
    wheel = interpolate_poses(t, poses, stamps[keep] + offset)
    lo = LaserOdometry(config=cfg.laser_odometry, laser=cfg.laser)
    corrected, status = [], []
    for k, pose in zip(keep, wheel, strict=True):
        before = (lo.counters.matched, lo.counters.rejected)
        corrected.append(lo.on_scan(pose, points[int(k)], float(stamps[k])))
        after = (lo.counters.matched, lo.counters.rejected)
        status.append("matched" if after[0] > before[0] else "rejected" if after[1] > before[1] else "kept")
    return ScanPass(stamps[keep], wheel, np.array(corrected), tuple(status), offset)


def step_heading_errors(poses: NDArray[np.float64], true: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(S - 1,)``: the turn of each step between consecutive ``poses`` minus the true turn (wrapped)."""
    from ptm_ros.model.geometry import between

    return np.array(
        [
            math.remainder(between(poses[k - 1], poses[k])[2] - between(true[k - 1], true[k])[2], math.tau)
            for k in range(1, len(true))
        ]
    )


def against_truth(
    scan: ScanPass, truth_stamps: NDArray[np.float64], truth_poses: NDArray[np.float64]
) -> dict:
    """The figures of the module docstring for one pass against the ground truth ``truth_poses (T, 3)``
    at ``truth_stamps``, over the scans inside its span (a step's status is its later scan's)."""
    from ptm_ros.model.geometry import interpolate_poses
    from ptm_ros.scoring.evaluation import absolute_trajectory_error

    inside = (scan.stamps >= truth_stamps[0]) & (scan.stamps <= truth_stamps[-1])
    true = interpolate_poses(truth_stamps, truth_poses, scan.stamps[inside])
    est = scan.corrected[inside]
    kinds = [s for s, i in zip(scan.status, inside, strict=True) if i][1:]
    err = step_heading_errors(est, true)
    return {
        "scans": int(inside.sum()),
        **{f"steps_{s}": kinds.count(s) for s in STATUSES},
        "ate_m": absolute_trajectory_error(est[:, :2], true[:, :2]),
        "heading_rms_rad": float(np.sqrt(np.mean(err**2))),
        "heading_sum_rad": float(err.sum()),
        **{f"heading_sum_{s}_rad": float(err[[k == s for k in kinds]].sum()) for s in STATUSES},
        "wheel_heading_sum_rad": float(step_heading_errors(scan.wheel[inside], true).sum()),
    }


def write_md(doc: dict[str, Any], path: Path) -> None:
    """The markdown of :func:`main`'s record."""
    lines = [
        "# The laser odometry against the ground truth, scan by scan (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_laser_odometry.py` ({doc['minutes']:.0f} min). The "
        "laser odometry at the defaults over every scan of each log (as logged and as "
        "`bench/bench_perturbed_runs.py` perturbs it), each corrected pose against the ground truth at its "
        "stamp. ATE: RMS position error after the best rigid 2-D alignment. Heading: the error of each "
        "scan step's corrected turn against the true turn; its sum is the net drift, split by the step's "
        "status (rejected: the match failed and the step kept the wheels' motion).",
        "",
        "| run | log | time offset (s) | scans | steps matched / rejected / kept | ATE (m) | heading RMS "
        "per step (rad) | heading drift (rad): all / matched / rejected / kept | wheels' heading drift "
        "(rad) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["rows"]:
        if "error" in r:
            lines.append(f"| {r['run']} | {r['log']} | failed: {r['error'][-120:]!r} |||||||")
            continue
        lines.append(
            f"| {r['run']} | {r['log']} | {r['time_offset']:g} | {r['scans']} | "
            f"{r['steps_matched']} / {r['steps_rejected']} / {r['steps_kept']} | {r['ate_m']:.2f} | "
            f"{r['heading_rms_rad']:.4f} | {r['heading_sum_rad']:+.2f} / {r['heading_sum_matched_rad']:+.2f} "
            f"/ {r['heading_sum_rejected_rad']:+.2f} / {r['heading_sum_kept_rad']:+.2f} | "
            f"{r['wheel_heading_sum_rad']:+.2f} |"
        )
    lines += ["", "## Commands", "", "    PYTHONPATH=. .venv/bin/python bench/bench_laser_odometry.py", ""]
    path.write_text("\n".join(lines))


def main(argv: Sequence[str] | None = None) -> int:
    from ptm_ros.io.groundtruth import load_ground_truth

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "out" / "perturbed")
    parser.add_argument("--out", type=Path, default=BENCH, help="where laser_odometry.{json,md} are written")
    args = parser.parse_args(argv)
    if not (DATASETS / "README.md").is_file():
        print(f"[laser-odometry] {DATASETS} absent: nothing to do", flush=True)
        return 0
    t0 = time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    truths: dict[Path, Any] = {}
    for name, label, bag, truth_file in perturbed_logs(args.work):
        if truth_file not in truths:  # one ground truth serves the run's four logs
            truths[truth_file] = load_ground_truth(truth_file)
        truth = truths[truth_file]
        row: dict[str, Any] = {"run": name, "log": label}
        try:
            scan = laser_odometry_pass(bag)
            row |= {"time_offset": scan.time_offset}
            row |= against_truth(scan, truth.stamps, truth.poses_corrected)
        except Exception as exc:  # one failed log is reported, the others still run
            row["error"] = f"{type(exc).__name__}: {exc}"
        rows.append(row)
        print(f"[laser-odometry] {row}", flush=True)
    write_bench({**when_and_where(t0), "rows": rows}, args.out / "laser_odometry.json", write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
