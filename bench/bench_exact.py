"""Benchmark of the particle filter against exact enumeration on simulated runs (issue #23).

For each of ``--runs`` random small runs (the worlds of :data:`BENCH_WORLDS` in turn, a fresh noise seed
each, 8 or 9 place visits) the script simulates a bag with ``ptm-sim`` and runs ``ptm-run`` on it with
``--method exact`` (enumeration of every topology, :func:`ptm_ros.model.posterior.exact_posterior`) and with
``--method rbpf --particles N``, then compares the ``ptm.json``: total variation, and the mass each puts on
the exact MAP topology. The filter runs twice: at the defaults (its topologies reweighted with the batch
metric evidence, :mod:`ptm_ros.inference.reweighting`) and with ``inference.reweight: false`` (its
sequential EKF weights; ``tv_sequential``), so that the bench shows both which topologies the filter keeps
and what its own approximation of the batch model's weights costs. Only the command-line
tools are used (their interface is stable), so the benchmark does not depend on where the pipeline's
functions live.

``ptm.json`` lists the ``top`` most probable topologies (here ``--top``, 500 by default); the total
variation is computed over the union of both lists, and ``tail_exact`` / ``tail_rbpf`` (the probability
left out of each list) bound its error: ``|TV - TV_listed| <= (tail_exact + tail_rbpf) / 2``.

A run whose detector finds fewer than 8 or more than 9 visits is skipped (and listed), and further
seeds are drawn until ``--runs`` runs are scored. Bags and the exact results are kept under ``--work``
and reused when present (the exact enumeration of a 9-visit run takes minutes; it does not depend on
the filter) while the parameters they were computed with are today's (the ``config.yaml`` ``ptm-run``
writes beside them; a changed default enumerates again); the filter always runs afresh. Writes
``bench/exact.json`` (beside this script, or ``--out``) and prints one line per run and the median / max.
No timing is asserted.

Usage: ``PYTHONPATH=. .venv/bin/python bench/bench_exact.py [--runs 24] [--particles 1000]
[--work out/bench_exact] [--out FILE]``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import io
import json
import platform
import time
from pathlib import Path

import numpy as np
import yaml

from ptm_ros.config import load_config
from ptm_ros.configio import to_dict
from ptm_ros.tools import run as ptm_run
from ptm_ros.tools import sim as ptm_sim

BENCH = Path(__file__).resolve().parent
#: The worlds the runs cycle through: fixed (not "every world of the simulator"), so that a world added
#: later neither changes the runs nor invalidates their cached exact enumerations.
BENCH_WORLDS = ("aliased-loop", "multi-loop", "t-junction", "two-loop")
VISITS = (8, 9)
MAX_ATTEMPTS_FACTOR = 3  # give up after this many times --runs simulations


def _quiet(main, argv: list[str]) -> tuple[int, str]:
    """Run a CLI ``main(argv)`` with its stdout and stderr captured; ``(exit code, captured text)``."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        code = main(argv)
    return int(code or 0), buf.getvalue()


def _topologies(ptm_path: Path) -> dict[tuple[int, ...], float]:
    doc = json.loads(ptm_path.read_text())
    return {tuple(t["labels"]): float(t["probability"]) for t in doc["topologies"]}


def _run_ptm(
    bag: Path, out: Path, params: Path, *, method: str, particles: int, seed: int
) -> tuple[int, str]:
    argv = [str(bag), "--out", str(out), "--method", method, "--params", str(params), "--seed", str(seed)]
    argv += ["--particles", str(particles), "--no-report", "--no-map", "--quiet"]
    return _quiet(ptm_run.main, argv)


def _current(saved: Path, params: Path) -> bool:
    """Whether a cached result's ``config.yaml`` holds today's parameters (``params`` on the defaults) but
    for ``inference`` (the method): an enumeration made under other defaults is stale."""
    if not saved.exists():
        return False
    cached, today = yaml.safe_load(saved.read_text()), to_dict(load_config(params))
    return all(cached.get(part) == value for part, value in today.items() if part != "inference")


