"""The noise models against the truth (issue #23): the heading noise learned from a run
(``model.odometry.learn_heading``) and the covariance of the laser registrations.

For each real run in ``../shared/datasets`` (converted once under ``--work``) and each simulated world of
``--worlds`` at the odometry noise levels ``--noise`` of ``bench_calibration.py`` (seed 0):

* **measured**: the laser-corrected odometry's heading error against the ground truth over consecutive
  stretches of ``--window`` m of true travel, its mean square divided by the mean heading variance the
  default model gives the same stretches (``a_th ρ + c_th ℓ``): the scale a perfect estimator would learn;
* **measured over revisits**: the same error between the visits of one place in truth (less than 1.5 m
  apart, at least ``REVISIT_GAP`` visits apart), squared over the default model's heading variance of the
  path between them and averaged: the scale a loop's likelihood needs (errors that cancel over a loop lower
  the stretches' ratio, not this one). Also a constant heading drift per metre of travel fitted to those
  errors by least squares (``drift_rad_per_m``) and the ratio once it is taken out: how much of the loops'
  heading error is a drift, which the model's random walk does not have;
* **learned**: the scale the filter session learns from the run's own laser registrations, no ground truth
  (:mod:`ptm_ros.model.heading_noise`, as ``ptm-run`` at the default parameters), with the registrations and
  the outlier fraction behind it;
* **registrations**: each valid registration of the run (the pairs the filter asked about) against the
  true relative pose of its two visits, for the pairs closer in truth than ``ptm-eval``'s different-place
  radius (4 m): its error in translation and heading, and its squared Mahalanobis distance under its own
  covariance (χ² with 3 degrees of freedom if the covariance were right: ``CHI2_3_99`` is exceeded by 1 % of
  the pairs). Those more than ``ALIAS_RAD`` off in heading are counted as aliases and left out of the error
  figures.

Writes ``bench/heading_noise.json`` and ``bench/heading_noise.md``.

    PYTHONPATH=. .venv/bin/python bench/bench_heading_noise.py [--work out/heading_noise]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from run_all import DATASETS, REAL_RUNS, prepare_runs, write_bench

if TYPE_CHECKING:
    from ptm_ros.io.groundtruth import GroundTruthTrajectory
    from ptm_ros.model.geometry import RelativePose
    from ptm_ros.model.visits import Visit

BENCH = Path(__file__).resolve().parent
#: A registration this far off the true relative heading is an alias (a symmetric mismatch), not noise.
ALIAS_RAD = 0.5
#: Revisits are pairs of visits of one place in truth at least this many visits apart.
REVISIT_GAP = 5
#: The 99 % quantile of χ² with 3 degrees of freedom.
CHI2_3_99 = 11.345
WORLDS = ("aliased-loop", "twin-rooms", "room-row", "aliased-ring")
NOISE = ("sim", "model", "twice-model")


def measured_ratio(stamps: np.ndarray, corrected: np.ndarray, truth: Any, window: float) -> dict[str, float]:
    """Mean square heading error of ``corrected`` (poses at ``stamps``) over ``window`` m stretches of the
    truth's travel, against the default model's mean heading variance of the same stretches."""
    from ptm_ros.model.geometry import between, interpolate_poses, wrap_angle
    from ptm_ros.model.odometry import OdometryConfig

    inside = (truth.stamps >= stamps[0]) & (truth.stamps <= stamps[-1])
    t, g = truth.stamps[inside], truth.poses_corrected[inside]
    c = interpolate_poses(stamps, corrected, t)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g[:, :2], axis=0).T))])
    turned = np.concatenate([[0.0], np.cumsum(np.abs(wrap_angle(np.diff(g[:, 2]))))])
    cfg = OdometryConfig()
    err, var, i = [], [], 0
    while (j := int(np.searchsorted(travel, travel[i] + window))) < len(t):
        err.append(float(wrap_angle(between(c[i], c[j])[2] - between(g[i], g[j])[2])) ** 2)
        var.append(cfg.a_th * (turned[j] - turned[i]) + cfg.c_th * (travel[j] - travel[i]))
        i = j
    if not err:
        return {"stretches": 0}
    return {
        "stretches": len(err),
        "mean_square": float(np.mean(err)),
        "ratio": float(np.mean(err) / np.mean(var)),
    }


def revisit_ratio(visits: Sequence[Visit], truth: GroundTruthTrajectory) -> dict[str, float]:
    """The corrected odometry's heading error between the visits of one place in truth, squared, over the
    default model's heading variance of the path between them, averaged; the least-squares heading drift per
    metre of those errors and the same ratio without it (module docstring)."""
    from ptm_ros.io.groundtruth import within_span
    from ptm_ros.model.geometry import interpolate_poses, wrap_angle
    from ptm_ros.model.odometry import OdometryConfig, path_heading_variances
    from ptm_ros.scoring.evaluation import pair_truth

    stamps = np.array([v.stamp for v in visits], dtype=float)
    g = interpolate_poses(truth.stamps, truth.poses_corrected, stamps)
    heading = np.array([v.pose[2] for v in visits], dtype=float)
    cum = path_heading_variances(visits, OdometryConfig())
    xy = np.where(within_span(truth, stamps, 0.0)[:, None], g[:, :2], np.nan)  # no truth: unscored
    i, j, same = pair_truth(xy)  # what ptm-eval scores as one place
    keep = same & (j - i >= REVISIT_GAP)
    i, j = i[keep], j[keep]
    if len(i) == 0:
        return {"revisits": 0}
    error = wrap_angle((heading[j] - heading[i]) - (g[j, 2] - g[i, 2]))
    var = cum[j] - cum[i]
    path = np.concatenate([[0.0], np.cumsum([v.travel for v in visits[1:]])])
    length = path[j] - path[i]
    drift = float(np.sum(error * length) / np.sum(length * length)) if np.any(length > 0) else 0.0
    return {
        "revisits": len(i),
        "revisit_ratio": float(np.mean(error**2 / var)),
        "drift_rad_per_m": drift,
        "ratio_without_drift": float(np.mean((error - drift * length) ** 2 / var)),
    }


def registration_errors(
    stamps: np.ndarray,
    registrations: Sequence[RelativePose],
    truth: GroundTruthTrajectory,
    floor: tuple[float, float],
) -> dict[str, float]:
    """Valid registrations (``RelativePose``, of visits at ``stamps``) against the truth's relative poses
    (module docstring); ``floor`` the registration covariance's floor ``(σ_xy, σ_θ)``, for comparison."""
    from ptm_ros.io.groundtruth import within_span
    from ptm_ros.model.geometry import between, interpolate_poses, wrap_angle
    from ptm_ros.scoring.evaluation import EvalConfig

    apart = EvalConfig().different_radius
    t = np.asarray(stamps, dtype=float)
    inside = within_span(truth, t, 0.0)
    g = interpolate_poses(truth.stamps, truth.poses_corrected, t)
    trans, head, maha, aliases = [], [], [], 0
    for z in registrations:
        if not (inside[z.i] and inside[z.j]) or np.hypot(*(g[z.i, :2] - g[z.j, :2])) >= apart:
            continue
        e = np.asarray(z.mean, dtype=float) - between(g[z.i], g[z.j])
        e[2] = wrap_angle(e[2])
        if abs(e[2]) > ALIAS_RAD:
            aliases += 1
            continue
        trans.append(float(np.hypot(e[0], e[1])))
        head.append(abs(float(e[2])))
        maha.append(float(e @ np.linalg.solve(np.asarray(z.cov, dtype=float), e)))
    out: dict[str, float] = {
        "scored": len(trans),
        "aliases": aliases,
        "floor_xy": floor[0],
        "floor_th": floor[1],
    }
    if trans:
        for name, v in (("xy", np.array(trans)), ("th", np.array(head))):
            out[f"{name}_rms"] = float(np.sqrt(np.mean(v * v)))
            out[f"{name}_median"] = float(np.median(v))
            out[f"{name}_p90"] = float(np.quantile(v, 0.9))
        out["beyond_chi2_99"] = float(np.mean(np.array(maha) > CHI2_3_99))
    return out


