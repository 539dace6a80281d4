"""Load: the node suite on a long simulated run at robot sensor rates, replayed fast (issue #9).

1. Simulates (:mod:`ptm_ros.io.simulator`) a run through a world whose route loops (``--world``, default
   ``multi-loop``) with odometry at ``--odom-rate`` (100 Hz), laser scans at ``--scan-rate`` (40 Hz) and a
   panorama every ``speed / --pano-rate`` m of travel (10 Hz at the simulator's 0.5 m/s), for the fewest
   place visits that last ``--sim-hours`` (1 h) of sim time, into ``--bag`` (kept and reused while its
   ``load_sim.json`` matches these settings).
2. Replays it through ``ptm-bringup --rate R`` (separate processes over DDS, ``config/demo.yaml`` plus the
   filter's live setting ``refit_max_visits: --refit-max-visits``: beyond that many visits the appearance
   priors are frozen and every visit costs one filter update; ``0`` = ``ptm-bringup``'s exact replay,
   O(N) updates per visit) and samples ``ptm-bringup`` and every child every ``--interval`` s from
   ``/proc`` (the helpers of ``bench_nodes.py``: VmRSS, VmHWM, CPU ticks).
3. Writes ``--json`` (``bench/load.json``): per node the RSS over time (downsampled to ``--points``),
   peak RSS and the RSS trend after warm-up (a least-squares line over the replay without its first
   ``--warmup`` fraction, in MiB per hour of sim time and of wall time); CPU; the filter's per-visit
   update time (its ``visit N: ... updated|replayed in M ms`` log line) as median per decile of the visit
   index; the lag of each visit behind the replay (wall time the filter logged it minus wall time the
   player was due to publish the visit's stamp, a measure of the queues between them); messages sent,
   received and skipped; visits published, mapped and in ptm.json; wall time.

    PYTHONPATH=. .venv/bin/python bench/bench_load.py [--rate 5] [--sim-hours 1] [--bag /tmp/ptm_load/bag]

Run it with the Makefile's ROS environment variables or without (``bench_nodes.ros_env`` fills the same
defaults). The bag of one simulated hour is about 1.6 GB (1.2 GB of panoramas), so it lives under /tmp.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import ast
import itertools
import json
import math
import re
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
sys.path.insert(0, str(BENCH))

from bench_nodes import CLK_TCK, MIB, Series, logged, start_replay, track_children  # noqa: E402

SIM_FILE = "load_sim.json"
VISIT_LINE = re.compile(
    r"\[topology_filter\]: visit (\d+): (\d+) topologies, ESS ([\d.]+), (updated|replayed) in (\d+) ms"
)
KEEP_LINES = 400  # log lines kept for an error report
RENDER_CHUNK = 250  # panoramas rendered at once (~1.6 MB of intermediates each)


# ---------------------------------------------------------------------------------------- the bag


@dataclass(frozen=True)
class LoadSim:
    """What to simulate: world, sim time (h), sensor rates (Hz) and seed."""

    world: str = "multi-loop"
    hours: float = 1.0
    odom_rate: float = 100.0
    scan_rate: float = 40.0
    pano_rate: float = 10.0
    seed: int = 0

    def config(self) -> Any:
        """The :class:`~ptm_ros.io.simulator.SimConfig`: panoramas every ``speed / pano_rate`` m."""
        from ptm_ros.io.simulator import CameraConfig, LaserConfig, SimConfig

        speed = SimConfig().speed
        return SimConfig(
            odom_rate=self.odom_rate,
            laser=LaserConfig(rate=self.scan_rate),
            camera=CameraConfig(spacing=speed / self.pano_rate),
        )

    def visits(self) -> int:
        """The fewest place visits of the world's (cycled) route whose path lasts ``hours``."""
        from ptm_ros.io.simulator import plan_trajectory
        from ptm_ros.io.worlds import get_world

        world, config, target = get_world(self.world), self.config(), 3600.0 * self.hours
        n = world.default_visits
        per_visit = plan_trajectory(world, config, n).total_time / n
        n = max(2, math.ceil(target / per_visit))
        while n > 2 and plan_trajectory(world, config, n - 1).total_time >= target:
            n -= 1
        while plan_trajectory(world, config, n).total_time < target:
            n += 1
        return n


