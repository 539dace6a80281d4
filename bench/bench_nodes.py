"""Per-node CPU and memory of the node suite replaying ``bags/demo`` at 1× and 10× (issue #6).

Runs ``ptm-bringup --bag bags/demo --params config/demo.yaml --no-report`` once per ``--rates`` value
(separate processes over DDS, as ``make demo`` does) and samples ``ptm-bringup`` and every child it
starts (the three nodes and the bag player) every ``--interval`` s from ``/proc``: CPU time
(``utime + stime`` of ``/proc/<pid>/stat``, clock ticks of ``os.sysconf("SC_CLK_TCK")``, all threads)
and memory (``VmRSS``, and the kernel's peak ``VmHWM``, of ``/proc/<pid>/status``). Per node:

* ``cpu_mean_pct``: CPU time over the sampled lifetime (100 % = one core; may exceed 100 with threads);
* ``cpu_replay_pct``: the same while the bag player ran (the steady load of a replay at that rate);
* ``cpu_peak_pct``: the busiest ``--interval``;
* ``rss_mean_mib`` / ``rss_peak_mib``: mean of the sampled VmRSS, peak VmHWM.

Per run: wall time, replay time, how long mapping took after the bag ended, load average before and after,
messages the player sent and the detector received, landmark visits ``ptm-run`` finds offline, the
detector published, the filter mapped and ptm.json holds (``lost`` = offline − ptm.json). The CPU of the
last ``--interval`` before a process exits is not seen. Writes ``bench/nodes.json``.

    PYTHONPATH=. .venv/bin/python bench/bench_nodes.py [--rates 1 10] [--interval 0.5] [--work DIR]

Run it with the Makefile's ROS environment (``make bench`` sets it); variables it lacks get the same
defaults (localhost discovery, ``config/fastdds.xml``, a domain derived from the pid).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import ast
import json
import re
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
CLK_TCK = os.sysconf("SC_CLK_TCK")
MIB = 1024.0  # kB per MiB (/proc reports kB)


# ------------------------------------------------------------------------------------------ /proc


def read_stat(pid: int) -> tuple[int, int] | None:
    """``(ppid, utime + stime in clock ticks)`` of a live process, None when it is gone or a zombie."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    rest = text.rsplit(")", 1)[1].split()  # fields 3.. (the command name may contain spaces)
    if rest[0] == "Z":
        return None
    return int(rest[1]), int(rest[11]) + int(rest[12])  # fields 4 (ppid), 14 (utime), 15 (stime)


def read_memory(pid: int) -> tuple[int, int] | None:
    """``(VmRSS, VmHWM)`` in kB, None when the process is gone."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return None
    kb = {
        k: int(v.split()[0]) for k, _, v in (line.partition(":") for line in lines) if k in ("VmRSS", "VmHWM")
    }
    return (kb["VmRSS"], kb["VmHWM"]) if len(kb) == 2 else None


def children_of(pid: int) -> list[int]:
    """Live processes whose parent is ``pid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (stat := read_stat(int(entry.name))) is not None and stat[0] == pid:
            out.append(int(entry.name))
    return out


def process_name(pid: int) -> str:
    """The suite's name of a process from its command line (``ptm_ros.nodes.<name>`` → ``<name>``)."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return f"pid{pid}"
    for i, arg in enumerate(cmd[:-1]):
        if arg == b"-m":
            module = cmd[i + 1].decode()
            return "ptm_bringup" if module.endswith(".bringup") else module.rsplit(".", 1)[-1]
    return Path(cmd[0].decode()).name if cmd and cmd[0] else f"pid{pid}"


@dataclass
class Series:
    """The samples of one process: monotonic time (s), CPU ticks, VmRSS and VmHWM (kB)."""

    name: str
    pid: int
    t: list[float] = field(default_factory=list)
    ticks: list[int] = field(default_factory=list)
    rss_kb: list[int] = field(default_factory=list)
    hwm_kb: list[int] = field(default_factory=list)

    def sample(self, now: float) -> bool:
        stat, mem = read_stat(self.pid), read_memory(self.pid)
        if stat is None or mem is None:
            return False
        self.t.append(now)
        self.ticks.append(stat[1])
        self.rss_kb.append(mem[0])
        self.hwm_kb.append(mem[1])
        return True

    def cpu_pct(self, t0: float, t1: float) -> float | None:
        """Mean CPU % between the samples nearest to ``t0`` and ``t1`` (None with fewer than two)."""
        idx = [i for i, t in enumerate(self.t) if t0 - 1e-9 <= t <= t1 + 1e-9]
        if len(idx) < 2 or self.t[idx[-1]] <= self.t[idx[0]]:
            return None
        dt = self.t[idx[-1]] - self.t[idx[0]]
        return 100.0 * (self.ticks[idx[-1]] - self.ticks[idx[0]]) / CLK_TCK / dt

    def summary(self, replay: tuple[float, float] | None) -> dict[str, Any]:
        steps = [
            100.0 * (b - a) / CLK_TCK / (tb - ta)
            for a, b, ta, tb in zip(self.ticks, self.ticks[1:], self.t, self.t[1:], strict=False)
            if tb > ta
        ]
        mean = self.cpu_pct(self.t[0], self.t[-1]) if self.t else None
        return {
            "pid": self.pid,
            "samples": len(self.t),
            "sampled_s": round(self.t[-1] - self.t[0], 2) if self.t else 0.0,
            "cpu_s": round(self.ticks[-1] / CLK_TCK, 2) if self.ticks else None,
            "cpu_mean_pct": None if mean is None else round(mean, 1),
            "cpu_replay_pct": None if replay is None or (r := self.cpu_pct(*replay)) is None else round(r, 1),
            "cpu_peak_pct": round(max(steps), 1) if steps else None,
            "rss_mean_mib": round(sum(self.rss_kb) / len(self.rss_kb) / MIB, 1) if self.rss_kb else None,
            "rss_peak_mib": round(max(self.hwm_kb) / MIB, 1) if self.hwm_kb else None,
        }


# --------------------------------------------------------------------------------------------- run


def ros_env() -> dict[str, str]:
    """Our environment with the Makefile's ROS variables where they are missing."""
    env = dict(os.environ)
    env.setdefault("AMENT_PREFIX_PATH", sys.prefix)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", str(os.getpid() % 200 + 20))
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(REPO / "config" / "fastdds.xml"))
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def start_replay(cmd: list[str], *, new_session: bool = False) -> subprocess.Popen[str]:
    """Start ``cmd`` (ptm-bringup) with :func:`ros_env`, its stdout and stderr in one text pipe, no stdin;
    ``new_session``: in a session of its own (a terminal's SIGINT does not reach it)."""
    return subprocess.Popen(
        cmd,
        env=ros_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        text=True,
        start_new_session=new_session,
    )


