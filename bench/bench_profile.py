"""Where a whole ``ptm-run`` spends its time (issue #27): cProfile of the run, top functions by share.

For each real run of ``../shared/datasets`` (or ``--only NAME``), ``ptm-run BAG --out DIR --quiet`` runs
under :mod:`cProfile` in this process; the table lists the functions with the largest cumulative and
self (``tottime``) shares of the profiled wall time, and the pipeline's phases from ``ptm.json``'s
``timing``. Start-up imports before ``main`` are not in the profile; the whole-process wall time is
measured separately (``ptm-run`` in a fresh interpreter). Writes ``bench/profile.json`` and
``bench/profile.md``.

    PYTHONPATH=. .venv/bin/python bench/bench_profile.py [--only intel] [--top 25] [--work out/profile]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import cProfile
import io
import json
import pstats
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from run_all import DATASETS, REAL_RUNS

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent


def whole_process_s(bag: Path, out: Path) -> float:
    """Wall time of ``ptm-run BAG --out OUT --quiet`` in a fresh interpreter (imports included)."""
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "ptm_ros.tools.run", str(bag), "--out", str(out), "--quiet"],
        check=True,
        capture_output=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        cwd=REPO,
    )
    return time.perf_counter() - t0


def profiled(bag: Path, out: Path, top: int) -> dict[str, Any]:
    """Profile ``ptm-run`` in this process: the top functions by cumulative and by self time."""
    from ptm_ros.tools import run as ptm_run

    prof = cProfile.Profile()
    log = io.StringIO()
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        prof.enable()
        t0 = time.perf_counter()
        code = ptm_run.main([str(bag), "--out", str(out), "--quiet"])
        wall = time.perf_counter() - t0
        prof.disable()
    if code != 0:
        return {"error": log.getvalue()[-1000:]}
    stats = pstats.Stats(prof)
    rows = []
    for (path, line, func), (_, ncalls, tottime, cumtime, _) in stats.stats.items():
        name = f"{Path(path).name}:{line}({func})" if line else func
        rows.append({"function": name, "calls": ncalls, "self_s": tottime, "cumulative_s": cumtime})
    timing = json.loads((out / "ptm.json").read_text()).get("timing", {})
    return {
        "profiled_wall_s": wall,
        "timing": timing,
        "by_cumulative": sorted(rows, key=lambda r: -r["cumulative_s"])[:top],
        "by_self": sorted(rows, key=lambda r: -r["self_s"])[:top],
    }


def write_markdown(doc: dict[str, Any], path: Path) -> None:
    lines = [
        "# Where `ptm-run` spends its time (issue #27)",
        "",
        f"Generated {doc['generated']} by `bench/bench_profile.py`; load average "
        f"{', '.join(f'{x:.1f}' for x in doc['load_average'])} on this 2-core machine (shares are "
        "meaningful under load, absolute times less so). `ptm-run BAG --out DIR --quiet` at the default "
        "parameters; *whole process*: a fresh interpreter, imports included; the profile runs in-process.",
    ]
    for name, r in doc["runs"].items():
        if "error" in r:
            lines += ["", f"## {name}", "", f"failed: {r['error']}"]
            continue
        wall = r["profiled_wall_s"]
        phases = ", ".join(f"{k} {v:.1f} s" for k, v in r["timing"].items() if isinstance(v, int | float))
        lines += [
            "",
            f"## {name}",
            "",
            f"Whole process {r['whole_process_s']:.1f} s; profiled {wall:.1f} s; ptm.json timing: {phases}.",
            "",
            "| function | calls | cumulative s | share | self s | self share |",
            "|---|---|---|---|---|---|",
        ]
        for f in r["by_cumulative"]:
            lines.append(
                f"| `{f['function']}` | {f['calls']} | {f['cumulative_s']:.2f} "
                f"| {f['cumulative_s'] / wall:.0%} | {f['self_s']:.2f} | {f['self_s'] / wall:.0%} |"
            )
        lines += ["", "Largest self times:", "", "| function | calls | self s | share |", "|---|---|---|---|"]
        for f in r["by_self"]:
            lines.append(
                f"| `{f['function']}` | {f['calls']} | {f['self_s']:.2f} | {f['self_s'] / wall:.0%} |"
            )
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", default=None, help="only these runs")
    parser.add_argument("--top", type=int, default=25, help="functions listed per table")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "profile")
    args = parser.parse_args(argv)
    from ptm_ros.tools.convert import convert

    args.work.mkdir(parents=True, exist_ok=True)
    runs: dict[str, Any] = {}
    for name, log, _ in REAL_RUNS:
        if (args.only and name not in args.only) or not (DATASETS / log).is_file():
            continue
        bag = args.work / f"{name}.bag"
        if not bag.exists():
            convert(DATASETS / log, bag)
        rec = profiled(bag, args.work / f"{name}-profiled", args.top)
        rec["whole_process_s"] = whole_process_s(bag, args.work / f"{name}-whole")
        runs[name] = rec
        print(f"[profile] {name}: whole process {rec['whole_process_s']:.1f} s", flush=True)
    doc = {
        "benchmark": "profile",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "load_average": list(os.getloadavg()),
        "runs": runs,
    }
    (BENCH / "profile.json").write_text(json.dumps(doc, indent=1))
    write_markdown(doc, BENCH / "profile.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
