"""``make bench``: every benchmark of ptm_ros, results written under ``bench/``.

1. Component benchmarks (each writes its own JSON beside this script): the metric likelihood
   (``bench_odometry.py``), log P(T|Z) (``bench_posterior.py``), the particle filter (``bench_rbpf.py``),
   MCMC (``bench_mcmc.py``), the surprise detectors (``bench_surprise.py``), the node suite's CPU and
   memory over DDS (``bench_nodes.py``), the map publisher's online occupancy map against ``ptm-run``'s
   (``bench_online_map.py``) and the calibration of the MAP probability over simulated aliased worlds and
   their controls (``bench_calibration.py``: ``calibration.{json,md,png}``, about an hour on one core,
   resumable) and corrupted bags through ``ptm-run``/``ptm-eval`` with a larger budget than the test's
   (``bench_fuzz.py``: ``fuzz.json``), the laser fitness densities and the registration outlier
   probability fitted leave one run out (``bench_fitness_loo.py``: ``fitness_loo.{json,md}``, summarised
   in ``results.md``) and the model's odometry noise against the real errors
   (``bench_odometry_noise.py``: ``odometry_noise.{json,md}``),
   ``make demo``'s world over 20 seeds (``bench_demo.py``: ``demo_seeds.{json,md}``), the laser time
   offset learned from simulated and real runs (``bench_time_offset.py``: ``time_offset.{json,md}``) and the
   occupancy maps of every simulated world and real run against their references (``bench_maps.py``:
   ``maps_quality.json``, summarised in ``results.md``) and why the MAP misses same-place pairs on the
   real runs (``bench_missed_pairs.py``: ``missed_pairs.{json,md}``) and the real runs' logs made
   unlike themselves, a laser at half the rate and drifting wheels (``bench_perturbed_runs.py``:
   ``perturbed_runs.{json,md}``), the laser odometry over a family of small perturbations
   (``bench_laser_odometry.py``: ``laser_odometry.{json,md}``), the filter against MCMC on the real runs
   (``bench_filter_vs_batch.py``: ``filter_vs_batch.{json,md}``), the heading noise and the laser
   registrations against the truth (``bench_heading_noise.py``: ``heading_noise.{json,md}``) and each wrong
   merge of the perturbed real runs decomposed by the batch model (``bench_wrong_merges.py``:
   ``wrong_merges.{json,md}``) and the odometry check on those runs, reported and used
   (``bench_translation_noise.py``: ``translation_noise.{json,md}``), when present.
2. The pipeline on every simulated world and on every real run in ``../shared/datasets`` (when
   present), scored against ground truth beside two reference methods a user might use instead:
   greedy nearest-neighbour data association on odometry and robust pose-graph loop closure over the
   landmark patches (:mod:`ptm_ros.scoring.baselines`); for the pipeline also the absolute trajectory errors
   of the smoothed MAP trajectory and of the raw odometry (``ate_smoothed_m``, ``ate_odometry_m``) and the
   route graph's edge segments through the walls of the run's own map (``route_edges_crossing_walls``,
   recorded, not asserted) and the map's quality against the same scans at the ground-truth poses
   (``map_leak``, ``map_free_area_ratio``, ``map_wall_precision``, ``map_wall_recall``:
   :mod:`ptm_ros.maps.map_quality`, issue #24). Every
   run with scans is also calibrated for the laser's time offset (``ptm-calibrate``, no ground truth);
   where it chooses a non-zero offset the pipeline runs again with it (``ptm-rbpf calibrated``). Every
   run is also replayed with landmarks fixed in the environment (``--detector ground-truth``: a
   simulated world's own places, on a real run landmarks placed every 5 m along the true path, the
   protocol of the thesis' Intel experiment, Ch. 4.5), with the filter (``ptm-rbpf gt-landmarks``) and, on the
   real runs, with MCMC (``ptm-mcmc gt-landmarks``; the thesis used MC³ there). Writes
   ``bench/results.json``, ``bench/results.md`` and the occupancy maps of every run,
   ``bench/maps/<run>.png``, with the map beside its reference, ``bench/maps/<run>-vs-reference.png``
   (the report's ``map_comparison.png``; both downscaled to at most 300 kB; ``<run>-calibrated…`` for
   the calibrated rerun).

``--only NAME ...`` restricts both parts to the named runs and component scripts (e.g.
``--only intel``, ``--only bench_nodes.py``).

    PYTHONPATH=. .venv/bin/python bench/run_all.py [--skip-components] [--only NAME ...] [--work out/bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import itertools
import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
DATASETS = REPO.parent / "shared" / "datasets"
MAPS = BENCH / "maps"
MAX_MAP_BYTES = 300_000
COMPONENTS = (
    "bench_odometry.py",
    "bench_posterior.py",
    "bench_rbpf.py",
    "bench_filter.py",
    "bench_mcmc.py",
    "bench_surprise.py",
    "bench_nodes.py",
    "bench_online_map.py",
    "bench_calibration.py",
    "bench_fuzz.py",
    "bench_fitness_loo.py",
    "bench_odometry_noise.py",
    "bench_maps.py",
    "bench_demo.py",
    "bench_time_offset.py",
    "bench_missed_pairs.py",
    "bench_perturbed_runs.py",
    "bench_laser_odometry.py",
    "bench_filter_vs_batch.py",
    "bench_heading_noise.py",
    "bench_wrong_merges.py",
    "bench_translation_noise.py",
)
SIM_WORLDS = (("aliased-loop", 1), ("two-loop", 1), ("multi-loop", 1))
REAL_RUNS = (
    ("intel", "intel/intel-raw-910.clf.gz", "intel/intel-gt-910.txt"),
    ("aces", "aces/aces-raw-440.clf.gz", "aces/aces-gt-440.txt"),
    ("mit-csail", "mit-csail/mit-csail.clf.gz", "mit-csail/mit-csail-gt-406.txt"),
)


def ptm_run_scored(bag: Path, truth: Path, out: Path, *options: str) -> tuple[Any, dict[str, Any]] | str:
    """``ptm-run BAG --out OUT --ground-truth TRUTH OPTIONS`` in this process, its output captured: the
    PTM it wrote and its score against ``truth`` (``Score.as_dict(per_topology=False)``), or the end of its
    output when it failed."""
    import contextlib
    import io

    from ptm_ros.model.ptm import load_ptm
    from ptm_ros.tools import run as ptm_run
    from ptm_ros.tools.outputs import score_against

    log = io.StringIO()
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        code = ptm_run.main([str(bag), "--out", str(out), "--ground-truth", str(truth), *options])
    if code != 0:
        return log.getvalue()[-1000:]
    ptm = load_ptm(out / "ptm.json")
    return ptm, score_against(ptm, truth).as_dict(per_topology=False)


def shared_data_ready(tag: str, *dirs: Path) -> bool:
    """Whether ``../shared/datasets`` is here (else a line saying so, under ``[tag]``), with ``dirs`` made:
    the start of every benchmark on the shared real runs."""
    if not (DATASETS / "README.md").is_file():
        print(f"[{tag}] {DATASETS} absent: nothing to do", flush=True)
        return False
    for d in dirs:
        d.mkdir(parents=True, exist_ok=True)
    return True


def when_and_where(t0: float) -> dict[str, Any]:
    """A benchmark record's ``generated`` (local time), ``machine`` and ``minutes`` since ``t0``
    (:func:`time.perf_counter`)."""
    import platform

    return {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": platform.platform(),
        "minutes": (time.perf_counter() - t0) / 60.0,
    }


def write_bench(doc: dict, out: Path, write_md: Callable[[dict, Path], None]) -> None:
    """A benchmark's record: ``doc`` to ``out`` (JSON) and its markdown (``write_md``) beside it, printed."""
    out.write_text(json.dumps(doc, indent=1))
    write_md(doc, out.with_suffix(".md"))
    print(out.with_suffix(".md").read_text())