def track_children(pid: int, series: dict[int, Series]) -> None:
    """Add a :class:`Series` for each child process of ``pid`` not sampled yet."""
    for child in children_of(pid):
        if child not in series:
            series[child] = Series(process_name(child), child)


def run_bringup(bag: Path, params: Path, rate: float, out: Path, interval: float) -> dict[str, Any]:
    """One ``ptm-bringup`` replay, sampled; the raw figures (see :func:`summarize`)."""
    cmd = [sys.executable, "-m", "ptm_ros.tools.bringup", "--bag", str(bag), "--rate", f"{rate:g}"]
    cmd += ["--params", str(params), "--out", str(out), "--no-report"]
    lines: list[tuple[float, str]] = []
    load_start = os.getloadavg()
    t_start = time.monotonic()
    proc = start_replay(cmd)

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append((time.monotonic(), line.rstrip("\n")))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    series: dict[int, Series] = {proc.pid: Series("ptm_bringup", proc.pid)}
    next_tick = time.monotonic()
    while proc.poll() is None:
        now = time.monotonic()
        track_children(proc.pid, series)
        for s in series.values():
            s.sample(now)
        next_tick += interval
        time.sleep(max(next_tick - time.monotonic(), 0.0))
    wall = time.monotonic() - t_start
    reader.join(timeout=10.0)
    return {
        "rate": rate,
        "exit_code": proc.returncode,
        "wall_s": wall,
        "t_start": t_start,
        "load_average": {"start": load_start, "end": os.getloadavg()},
        "series": list(series.values()),
        "lines": lines,
    }


def logged(lines: list[tuple[float, str]], pattern: str) -> tuple[float, re.Match[str]] | None:
    """The reception time and match of the first log line matching ``pattern``."""
    rx = re.compile(pattern)
    for t, line in lines:
        if (m := rx.search(line)) is not None:
            return t, m
    return None


def summarize(raw: dict[str, Any], out: Path, bag_duration_s: float, visits_offline: int) -> dict[str, Any]:
    """Per-node figures, messages and visits sent vs received, timings of one run."""
    lines = raw["lines"]
    played = logged(lines, r"\[ptm_bag_player\]: published (\d+) messages in ([\d.]+) s: (\{.*\})")
    announced = logged(lines, r"\[landmark_detector\]: end of input announced: (\{.*\})")
    missing = logged(lines, r"messages never arrived (\{.*\})")
    finished = logged(lines, r"\[landmark_detector\]: input finished: (\d+) landmark visits")
    mapped = logged(lines, r"\[topology_filter\]: end of visits reported \((\d+)\); (\d+) in the map")
    bag_done = logged(lines, r"\[ptm-bringup\] bag finished")
    wrote = logged(lines, r"\[ptm-bringup\] wrote .*ptm\.json: (\d+) visits")
    sent = ast.literal_eval(played[1].group(3)) if played else None
    received = None
    if announced is not None:
        lost = ast.literal_eval(missing[1].group(1)) if missing else {}
        received = {k: v - lost.get(k, 0) for k, v in ast.literal_eval(announced[1].group(1)).items()}
    ptm_file = out / "ptm.json"
    doc = json.loads(ptm_file.read_text()) if ptm_file.is_file() else {}
    in_ptm = len(doc.get("landmarks", [])) if doc else None
    player = next((s for s in raw["series"] if s.name == "bag_player" and s.t), None)
    replay = (player.t[0], player.t[-1]) if player is not None else None
    return {
        "rate": raw["rate"],
        "exit_code": raw["exit_code"],
        "wall_s": round(raw["wall_s"], 2),
        "bag_duration_s": round(bag_duration_s, 2),
        "replay_s": float(played[1].group(2)) if played else None,
        "mapping_after_bag_s": round(wrote[0] - bag_done[0], 2) if wrote and bag_done else None,
        "load_average": {k: [round(x, 2) for x in v] for k, v in raw["load_average"].items()},
        "messages": {"sent": sent, "received_by_detector": received},
        "visits": {
            "offline": visits_offline,
            "sent_by_detector": int(finished[1].group(1)) if finished else None,
            "received_by_filter": int(mapped[1].group(2)) if mapped else None,
            "in_ptm_json": in_ptm,
            "lost": None if in_ptm is None else visits_offline - in_ptm,
        },
        "filter_counters": {
            k: doc.get("diagnostics", {}).get(k)
            for k in ("messages", "invalid", "rejected", "duplicates", "gaps")
            if doc
        },
        "nodes": {s.name: s.summary(replay) for s in raw["series"] if s.t},
    }


