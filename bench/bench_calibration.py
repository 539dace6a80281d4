"""Calibration benchmark (issue #23, "an honest posterior"): is the stated MAP probability honest?

For every world family of :data:`ptm_ros.io.worlds.CALIBRATION_FAMILIES` (``loop``, ``ring``,
``twin-rooms``, ``room-row``), its aliased world and its control (same geometry, distinct textures), every
odometry noise level of :data:`NOISE_LEVELS` (from half the simulator's default to twice the model's,
plus a systematic scale error and a systematic heading drift) and seeds 0, 1, ...: simulate the world's
default route (:func:`ptm_ros.io.simulator.simulate`, default sensors), run ``ptm-run`` on the bag at the
default parameters (default detector for a bag with scans; ``--no-map --no-report``) and score the
``ptm.json`` with :func:`ptm_ros.tools.evaluate.calibration_record`: the MAP probability, whether the MAP
topology is exactly the true one, the consistent mass and the mass on the true topology.

Figures (:func:`ptm_ros.scoring.evaluation.calibration_summary`) overall, per family, per family x variant,
per variant and per noise level: ECE (10 equal-width bins) and its chance level (a calibrated mapper's mean
ECE on the same stated probabilities), Brier score, overconfident failures (consistent mass < 0.05),
mean mass on the true topology, MAP-right rate against the mean stated MAP probability, and the failing
MAPs' kind (false merges only, missed merges only, both); and the pair calibration (``ptm-eval``'s
``pair_calibration``: how often the visit pairs stated at each P(same place) are one place), pooled over all
runs and per family x variant. Writes ``--out`` (``bench/calibration.json``),
``bench/calibration.md`` and the reliability diagram ``bench/calibration.png`` (beside ``--out``).

The runs are taken seed-major over the grid (all cells with seed 0, then seed 1, ...), so ``--runs N``
covers the grid evenly; ``--quick`` is a smoke test (one run per world unless ``--runs``). Each finished
run is appended to ``WORK/records.jsonl`` and skipped when the benchmark is started again (resume after an
interruption; ``--fresh`` starts over). Bags are deleted after their run unless ``--keep-bags``.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python bench/bench_calibration.py [--runs 240] [--quick]
        [--jobs 1] [--out bench/calibration.json] [--work out/calibration]
        [--params FILE] [--families NAME ...] [--noise LEVEL ...]

``--params FILE`` runs ``ptm-run --params FILE`` instead of the defaults (a diagnostic: e.g. without the
laser odometry), its records kept apart under ``WORK/full-<stem>``. ``--scan-rate HZ`` and
``--panorama-spacing M`` simulate other sensors than the simulator's (10 Hz scans, a panorama every metre:
0.5 Hz at its 0.5 m/s), e.g. 5 Hz and 0.5 m (1 Hz), the rates of a held-out check; their records are kept
apart under ``WORK/full-scan<HZ>-pano<M>``. ``--noise 4x-model`` runs a level of :data:`STRESS_LEVELS`,
outside the default grid: wheel odometry four times noisier than the model assumes.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import io
import json
import platform
import shutil
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from run_all import pair_calibration_section

from ptm_ros.io.simulator import OdometryNoiseConfig, SimConfig
from ptm_ros.scoring.evaluation import CalibrationSummary

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
DEFAULT_RUNS = 240
#: Seed of the chance-level redraws.
CHANCE_SEED = 2026

_SIM = OdometryNoiseConfig()
#: Odometry noise levels, from below the simulator's defaults to twice the model's (OdometryConfig:
#: 5 cm/√m translation, 0.05 rad/√rad turning, 0.02 rad/√m heading per metre), and two systematic errors.
NOISE_LEVELS: dict[str, OdometryNoiseConfig] = {
    "half-sim": OdometryNoiseConfig(trans=0.015, rot=0.0025, turn=0.01, bias_init=2.5e-4, bias_walk=5e-5),
    "sim": _SIM,
    "model": OdometryNoiseConfig(trans=0.05, rot=0.02, turn=0.05, bias_init=5e-4, bias_walk=1e-4),
    "twice-model": OdometryNoiseConfig(trans=0.1, rot=0.04, turn=0.1, bias_init=1e-3, bias_walk=2e-4),
    "scale+3%": OdometryNoiseConfig(**{**asdict(_SIM), "scale": 0.03}),
    "drift-5mrad/m": OdometryNoiseConfig(**{**asdict(_SIM), "bias_mean": 0.005}),
}
#: Levels beyond the default grid (``--noise`` only): how the posterior fares on a robot far noisier than
#: the model assumes.
STRESS_LEVELS: dict[str, OdometryNoiseConfig] = {
    "4x-model": OdometryNoiseConfig(trans=0.2, rot=0.08, turn=0.2, bias_init=2e-3, bias_walk=4e-4),
}


@dataclass(frozen=True)
class Case:
    """One run of the grid."""

    family: str
    variant: str  # "aliased" or "control"
    world: str
    noise: str
    seed: int

    @property
    def key(self) -> str:
        """Unique name of the run (its directory under the work directory)."""
        return f"{self.world}__{self.noise}__s{self.seed}"


CASE_KEYS = ("family", "variant", "world", "noise", "seed")


@dataclass(frozen=True)
class Sensors:
    """Sensor rates other than the simulator's: scans per second, metres of travel between panoramas."""

    scan_rate: float
    panorama_spacing: float

    @property
    def tag(self) -> str:
        """The suffix of the work directory of runs with these sensors."""
        return f"scan{self.scan_rate:g}-pano{self.panorama_spacing:g}"


