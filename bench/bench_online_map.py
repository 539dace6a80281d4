"""The map publisher's online occupancy map against ``ptm-run``'s offline map (issue #8).

For each run (the real runs of ``../shared/datasets`` and the simulated multi-loop world), replays the bag
through ``ptm-bringup`` (detector, filter and map publisher over DDS; ``--rate``, default 0 = as fast as
the nodes take it) and runs ``ptm-run`` on the same bag with the same parameters, then compares:

* the ensembles: same MAP topology (labels), same visits;
* the maps (both nav2 map_server files, trinary): cells known to both that have the same class
  (``agreement``), occupied cells online / offline, grid sizes;
* the map publisher's work: maps drawn during the replay, the time of the last one, keyframe scans.

The live map is measured as the map publisher draws it by default: ``ptm-bringup --bag`` sets the
thinning to none (``ptm_ros.maps.mapping.every_sample``: every odometry sample and scan, so that its files
are ``ptm-run``'s), and this benchmark gives both tools a ROS parameter file
(:func:`default_thinning`) that puts the default ``mapping.*`` thinning back; the nodes apply it after
the bringup's own settings, ``ptm-run`` does not draw from the stream and is unaffected.

Writes ``bench/online_map.json`` (with the thinning used, ``mapping``).

    PYTHONPATH=. .venv/bin/python bench/bench_online_map.py [--only intel ...] [--rate 0] [--work out/bench]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
sys.path.insert(0, str(BENCH))

from run_all import prepare_runs  # noqa: E402 - a sibling benchmark script

from ptm_ros.maps.mapping import MappingConfig, every_sample  # noqa: E402
from ptm_ros.maps.occupancy import OCCUPIED, UNKNOWN, aligned_windows, load_map  # noqa: E402
from ptm_ros.model.ptm import load_ptm  # noqa: E402


def ros_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(REPO / "config" / "fastdds.xml"))
    env.setdefault("ROS_DOMAIN_ID", str(30 + os.getpid() % 150))
    env.setdefault("AMENT_PREFIX_PATH", sys.prefix)
    env["PYTHONPATH"] = str(REPO)
    return env


def thinning() -> dict[str, float]:
    """The default values of the ``mapping`` fields that :func:`ptm_ros.maps.mapping.every_sample` (what
    ``ptm-bringup --bag`` applies) sets to no thinning."""
    default = MappingConfig()
    unthinned = every_sample(default)
    return {
        name: getattr(default, name)
        for name in vars(default)
        if getattr(default, name) != getattr(unthinned, name)
    }


def default_thinning(path: Path) -> Path:
    """A ROS parameter file (all nodes) with :func:`thinning`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"mapping": thinning()}}}))
    return path


def bench_run(name: str, bag: Path, work: Path, rate: float) -> dict[str, Any]:
    bin_dir = Path(sys.executable).parent
    online, offline = work / "online" / name, work / "offline" / name
    params = default_thinning(work / "default_thinning.yaml")
    t0 = time.perf_counter()
    cmd = [str(bin_dir / "ptm-bringup"), "--bag", str(bag), "--rate", str(rate), "--out", str(online)]
    cmd += ["--params", str(params)]
    proc = subprocess.run(
        [*cmd, "--no-report"],
        env=ros_env(),
        capture_output=True,
        text=True,
        check=False,
    )
    wall_online = time.perf_counter() - t0
    t0 = time.perf_counter()
    off = subprocess.run(
        [
            str(bin_dir / "ptm-run"),
            str(bag),
            "--out",
            str(offline),
            "--params",
            str(params),
            "--no-report",
            "--quiet",
        ],
        env=ros_env(),
        capture_output=True,
        text=True,
        check=False,
    )
    wall_offline = time.perf_counter() - t0
    row: dict[str, Any] = {
        "run": name,
        "bringup_exit": proc.returncode,
        "ptm_run_exit": off.returncode,
        "wall_bringup_s": round(wall_online, 1),
        "wall_ptm_run_s": round(wall_offline, 1),
    }
    if proc.returncode != 0 or off.returncode != 0 or not (online / "map.yaml").is_file():
        row["log_tail"] = (proc.stdout + proc.stderr)[-2000:]
        return row
    p_on, p_off = load_ptm(online / "ptm.json"), load_ptm(offline / "ptm.json")
    row["visits"] = len(p_on.landmarks)
    row["same_visits"] = p_on.landmarks == p_off.landmarks
    row["same_map_topology"] = p_on.topologies[0].labels == p_off.topologies[0].labels
    m_on, m_off = load_map(online / "map.yaml"), load_map(offline / "map.yaml")
    a, b = aligned_windows(m_on.data, m_on.origin, m_off.data, m_off.origin, m_off.resolution)
    known = (a != UNKNOWN) & (b != UNKNOWN)
    row["agreement"] = round(float(np.mean(a[known] == b[known])), 4)
    row["cells_known_both"] = int(known.sum())
    row["occupied_online"] = int(np.sum(m_on.data == OCCUPIED))
    row["occupied_offline"] = int(np.sum(m_off.data == OCCUPIED))
    row["grid_online"] = list(m_on.data.shape[::-1])
    row["grid_offline"] = list(m_off.data.shape[::-1])
    for line in proc.stdout.splitlines():
        if "wrote" in line and "map.yaml" in line and "[ptm-bringup]" in line:
            row["bringup_map_line"] = line.split("] ", 1)[1]
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", nargs="*", default=None)
    p.add_argument("--rate", type=float, default=0.0)
    p.add_argument("--work", type=Path, default=REPO / "out" / "bench")
    args = p.parse_args()
    runs = [r for r in prepare_runs(args.work, args.only) if r[1] == "real" or r[0] == "multi-loop"]
    rows = []
    for name, _, bag, _ in runs:
        row = bench_run(name, bag, args.work / "online_map", args.rate)
        print(json.dumps(row), flush=True)
        rows.append(row)
    out = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": "PYTHONPATH=. .venv/bin/python bench/bench_online_map.py",
        "rate": args.rate,
        "mapping": thinning(),
        "load_average": list(os.getloadavg()),
        "runs": rows,
    }
    (BENCH / "online_map.json").write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