def one_run(bag: Path, truth_path: Path, window: float) -> dict[str, Any]:
    """Measured and learned scale of one bag at the default parameters (laser-surprise visits)."""
    from ptm_ros.config import PtmConfig
    from ptm_ros.factories import with_detector_kind
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.geometry import RelativePose
    from ptm_ros.session import FilterSession, filter_visits
    from ptm_ros.tools.outputs import run_odometry
    from ptm_ros.tools.pipeline import corrected_odometry, detect_visits, run_extractor, run_sensors

    run = read_run(bag)
    config = with_detector_kind(PtmConfig(), **run_sensors(run))
    extractor = run_extractor(run, config)
    visits = detect_visits(run, config, extractor=extractor)
    odom = run_odometry(run)
    out: dict[str, Any] = {"visits": len(visits)}
    truth = load_ground_truth(truth_path)
    out["revisits"] = revisit_ratio(visits, truth)
    out["measured"] = measured_ratio(
        np.asarray(odom.stamps), corrected_odometry(run, extractor), truth, window
    )
    t0 = time.perf_counter()
    session = filter_visits(FilterSession(config, fitted_to=visits), visits)
    out["learned"] = session.heading.as_dict()
    out["filter_s"] = time.perf_counter() - t0
    out["replays"] = session.replays
    valid = sorted(
        (z for z in session.pairs.values() if isinstance(z, RelativePose)), key=lambda z: (z.i, z.j)
    )
    floor = (config.laser.min_std_xy, config.laser.min_std_yaw)
    out["registrations"] = registration_errors(np.array([v.stamp for v in visits]), valid, truth, floor)
    return out