def grid(
    runs: int,
    quick: bool = False,
    families: Sequence[str] | None = None,
    noise_levels: Sequence[str] | None = None,
) -> list[Case]:
    """The first ``runs`` cases, seed-major over families x variants x noise levels (``quick``: the
    simulator's noise level only; ``families`` / ``noise_levels`` restrict the grid)."""
    from ptm_ros.io.worlds import CALIBRATION_FAMILIES

    levels = list(noise_levels) if noise_levels else ["sim"] if quick else list(NOISE_LEVELS)
    cells = [
        (family, variant, world, noise)
        for noise in levels
        for family, pair in CALIBRATION_FAMILIES.items()
        if not families or family in families
        for variant, world in zip(("aliased", "control"), pair, strict=True)
    ]
    out: list[Case] = []
    seed = 0
    while len(out) < runs:
        out += [Case(f, v, w, n, seed) for f, v, w, n in cells][: runs - len(out)]
        seed += 1
    return out


def noise_level(name: str) -> OdometryNoiseConfig:
    """The odometry noise of a level of :data:`NOISE_LEVELS` or :data:`STRESS_LEVELS`."""
    return {**NOISE_LEVELS, **STRESS_LEVELS}[name]


def levels_of(rows: Sequence[Mapping[str, Any]]) -> dict[str, OdometryNoiseConfig]:
    """The default grid's noise levels and any stress level that ``rows`` ran."""
    used = {r["noise"] for r in rows}
    return {**NOISE_LEVELS, **{k: v for k, v in STRESS_LEVELS.items() if k in used}}


def sim_config(case: Case, sensors: Sensors | None = None) -> SimConfig:
    """The simulator's configuration of a case: its odometry noise level, and ``sensors`` (or the
    simulator's own scan rate and panorama spacing)."""
    config = SimConfig(odometry=noise_level(case.noise))
    if sensors is None:
        return config
    laser = replace(config.laser, rate=sensors.scan_rate)
    camera = replace(config.camera, spacing=sensors.panorama_spacing)
    return replace(config, laser=laser, camera=camera)


def run_case(
    case: Case, work: str, keep_bags: bool, params: str | None = None, sensors: Sensors | None = None
) -> dict[str, Any]:
    """Simulate (with ``sensors``, or the simulator's), ``ptm-run`` at default parameters (or with
    ``--params params``), score: the case's record (JSON values)."""
    from ptm_ros.io.simulator import simulate, write_run
    from ptm_ros.io.worlds import get_world
    from ptm_ros.model.ptm import load_ptm
    from ptm_ros.tools import run as ptm_run
    from ptm_ros.tools.evaluate import calibration_record

    t0 = time.perf_counter()
    root = Path(work) / case.key
    bag, out = root / "bag", root / "out"
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    sim = simulate(get_world(case.world), sim_config(case, sensors), np.random.default_rng(case.seed))
    write_run(sim, bag)
    drift = float(np.hypot(*sim.odometry_error()[-1, :2]))
    t1 = time.perf_counter()
    log = io.StringIO()
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        extra = ["--params", params] if params else []
        code = ptm_run.main([str(bag), "--out", str(out), "--no-map", "--no-report", "--quiet", *extra])
    t2 = time.perf_counter()
    row: dict[str, Any] = {**asdict(case), "sim_s": t1 - t0, "run_s": t2 - t1, "exit_code": code}
    row["final_odometry_error_m"] = drift
    row["n_passages"] = len(sim.passages)
    if code != 0:
        row["error"] = log.getvalue()[-2000:]
    else:
        ptm = load_ptm(out / "ptm.json")
        row.update(calibration_record(ptm, bag / "ground_truth.json"))
        row["map_labels"] = list(ptm.map_topology.labels)
        row["detector"] = ptm.extra.get("detector")
        row["true_places"] = true_place_names(case.world, out / "ptm.json")
    if not keep_bags:
        shutil.rmtree(bag, ignore_errors=True)
    return row


