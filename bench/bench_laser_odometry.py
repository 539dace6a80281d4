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
* ``family_ate_m``: the ATE of the same log under a family of small perturbations (the time offset
  shifted by 0, -0.05 and -0.1 s from the learned one; all scans or the first 10 left out), and its
  geometric mean; ``family_without_second_look_ate_m`` the same with ``defer_scans`` 0. The laser
  odometry is deterministic but chaotic: one accept/reject decision moves a log's ATE by metres, so one
  pass per log is one draw, and a change to the front end is judged over the family.

Writes ``bench/laser_odometry.{json,md}`` (``--out``). About four minutes on two cores (``--jobs``).

    PYTHONPATH=. .venv/bin/python bench/bench_laser_odometry.py [--work out/perturbed] [--out bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import time
from collections.abc import Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from bench_perturbed_runs import perturbed_logs
from numpy.typing import NDArray
from run_all import shared_data_ready, when_and_where, write_bench

if TYPE_CHECKING:
    from ptm_ros.io.groundtruth import GroundTruthTrajectory

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


@dataclass(frozen=True)
class LogInput:
    """One log's wheel odometry ``(stamps, poses)``, its scans ``(scan_stamps, points)`` and the time
    offset learned from its first ``learn_scans`` scans."""

    stamps: NDArray[np.float64]
    poses: NDArray[np.float64]
    scan_stamps: NDArray[np.float64]
    points: list[NDArray[np.float64]]
    learned_offset: float


def load_log(bag: Path) -> LogInput:
    """Read ``bag`` and learn its time offset at the defaults (as ``ptm-run`` does)."""
    from ptm_ros.config import PtmConfig
    from ptm_ros.io.bag import read_run
    from ptm_ros.maps.mapping import scan_points
    from ptm_ros.perception.laser_odometry import RunInput, learn_time_offset

    cfg = PtmConfig()
    run = read_run(bag, odom_topic=cfg.topics.odom, scan_topic=cfg.topics.scan, image_topic=None)
    assert run.odometry is not None and run.scans is not None
    t, poses = run.odometry.stamps, run.odometry.poses
    stamps, points = scan_points(run.scans, cfg.laser)
    first = cfg.laser_odometry.learn_scans
    offset = learn_time_offset(
        RunInput.of(t, poses, stamps[:first], points[:first]), cfg.laser_odometry, cfg.laser
    ).offset
    return LogInput(t, poses, stamps, list(points), offset)


def laser_odometry_pass(
    log: LogInput, offset_shift: float = 0.0, skip: int = 0, overrides: dict[str, Any] | None = None
) -> ScanPass:
    """The laser odometry (the defaults, but ``overrides`` of ``LaserOdometryConfig``) over the scans of
    ``log`` at its learned time offset plus ``offset_shift`` (within [-1, 0]), leaving out its first
    ``skip`` scans."""
    from dataclasses import replace

    from ptm_ros.config import PtmConfig
    from ptm_ros.model.geometry import interpolate_poses
    from ptm_ros.perception.laser_odometry import LaserOdometry

    cfg = PtmConfig()
    offset = min(0.0, max(-1.0, round(log.learned_offset + offset_shift, 9)))
    t, stamps = log.stamps, log.scan_stamps
    keep = np.flatnonzero((stamps + offset >= t[0]) & (stamps + offset <= t[-1]))[skip:]
    wheel = interpolate_poses(t, log.poses, stamps[keep] + offset)
    lo = LaserOdometry(config=replace(cfg.laser_odometry, **(overrides or {})), laser=cfg.laser)
    corrected, status = [], []
    for k, pose in zip(keep, wheel, strict=True):
        before = (lo.counters.matched, lo.counters.rejected)
        corrected.append(lo.on_scan(pose, log.points[int(k)], float(stamps[k])))
        after = (lo.counters.matched, lo.counters.rejected)
        status.append("matched" if after[0] > before[0] else "rejected" if after[1] > before[1] else "kept")
    return ScanPass(stamps[keep], wheel, np.array(corrected), tuple(status), offset)


#: The family of small perturbations each log is also run under (:func:`family_passes`): the time offset
#: shifted from the learned one (s) and the first scans left out. The laser odometry is deterministic, and
#: one accept/reject decision can move a whole log's ATE by metres (MIT CSAIL as logged: 1.7 m at the
#: learned offset, 5.3 m at 0.05 s from it), so a single pass per log is one draw of a chaotic process.
FAMILY_SHIFTS = (0.0, -0.05, -0.1)
FAMILY_SKIPS = (0, 10)
#: The variant the family is also run under, to show what the second look at a rejection
#: (``defer_scans``) does.
WITHOUT_SECOND_LOOK = {"defer_scans": 0}


def family_pass(
    log: LogInput,
    truth_stamps: NDArray[np.float64],
    truth_poses: NDArray[np.float64],
    args: tuple[float, int, dict[str, Any]],
) -> dict[str, Any]:
    """One pass of the family (``args``: :func:`laser_odometry_pass`'s shift, skip and overrides): its
    time offset and :func:`against_truth`'s figures."""
    scan = laser_odometry_pass(log, *args)
    return {"time_offset": scan.time_offset, **against_truth(scan, truth_stamps, truth_poses)}


def family_passes(
    log: LogInput,
    truth_stamps: NDArray[np.float64],
    truth_poses: NDArray[np.float64],
    overrides: dict[str, Any],
    pool: Executor,
) -> list[dict[str, Any]]:
    """Every pass of the family (:data:`FAMILY_SHIFTS` × :data:`FAMILY_SKIPS`, the log itself first: shift
    0, skip 0), run in ``pool`` (an executor)."""
    args = [(shift, skip, overrides) for shift in FAMILY_SHIFTS for skip in FAMILY_SKIPS]
    futures = [pool.submit(family_pass, log, truth_stamps, truth_poses, a) for a in args]
    return [f.result() for f in futures]


def geometric_mean(values: Sequence[float]) -> float:
    """The geometric mean of positive ``values``."""
    return float(np.exp(np.mean(np.log(values))))


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
) -> dict[str, Any]:
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
        "status (rejected: the match failed and the step kept the wheels' motion). Family: the same log "
        "under 6 small perturbations (time offset shifted by 0, -0.05, -0.1 s from the learned one; the first"
        " 0 or 10 scans left out), since one accept/reject decision can move a log's ATE by metres; and the "
        "same family without the second look at a rejection (`defer_scans` 0).",
        "",
        "| run | log | time offset (s) | scans | steps matched / rejected / kept | ATE (m) | heading RMS "
        "per step (rad) | heading drift (rad): all / matched / rejected / kept | wheels' heading drift "
        "(rad) | family ATE (m): geometric mean [range] | the same without the second look |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
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
            f"{r['wheel_heading_sum_rad']:+.2f} | {_family(r['family_ate_m'])} | "
            f"{_family(r['family_without_second_look_ate_m'])} |"
        )
    done = [r for r in doc["rows"] if "error" not in r]
    if done:
        both = [
            geometric_mean([a for r in done for a in r[k]])
            for k in ("family_ate_m", "family_without_second_look_ate_m")
        ]
        lines += [
            "",
            f"Over all {len(done)} logs × {len(FAMILY_SHIFTS) * len(FAMILY_SKIPS)} passes of the family, the "
            f"geometric mean ATE is {both[0]:.2f} m at the defaults and {both[1]:.2f} m without the second "
            "look at a rejection (`defer_scans` 0).",
        ]
    lines += ["", "## Commands", "", "    PYTHONPATH=. .venv/bin/python bench/bench_laser_odometry.py", ""]
    path.write_text("\n".join(lines))