def pair_calibration_section(groups: Mapping[str, Sequence[Mapping[str, Any]]], pooled: str) -> list[str]:
    """A markdown section: per group (label -> records holding ``ptm-eval``'s ``pair_calibration``), the
    pooled pair calibration (:class:`ptm_ros.scoring.evaluation.PairReliability`); ``pooled`` says over what
    (e.g. "pooled over seeds"). Empty without a record."""
    from ptm_ros.tools.evaluate import pooled_pairs

    tables = {label: pooled_pairs(rs) for label, rs in groups.items() if rs}
    if not tables:
        return []
    edges = next(iter(tables.values())).edges
    mids = [f"{lo:g}–{hi:g}" for lo, hi in itertools.pairwise(edges[1:-1])]
    lines = [
        "",
        "## Pair calibration",
        "",
        "How often the visit pairs the PTM states at each P(same place) are one place in truth (`ptm-eval`'s "
        "`pair_calibration`; scored pairs: same < 1.5 m, different > 4 m, outside the chains of visits no "
        f"topology can score right), {pooled}. "
        "*Doubtful*: pairs stated between 0.02 and 0.98; *gap*: their ECE (the pair-weighted mean over the "
        "middle bins of |share one place − mean stated P|); *confident false merges*: different pairs stated "
        "≥ 0.98; *confident misses*: same pairs stated < 0.02. Middle bins: share one place / mean stated P "
        "(pairs). The pairs of one run are not independent (one merge decides many).",
        "",
        "| group | pairs | same | doubtful | gap | confident false merges | confident misses | "
        + " | ".join(mids)
        + " |",
        "|---|---|---|---|---|---|---|" + "---|" * len(mids),
    ]
    for label, t in tables.items():
        cells = [
            label,
            str(sum(t.count)),
            str(sum(t.same)),
            str(t.doubtful),
            "–" if not t.doubtful else f"{t.doubtful_gap:.2f}",
            str(t.confident_false_merges),
            str(t.confident_misses),
        ]
        cells += [
            "–" if not b.count else f"{b.accuracy:.2f} / {b.mean_probability:.2f} ({b.count})"
            for b in t.bins[1:-1]
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def run_components(names: list[str] | None) -> list[dict]:
    out = []
    for script in COMPONENTS:
        path = BENCH / script
        if not path.is_file() or (names and script not in names):
            continue
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, str(path)], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, check=False
        )
        out.append({"script": script, "exit_code": proc.returncode, "wall_s": time.perf_counter() - t0})
        print(f"[bench] {script}: exit {proc.returncode} in {out[-1]['wall_s']:.1f} s", flush=True)
    return out


