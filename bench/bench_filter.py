"""The particle filter alone on the real runs (issue #27): its own cost, without detection or registration.

For each real run of ``../shared/datasets`` (or ``--only NAME``), the landmark visits are detected once and
the laser registrations the filter session asks for are made once; both are cached under ``--work``
(pickled; delete the directory after a change to detection or registration). Then a fresh
:class:`ptm_ros.session.FilterSession` at the default parameters filters the visits ``--repeats`` times
with those registrations read from the cache: the heading-noise and visit-offset replays are included,
the registration work and the worker processes are not. Reported per run: CPU time of the whole pass
(minimum and median over the repeats), the per-visit update time of the final filter (median, p95), the
replays, and a digest of the PTM's weights (the same digest before and after a change means the same
weights to the last bit). Writes ``bench/filter.json`` and ``bench/filter.md``. Timings only; nothing is
asserted.

    PYTHONPATH=. .venv/bin/python bench/bench_filter.py [--only intel] [--repeats 3] [--work out/bench_filter]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import hashlib
import json
import pickle
import platform
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from run_all import prepare_runs

from ptm_ros.config import PtmConfig
from ptm_ros.factories import Registration, with_detector_kind
from ptm_ros.io.bag import read_run
from ptm_ros.model.visits import Visit
from ptm_ros.session import FilterSession, filter_visits
from ptm_ros.tools.pipeline import detect_visits, run_extractor, run_sensors

BENCH = Path(__file__).resolve().parent
Pairs = dict[tuple[int, int], Registration]


def cached_inputs(bag: Path, path: Path) -> tuple[PtmConfig, list[Visit], Pairs]:
    """The run's configuration (the defaults for its sensors), visits, and the registrations a filter session
    asks for: made once and pickled to ``path`` (the bag is read only then)."""
    if path.is_file():
        with path.open("rb") as f:
            sensors, visits, pairs = pickle.load(f)  # the bench's own cache
        return with_detector_kind(PtmConfig(), **sensors), visits, pairs
    run = read_run(bag)
    sensors = run_sensors(run)
    config = with_detector_kind(PtmConfig(), **sensors)
    visits = detect_visits(run, config, extractor=run_extractor(run, config))
    pairs = dict(filter_visits(FilterSession(config, fitted_to=visits), visits).pairs)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump((sensors, visits, pairs), f)
    return config, visits, pairs


def one_pass(config: PtmConfig, visits: list[Visit], pairs: Pairs) -> dict[str, Any]:
    """One filter pass over ``visits`` with the cached registrations: CPU time, update times, digest."""
    t0 = time.process_time()
    session = FilterSession(config, fitted_to=visits, registrar=lambda i, j: pairs[(i, j)])
    filter_visits(session, visits)
    cpu = time.process_time() - t0
    flt = session.filter
    assert flt is not None  # at least one visit was filtered
    updates = sorted(1000.0 * h.update_s for h in flt.history)
    digest = hashlib.sha1(repr(sorted(flt.ptm_weights().items())).encode()).hexdigest()[:12]
    return {
        "cpu_s": cpu,
        "update_ms_median": statistics.median(updates),
        "update_ms_p95": updates[int(0.95 * (len(updates) - 1))],
        "replays": session.replays,
        "digest": digest,
    }


def write_md(doc: dict[str, Any], path: Path) -> None:
    load = ", ".join(f"{x:.1f}" for x in doc["load_average"])
    lines = [
        "# The particle filter alone on the real runs (issue #27)",
        "",
        f"Generated {doc['generated']} by `bench/bench_filter.py`; load average {load} on this "
        f"{doc['machine']['cpus']}-core machine. "
        "The filter session at the default parameters over each run's visits, its registrations read from a "
        "cache (detection and registration excluded, the learned noise's replays included); CPU time of the "
        f"pass over {doc['repeats']} repeats, the final filter's per-visit update time.",
        "",
        "| run | visits | CPU s min | CPU s median | update ms median | update ms p95 | replays | digest |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        lines.append(
            f"| {r['run']} | {r['visits']} | {r['cpu_s_min']:.2f} | {r['cpu_s_median']:.2f} | "
            f"{r['update_ms_median']:.1f} | {r['update_ms_p95']:.1f} | {r['replays']} | `{r['digest']}` |"
        )
    lines += ["", "## Command", "", f"    {doc['command']}", ""]
    path.write_text("\n".join(lines))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="real run names")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--work", type=Path, default=BENCH.parent / "out" / "bench_filter")
    args = parser.parse_args(argv)
    runs = []
    for name, kind, bag, _ in prepare_runs(BENCH.parent / "out" / "bench", args.only):
        if kind != "real":
            continue
        config, visits, pairs = cached_inputs(bag, args.work / f"{name}.pkl")
        passes = [one_pass(config, visits, pairs) for _ in range(args.repeats)]
        cpu = [p["cpu_s"] for p in passes]
        best = passes[cpu.index(min(cpu))]
        row = {
            "run": name,
            "visits": len(visits),
            "cpu_s_min": min(cpu),
            "cpu_s_median": statistics.median(cpu),
            **{k: best[k] for k in ("update_ms_median", "update_ms_p95", "replays", "digest")},
        }
        print(f"[filter] {name}: CPU {row['cpu_s_min']:.2f} s, p95 {row['update_ms_p95']:.1f} ms", flush=True)
        runs.append(row)
    doc = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": "PYTHONPATH=. .venv/bin/python bench/bench_filter.py",
        "load_average": list(os.getloadavg()),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "repeats": args.repeats,
        "runs": runs,
    }
    (BENCH / "filter.json").write_text(json.dumps(doc, indent=1) + "\n")
    write_md(doc, BENCH / "filter.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