def true_place_names(world_name: str, ptm_path: Path) -> list[str]:
    """The place each landmark of a run's ``ptm.json`` was detected at: the place nearest to the true
    position at its stamp. The true path depends on the world and the default motion only (not on the
    noise or the seed), so it is recomputed here rather than read from the (deleted) bag."""
    from ptm_ros.io.simulator import SimConfig, plan_trajectory
    from ptm_ros.io.worlds import get_world
    from ptm_ros.model.ptm import load_ptm

    world, config = get_world(world_name), SimConfig()
    ptm = load_ptm(ptm_path)
    t = np.array([lm.stamp for lm in ptm.landmarks], dtype=float) - config.start_stamp
    xy = plan_trajectory(world, config).pose_at(t)[:, :2]
    d = np.hypot(xy[:, None, 0] - world.place_xy[None, :, 0], xy[:, None, 1] - world.place_xy[None, :, 1])
    return [world.places[k].id for k in np.argmin(d, axis=1)]


def wrong_pairs(rows: Iterable[dict[str, Any]], top: int = 5) -> dict[str, dict[str, Any]]:
    """Per world, over its wrong MAPs: the place pairs most often merged (with their distance, m) and the
    places most often split (visit pairs counted)."""
    from ptm_ros.io.worlds import get_world

    merged: dict[str, dict[tuple[str, str], int]] = {}
    split: dict[str, dict[str, int]] = {}
    for r in rows:
        if r.get("map_right") is not False or "true_places" not in r:
            continue
        lab, ids = r["map_labels"], r["true_places"]
        m, sp = merged.setdefault(r["world"], {}), split.setdefault(r["world"], {})
        for i in range(len(lab)):
            for j in range(i + 1, len(lab)):
                if lab[i] == lab[j] and ids[i] != ids[j]:
                    key = (min(ids[i], ids[j]), max(ids[i], ids[j]))
                    m[key] = m.get(key, 0) + 1
                elif lab[i] != lab[j] and ids[i] == ids[j]:
                    sp[ids[i]] = sp.get(ids[i], 0) + 1
    out: dict[str, dict[str, Any]] = {}
    for world in sorted(set(merged) | set(split)):
        w = get_world(world)

        def dist(a: str, b: str, w: Any = w) -> float:
            pa, pb = w.place(a), w.place(b)
            return round(float(np.hypot(pa.x - pb.x, pa.y - pb.y)), 1)

        out[world] = {
            "merged": [
                {"places": list(k), "distance_m": dist(*k), "pairs": n}
                for k, n in sorted(merged[world].items(), key=lambda kv: -kv[1])[:top]
            ],
            "split": [
                {"place": k, "pairs": n} for k, n in sorted(split[world].items(), key=lambda kv: -kv[1])[:top]
            ],
        }
    return out