def bag_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def simulate_chunked(sim: LoadSim, visits: int, chunk: int = RENDER_CHUNK) -> Any:
    """:func:`~ptm_ros.io.simulator.simulate` with the panoramas rendered ``chunk`` at a time.

    ``PanoramaRenderer.render`` holds float64 intermediates of every panorama it is given at once (about
    1.6 MB each: one simulated hour at 10 Hz would need ~58 GB), so the run is simulated without camera
    and its panoramas rendered here, one every ``spacing`` m of true travel, at the odometry stamp
    where that distance is first reached (as ``simulate`` places them; the pixel noise draws continue
    the same generator, so the images differ from ``simulate``'s in noise only).
    """
    import dataclasses

    from ptm_ros.io.simulator import PanoramaRenderer, simulate
    from ptm_ros.io.worlds import get_world

    world, config, rng = get_world(sim.world), sim.config(), np.random.default_rng(sim.seed)
    cam = config.camera
    blind = dataclasses.replace(config, camera=dataclasses.replace(cam, enabled=False))
    run = simulate(world, blind, rng, visits=visits)
    true = run.true_poses
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(true[:, :2], axis=0).T))])
    marks = np.arange(math.floor(travelled[-1] / cam.spacing + 1e-9) + 1) * cam.spacing
    idx = np.unique(np.minimum(np.searchsorted(travelled, marks - 1e-9), len(true) - 1))
    renderer = PanoramaRenderer.build(world, cam)
    images = np.empty((len(idx), cam.height, cam.width), dtype=np.uint8)
    for lo in range(0, len(idx), chunk):
        images[lo : lo + chunk] = renderer.render(true[idx[lo : lo + chunk]], rng)
    return dataclasses.replace(
        run, config=config, image_stamps=run.odom_stamps[idx], image_poses=true[idx], images=images
    )


def ensure_bag(bag: Path, sim: LoadSim) -> dict[str, Any]:
    """Simulate ``sim`` into ``bag`` unless it already holds exactly that run; the run's figures."""
    import gc
    import shutil

    from ptm_ros.io.simulator import write_run

    sidecar = bag / SIM_FILE
    if sidecar.is_file():
        doc = json.loads(sidecar.read_text())
        if doc.get("settings") == asdict(sim):
            return doc
    if bag.exists():
        shutil.rmtree(bag)
    visits = sim.visits()
    print(f"[bench_load] simulating {visits} visits of {sim.world} ({sim.hours:g} h)", flush=True)
    t0 = time.monotonic()
    run = simulate_chunked(sim, visits)
    t1 = time.monotonic()
    write_run(run, bag)
    doc = {
        "settings": asdict(sim),
        "visits_planned": visits,
        "passages": len(run.passages),
        "duration_s": round(run.duration, 2),
        "path_length_m": round(run.path_length, 1),
        "messages": {
            "/odom": len(run.odom_stamps),
            "/scan": len(run.scan_stamps),
            "/panorama": len(run.image_stamps),
        },
        "simulate_s": round(t1 - t0, 1),
        "write_s": round(time.monotonic() - t1, 1),
    }
    del run
    gc.collect()
    doc["bytes"] = bag_size(bag)
    sidecar.write_text(json.dumps(doc, indent=1) + "\n")
    return doc


def write_params(src: Path, refit_max_visits: int, out: Path) -> Path:
    """``src`` in ROS parameter-file form plus the filter's ``refit_max_visits`` (overrides ptm-bringup's)."""
    import yaml

    doc = yaml.safe_load(src.read_text()) or {}
    if not any(isinstance(v, dict) and "ros__parameters" in v for v in doc.values()):
        doc = {"/**": {"ros__parameters": doc}}
    section = doc.setdefault("topology_filter", {}).setdefault("ros__parameters", {})
    section["refit_max_visits"] = refit_max_visits
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out