def _family(ates: Sequence[float]) -> str:
    return f"{geometric_mean(ates):.2f} [{min(ates):.2f}–{max(ates):.2f}]"


def log_row(name: str, label: str, bag: Path, truth: GroundTruthTrajectory, pool: Executor) -> dict[str, Any]:
    """The figures of one log (the module docstring) against ``truth`` (its ground truth), or its error."""
    row: dict[str, Any] = {"run": name, "log": label}
    try:
        log = load_log(bag)
        for key, overrides in (("family", {}), ("family_without_second_look", WITHOUT_SECOND_LOOK)):
            passes = family_passes(log, truth.stamps, truth.poses_corrected, overrides, pool)
            if not overrides:  # the log itself at the defaults: the family's first pass
                row |= passes[0]
            ates = [p["ate_m"] for p in passes]
            row[f"{key}_ate_m"] = ates
            row[f"{key}_ate_geomean_m"] = geometric_mean(ates)
    except Exception as exc:  # one failed log is reported, the others still run
        row["error"] = f"{type(exc).__name__}: {exc}"
    return row


def main(argv: Sequence[str] | None = None) -> int:
    from ptm_ros.io.groundtruth import load_ground_truth

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "out" / "perturbed")
    parser.add_argument("--out", type=Path, default=BENCH, help="where laser_odometry.{json,md} are written")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes for the family")
    args = parser.parse_args(argv)
    if not shared_data_ready("laser-odometry", args.work, args.out):
        return 0
    t0 = time.perf_counter()
    rows = []
    truths: dict[Path, GroundTruthTrajectory] = {}
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for name, label, bag, truth_file in perturbed_logs(args.work):
            if truth_file not in truths:  # one ground truth serves the run's four logs
                truths[truth_file] = load_ground_truth(truth_file)
            rows.append(log_row(name, label, bag, truths[truth_file], pool))
            print(f"[laser-odometry] {rows[-1]}", flush=True)
    write_bench({**when_and_where(t0), "rows": rows}, args.out / "laser_odometry.json", write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