def run_all(  # noqa: PLR0917 (the benchmark's options, positionally)
    cases: Sequence[Case],
    work: Path,
    jobs: int,
    keep_bags: bool,
    params: str | None = None,
    sensors: Sensors | None = None,
) -> list[dict[str, Any]]:
    """Every case's record, reusing ``work/records.jsonl`` and appending to it as runs finish."""
    work.mkdir(parents=True, exist_ok=True)
    ledger = work / "records.jsonl"
    done: dict[str, dict[str, Any]] = {}
    if ledger.is_file():
        for line in ledger.read_text().splitlines():
            if line.strip():
                rec = json.loads(line)
                ptm_path = work / Case(*(rec[k] for k in CASE_KEYS)).key / "out" / "ptm.json"
                if rec["exit_code"] == 0 and "true_places" not in rec and ptm_path.is_file():
                    rec["true_places"] = true_place_names(rec["world"], ptm_path)  # older records
                done[Case(*(rec[k] for k in CASE_KEYS)).key] = rec
    todo = [c for c in cases if c.key not in done]
    print(
        f"[calibration] {len(cases)} runs, {len(cases) - len(todo)} already done, {jobs} job(s)", flush=True
    )

    def record(rec: dict[str, Any], k: int) -> None:
        done[Case(*(rec[k] for k in CASE_KEYS)).key] = rec
        with ledger.open("a") as fh:
            fh.write(json.dumps(rec) + "\n")
        status = (
            f"error (exit {rec['exit_code']})"
            if rec["exit_code"]
            else f"MAP p={rec['map_probability']:.3f} right={rec['map_right']} "
            f"consistent={rec['consistent_mass']:.3f}"
        )
        print(
            f"[calibration] {k}/{len(todo)} {rec['world']} {rec['noise']} s{rec['seed']}: {status} "
            f"({rec['sim_s'] + rec['run_s']:.1f} s)",
            flush=True,
        )

    if jobs <= 1:
        for k, case in enumerate(todo, 1):
            record(run_case(case, str(work), keep_bags, params, sensors), k)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(run_case, c, str(work), keep_bags, params, sensors) for c in todo]
            for k, fut in enumerate(futures, 1):
                record(fut.result(), k)
    return [done[c.key] for c in cases]


def failure_kinds(rows: Iterable[dict[str, Any]]) -> dict[str, int]:
    """How the wrong MAPs are wrong: false merges only, missed merges only, or both."""
    kinds = {"merged_only": 0, "split_only": 0, "both": 0}
    for r in rows:
        if r.get("map_right") is False:
            fm, mm = r["map_false_merges"], r["map_missed_merges"]
            kinds["both" if fm and mm else "merged_only" if fm else "split_only"] += 1
    return kinds


def summarize(rows: Sequence[dict[str, Any]]) -> tuple[dict[str, Any], CalibrationSummary | None]:
    """The figures of a group of runs (JSON values) and its summary (None without a scored run)."""
    from ptm_ros.tools.evaluate import summarize_records

    ok = [r for r in rows if r["exit_code"] == 0]
    summary = summarize_records(ok, np.random.default_rng(CHANCE_SEED))
    scored = [r for r in ok if r["map_right"] is not None]
    doc: dict[str, Any] = {
        "n_runs": len(rows),
        "n_errors": len(rows) - len(ok),
        "n_without_true_topology": len(ok) - len(scored),
        "overconfident_failures_all_runs": sum(bool(r["overconfident_failure"]) for r in ok),
        "failure_kinds": failure_kinds(scored),
        "mean_false_merges": float(np.mean([r["map_false_merges"] for r in scored])) if scored else None,
        "mean_missed_merges": float(np.mean([r["map_missed_merges"] for r in scored])) if scored else None,
        "mean_run_s": float(np.mean([r["sim_s"] + r["run_s"] for r in rows])) if rows else None,
    }
    if summary is not None:
        doc.update(summary.as_dict())
    return doc, summary