def write_md(doc: dict[str, Any], path: Path) -> None:
    from ptm_ros.scoring.evaluation import EvalConfig

    lines = [
        "# The noise models against the truth (issue #23)",
        "",
        "## The heading noise learned from the run",
        "",
        f"Generated {doc['generated']} by `bench/bench_heading_noise.py` ({doc['wall_s'] / 60:.0f} min). "
        f"*Measured*: the laser-corrected odometry's heading error against the ground truth over "
        f"{doc['window_m']:.0f} m stretches of true travel, its mean square over the default model's heading "
        "variance of the same stretches (what a perfect estimator would learn). *Over revisits*: the same "
        f"error between visits of one place in truth (less than 1.5 m apart, at least {REVISIT_GAP} visits "
        "apart), squared, over the default model's heading variance of the path between them, averaged: the "
        "scale a loop's likelihood needs; *drift*: a constant heading drift per metre fitted to those errors "
        "(least squares), and the ratio once it is taken out. *Learned*: the scale "
        "`ptm-run` learns at the default parameters from the run's own laser registrations, no ground truth "
        "(`ptm_ros.model.heading_noise`; lattice 2^(m/2), prior log k ~ N(0, 1)). Laser-surprise visits.",
        "",
        "| run | noise | visits | stretches | measured ratio | revisits | over revisits | drift (rad/m) "
        "| without drift | learned scale | registrations | outliers | filter s (replays) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        m, lr = r["measured"], r["learned"]
        ratio = f"{m['ratio']:.3f}" if "ratio" in m else "–"
        rv = r.get("revisits", {})
        over = f"{rv['revisit_ratio']:.3f}" if "revisit_ratio" in rv else "–"
        drift = (
            f"{rv['drift_rad_per_m']:+.4f} | {rv['ratio_without_drift']:.3f}"
            if "revisit_ratio" in rv
            else "– | –"
        )
        lines.append(
            f"| {r['run']} | {r.get('noise', 'real')} | {r['visits']} | {m['stretches']} | {ratio} | "
            f"{rv.get('revisits', '–')} | {over} | {drift} | "
            f"{lr['scale']:.3g} | {lr['registrations']} | {lr['outlier_fraction']:.2f} | "
            f"{r['filter_s']:.1f} ({r['replays']}) |"
        )
    lines += [
        "",
        "## The laser registrations against the truth",
        "",
        f"Each valid registration of visits less than {EvalConfig().different_radius:.0f} m apart in truth "
        "(the pairs the filter asked about), against the true relative pose of its visits: the error of its "
        "translation (m) and heading (rad), and the share of them outside the 99 % ellipsoid of their own "
        f"covariance (1 % if the covariance were right). Those more than {ALIAS_RAD} rad off in heading are "
        "aliases, counted apart. The registrations' covariance is the point-to-plane fit's, floored at "
        "`laser.min_std_xy` and "
        "`laser.min_std_yaw` (the floor columns).",
        "",
        "| run | noise | scored | aliases | xy rms | xy median | xy p90 | floor xy | θ rms | θ median "
        "| θ p90 | floor θ | outside 99 % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        g = r.get("registrations", {})
        if not g.get("scored"):
            continue
        lines.append(
            f"| {r['run']} | {r.get('noise', 'real')} | {g['scored']} | {g['aliases']} | {g['xy_rms']:.3f} | "
            f"{g['xy_median']:.3f} | {g['xy_p90']:.3f} | {g['floor_xy']:.3f} | {g['th_rms']:.3f} | "
            f"{g['th_median']:.3f} | {g['th_p90']:.3f} | {g['floor_th']:.3f} | {g['beyond_chi2_99']:.2f} |"
        )
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=list(WORLDS))
    parser.add_argument("--noise", nargs="+", default=list(NOISE), help="bench_calibration.py's noise levels")
    parser.add_argument("--window", type=float, default=30.0, help="stretch of true travel (m)")
    parser.add_argument("--work", type=Path, default=BENCH.parent / "out" / "heading_noise")
    parser.add_argument("--out", type=Path, default=BENCH / "heading_noise.json")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(BENCH))
    from bench_calibration import NOISE_LEVELS

    from ptm_ros.io.simulator import SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world

    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs = []
    if DATASETS.is_dir():
        for name, _, bag, gt in prepare_runs(args.work, [name for name, _, _ in REAL_RUNS]):
            runs.append({"run": name, **one_run(bag, gt, args.window)})
            print(f"[heading] {name}: {runs[-1]}", flush=True)
    for world in args.worlds:
        for noise in args.noise:
            bag = args.work / "sim" / f"{world}-{noise}"
            if not bag.exists():
                sim = simulate(
                    get_world(world), SimConfig(odometry=NOISE_LEVELS[noise]), np.random.default_rng(0)
                )
                write_run(sim, bag)
            runs.append(
                {"run": world, "noise": noise, **one_run(bag, bag / "ground_truth.json", args.window)}
            )
            print(f"[heading] {world} {noise}: {runs[-1]}", flush=True)
    doc = {
        "benchmark": "heading_noise",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "wall_s": time.perf_counter() - t0,
        "window_m": args.window,
        "runs": runs,
    }
    write_bench(doc, args.out, write_md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