def prepare_runs(work: Path, only: list[str] | None) -> list[tuple[str, str, Path, Path]]:
    """(name, kind, bag, ground truth) of every run to benchmark; bags are made once under ``work``."""
    from ptm_ros.io.simulator import SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world
    from ptm_ros.tools.convert import convert

    runs = []
    for world, seed in SIM_WORLDS:
        if only and world not in only:
            continue
        bag = work / "sim" / f"{world}-s{seed}"
        if not bag.exists():
            write_run(simulate(get_world(world), SimConfig(), np.random.default_rng(seed)), bag)
        runs.append((world, "simulated", bag, bag / "ground_truth.json"))
    if not (DATASETS / "README.md").is_file():
        print(f"[bench] {DATASETS} absent: real runs skipped", flush=True)
        return runs
    for name, log, gt in REAL_RUNS:
        if only and name not in only:
            continue
        bag = work / "real" / name
        if not bag.exists():
            bag.parent.mkdir(parents=True, exist_ok=True)
            convert(DATASETS / log, bag)
        runs.append((name, "real", bag, DATASETS / gt))
    return runs


def single_topology_ptm(visits, labels, method: str):
    from ptm_ros.model.ptm import Landmark, make_ptm

    landmarks = [Landmark(v.index, v.stamp, v.pose) for v in visits]
    return make_ptm(landmarks, {tuple(labels): 1.0}, inference={"method": method})