def offline_visits(bag: Path, params: Path) -> int:
    """Landmark visits ``ptm-run`` finds on the bag (the reference count)."""
    from ptm_ros.io.bag import read_run
    from ptm_ros.tools.bringup import load_parameters
    from ptm_ros.tools.pipeline import detect_visits

    config, _ = load_parameters(params)
    return len(detect_visits(read_run(bag), config))


def format_table(runs: list[dict[str, Any]]) -> str:
    head = ("cpu mean %", "replay %", "peak %", "rss MiB", "peak MiB")
    rows = [f"{'rate':>4} {'node':<18} " + " ".join(f"{h:>10}" for h in head)]
    for run in runs:
        for name, n in run["nodes"].items():
            cells = [
                n["cpu_mean_pct"],
                n["cpu_replay_pct"],
                n["cpu_peak_pct"],
                n["rss_mean_mib"],
                n["rss_peak_mib"],
            ]
            text = " ".join(f"{'-' if c is None else f'{c:.1f}':>10}" for c in cells)
            rows.append(f"{run['rate']:>4g} {name:<18} {text}")
        v = run["visits"]
        counts = "/".join(
            str(v[k]) for k in ("offline", "sent_by_detector", "received_by_filter", "in_ptm_json")
        )
        rows.append(
            f"     wall {run['wall_s']:.1f} s, replay {run['replay_s']} s, "
            f"visits offline/sent/mapped/ptm.json {counts}, load {run['load_average']['start']}"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, default=REPO / "bags" / "demo")
    parser.add_argument("--params", type=Path, default=REPO / "config" / "demo.yaml")
    parser.add_argument(
        "--rates", type=float, nargs="+", default=[1.0, 10.0], help="replay rates (default 1 10)"
    )
    parser.add_argument("--interval", type=float, default=0.5, help="s between samples (default 0.5)")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "bench" / "nodes")
    parser.add_argument(
        "--json", type=Path, default=BENCH / "nodes.json", help="output (default bench/nodes.json)"
    )
    args = parser.parse_args(argv)
    if any(r <= 0.0 for r in args.rates) or args.interval <= 0.0:
        parser.error("rates and interval must be > 0 (rate 0 is unpaced: no real-time figure)")
    from rosbags.rosbag2 import Reader

    from ptm_ros.nodes.bag_player import bag_topics

    with Reader(args.bag) as reader:
        duration_s = reader.duration / 1e9
    topics = bag_topics(args.bag)
    visits = offline_visits(args.bag, args.params)
    runs = []
    for rate in args.rates:
        out = args.work / f"rate{rate:g}"
        print(f"[bench_nodes] replaying {args.bag.name} at {rate:g}x", flush=True)
        raw = run_bringup(args.bag.resolve(), args.params.resolve(), rate, out.resolve(), args.interval)
        runs.append(summarize(raw, out, duration_s, visits))
        if raw["exit_code"] != 0:
            tail = "\n".join(line for _, line in raw["lines"][-30:])
            print(f"[bench_nodes] ptm-bringup exited with {raw['exit_code']}:\n{tail}", flush=True)
    doc = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": " ".join(["PYTHONPATH=. .venv/bin/python bench/bench_nodes.py", *(argv or sys.argv[1:])]),
        "machine": {"cpus": os.cpu_count(), "clk_tck": CLK_TCK},
        "bag": str(args.bag),
        "params": str(args.params),
        "bag_messages": {name: t.count for name, t in topics.items()},
        "interval_s": args.interval,
        "runs": runs,
    }
    args.json.write_text(json.dumps(doc, indent=1) + "\n")
    print(format_table(runs), flush=True)
    print(f"[bench_nodes] wrote {args.json}", flush=True)
    return int(any(r["exit_code"] != 0 or r["visits"]["lost"] != 0 for r in runs))


if __name__ == "__main__":
    sys.exit(main())