# ---------------------------------------------------------------------------------------- the run


@dataclass
class Replay:
    """A sampled ``ptm-bringup`` run: exit code, start and end (monotonic s), the ``/proc`` series per
    pid and what its output told: the filter's per-visit lines ``(wall, index, topologies, how, ms)``,
    the other lines ``(wall, text)`` and the last :data:`KEEP_LINES` lines."""

    code: int = -1
    t_start: float = 0.0
    t_end: float = 0.0
    series: dict[int, Series] = field(default_factory=dict)
    visits: list[tuple[float, int, int, str, float]] = field(default_factory=list)
    lines: list[tuple[float, str]] = field(default_factory=list)
    tail: deque[str] = field(default_factory=lambda: deque(maxlen=KEEP_LINES))
    interrupted: str = ""  # why the replay was stopped early ("" = it ran to the bag's end)
    threads: dict[str, dict[str, int]] = field(default_factory=dict)  # CPU ticks per node, thread name


def thread_ticks(pid: int) -> dict[str, int]:
    """CPU ticks (utime + stime) of a process's threads, summed per thread name (``comm``)."""
    out: dict[str, int] = {}
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            text = (task / "stat").read_text()
        except OSError:
            continue
        name = text[text.index("(") + 1 : text.rindex(")")]
        rest = text.rsplit(")", 1)[1].split()
        out[name] = out.get(name, 0) + int(rest[11]) + int(rest[12])
    return out


def run_replay(cmd: list[str], interval: float, log_file: Path, max_wall: float) -> Replay:
    """Run ``cmd`` (ptm-bringup), sampling it and its children every ``interval`` s, its output copied
    to ``log_file``. After ``max_wall`` s, or on SIGINT / SIGTERM, it gets one SIGINT (it then maps the
    visits completed so far and writes ptm.json) and is sampled until it exits."""
    log = Replay()
    t_start = log.t_start = time.monotonic()
    proc = start_replay(cmd, new_session=True)  # our SIGINT reaches it only through us

    def read() -> None:
        assert proc.stdout is not None
        with log_file.open("w") as fh:
            for raw in proc.stdout:
                now, line = time.monotonic(), raw.rstrip("\n")
                fh.write(raw)
                m = VISIT_LINE.search(line)
                if m is not None:
                    i, k, _, how, ms = m.groups()
                    log.visits.append((now, int(i), int(k), how, float(ms)))
                else:
                    log.lines.append((now, line))
                log.tail.append(line)

    def interrupt(signum: int, frame: Any) -> None:
        log.interrupted = log.interrupted or f"signal {signum}"

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    series = log.series
    series[proc.pid] = Series("ptm_bringup", proc.pid)
    next_tick = last_report = time.monotonic()
    stopped = False
    try:
        while proc.poll() is None:
            now = time.monotonic()
            if now - t_start > max_wall and not log.interrupted:
                log.interrupted = f"--max-wall {max_wall:g} s"
            if log.interrupted and not stopped:
                print(f"[bench_load] stopping the replay ({log.interrupted})", flush=True)
                proc.send_signal(signal.SIGINT)
                stopped = True
            track_children(proc.pid, series)
            for s in series.values():
                if s.sample(now):  # threads come and go: keep each name's largest (latest) count
                    seen = log.threads.setdefault(s.name, {})
                    for name, ticks in thread_ticks(s.pid).items():
                        seen[name] = max(seen.get(name, 0), ticks)
            if now - last_report > 60.0:
                last_report = now
                rss = {
                    s.name: round(s.rss_kb[-1] / MIB) for s in series.values() if s.rss_kb and s.t[-1] == now
                }
                print(
                    f"[bench_load] {now - t_start:.0f} s: {len(log.visits)} visits mapped, RSS MiB {rss}",
                    flush=True,
                )
            next_tick += interval
            time.sleep(max(next_tick - time.monotonic(), 0.0))
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    t_end = time.monotonic()
    reader.join(timeout=10.0)
    log.code, log.t_end = proc.returncode, t_end
    return log


# ----------------------------------------------------------------------------------------- figures