def score_row(score) -> dict:
    s = score.as_dict(per_topology=False)
    keys = (
        "n_visits",
        "n_true_places",
        "map_f1",
        "map_precision",
        "map_recall",
        "posterior_f1",
        "consistent_mass",
        "attainable_consistent_mass",
        "n_contradictory_pairs",
        "true_topology_mass",
        "n_scored_pairs",
        "n_same_pairs",
    )
    return {k: s.get(k) for k in keys}


def copy_map(src: Path, dst: Path, max_bytes: int = MAX_MAP_BYTES) -> Path:
    """Copy a PNG, downscaled (area averaging, 80 % per step) until it is at most ``max_bytes``."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    if dst.stat().st_size <= max_bytes:
        return dst
    import cv2

    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    scale = 1.0
    while dst.stat().st_size > max_bytes and scale > 0.1:
        scale *= 0.8
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst), small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return dst


def pipeline_row(name: str, kind: str, bag: Path, gt: Path, out: Path, config, method: str):  # noqa: PLR0917
    """``ptm-run``'s pipeline on one run with ``config``, with ``ptm-run``'s worker processes (one per
    CPU): its result and its results row."""
    from ptm_ros.tools.pipeline import run_offline

    t0 = time.perf_counter()
    result = run_offline(bag, out, config, ground_truth=gt, jobs=os.cpu_count() or 1)
    wall = time.perf_counter() - t0
    row = {"run": name, "kind": kind, "method": method, "wall_s": wall, **score_row(result.score)}
    row["time_offset_s"] = config.laser_odometry.time_offset
    row["map_places"] = len(set(result.ptm.topologies[0].labels))
    row["update_ms_median"] = result.ptm.inference.get("update_ms_median")
    row["update_ms_p95"] = result.ptm.inference.get("update_ms_p95")
    ate = result.trajectory_error or {}
    row["ate_smoothed_m"] = ate.get("ate_smoothed_m")
    row["ate_odometry_m"] = ate.get("ate_odometry_m")
    row["map_s"] = result.ptm.timing.get("map_s")
    row["route_edges_crossing_walls"] = route_edges_crossing_walls(result.files)
    row.update(map_quality_row(result.ptm.extra.get("map_quality")))
    return result, row


#: The map-quality figures of a results row (``map_<key>``: the keys of ptm.json's ``map_quality``).
MAP_QUALITY_KEYS = ("leak", "free_area_ratio", "wall_precision", "wall_recall")


def map_quality_row(quality: Mapping | None) -> dict:
    """``map_leak``, ``map_free_area_ratio``, ``map_wall_precision``, ``map_wall_recall`` of ptm.json's
    ``map_quality`` (:mod:`ptm_ros.maps.map_quality`; None without a map or a ground truth)."""
    return {f"map_{k}": (quality or {}).get(k) for k in MAP_QUALITY_KEYS}


def copy_map_figures(name: str, result) -> dict:
    """``map.png`` and the report's side-by-side ``map_comparison.png`` of a pipeline result copied to
    ``bench/maps/<name>.png`` and ``bench/maps/<name>-vs-reference.png`` (downscaled, :func:`copy_map`);
    their paths relative to ``bench/`` (``map_png``, ``map_comparison_png``), those that exist."""
    from ptm_ros.reporting.report import MAP_COMPARISON

    out = {}
    if "map_png" in result.files:
        out["map_png"] = copy_map(result.files["map_png"], MAPS / f"{name}.png")
    if result.report_path is not None and (result.report_path.parent / MAP_COMPARISON).is_file():
        src = result.report_path.parent / MAP_COMPARISON
        out["map_comparison_png"] = copy_map(src, MAPS / f"{name}-vs-reference.png")
    return {k: v.relative_to(BENCH).as_posix() for k, v in out.items()}


def route_edges_crossing_walls(files: Mapping[str, Path]) -> int | None:
    """Edge segments of the written ``route_graph.geojson`` that cross occupied cells of the run's own
    ``map.yaml`` (:func:`ptm_ros.maps.routes.crossing_segments`, issue #24); None without a map. Recorded,
    not asserted."""
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.occupancy import load_map
    from ptm_ros.maps.routes import crossing_segments

    if "map_yaml" not in files or "route_graph" not in files:
        return None
    grid = load_map(files["map_yaml"])
    doc = json.loads(Path(files["route_graph"]).read_text())
    return crossing_segments(doc, ClassGrid(grid.classes(), grid.origin, grid.resolution))


def bench_run(name: str, kind: str, bag: Path, gt: Path, work: Path) -> dict:
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.scoring.baselines import (
        GreedyConfig,
        LoopClosureConfig,
        greedy_association,
        robust_loop_closure,
    )
    from ptm_ros.tools.calibrate import calibrate_run
    from ptm_ros.tools.evaluate import score_against_ground_truth
    from ptm_ros.tools.pipeline import detect_visits, make_registrar

    config = load_config()
    result, row = pipeline_row(name, kind, bag, gt, work / "out" / name, config, "ptm-rbpf")
    rows = [row]
    out = {
        "run": name,
        "rows": rows,
        "figures": [{"method": row["method"], **copy_map_figures(name, result)}],
    }
    run = read_run(bag)
    if run.scans is not None:  # the laser's time offset, from the bag alone (ptm-calibrate)
        t0 = time.perf_counter()
        cal = calibrate_run(run, config)
        out["calibration"] = {**cal.as_dict(), "wall_s": time.perf_counter() - t0}
        if cal.time_offset != 0.0:
            dest = work / "out" / f"{name}-calibrated"
            result, row = pipeline_row(name, kind, bag, gt, dest, cal.applied(config), "ptm-rbpf calibrated")
            rows.append(row)
            out["figures"].append({"method": row["method"], **copy_map_figures(f"{name}-calibrated", result)})
    fixed = replace(config, detector=replace(config.detector, kind="ground-truth"))
    methods = [("rbpf", "ptm-rbpf gt-landmarks")] + (
        [("mcmc", "ptm-mcmc gt-landmarks")] if kind == "real" else []
    )
    for method, label in methods:
        cfg = replace(fixed, inference=replace(fixed.inference, method=method))
        _, row = pipeline_row(name, kind, bag, gt, work / "out" / f"{name}-gt-{method}", cfg, label)
        rows.append(row)
    visits = detect_visits(run, config)
    t0 = time.perf_counter()
    labels = greedy_association(visits, config.model.odometry, GreedyConfig())
    wall = time.perf_counter() - t0
    score = score_against_ground_truth(single_topology_ptm(visits, labels, "greedy"), gt)
    rows.append(
        {
            "run": name,
            "kind": kind,
            "method": "greedy-nn",
            "wall_s": wall,
            **score_row(score),
            "map_places": len(set(labels)),
        }
    )
    t0 = time.perf_counter()
    registrar = make_registrar(visits, config)
    labels, _details = robust_loop_closure(
        visits, config.model.odometry, config.laser, LoopClosureConfig(), registrar=registrar
    )
    wall = time.perf_counter() - t0
    score = score_against_ground_truth(single_topology_ptm(visits, labels, "robust-loop-closure"), gt)
    rows.append(
        {
            "run": name,
            "kind": kind,
            "method": "robust-loop-closure",
            "wall_s": wall,
            **score_row(score),
            "map_places": len(set(labels)),
        }
    )
    return out


def fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def write_results(components: list[dict], runs: list[dict]) -> None:
    doc = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "load_average": os.getloadavg(),
        "components": components,
        "runs": runs,
    }
    (BENCH / "results.json").write_text(json.dumps(doc, indent=1) + "\n")
    cols = (
        "run",
        "method",
        "time_offset_s",
        "n_visits",
        "n_true_places",
        "map_places",
        "map_f1",
        "posterior_f1",
        "consistent_mass",
        "attainable_consistent_mass",
        "true_topology_mass",
        "ate_smoothed_m",
        "ate_odometry_m",
        "wall_s",
        "update_ms_median",
        "update_ms_p95",
    )
    lines = [
        "# ptm_ros benchmark results",
        "",
        f"Generated {doc['generated']} by `make bench` (`bench/run_all.py`); load average "
        f"{', '.join(f'{x:.1f}' for x in doc['load_average'])} on this 2-core machine.",
        "",
        "Scores against ground truth (same place < 1.5 m, different > 4 m): `map_f1` of the most probable "
        "topology, `posterior_f1` from expected pair counts, `consistent_mass` = mass with no scored pair "
        "wrong, `attainable_consistent_mass` = the same outside pairs no topology can score right (a < 1.5 m "
        "chain of visits spanning > 4 m; `n_contradictory_pairs` in results.json). Reference methods "
        "commit to one topology (probability 1). `ate_smoothed_m` / "
        "`ate_odometry_m`: absolute trajectory error (RMSE after the best rigid 2-D alignment, m) of the "
        "smoothed trajectory of the most probable topology and of the raw odometry, at the odometry stamps "
        "inside the ground truth's span. `wall_s` includes the occupancy map (`map_s` in results.json) "
        "and the report, with `ptm-run`'s worker processes (one per CPU). "
        "`ptm-rbpf` runs with the default parameters; `ptm-rbpf calibrated` (only where the calibration "
        "below chose a non-zero offset) with `laser_odometry.time_offset` = `time_offset_s` (s) from "
        "`ptm-calibrate`, everything else default. `gt-landmarks`: landmarks fixed in the environment "
        "(`ptm-run --detector ground-truth`: the simulated world's places; on the real runs landmarks "
        "placed every 5 m along the true path, visited within 1 m, as in the thesis' Intel experiment, "
        "Ch. 4.5 and Fig. 57: 63 visits, 72 % of the mass on the true topology with MC³), defaults "
        "otherwise; "
        "`true_topology_mass` = mass of the exactly-true topology (visits of one landmark share a label).",
        "",
        "| " + " | ".join(cols) + " |",
        "|" + "---|" * len(cols),
    ]
    for run in runs:
        for r in run["rows"]:
            lines.append("| " + " | ".join(fmt(r.get(c)) for c in cols) + " |")
    cals = [(run["run"], run["calibration"]) for run in runs if run.get("calibration")]
    if cals:
        lines += ["", "## Laser time offset (`ptm-calibrate`, no ground truth)", ""]
        lines += [
            "RMS of the laser odometry's per-scan heading corrections (mrad) with the scans taken `offset` s "
            "from their stamps; the chosen offset has the smallest RMS, if it is at least 5 % below the "
            "RMS at 0 (`ptm_ros.perception.laser_odometry.best_time_offset`).",
            "",
        ]
        offsets = [s["offset"] for s in cals[0][1]["offsets"]]
        lines += ["| run | scans | " + " | ".join(f"{o:g}" for o in offsets) + " | chosen | wall_s |"]
        lines += ["|" + "---|" * (len(offsets) + 4)]
        for name, cal in cals:
            rms = {s["offset"]: s["rms_yaw_correction"] for s in cal["offsets"]}
            cells = [fmt(None if rms.get(o) is None else 1e3 * rms[o]) for o in offsets]
            lines.append(
                f"| {name} | {cal['scans']} | " + " | ".join(cells) + f" | {cal['time_offset']:g} | "
                f"{cal['wall_s']:.1f} |"
            )
    lines += map_section(runs)
    lines += maps_quality_section(BENCH / "maps_quality.json")
    lines += loo_section(BENCH / "fitness_loo.json")
    lines += ["", "Component benchmarks (their own JSON files beside this one):", ""]
    lines += [f"- `{c['script']}`: exit {c['exit_code']}, {c['wall_s']:.1f} s" for c in components]
    (BENCH / "results.md").write_text("\n".join(lines) + "\n")


def map_section(runs: list[dict]) -> list[str]:
    """The occupancy maps of every run (simulated and real): their quality against the reference, per
    pipeline row with a map, and the figures (the map, and the map beside its reference)."""
    rows = [r for run in runs for r in run["rows"] if r.get("map_leak") is not None]
    maps = [(run["run"], f) for run in runs for f in run.get("figures", ()) if f.get("map_png")]
    if not rows and not maps:
        return []
    lines = ["", "## Occupancy maps against the reference (issue #24)", ""]
    lines += [
        "The map (`ptm-run`'s `map.pgm`: scans placed along the smoothed trajectory of the most probable "
        "topology) against a reference made of the same scans at the ground-truth poses, with only the "
        "beams that returned, carried onto it by the ATE alignment (`ptm_ros.maps.map_quality`): "
        "`leak` = share "
        "of the map's free cells more than 0.3 m from every cell the reference saw (issue: <= 0.02); "
        "`free_area_ratio` = the map's free area over the reference's (issue: 0.8-1.25); wall precision / "
        "recall = share of the map's occupied cells within 0.2 m of a reference wall / of the reference's "
        "walls within 0.2 m of one of the map's; `route_edges_crossing_walls` = route-graph edge segments "
        "through the map's own walls.",
        "",
    ]
    if rows:
        cols = ("run", "method", "time_offset_s", *(f"map_{k}" for k in MAP_QUALITY_KEYS))
        cols += ("ate_smoothed_m", "route_edges_crossing_walls")
        lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    if maps:
        lines += [
            "",
            "Figures: the map (`map.png`) and the map beside its reference (the report's "
            "`map_comparison.png`: leaked free cells in red), at the default parameters and, where the "
            "calibration chose an offset, calibrated.",
            "",
        ]
        for name, f in maps:
            figs = [f"[map]({f['map_png']})"]
            if f.get("map_comparison_png"):
                figs.append(f"[beside the reference]({f['map_comparison_png']})")
            lines.append(f"- {name} ({f['method']}): " + ", ".join(figs))
        lines.append("")
        lines += [
            f"![{name} ({f['method']})]({f.get('map_comparison_png') or f['map_png']})" for name, f in maps
        ]
    return lines


def maps_quality_section(path: Path) -> list[str]:
    """Every simulated world's and real run's map quality (``bench_maps.py``'s JSON): the map at the
    default parameters (and calibrated), the same occupancy model at the true poses, the model before
    issue #24 on the same trajectory."""
    if not path.is_file():
        return []
    doc = json.loads(path.read_text())
    lines = [
        "",
        "### Every simulated world and real run (`bench/bench_maps.py`)",
        "",
        f"`bench/maps_quality.json` (generated {doc['generated']}; `bench/maps_quality.md` discusses it): "
        "leak, free-area ratio, wall precision and recall of the map; `model leak` = the same occupancy "
        "model with the scans at the true poses (what the ray model alone leaks); `before` = the model at "
        "the start of issue #24 on the same trajectory (maps `bench/maps/<run>-before.png`).",
        "",
        "| run | method | leak | free-area ratio | wall precision | wall recall | ATE (m) | model leak "
        "| before: leak | before: free-area ratio |",
        "|" + "---|" * 10,
    ]
    for run in doc["runs"]:
        for r in run["rows"]:
            d = r.get("diagnosis") or {}
            cells = [r.get(f"map_{k}") for k in MAP_QUALITY_KEYS] + [r.get("ate_smoothed_m")]
            cells += [(d.get("model") or {}).get("leak")]
            cells += [(d.get("before") or {}).get(k) for k in ("leak", "free_area_ratio")]
            lines.append(f"| {run['run']} | {r['method']} | " + " | ".join(fmt(c) for c in cells) + " |")
    return lines


#: The key of the simulated worlds' counts in ``bench_fitness_loo.py``'s JSON (not fitted on the real runs).
SIMULATED = "simulated"
#: The column of each row label of ``bench_fitness_loo.py``'s held-out runs in ``results.md``.
LOO_HEADERS = {"defaults": "in-sample (defaults)", "leave-one-out": "leave-one-out (densities)"}


def outlier_table(doc: Mapping) -> list[str]:
    """ε per fitting set of ``bench_fitness_loo.py``'s JSON, beside the default, with its counts."""
    from ptm_ros.model.odometry import OdometryConfig

    return [
        "| fitted on | ε | aliases / valid |",
        "|---|---|---|",
        f"| defaults (`OdometryConfig`) | {OdometryConfig().registration_outlier} | – |",
        *(
            f"| {name} | {f['registration_outlier']:.3f} | {f['aliases']}/{f['valid']} |"
            for name, f in doc["outlier_fits"].items()
        ),
    ]


def loo_section(path: Path) -> list[str]:
    """The leave-one-run-out figures of the constants fitted on the real runs (``bench_fitness_loo.py``'s
    JSON), beside the in-sample ones: ε per fitting set, and mean MAP F1 over its seeds per held-out run."""
    if not path.is_file():
        return []
    doc = json.loads(path.read_text())
    lines = [
        "",
        "## Constants fitted on the real runs, leave one run out",
        "",
        "The laser fitness densities (`laser.fitness_*`) and the registration outlier probability ε "
        "(`model.odometry.registration_outlier`) were fitted on Intel, ACES and MIT-CSAIL. Each run is "
        "scored with those fitted on the other two (`bench/fitness_loo.md`, "
        f"generated {doc['generated']}).",
    ]
    if "outlier_fits" in doc:
        sim = doc["outlier_counts"][SIMULATED]
        lines += [
            "",
            "ε is the fraction of the valid registrations of one-place pairs off the true relative pose by > "
            f"{doc['alias']['max_xy_m']} m or > {doc['alias']['max_yaw_rad']} rad, the simulated worlds' "
            f"{sim['aliases']}/{sim['valid']} included in every fit:",
            "",
            *outlier_table(doc),
        ]
    labels = list(dict.fromkeys(r["densities"] for r in doc["runs"]))
    lines += [
        "",
        f"Mean MAP F1 (precision) over seeds {sorted({r['seed'] for r in doc['runs']})}, in-sample (the "
        "defaults) and leave-one-out:",
        "",
        "| run | " + " | ".join(LOO_HEADERS.get(x, x) for x in labels) + " |",
        "|---|" + "---|" * len(labels),
    ]
    for run in dict.fromkeys(r["run"] for r in doc["runs"]):
        cells = []
        for label in labels:
            rs = [r for r in doc["runs"] if r["run"] == run and r["densities"] == label and "map_f1" in r]
            f1 = np.mean([r["map_f1"] for r in rs]) if rs else float("nan")
            pr = np.mean([r["map_precision"] for r in rs]) if rs else float("nan")
            cells.append(f"{f1:.3f} ({pr:.3f})")
        lines.append(f"| {run} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-components", action="store_true")
    parser.add_argument("--only", nargs="*", default=None, help="run names / component scripts to run")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "bench")
    args = parser.parse_args()
    components = [] if args.skip_components else run_components(args.only)
    runs = []
    for name, kind, bag, gt in prepare_runs(args.work, args.only):
        print(f"[bench] pipeline on {name} ({kind})", flush=True)
        runs.append(bench_run(name, kind, bag, gt, args.work))
        for r in runs[-1]["rows"]:
            print(
                f"[bench]   {r['method']:>20}: MAP F1 {fmt(r.get('map_f1'))}, "
                f"posterior F1 {fmt(r.get('posterior_f1'))}, {r['wall_s']:.1f} s",
                flush=True,
            )
        write_results(components, runs)
    write_results(components, runs)


if __name__ == "__main__":
    main()