def group(rows: Sequence[dict[str, Any]], key: Callable[[dict[str, Any]], str]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(key(r), []).append(r)
    return out


COLUMNS = (
    ("n_runs", "runs"),
    ("ece", "ECE"),
    ("chance_ece", "chance ECE"),
    ("brier", "Brier"),
    ("map_right_rate", "MAP right"),
    ("mean_map_probability", "mean MAP p"),
    ("overconfident_failures", "overconf. failures"),
    ("mean_true_topology_mass", "mean true mass"),
    ("failure_kinds", "wrong MAPs: merged / split / both"),
    ("n_without_true_topology", "no exact truth"),
)


def _cell(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, dict):
        return " / ".join(str(x) for x in v.values())
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


def table(title: str, groups: dict[str, dict[str, Any]]) -> list[str]:
    lines = [f"### {title}", "", "| group | " + " | ".join(c[1] for c in COLUMNS) + " |"]
    lines.append("|---|" + "---|" * len(COLUMNS))
    for name, doc in groups.items():
        lines.append(f"| {name} | " + " | ".join(_cell(doc.get(c[0])) for c in COLUMNS) + " |")
    return [*lines, ""]


def wrong_maps_section(wrong: dict[str, dict[str, Any]]) -> list[str]:
    """Markdown: per world, the place pairs its wrong MAPs merge most and the places they split most."""
    lines = [
        "### What the wrong MAPs get wrong",
        "",
        "Per world, over its wrong MAP topologies: the place pairs most often merged (distance between the "
        "places; visit pairs counted) and the places most often split into several (visit pairs counted).",
        "",
        "| world | merged place pairs | split places |",
        "|---|---|---|",
    ]
    for world, doc in wrong.items():
        merged = ", ".join(
            f"{'~'.join(m['places'])} ({m['distance_m']:g} m) x{m['pairs']}" for m in doc["merged"]
        )
        split = ", ".join(f"{m['place']} x{m['pairs']}" for m in doc["split"])
        lines.append(f"| {world} | {merged or '–'} | {split or '–'} |")
    return [*lines, ""]


def pair_groups(rows: Sequence[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """The runs with a pair calibration (records of ``ptm-eval``'s ``calibration_record``), all of them and
    per family and variant."""
    ok = [r for r in rows if r["exit_code"] == 0 and r.get("pair_calibration")]
    return {"all": ok, **group(ok, lambda r: f"{r['family']} {r['variant']}")} if ok else {}


def write_outputs(rows: Sequence[dict[str, Any]], out: Path, args: argparse.Namespace, wall: float) -> None:
    from ptm_ros.io.calibration_plot import write_reliability_diagram
    from ptm_ros.scoring.evaluation import OVERCONFIDENT_MASS

    overall, overall_summary = summarize(rows)
    levels = levels_of(rows)
    by = {
        "family": group(rows, lambda r: r["family"]),
        "family_variant": group(rows, lambda r: f"{r['family']} {r['variant']}"),
        "variant": group(rows, lambda r: r["variant"]),
        "noise": group(rows, lambda r: r["noise"]),
    }
    summaries = {kind: {k: summarize(v) for k, v in groups.items()} for kind, groups in by.items()}
    docs = {kind: {k: d for k, (d, _) in s.items()} for kind, s in summaries.items()}
    record = {
        "benchmark": "calibration of the MAP probability on simulated aliased worlds (issue #23)",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": " ".join(sys.argv),
        "runs_requested": args.runs,
        "quick": args.quick,
        "params": None if args.params is None else str(args.params),
        "sensors": {"scan_rate_hz": args.scan_rate, "panorama_spacing_m": args.panorama_spacing},
        "wall_s": wall,
        "noise_levels": {k: asdict(v) for k, v in levels.items()},
        "definitions": {
            "map_right": "the MAP topology equals the ground-truth topology (true place ids) exactly",
            "ece": "10 equal-width bins of the MAP probability, run-weighted |fraction right - mean p|",
            "chance_ece": "mean ECE of Bernoulli(p) redraws of the outcomes (2000, seed "
            f"{CHANCE_SEED}); chance_ece_p95 their 95th percentile",
            "overconfident_failure": f"consistent mass < {OVERCONFIDENT_MASS}",
        },
        "environment": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cpus": os.cpu_count(),
            "load_average": os.getloadavg(),
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
            "jobs": args.jobs,
        },
        "overall": overall,
        "wrong_maps_by_world": wrong_pairs(rows),
        **{f"by_{k}": v for k, v in docs.items()},
        "runs": list(rows),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    md = out.with_suffix(".md")
    png = out.with_suffix(".png")
    lines = [
        "# Calibration of the MAP probability (issue #23)",
        "",
        f"Generated {record['generated']} by `bench/bench_calibration.py` ({len(rows)} runs"
        f"{', --quick' if args.quick else ''}; {sum(r['sim_s'] + r['run_s'] for r in rows) / 60:.0f} min of "
        f"simulation and `ptm-run`, {args.jobs} job(s)); "
        f"per-run records in `{out.name}`, reliability diagram `{png.name}`.",
        "",
        "Each run: a calibration world (aliased, or its control with distinct textures) simulated with one "
        "odometry noise level and seed"
        + (f" ({_sensor_text(args)})" if args.scan_rate or args.panorama_spacing else "")
        + ", `ptm-run` at "
        + (f"the parameters of `{args.params}`" if args.params else "the default parameters")
        + " (laser-surprise detector), "
        "scored against the simulator's places. *MAP right*: the MAP topology is exactly the true one. "
        "*ECE*: 10 equal-width bins of the stated MAP probability; *chance ECE*: the mean ECE a perfectly "
        "calibrated mapper shows on the same probabilities (outcomes redrawn as Bernoulli(p)). "
        f"*Overconfident failure*: consistent mass < {OVERCONFIDENT_MASS} (runs with an exact truth). "
        "*Wrong MAPs*: counts of wrong MAP topologies that only merge distinct places / only split one "
        "place / do both. *No exact truth*: runs with a landmark more than 1.5 m from every place (left "
        "out of the figures).",
        "",
        *table("Overall", {"all": overall}),
        *table("Per family", docs["family"]),
        *table("Per family and variant", docs["family_variant"]),
        *table("Aliased vs control", docs["variant"]),
        *table("Per odometry noise level", docs["noise"]),
        "Noise levels (`OdometryNoiseConfig`): "
        + "; ".join(
            f"`{k}`: " + ", ".join(f"{f}={x:g}" for f, x in asdict(v).items() if x != 0.0)
            for k, v in levels.items()
        ),
        "",
        *wrong_maps_section(record["wrong_maps_by_world"]),
        *pair_calibration_section(pair_groups(rows), "pooled over seeds and noise levels"),
        "",
        f"![reliability diagram]({png.name})",
        "",
    ]
    md.write_text("\n".join(lines))
    curves = {k: s for k, (_, s) in summaries["family"].items() if s is not None}
    if overall_summary is not None:
        curves = {"all": overall_summary, **curves}
        write_reliability_diagram(png, curves, title=f"MAP calibration, {len(rows)} simulated runs")
    print(md.read_text())


def _sensor_text(args: argparse.Namespace) -> str:
    """The sensors a run was simulated with, where not the simulator's, in words."""
    parts = [f"scans at {args.scan_rate:g} Hz"] if args.scan_rate else []
    parts += [f"a panorama every {args.panorama_spacing:g} m"] if args.panorama_spacing else []
    return " and ".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=None, help=f"number of runs (default {DEFAULT_RUNS})")
    parser.add_argument("--quick", action="store_true", help="smoke test: one run per world")
    parser.add_argument(
        "--out", type=Path, default=None, help="default bench/calibration.json (--quick: under --work)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="parallel runs (default 1)")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "calibration")
    parser.add_argument("--fresh", action="store_true", help="ignore the records of earlier runs")
    parser.add_argument("--keep-bags", action="store_true", help="keep the simulated bags")
    parser.add_argument(
        "--params", type=Path, default=None, help="ptm-run --params FILE (default: the default parameters)"
    )
    parser.add_argument("--families", nargs="+", default=None, help="only these families")
    parser.add_argument("--scan-rate", type=float, default=None, help="simulated scans per second")
    parser.add_argument("--panorama-spacing", type=float, default=None, help="metres between panoramas")
    parser.add_argument(
        "--noise", nargs="+", default=None, choices=[*NOISE_LEVELS, *STRESS_LEVELS], help="only these levels"
    )
    args = parser.parse_args(argv)
    if args.runs is None:
        args.runs = 8 if args.quick else DEFAULT_RUNS
    if args.runs < 1 or args.jobs < 1:
        parser.error("--runs and --jobs must be >= 1")
    work = args.work / ("quick" if args.quick else "full")
    if args.params is not None:
        work = work.with_name(f"{work.name}-{args.params.stem}")
    sensors = None
    if args.scan_rate is not None or args.panorama_spacing is not None:
        default = SimConfig()
        sensors = Sensors(
            default.laser.rate if args.scan_rate is None else args.scan_rate,
            default.camera.spacing if args.panorama_spacing is None else args.panorama_spacing,
        )
        if sensors.scan_rate <= 0.0 or sensors.panorama_spacing <= 0.0:
            parser.error("--scan-rate and --panorama-spacing must be > 0")
        work = work.with_name(f"{work.name}-{sensors.tag}")
    if args.out is None:
        args.out = work / "calibration.json" if args.quick else BENCH / "calibration.json"
    if args.fresh and work.exists():
        shutil.rmtree(work)
    t0 = time.perf_counter()
    cases = grid(args.runs, args.quick, args.families, args.noise)
    params = None if args.params is None else str(args.params.resolve())
    rows = run_all(cases, work, args.jobs, args.keep_bags, params, sensors)
    write_outputs(rows, args.out, args, time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