def downsample(t: np.ndarray, y: np.ndarray, points: int) -> list[list[float]]:
    """At most ``points`` ``[t, y]`` pairs: the maximum of ``y`` in each of ``points`` equal time bins."""
    if len(t) <= points:
        return [[round(float(a), 1), round(float(b), 1)] for a, b in zip(t, y, strict=True)]
    edges = np.linspace(t[0], t[-1], points + 1)
    out = []
    for lo, hi in itertools.pairwise(edges):
        sel = (t >= lo) & (t <= hi)
        if np.any(sel):
            k = np.flatnonzero(sel)[np.argmax(y[sel])]
            out.append([round(float(t[k]), 1), round(float(y[k]), 1)])
    return out


def rss_trend(s: Series, window: tuple[float, float], sim_per_wall: float) -> dict[str, Any]:
    """RSS at the window's ends and its least-squares slope over the window (MiB per hour)."""
    t = np.asarray(s.t)
    rss = np.asarray(s.rss_kb, dtype=float) / MIB
    sel = (t >= window[0]) & (t <= window[1])
    if np.count_nonzero(sel) < 3:
        return {"samples": int(np.count_nonzero(sel))}
    slope_s = float(np.polyfit(t[sel] - window[0], rss[sel], 1)[0])  # MiB per wall second
    return {
        "samples": int(np.count_nonzero(sel)),
        "rss_after_warmup_mib": round(float(rss[sel][0]), 1),
        "rss_end_mib": round(float(rss[sel][-1]), 1),
        "rss_max_after_warmup_mib": round(float(rss[sel].max()), 1),
        "growth_mib_per_wall_hour": round(3600.0 * slope_s, 2),
        "growth_mib_per_sim_hour": round(3600.0 * slope_s / sim_per_wall, 2),
    }


def deciles(index: np.ndarray, values: np.ndarray) -> list[dict[str, Any]]:
    """Median, 90th percentile and count of ``values`` per decile of ``index``."""
    out = []
    for part in np.array_split(np.argsort(index, kind="stable"), 10):
        if len(part) == 0:
            continue
        v = values[part]
        out.append(
            {
                "visits": [int(index[part].min()), int(index[part].max())],
                "median": round(float(np.median(v)), 1),
                "p90": round(float(np.percentile(v, 90)), 1),
                "n": len(part),
            }
        )
    return out