def compare(exact: dict, rbpf: dict) -> dict:
    """TV over the union of the listed topologies, the masses on the exact MAP, and the unlisted tails."""
    keys = set(exact) | set(rbpf)
    tv = 0.5 * sum(abs(exact.get(k, 0.0) - rbpf.get(k, 0.0)) for k in keys)
    exact_map = max(exact, key=exact.__getitem__)
    rbpf_map = max(rbpf, key=rbpf.__getitem__)
    return {
        "tv": tv,
        "exact_map": list(exact_map),
        "exact_map_mass_exact": exact[exact_map],
        "exact_map_mass_rbpf": rbpf.get(exact_map, 0.0),
        "map_equal": exact_map == rbpf_map,
        "tail_exact": max(0.0, 1.0 - sum(exact.values())),
        "tail_rbpf": max(0.0, 1.0 - sum(rbpf.values())),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=24, help="runs to score (default 24)")
    parser.add_argument("--particles", type=int, default=1000, help="particles of the filter")
    parser.add_argument("--top", type=int, default=500, help="topologies listed in ptm.json")
    parser.add_argument("--first-seed", type=int, default=100, help="noise seed of the first run")
    parser.add_argument("--filter-seed", type=int, default=0, help="seed of the filter's resampling")
    parser.add_argument("--work", type=Path, default=BENCH.parent / "out" / "bench_exact")
    parser.add_argument("--out", type=Path, default=BENCH / "exact.json")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    params = args.work / "params.yaml"
    params.write_text(f"inference:\n  top: {args.top}\n")
    sequential = args.work / "params_sequential.yaml"
    sequential.write_text(f"inference:\n  top: {args.top}\n  reweight: false\n")
    worlds = list(BENCH_WORLDS)
    rows, skipped = [], []
    attempt = 0
    while len(rows) < args.runs and attempt < MAX_ATTEMPTS_FACTOR * args.runs:
        world = worlds[attempt % len(worlds)]
        n = VISITS[(attempt // len(worlds)) % len(VISITS)]
        seed = args.first_seed + attempt
        attempt += 1
        name = f"{world}-seed{seed}-n{n}"
        bag = args.work / name / "bag"
        if not bag.exists():
            code, text = _quiet(
                ptm_sim.main, [str(bag), "--seed", str(seed), "--world", world, "--landmarks", str(n)]
            )
            if code:
                skipped.append({"run": name, "reason": f"ptm-sim exit {code}: {text.strip()[-200:]}"})
                continue
        exact_json = args.work / name / "exact" / "ptm.json"
        t0 = time.perf_counter()
        if not _current(exact_json.parent / "config.yaml", params):
            code, text = _run_ptm(
                bag, exact_json.parent, params, method="exact", particles=args.particles, seed=0
            )
            if code:
                skipped.append({"run": name, "reason": f"exact: exit {code}: {text.strip()[-200:]}"})
                continue
        exact_s = time.perf_counter() - t0
        doc = json.loads(exact_json.read_text())
        n_visits = len(doc["landmarks"])
        if n_visits not in VISITS:
            skipped.append({"run": name, "reason": f"{n_visits} visits detected"})
            continue
        rbpf_json = args.work / name / "rbpf" / "ptm.json"
        t0 = time.perf_counter()
        code, text = _run_ptm(
            bag, rbpf_json.parent, params, method="rbpf", particles=args.particles, seed=args.filter_seed
        )
        rbpf_s = time.perf_counter() - t0
        if code:
            msg = f"ptm-run --method rbpf failed on {name}: {text}"
            raise RuntimeError(msg)
        seq_json = args.work / name / "rbpf_sequential" / "ptm.json"
        code, text = _run_ptm(
            bag, seq_json.parent, sequential, method="rbpf", particles=args.particles, seed=args.filter_seed
        )
        if code:
            msg = f"ptm-run --method rbpf (sequential weights) failed on {name}: {text}"
            raise RuntimeError(msg)
        exact, rbpf = _topologies(exact_json), _topologies(rbpf_json)
        row = {"run": name, "world": world, "seed": seed, "visits": n_visits, **compare(exact, rbpf)}
        seq = compare(exact, _topologies(seq_json))
        row["tv_sequential"], row["exact_map_mass_sequential"] = seq["tv"], seq["exact_map_mass_rbpf"]
        row["exact_s"], row["rbpf_s"] = exact_s, rbpf_s
        rows.append(row)
        print(
            f"{name:28} N={n_visits} TV {row['tv']:.4f}  MAP mass exact {row['exact_map_mass_exact']:.3f} "
            f"rbpf {row['exact_map_mass_rbpf']:.3f}{'' if row['map_equal'] else '  (MAP differs)'}; "
            f"sequential weights: TV {row['tv_sequential']:.4f}, "
            f"MAP mass {row['exact_map_mass_sequential']:.3f}",
            flush=True,
        )
    tvs = np.array([r["tv"] for r in rows])
    seq_tvs = np.array([r["tv_sequential"] for r in rows])
    summary = {
        "runs": len(rows),
        "particles": args.particles,
        "tv_median": float(np.median(tvs)) if len(tvs) else None,
        "tv_max": float(np.max(tvs)) if len(tvs) else None,
        "tv_mean": float(np.mean(tvs)) if len(tvs) else None,
        "tv_sequential_median": float(np.median(seq_tvs)) if len(seq_tvs) else None,
        "tv_sequential_max": float(np.max(seq_tvs)) if len(seq_tvs) else None,
        "map_equal": int(sum(r["map_equal"] for r in rows)),
        "max_tail": float(max((max(r["tail_exact"], r["tail_rbpf"]) for r in rows), default=0.0)),
    }
    result = {
        "machine": {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count()},
        "summary": summary,
        "runs": rows,
        "skipped": skipped,
    }
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(
        f"{summary['runs']} runs, {args.particles} particles: TV median {summary['tv_median']:.4f}, "
        f"max {summary['tv_max']:.4f}, mean {summary['tv_mean']:.4f} (sequential weights: median "
        f"{summary['tv_sequential_median']:.4f}, max {summary['tv_sequential_max']:.4f}); MAP equal in "
        f"{summary['map_equal']}; "
        f"unlisted mass <= {summary['max_tail']:.2g}; {len(skipped)} skipped"
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
