"""Occupancy maps of every simulated world and real run against their references (issue #24).

For each run, ``ptm-run``'s pipeline at the default parameters (:func:`run_all.pipeline_row`, one
process) scored against its ground truth: the map's quality (ptm.json's ``map_quality``:
:mod:`ptm_ros.maps.map_quality`), the trajectory error and the route-graph segments through the map's
walls, the figures copied to ``bench/maps/<run>.png`` and ``bench/maps/<run>-vs-reference.png``
(:func:`run_all.copy_map_figures`). Where ``ptm-calibrate`` chooses a laser time offset (from the bag
alone) the run is repeated with it (``ptm-rbpf calibrated``, figures ``<run>-calibrated…``), as
``make bench`` does.

Where the leak comes from, per run (``diagnosis``):

* ``model``: the same occupancy model (``occupancy.*`` defaults) with the scans at the ground-truth
  poses, against the same reference. Its leak is what the ray model alone puts outside the reference
  (no-return beams, clipping); the rest of the map's leak is the trajectory's.
* ``span``: the map drawn along the same smoothed trajectory from the scans inside the ground truth's
  time span only (the reference has none outside it, so free space that only those scans saw cannot be
  judged).
* ``passes``: the beam passes through the map's leaked cells: their distance from the sensor (quantiles,
  m) and the share made by no-return beams.
* ``before``: the occupancy model at the start of issue #24 (86263b0: ``l_free`` -0.4, a no-return beam
  clearing ``max_range``, 20 m; :data:`BEFORE`) on the same trajectory and scans, against the same
  reference; its map is drawn to ``bench/maps/<run>-before.png``.

Writes ``bench/maps_quality.json``; ``bench/maps_quality.md`` quotes it.

    PYTHONPATH=. .venv/bin/python bench/bench_maps.py [--worlds bench|all] [--only NAME ...] [--work DIR]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
sys.path.insert(0, str(BENCH))

from run_all import MAPS, SIM_WORLDS, copy_map, copy_map_figures, pipeline_row, prepare_runs  # noqa: E402

from ptm_ros.config import PtmConfig, load_config  # noqa: E402
from ptm_ros.io.bag import RunData, read_run  # noqa: E402
from ptm_ros.io.groundtruth import GroundTruthTrajectory, load_ground_truth  # noqa: E402
from ptm_ros.io.simulator import SimConfig, simulate, write_run  # noqa: E402
from ptm_ros.io.worlds import WORLDS, get_world  # noqa: E402
from ptm_ros.maps.map_quality import leaked_cells, map_quality  # noqa: E402
from ptm_ros.maps.mapping import grid_along  # noqa: E402
from ptm_ros.maps.occupancy import grid_traversal, save_png, scan_beams  # noqa: E402
from ptm_ros.tools.calibrate import calibrate_run  # noqa: E402
from ptm_ros.tools.outputs import class_grid, reference_classes  # noqa: E402

QUALITY = ("leak", "free_area_ratio", "wall_precision", "wall_recall")
MAPS_TMP = Path(tempfile.gettempdir()) / f"bench_maps_{os.getpid()}.png"  # full size, before copy_map
#: ``occupancy.*`` of the map before issue #24 (86263b0), the rest as today.
BEFORE = {"l_free": -0.4, "missing_ray_length": 20.0}


def figures(quality: Any) -> dict[str, float]:
    d = quality.as_dict() if hasattr(quality, "as_dict") else dict(quality or {})
    return {k: d.get(k) for k in QUALITY}


def other_worlds(work: Path, done: set[str]) -> list[tuple[str, str, Path, Path]]:
    """The simulated worlds the bench does not run, made as :func:`run_all.prepare_runs` makes its own
    (seed 1)."""
    runs = []
    for world in sorted(set(WORLDS) - done):
        bag = work / "sim" / f"{world}-s1"
        if not bag.exists():
            write_run(simulate(get_world(world), SimConfig(), np.random.default_rng(1)), bag)
        runs.append((world, "simulated", bag, bag / "ground_truth.json"))
    return runs


def leak_passes(
    run: RunData, trajectory: np.ndarray, product: Any, reference: Any, *, alignment: dict, config: PtmConfig
) -> dict[str, Any]:
    """The beam passes (as the map drew them) through the map's leaked cells: distance from the sensor
    (quantiles, m), share beyond 5 and 10 m, share by no-return beams."""
    from ptm_ros.model.geometry import interpolate_poses

    leak = leaked_cells(product, reference, theta=alignment["theta"], t=(alignment["x"], alignment["y"]))
    sc, oc = run.scans, config.occupancy
    st = np.asarray(sc.stamps, dtype=float)
    ost = np.asarray(run.odometry.stamps, dtype=float)
    keep = np.flatnonzero((st >= ost[0]) & (st <= ost[-1]))
    poses = interpolate_poses(ost, trajectory, st[keep])

    def field_of(value: Any) -> np.ndarray:
        return np.broadcast_to(np.asarray(value, dtype=float).reshape(-1), st.shape)[keep]

    a0, da, rmax, rmin = (field_of(v) for v in (sc.angle_min, sc.angle_increment, sc.range_max, sc.range_min))
    lo, res = np.asarray(product.origin[:2]), product.resolution
    h, w = leak.shape
    dist, no_return = [], []
    for k, idx in enumerate(keep):
        beams, _ = scan_beams(
            poses[k],
            np.asarray(sc.ranges[idx], dtype=float),
            angle_min=a0[k],
            angle_increment=da[k],
            range_min=rmin[k],
            range_max=rmax[k],
            max_range=oc.max_range,
            missing_ray_length=oc.missing_ray_length,
        )
        if len(beams.ends) == 0:
            continue
        ix, iy, ray = grid_traversal((beams.origin - lo) / res, (beams.ends - lo) / res)
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        ix, iy, ray = ix[inside], iy[inside], ray[inside]
        m = leak[iy, ix]
        centres = (np.column_stack([ix[m], iy[m]]) + 0.5) * res + lo
        dist.append(np.linalg.norm(centres - beams.origin, axis=1))
        no_return.append(~beams.hit[ray[m]])
    d = np.concatenate(dist) if dist else np.zeros(0)
    nr = np.concatenate(no_return) if no_return else np.zeros(0, dtype=bool)
    if len(d) == 0:
        return {"passes": 0}
    return {
        "passes": len(d),
        "distance_quantiles_m": {str(q): float(np.quantile(d, q)) for q in (0.25, 0.5, 0.75, 0.9)},
        "beyond_5m": float(np.mean(d > 5.0)),
        "beyond_10m": float(np.mean(d > 10.0)),
        "no_return": float(np.mean(nr)),
    }


def diagnose(
    run: RunData, truth: GroundTruthTrajectory, result: Any, config: PtmConfig, before_png: Path | None = None
) -> dict[str, Any]:
    """The ``diagnosis`` of the module docstring for one pipeline result (the map of :data:`BEFORE` drawn
    to ``before_png`` when given)."""
    reference = reference_classes(run, truth, config)
    traj = result.trajectory
    if reference is None or traj is None or result.trajectory_error is None:
        return {}
    alignment = result.trajectory_error["alignment"]
    motion = {"theta": alignment["theta"], "t": (alignment["x"], alignment["y"])}
    order = np.argsort(truth.stamps, kind="stable")
    at_truth = grid_along(truth.stamps[order], truth.poses_corrected[order], run.scans, config.occupancy)
    out: dict[str, Any] = {"model": figures(map_quality(class_grid(at_truth, config), reference))}
    stamps = np.asarray(run.odometry.stamps, dtype=float)
    inside = (stamps >= truth.stamps.min()) & (stamps <= truth.stamps.max())
    span = grid_along(stamps[inside], traj[inside], run.scans, config.occupancy)
    out["span"] = figures(map_quality(class_grid(span, config), reference, **motion))
    scan_stamps = np.asarray(run.scans.stamps, dtype=float)
    outside = (scan_stamps < truth.stamps.min()) | (scan_stamps > truth.stamps.max())
    out["scans_outside_span"] = int(np.count_nonzero(outside))
    product = class_grid(grid_along(stamps, traj, run.scans, config.occupancy), config)
    out["passes"] = leak_passes(run, traj, product, reference, alignment=alignment, config=config)
    old = replace(config, occupancy=replace(config.occupancy, **BEFORE))
    before = grid_along(stamps, traj, run.scans, old.occupancy)
    out["before"] = figures(map_quality(class_grid(before, old), reference, **motion))
    if before_png is not None:
        title = f"occupancy model before issue #24 ({', '.join(f'{k} {v:g}' for k, v in BEFORE.items())})"
        save_png(before, MAPS_TMP, trajectory=traj, title=title)
        out["before_png"] = copy_map(MAPS_TMP, before_png).relative_to(BENCH).as_posix()
    return out


def bench_run(name: str, kind: str, bag: Path, gt: Path, work: Path) -> dict[str, Any]:
    config = load_config()
    run = read_run(bag)
    truth = load_ground_truth(gt)
    t0 = time.perf_counter()
    result, row = pipeline_row(name, kind, bag, gt, work / "maps" / name, config, "ptm-rbpf")
    diagnosis = diagnose(run, truth, result, config, before_png=MAPS / f"{name}-before.png")
    rows = [{**row, "figures": copy_map_figures(name, result), "diagnosis": diagnosis}]
    cal = calibrate_run(run, config)
    if cal.time_offset != 0.0:
        used = cal.applied(config)
        dest = work / "maps" / f"{name}-calibrated"
        result, row = pipeline_row(name, kind, bag, gt, dest, used, "ptm-rbpf calibrated")
        rows.append({**row, "figures": copy_map_figures(f"{name}-calibrated", result)})
        rows[-1]["diagnosis"] = diagnose(run, truth, result, used)
    return {
        "run": name,
        "kind": kind,
        "time_offset": cal.time_offset,
        "rows": rows,
        "wall_s": time.perf_counter() - t0,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--worlds", choices=("bench", "all"), default="all", help="simulated worlds: the bench's or all"
    )
    p.add_argument("--only", nargs="*", default=None, help="run names")
    p.add_argument("--work", type=Path, default=REPO / "out" / "bench")
    args = p.parse_args()
    runs = prepare_runs(args.work, args.only)
    if args.worlds == "all":
        extra = other_worlds(args.work, {w for w, _ in SIM_WORLDS})
        runs = [r for r in extra if not args.only or r[0] in args.only] + runs
    out_path = BENCH / "maps_quality.json"
    doc: dict[str, Any] = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": "PYTHONPATH=. .venv/bin/python bench/bench_maps.py",
        "load_average": list(os.getloadavg()),
        "runs": [],
    }
    for name, kind, bag, gt in runs:
        print(f"[maps] {name} ({kind})", flush=True)
        doc["runs"].append(bench_run(name, kind, bag, gt, args.work))
        for r in doc["runs"][-1]["rows"]:
            q = ", ".join(f"{k} {r.get(f'map_{k}')}" for k in QUALITY)
            print(f"[maps]   {r['method']}: {q}; diagnosis {json.dumps(r['diagnosis'])}", flush=True)
        out_path.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