def summarize(
    log: Replay,
    out: Path,
    *,
    bag_start_s: float,
    bag_duration_s: float,
    rate: float,
    warmup: float,
    points: int,
) -> dict[str, Any]:
    """The figures of one replay (see the module docstring)."""
    lines, t_start, t_end = log.lines, log.t_start, log.t_end
    played = logged(lines, r"\[ptm_bag_player\]: published (\d+) messages in ([\d.]+) s: (\{.*\})")
    playing = logged(lines, r"\[ptm_bag_player\]: playing ")
    announced = logged(lines, r"\[landmark_detector\]: end of input announced: (\{.*\})")
    missing = logged(lines, r"messages never arrived (\{.*\})")
    finished = logged(lines, r"\[landmark_detector\]: input finished: (\d+) landmark visits")
    mapped = logged(lines, r"\[topology_filter\]: end of visits reported \((\d+)\); (\d+) in the map")
    wrote = logged(lines, r"\[ptm-bringup\] wrote .*ptm\.json: (\d+) visits")
    warnings = [line for _, line in lines if "[WARN]" in line or "[ERROR]" in line]
    sent = ast.literal_eval(played[1].group(3)) if played else None
    lost = ast.literal_eval(missing[1].group(1)) if missing else {}
    received = None
    if announced is not None:
        received = {k: v - lost.get(k, 0) for k, v in ast.literal_eval(announced[1].group(1)).items()}
    doc = json.loads((out / "ptm.json").read_text()) if (out / "ptm.json").is_file() else {}
    stamps = [lm["stamp"] for lm in doc.get("landmarks", [])]

    # the replay window and its speed
    replay_s = float(played[1].group(2)) if played else None
    p0 = playing[0] if playing else t_start
    p1 = p0 + replay_s if replay_s is not None else t_end
    # sim time processed: up to the stamp of the last visit the filter mapped, when it mapped it
    last = next(((w, i) for w, i, *_ in reversed(log.visits) if i < len(stamps)), None)
    processed_s = stamps[last[1]] - bag_start_s if last is not None else 0.0
    processing = processed_s / (last[0] - p0) if last is not None and last[0] > p0 else float("nan")
    sim_per_wall = bag_duration_s / (p1 - p0) if replay_s is not None and p1 > p0 else processing
    window = (p0 + warmup * (p1 - p0), p1)

    # per-visit update time and lag behind the replay
    v_index = np.array([v[1] for v in log.visits])
    v_ms = np.array([v[4] for v in log.visits])
    v_updated = np.array([v[3] == "updated" for v in log.visits], dtype=bool)
    due = [(i, wall, p0 + (stamps[i] - bag_start_s) / rate) for wall, i, *_ in log.visits if i < len(stamps)]
    lag_index = np.array([i for i, _, _ in due], dtype=int)
    lag_s = np.array([wall - at for _, wall, at in due])
    figures: dict[str, Any] = {
        "visits": len(v_index),
        "replays": int(np.count_nonzero(~v_updated)),
        "update_ms_median_per_decile": deciles(v_index, v_ms) if len(v_index) else [],
        "update_ms_median_per_decile_updates_only": deciles(v_index[v_updated], v_ms[v_updated])
        if np.any(v_updated)
        else [],
        "lag_s_per_decile": deciles(lag_index, lag_s) if len(lag_s) else [],
    }
    if np.count_nonzero(v_updated) >= 20:
        tail = v_updated & (v_index >= np.percentile(v_index[v_updated], 20))
        slope = float(np.polyfit(v_index[tail], v_ms[tail], 1)[0])
        figures["update_ms_slope_per_100_visits_after_first_fifth"] = round(100.0 * slope, 2)

    nodes = {}
    for s in log.series.values():
        if not s.t:
            continue
        t = np.asarray(s.t) - p0
        entry = s.summary((p0, p1))
        entry["rss_mib_over_time"] = downsample(t, np.asarray(s.rss_kb, dtype=float) / MIB, points)
        if s.name != "bag_player":
            entry["trend"] = rss_trend(s, window, sim_per_wall)
        ticks = sorted(log.threads.get(s.name, {}).items(), key=lambda kv: -kv[1])
        entry["cpu_s_by_thread"] = {k: round(v / CLK_TCK, 1) for k, v in ticks[:6] if v > 0}
        nodes[s.name] = entry
    return {
        "exit_code": log.code,
        "interrupted": log.interrupted or None,
        "wall_s": round(t_end - t_start, 1),
        "replay_s": replay_s,
        "bag_duration_s": round(bag_duration_s, 1),
        "speedup_achieved": round(sim_per_wall, 2),
        "processed_sim_s": round(processed_s, 1),
        "processing_speedup": round(processing, 2),
        "mapping_after_bag_s": round(wrote[0] - p1, 1) if wrote else None,
        "warmup_s": round(window[0] - p0, 1),
        "messages": {
            "sent": sent,
            "received_by_detector": received,
            "never_arrived": lost,
            "warnings": len(warnings),
            "warning_lines": warnings[:20],
        },
        "visits": {
            "published_by_detector": int(finished[1].group(1)) if finished else None,
            "mapped_by_filter": int(mapped[1].group(2)) if mapped else None,
            "in_ptm_json": len(stamps) if doc else None,
        },
        "filter_counters": {
            k: v
            for k, v in doc.get("diagnostics", {}).items()
            if isinstance(v, int) and not isinstance(v, bool)
        },
        "filter": figures,
        "nodes": nodes,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="multi-loop")
    parser.add_argument("--sim-hours", type=float, default=1.0, help="sim time of the run (default 1 h)")
    parser.add_argument("--odom-rate", type=float, default=100.0)
    parser.add_argument("--scan-rate", type=float, default=40.0)
    parser.add_argument("--pano-rate", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bag", type=Path, default=Path("/tmp/ptm_load/bag"))
    parser.add_argument("--generate-only", action="store_true", help="simulate the bag and stop")
    parser.add_argument("--rate", type=float, default=5.0, help="replay rate (default 5)")
    parser.add_argument("--params", type=Path, default=REPO / "config" / "demo.yaml")
    parser.add_argument("--refit-max-visits", type=int, default=100, help="the filter's (default 100)")
    parser.add_argument("--interval", type=float, default=5.0, help="s between /proc samples (default 5)")
    parser.add_argument("--warmup", type=float, default=0.1, help="replay fraction before the RSS trend")
    parser.add_argument("--points", type=int, default=120, help="RSS samples kept per node (default 120)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="ptm-bringup --timeout (s)")
    parser.add_argument(
        "--max-wall", type=float, default=math.inf, help="stop the replay (SIGINT) after this many s"
    )
    parser.add_argument("--work", type=Path, default=Path("/tmp/ptm_load/out"))
    parser.add_argument("--json", type=Path, default=BENCH / "load.json")
    args = parser.parse_args(argv)
    if args.rate <= 0.0 or args.interval <= 0.0 or not 0.0 <= args.warmup < 1.0:
        parser.error("rate and interval must be > 0 and warmup in [0, 1)")
    sim = LoadSim(args.world, args.sim_hours, args.odom_rate, args.scan_rate, args.pano_rate, args.seed)
    bag = args.bag.resolve()
    made = ensure_bag(bag, sim)
    print(f"[bench_load] bag {bag}: {json.dumps(made)}", flush=True)
    if args.generate_only:
        return 0
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        bag_start_s, duration_s = reader.start_time / 1e9, reader.duration / 1e9
    out = args.work.resolve() / f"rate{args.rate:g}"
    params = write_params(args.params, args.refit_max_visits, args.work.resolve() / "params.yaml")
    cmd = [sys.executable, "-m", "ptm_ros.tools.bringup", "--bag", str(bag), "--rate", f"{args.rate:g}"]
    cmd += ["--params", str(params), "--out", str(out), "--no-report", "--timeout", f"{args.timeout:g}"]
    load_start = os.getloadavg()
    print(f"[bench_load] {' '.join(cmd)}", flush=True)
    log = run_replay(cmd, args.interval, args.work.resolve() / f"rate{args.rate:g}.log", args.max_wall)
    code = log.code
    run = summarize(
        log,
        out,
        bag_start_s=bag_start_s,
        bag_duration_s=duration_s,
        rate=args.rate,
        warmup=args.warmup,
        points=args.points,
    )
    run["load_average"] = {
        "start": [round(x, 2) for x in load_start],
        "end": [round(x, 2) for x in os.getloadavg()],
    }
    if code != 0:
        print("[bench_load] ptm-bringup failed:\n" + "\n".join(list(log.tail)[-40:]), flush=True)
    doc = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": " ".join(["PYTHONPATH=. .venv/bin/python bench/bench_load.py", *(argv or sys.argv[1:])]),
        "machine": {"cpus": os.cpu_count()},
        "bag": {"path": str(bag), **made},
        "rate": args.rate,
        "refit_max_visits": args.refit_max_visits,
        "interval_s": args.interval,
        "run": run,
    }
    args.json.write_text(json.dumps(doc, indent=1) + "\n")
    f, n = run["filter"], run["nodes"]
    print(
        f"[bench_load] exit {code}, wall {run['wall_s']} s, speed-up {run['speedup_achieved']}x, "
        f"visits {run['visits']}, RSS growth MiB/sim-h "
        f"{ {k: v.get('trend', {}).get('growth_mib_per_sim_hour') for k, v in n.items()} }, "
        f"update ms per decile {[d['median'] for d in f['update_ms_median_per_decile']]}",
        flush=True,
    )
    print(f"[bench_load] wrote {args.json}", flush=True)
    return int(code != 0)


if __name__ == "__main__":
    sys.exit(main())
