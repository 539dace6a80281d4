"""``ptm-bringup [--bag BAG] [--rate R] [--params YAML] [--out DIR]``: the node suite without ros2 launch.

Starts ``map_publisher``, ``topology_filter`` and ``landmark_detector`` as separate processes talking
over DDS (each in its own process group, logs streamed with a ``[node]`` prefix), waits until their
services are discovered, then — with ``--bag`` — starts ``ptm-bag-player`` (``use_sim_time`` on every
node). Every node gets the same parameters: ``DIR/params.yaml``, the full configuration (defaults, then
``--params``; with a bag, the detector ``ptm-run`` would pick and the map drawn from every odometry
sample and scan, :func:`ptm_ros.maps.mapping.every_sample`) in ROS parameter-file form, saved as
``DIR/config.yaml`` too; then the bringup's settings for an exact replay (the detector's ``stall_s: 0``
and ``trace_rows: 0``, the filter's ``refit_max_visits: 0``, ``use_sim_time`` with a bag); then
``--params`` itself when it is a ROS parameter file, so its per-node sections apply and may override
those (e.g. ``landmark_detector: ros__parameters: sensor_qos: sensor_data``).
The bag's ``topics.odom`` / ``scan`` / ``panorama`` are remapped onto the detector's ``odom`` / ``scan`` /
``panorama``, and the detector waits only for the streams the bag has (as ``ptm-run`` does).

End of a bag: the player announces it, the detector completes its last visits, the filter processes
them and marks its ensemble complete; ``ptm-bringup`` asks the map publisher (``/map_publisher/save_ptm``)
to write ``DIR/ptm.json`` — the ensemble it received over DDS — as soon as that ensemble is complete,
and then the occupancy map it drew online along the MAP topology's smoothed trajectory
(``/map_publisher/save_map``: ``DIR/map.yaml``, ``map.pgm``, ``map.png``), and takes that trajectory
(``ptm_trajectory``) and the detector's surprise trace (``/landmark_detector/surprise_trace``) before
the nodes stop. From these and the bag's odometry and scans it then writes what ``ptm-run`` writes, with
``ptm-run``'s own writers (:func:`ptm_ros.tools.outputs.write_outputs`, issue #24): ``ptm.json`` gains
``bag``, ``detector``, the input messages skipped and why (``diagnostics``: the landmark detector's
counts from its final ``/diagnostics`` status under ``ptm-run``'s keys, ``skipped`` and
``read_skipped`` among them, with the extractor's counters; the same warning line as ``ptm-run``) and,
with a ground truth (``--ground-truth``, else the bag's own), the trajectory errors and the map's
quality; ``route_graph.geojson`` (on the map's walls and trajectory) and the report
with ``ptm-run``'s figures (unless ``--no-report``). On the bundled bag every file but ``params.yaml``
(the nodes' parameters) and ``config.yaml``'s ``mapping`` section (unused by ``ptm-run``) has
``ptm-run``'s content, timings and counters aside (tested).
On SIGINT / SIGTERM it stops the player, has the detector complete its pending visits (``~/flush``),
gives the filter up to 30 s to map them (a second SIGINT skips the wait) and writes whatever the map
publisher has (nothing when it holds no visit). Then it stops every process: SIGINT to
its group, SIGTERM after 5 s, SIGKILL after 3 more; stray members of a group are killed too, so no
process outlives the bringup.

Faults (issue #9). A node that dies during the run ends it (exit 1), unless ``--respawn N``: then it is
restarted in place, up to N times per node. ``--autosave N`` has the filter save its state to
``DIR/topology_filter/state.npz`` every N visits (parameters ``state_file``, ``autosave_every``; a state
file left by an earlier run in DIR is deleted at the start); a respawned filter gets ``resume: true``,
continues from that file and takes the visits lost since the last save from the detector's
transient-local history, so the map ends exactly as without the fault (without ``--autosave`` it
rebuilds everything from that history). A respawned detector starts a new detector session from the
bag position it then sees (it never receives what was replayed while it was down, nor what the player
had sent ahead of it and it had not read yet), so the filter starts a new map of the rest of the run;
the player's reliable writers wait for a killed reader until DDS declares it gone. After a bag it
prints ``ptm-run``'s summary: the most probable topologies, scored against the ground truth when there
is one. Exit codes: 0 written, 1 a node failed / nothing to write / timeout, 2 bad arguments,
parameters, ground truth or bag (also a bag that ends without one landmark visit, as ``ptm-run`` refuses
it: said as soon as the filter's ensemble of the whole bag is empty).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from ptm_ros.config import PtmConfig

PROG = "ptm-bringup"
NODES = ("map_publisher", "topology_filter", "landmark_detector")
STOP_TIMEOUTS = (5.0, 3.0, 2.0)  # s after SIGINT, after SIGTERM, after SIGKILL
SIGINT_GRACE_S = 30.0  # s the filter gets to map the last visits after SIGINT (a second SIGINT skips)
STATE_FILE = "topology_filter/state.npz"  # the filter's saved state, relative to --out
MAP_TIMEOUT_S = 120.0  # s the map publisher gets, after the ensemble is complete, to draw every keyframe
REPLY_TIMEOUT_S = 30.0  # s to wait for the map's trajectory and for the detector's surprise trace


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="Start the ptm_ros nodes (and a bag player) over DDS.")
    p.add_argument(
        "--bag",
        type=Path,
        default=None,
        help="replay this rosbag2 and stop at its end (default: none, the nodes read the live topics)",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="replay speed (0 = as fast as the nodes keep up; default: %(default)s)",
    )
    p.add_argument(
        "--params",
        type=Path,
        default=None,
        help="YAML parameter file, plain or ROS form (default: none, the built-in defaults)",
    )
    p.add_argument(
        "--out", type=Path, default=Path("out/bringup"), help="output directory (default: %(default)s)"
    )
    p.add_argument(
        "--wait", type=float, default=60.0, help="s to wait for the nodes to come up (default: %(default)s)"
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        help="s to wait for the map after the bag ended (default: %(default)s)",
    )
    p.add_argument(
        "--ground-truth",
        type=Path,
        default=None,
        help="with --bag, score against this ground truth: a CARMEN *-gt-*.txt file or a ground_truth.json "
        "(default: the bag's own ground_truth.json, if any)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="use the ground truth even when it looks like another run's (most of the bag's odometry "
        "outside its time span, or the odometry not moving as it does; checked before the nodes start; "
        "default: off, refused)",
    )
    p.add_argument("--no-report", action="store_true", help="skip the report and figures (with --bag)")
    p.add_argument("--top", type=int, default=5, help="topologies to print (default: %(default)s)")
    p.add_argument(
        "--respawn",
        type=int,
        default=0,
        metavar="N",
        help="restart a node that dies, up to N times per node (default: %(default)s: a dead node ends "
        "the run)",
    )
    p.add_argument(
        "--autosave",
        type=int,
        default=0,
        metavar="N",
        help=f"the filter saves its state to DIR/{STATE_FILE} every N visits; a respawned filter resumes "
        "from it (default: %(default)s, off)",
    )
    return p


# ------------------------------------------------------------------------------------------ parameters


def _nest_dotted(params: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in params.items():
        *path, leaf = str(key).split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = _nest_dotted(value) if isinstance(value, dict) else value
    return out


def load_parameters(path: Path | None) -> tuple[Any, bool]:
    """The configuration of a ``--params`` file and whether it is a ROS parameter file.

    Node parameters (:data:`ptm_ros.nodes.common.NODE_PARAMETERS`) in a ROS file are left to the nodes.

    Raises:
        ConfigError: a malformed file, unknown keys or bad values.
    """
    from ptm_ros.config import PtmConfig, unwrap_ros_parameters
    from ptm_ros.configio import from_dict, load_yaml
    from ptm_ros.nodes.common import NODE_PARAMETERS

    if path is None:
        return PtmConfig(), False
    doc = load_yaml(path)
    is_ros = any(isinstance(v, dict) and "ros__parameters" in v for v in doc.values())
    if is_ros:
        stripped = {}
        for name, section in doc.items():
            params = section.get("ros__parameters") if isinstance(section, dict) else None
            if isinstance(params, dict):
                params = _nest_dotted({k: v for k, v in params.items() if k not in NODE_PARAMETERS})
            stripped[name] = {**section, "ros__parameters": params} if isinstance(section, dict) else section
        doc = unwrap_ros_parameters(stripped)
    return from_dict(PtmConfig, doc), is_ros


def odometry_frame(bag: Path, topic: str) -> str:
    """``header.frame_id`` of the bag's first odometry message ("odom" when empty)."""
    from ptm_ros.io.bag import iter_raw, typestore

    for raw in iter_raw(bag, [topic]):
        message = typestore().deserialize_cdr(raw.rawdata, raw.msgtype)
        # rosbags types a deserialized message as object; an odometry message has a header
        return message.header.frame_id or "odom"  # type: ignore[attr-defined]
    return "odom"


# ------------------------------------------------------------------------------------------- processes


@dataclass
class Child:
    """A started process (leader of its own process group) and the thread streaming its output."""

    name: str
    popen: subprocess.Popen[str]
    thread: threading.Thread = field(repr=False)

    @property
    def running(self) -> bool:
        return self.popen.poll() is None


def _stream(name: str, pipe: TextIO, out: TextIO, lock: threading.Lock) -> None:
    for line in pipe:
        with lock:
            out.write(f"[{name}] {line}" if line.endswith("\n") else f"[{name}] {line}\n")
            out.flush()
    pipe.close()


_PRINT_LOCK = threading.Lock()


@contextlib.contextmanager
def signals_blocked(signals: Collection[int]) -> Iterator[None]:
    """Block ``signals`` in this thread for the block (a process started meanwhile inherits the mask)."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def spawn(
    name: str, cmd: Sequence[str], env: dict[str, str], out: TextIO = sys.stdout, *, node: bool = False
) -> Child:
    """Start ``cmd`` in a new session (its own process group), streaming its output with a prefix.

    A ``node`` starts with SIGINT and SIGTERM blocked: its entry point (:func:`ptm_ros.nodes.common.run_node`)
    unblocks them once it answers them as a stop request, so a stop sent while the node still imports its
    modules ends it cleanly (exit code 0) instead of interrupting the import."""
    from ptm_ros.nodes.common import STOP_SIGNALS

    with signals_blocked(STOP_SIGNALS if node else ()):
        popen = subprocess.Popen(
            list(cmd),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            text=True,
            bufsize=1,
            start_new_session=True,
        )
    assert popen.stdout is not None
    thread = threading.Thread(target=_stream, args=(name, popen.stdout, out, _PRINT_LOCK), daemon=True)
    thread.start()
    return Child(name, popen, thread)


def _signal_group(child: Child, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(child.popen.pid, sig)


def stop_all(children: Sequence[Child], timeouts: Sequence[float] = STOP_TIMEOUTS) -> dict[str, int | None]:
    """SIGINT every group, then SIGTERM, then SIGKILL those still running; returns the exit codes."""
    for sig, wait in zip((signal.SIGINT, signal.SIGTERM, signal.SIGKILL), timeouts, strict=True):
        alive = [c for c in children if c.running]
        if not alive:
            break
        for c in alive:
            _signal_group(c, sig)
        deadline = time.monotonic() + wait
        for c in alive:
            with contextlib.suppress(subprocess.TimeoutExpired):
                c.popen.wait(timeout=max(deadline - time.monotonic(), 0.01))
    for c in children:
        _signal_group(c, signal.SIGKILL)  # stray members of a group whose leader has exited
        c.thread.join(timeout=2.0)
    return {c.name: c.popen.poll() for c in children}


def child_env() -> dict[str, str]:
    """The environment of the children: ours, unbuffered, one BLAS thread, ament prefix set."""
    env = dict(os.environ)
    env.setdefault("AMENT_PREFIX_PATH", sys.prefix)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    return env


def node_command(name: str, ros_args: Sequence[str]) -> list[str]:
    """``python -m ptm_ros.nodes.<name> --ros-args ...`` (independent of installed console scripts)."""
    return [sys.executable, "-m", f"ptm_ros.nodes.{name}", "--ros-args", *ros_args]


# ------------------------------------------------------------------------------------------- the run


@dataclass(frozen=True)
class Plan:
    """What to start: the node commands in start order, the player's command (with ``--bag``), timeouts,
    the configuration and the ground truth of a bag's outputs."""

    out: Path
    nodes: dict[str, list[str]]
    player: list[str] | None
    wait: float
    timeout: float
    config: PtmConfig  # the configuration the nodes run with (config.yaml)
    respawn: int = 0
    scans: bool = True  # the input has scans (an occupancy map is drawn)
    truth: Path | None = None  # the ground truth a bag's outputs are scored against

    def restart_command(self, name: str) -> list[str]:
        """The command of a respawned node: the filter resumes from its saved state (if any)."""
        extra = ["-p", "resume:=true"] if name == "topology_filter" else []
        return [*self.nodes[name], *extra]


def make_plan(args: argparse.Namespace) -> Plan:
    """Validate the parameters and the bag, write ``DIR/params.yaml`` and ``DIR/config.yaml``.

    Raises:
        PtmError: bad parameters or bag (nothing has been started).
    """
    from ptm_ros.config import ros_parameters_yaml, save_config
    from ptm_ros.errors import BagError, ConfigError
    from ptm_ros.factories import with_detector_kind
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.maps.mapping import every_sample
    from ptm_ros.nodes.bag_player import bag_topics
    from ptm_ros.tools.outputs import run_odometry
    from ptm_ros.tools.paths import output_dir
    from ptm_ros.tools.pipeline import check_ground_truth_of_run, find_ground_truth

    config, params_is_ros = load_parameters(args.params)
    t = config.topics
    topics = bag_topics(args.bag) if args.bag is not None else {}
    if args.bag is not None and t.odom not in topics:
        msg = f"bag {args.bag} has no odometry topic {t.odom} (topics: {sorted(topics)})"
        raise BagError(msg)
    if args.ground_truth is not None and args.bag is None:
        msg = "--ground-truth needs --bag (the score comes with the outputs written after a bag)"
        raise ConfigError(msg)
    truth = args.ground_truth
    if truth is None and args.bag is not None:
        truth = find_ground_truth(args.bag)  # a simulated bag's own, as ptm-run finds it
    if truth is not None and args.bag is not None:  # a bad file or another run's fails now, not after the run
        odometry = read_run(args.bag, odom_topic=t.odom, scan_topic=None, image_topic=None, require=(t.odom,))
        check_ground_truth_of_run(
            load_ground_truth(truth), run_odometry(odometry), force=args.force, log=_note
        )
    present = {
        name: topic in topics and topics[topic].count > 0
        for name, topic in (("scans", t.scan), ("images", t.panorama))
    }
    if args.bag is not None:  # ptm-run's map (every sample and scan) and the detector ptm-run picks
        config = with_detector_kind(config, has_scans=present["scans"], has_images=present["images"])
        config = replace(config, mapping=every_sample(config.mapping))
    frame = odometry_frame(args.bag, t.odom) if args.bag is not None else "odom"
    out: Path = output_dir(args.out.resolve())
    out.mkdir(parents=True, exist_ok=True)
    params_file = out / "params.yaml"
    params_file.write_text(ros_parameters_yaml(config))
    save_config(config, out / "config.yaml")
    # order matters (the last value wins): the configuration, the bringup's node settings, the user's
    # ROS parameter file (may override those), the outputs the bringup relies on
    mine = ["--params-file", str(params_file)]
    mine += ["-p", f"use_sim_time:={'true' if args.bag is not None else 'false'}"]
    users = ["--params-file", str(args.params.resolve())] if params_is_ros else []
    detector = [*mine, "-r", f"odom:={t.odom}", "-r", f"scan:={t.scan}", "-r", f"panorama:={t.panorama}"]
    if args.bag is not None:  # wait for the streams the bag has (as ptm-run does), however late they come
        for name in ("scans", "images"):
            detector += ["-p", f"use_{name}:={str(present[name]).lower()}"]
        detector += ["-p", "stall_s:=0.0", "-p", "trace_rows:=0"]  # the whole surprise trace, as ptm-run
    filt = [*mine, "-p", "refit_max_visits:=0", "-p", f"frame_id:={frame}"]
    state = out / STATE_FILE
    state.unlink(missing_ok=True)  # a previous run's state must never be resumed by this one
    if args.autosave > 0:
        filt += ["-p", f"state_file:={state}", "-p", f"autosave_every:={args.autosave}"]
    filt += users
    nodes = {
        "map_publisher": node_command("map_publisher", [*mine, *users, "-p", f"out_dir:={out}"]),
        "topology_filter": node_command(
            "topology_filter", [*filt, "-p", f"out_dir:={out / 'topology_filter'}"]
        ),
        "landmark_detector": node_command("landmark_detector", [*detector, *users]),
    }
    player = None
    if args.bag is not None:
        replay = [x for x in (t.odom, t.scan, t.panorama) if x in topics]
        player = [sys.executable, "-m", "ptm_ros.nodes.bag_player", str(args.bag.resolve())]
        player += ["--rate", f"{args.rate:g}", "--wait", f"{args.wait:g}", "--topics", *replay]
    return Plan(
        out=out,
        nodes=nodes,
        player=player,
        wait=args.wait,
        timeout=args.timeout,
        respawn=args.respawn,
        scans=args.bag is None or present["scans"],
        config=config,
        truth=truth,
    )


@dataclass(frozen=True)
class NodeOutputs:
    """What the nodes made beside ptm.json, collected before they stop: the map publisher's map files
    (keys of ``outputs.OUTPUT_FILES``) and the trajectory it drew them along (``(stamps, poses)``), the
    detector's surprise trace (None: none) and its input counts (its final ``/diagnostics`` values as
    ``ptm-run``'s ptm.json ``diagnostics``: :func:`ptm_ros.nodes.landmark_detector.input_counts`)."""

    map_files: dict[str, Path] = field(default_factory=dict)
    trajectory: tuple[Any, Any] | None = None
    surprise: Any | None = None
    input_counts: dict[str, Any] | None = None  # the detector's, ptm-run's diagnostics keys (None: none came)


class Bringup:
    """The running suite: children, the bringup's own ROS node (service clients) and the stop flag."""

    def __init__(self, plan: Plan) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        from ptm_ros.nodes.common import LATCHED_QOS

        self.plan = plan
        self.children: list[Child] = []
        self.respawns = dict.fromkeys(plan.nodes, 0)
        self.stop_requested = False
        self.error: str | None = None  # why the input was refused (exit code 2) after the nodes started
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("ptm_bringup", context=self.context)
        self.save_client = self.node.create_client(Trigger, "/map_publisher/save_ptm")
        self._clients = [
            self.save_client,
            self.node.create_client(Trigger, "/topology_filter/save_ptm"),
            self.node.create_client(Trigger, "/landmark_detector/flush"),
            self.node.create_client(Trigger, "/map_publisher/save_map"),
        ]
        self.trace_client = self.node.create_client(Trigger, "/landmark_detector/surprise_trace")
        self.graph_complete = False  # the filter's latest ensemble covers a finished input
        self.graph_visits: int | None = None  # the visits it holds
        self.node.create_subscription(String, "/ptm_graph", self._on_graph, LATCHED_QOS)
        self.trajectory: Any = None  # the map publisher's latest ptm_trajectory (nav_msgs/Path)
        self.node.create_subscription(PathMsg, "/ptm_trajectory", self._on_trajectory, LATCHED_QOS)
        self.detector_status: dict[str, str] | None = None  # the values of the detector's latest status
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)
        self.outputs = NodeOutputs()  # what the nodes made, for the outputs written after a bag
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on_graph(self, msg: Any) -> None:
        try:
            stream = json.loads(msg.data).get("stream", {})
        except (json.JSONDecodeError, AttributeError):
            return
        self.graph_complete = bool(isinstance(stream, dict) and stream.get("complete"))
        visits = stream.get("visits") if isinstance(stream, dict) else None
        self.graph_visits = visits if isinstance(visits, int) and not isinstance(visits, bool) else None

    def _on_trajectory(self, msg: Any) -> None:
        self.trajectory = msg

    def _on_diagnostics(self, msg: Any) -> None:
        from ptm_ros.nodes.landmark_detector import NODE_NAME as DETECTOR

        for status in msg.status:
            if status.hardware_id == DETECTOR:
                self.detector_status = {kv.key: kv.value for kv in status.values}

    def log(self, text: str) -> None:
        with _PRINT_LOCK:
            print(f"[{PROG}] {text}", flush=True)

    def failed_child(self, *, player: bool = True) -> Child | None:
        """A node that exited (at all) or (with ``player``) a player that exited with an error."""
        for c in self.children:
            code = c.popen.poll()
            if code is not None and (c.name != "player" or (player and code != 0)):
                return c
        return None

    def call(self, client: Any, timeout: float = 10.0) -> Any:
        """Call a Trigger service; the response, or None without an answer."""
        from std_srvs.srv import Trigger

        if not client.service_is_ready():
            return None
        future = client.call_async(Trigger.Request())
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        return future.result() if future.done() else None

    def wait_for_nodes(self) -> bool:
        """Wait until every node's services are discovered (False on timeout, stop or a dead node)."""
        deadline = time.monotonic() + self.plan.wait
        while time.monotonic() < deadline and not self.stop_requested:
            if self.failed_child() is not None:
                return False
            if all(c.service_is_ready() for c in self._clients):
                return True
            self.executor.spin_once(timeout_sec=0.1)
        return False

    def save(self) -> dict[str, Any] | None:
        """Ask the map publisher to write ptm.json; its parsed response, or None without an answer."""
        result = self.call(self.save_client)
        if result is None:
            return None
        if not result.success:
            return {"success": False, "message": result.message}
        try:
            return {"success": True, **json.loads(result.message)}
        except json.JSONDecodeError:
            return {"success": True, "message": result.message}

    def execute(self, env: dict[str, str]) -> int:
        """Start everything, supervise until the map is complete, SIGINT/SIGTERM or a failure."""
        for name, cmd in self.plan.nodes.items():
            self.children.append(spawn(name, cmd, env, node=True))
        if not self.wait_for_nodes():
            if self.stop_requested:
                return self.write_what_we_have()
            dead = self.failed_child()
            what = f"{dead.name} exited with code {dead.popen.poll()}" if dead else "not discovered in time"
            self.log(f"error: the nodes did not come up: {what}")
            return 1
        self.log("nodes are up")
        if self.plan.player is not None:
            self.children.append(spawn("player", self.plan.player, env))
        player_done_at: float | None = None
        while not self.stop_requested:
            dead = self.failed_child()
            if dead is not None and self.respawn(dead, env):
                continue
            if dead is not None:
                self.log(f"error: {dead.name} exited with code {dead.popen.poll()}")
                self.write_what_we_have()
                return 1
            if (
                self.plan.player is not None
                and player_done_at is None
                and self.children[-1].popen.poll() == 0
            ):
                player_done_at = time.monotonic()
                self.log("bag finished; waiting for the last visits to be mapped")
            if player_done_at is None:
                self.executor.spin_once(timeout_sec=0.1)
                continue
            if self.graph_complete and self.graph_visits == 0:  # the whole bag, and not one landmark
                self.log("the bag finished without a landmark visit: nothing to map")
                self.error = "no landmark visits were detected: nothing to map"
                return 2
            if self.graph_complete:  # the map publisher has it too, or will in a moment
                reply = self.save()
                if reply and reply.get("success") and reply.get("complete"):
                    return self.announce(reply)
                time.sleep(0.2)
            if time.monotonic() - player_done_at > self.plan.timeout:
                self.log(f"error: the map was not complete {self.plan.timeout:g} s after the bag ended")
                self.write_what_we_have()
                return 1
            self.executor.spin_once(timeout_sec=0.2)
        self.end_input()
        return self.write_what_we_have()

    def respawn(self, dead: Child, env: dict[str, str]) -> bool:
        """Restart a dead node in its place (``--respawn``); False when it may not be restarted."""
        if dead.name not in self.respawns or self.respawns[dead.name] >= self.plan.respawn:
            return False
        self.respawns[dead.name] += 1
        self.log(
            f"{dead.name} exited with code {dead.popen.poll()}; restarting it "
            f"({self.respawns[dead.name]} of {self.plan.respawn})"
        )
        stop_all([dead])  # its process group's stray members, its output thread
        restart = self.plan.restart_command(dead.name)
        self.children[self.children.index(dead)] = spawn(dead.name, restart, env, node=True)
        return True

    def end_input(self) -> None:
        """On SIGINT: stop the player, have the detector complete its visits (``~/flush``) and give the
        filter up to :data:`SIGINT_GRACE_S` to map them (a second SIGINT skips the wait)."""
        player = [c for c in self.children if c.name == "player"]
        stop_all(player)
        if self.call(self._clients[2], timeout=5.0) is None:
            return
        self.log(f"input ended; mapping the last visits (up to {SIGINT_GRACE_S:g} s, SIGINT again to skip)")
        self.stop_requested = False
        deadline = time.monotonic() + SIGINT_GRACE_S
        while not (self.graph_complete or self.stop_requested or time.monotonic() > deadline):
            if self.failed_child(player=False) is not None:
                return
            self.executor.spin_once(timeout_sec=0.1)
        self.stop_requested = True

    def announce(self, reply: dict[str, Any]) -> int:
        self.log(f"wrote {reply['path']}: {reply['visits']} visits, {reply['topologies']} topologies")
        info = self.save_map()
        if self.plan.player is not None and not self.stop_requested:  # a bag's end: ptm-run's outputs follow
            self.outputs = self.collect(info)
        return 0

    def save_map(self) -> dict[str, Any] | None:
        """Ask the map publisher to write the occupancy map (``DIR/map.yaml`` + its image + ``map.png``);
        with a bag, until the map covers every keyframe scan the detector sent (at most
        :data:`MAP_TIMEOUT_S`). A bag without scans has no map (logged, not an error). Returns the map
        publisher's answer (the files, the trajectory's length), None without a map."""
        if not self.plan.scans:
            self.log("no occupancy map: the input has no scans")
            return None
        deadline = time.monotonic() + MAP_TIMEOUT_S
        while True:
            result = self.call(self._clients[3], timeout=60.0)
            info = json.loads(result.message) if result is not None and result.success else None
            if (info is not None and info["complete"]) or time.monotonic() > deadline or self.stop_requested:
                break
            self.executor.spin_once(timeout_sec=0.5)
        if result is None:
            self.log("no occupancy map: the map publisher did not answer")
        elif info is None:
            self.log(f"no occupancy map: {result.message}")
        else:
            if not info["complete"]:
                self.log("warning: the map does not cover every keyframe scan (the map publisher lags)")
            self.log(
                f"wrote {info['yaml']}: {info['width']} x {info['height']} cells, {info['scans']} scans "
                f"(map {info['maps']} drawn online, {info['map_ms']:.0f} ms; input {info['input']})"
            )
        return info

    def collect(self, info: dict[str, Any] | None) -> NodeOutputs:
        """At a bag's end, before the nodes stop: what the outputs written after it need from them (the
        saved map of ``info``, its trajectory, the detector's surprise trace)."""
        counts = self.input_counts()
        if info is None:
            return NodeOutputs(surprise=self.surprise_trace(), input_counts=counts)
        files = {f"map_{kind}": Path(info[kind]) for kind in ("image", "yaml", "png")}
        return NodeOutputs(files, self.map_trajectory(info), self.surprise_trace(), counts)

    def input_counts(self) -> dict[str, Any] | None:
        """The detector's counts of the whole input, from its latest ``/diagnostics`` status once one says
        the input is finished (it publishes one at once, then every second), waiting up to
        :data:`REPLY_TIMEOUT_S` for it; as ``ptm-run``'s ptm.json ``diagnostics``
        (:func:`ptm_ros.nodes.landmark_detector.input_counts`). None (logged) when none comes."""
        from ptm_ros.nodes.landmark_detector import input_counts

        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while time.monotonic() < deadline and not self.stop_requested:
            status = self.detector_status
            if status is not None and status.get("finished") == "True":
                return input_counts(status)
            self.executor.spin_once(timeout_sec=0.1)
        self.log("warning: the detector's final counts did not arrive on /diagnostics: none in ptm.json")
        return None

    def map_trajectory(self, info: dict[str, Any]) -> tuple[Any, Any] | None:
        """``(stamps, poses)`` of the trajectory the saved map was drawn along (the map publisher's
        ``ptm_trajectory`` of ``info["trajectory"]`` poses), waiting up to :data:`REPLY_TIMEOUT_S` for it;
        None (logged) when it does not come."""
        from ptm_ros.nodes.common import path_arrays

        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while time.monotonic() < deadline and not self.stop_requested:
            msg = self.trajectory
            if msg is not None and len(msg.poses) == info["trajectory"]:
                return path_arrays(msg)
            self.executor.spin_once(timeout_sec=0.1)
        self.log("warning: the map's trajectory did not arrive: no trajectory error, route graph off the map")
        return None

    def surprise_trace(self) -> Any | None:
        """The detector's surprise trace (``~/surprise_trace``), None (logged) for a detector without one."""
        from ptm_ros.errors import DataError
        from ptm_ros.perception.surprise import trace_from_dict

        result = self.call(self.trace_client, timeout=REPLY_TIMEOUT_S)
        if result is None or not result.success:
            self.log(f"no surprise trace: {result.message if result else 'the detector did not answer'}")
            return None
        try:
            return trace_from_dict(json.loads(result.message))
        except (json.JSONDecodeError, DataError) as err:
            self.log(f"no surprise trace: {err}")
            return None

    def write_what_we_have(self) -> int:
        """Have the map publisher write whatever it has (on SIGINT or after an error)."""
        reply = self.save()
        if reply and reply.get("success"):
            return self.announce(reply)
        reason = reply.get("message") if reply else "the map publisher did not answer"
        self.log(f"nothing written to {self.plan.out / 'ptm.json'}: {reason}")
        return 1

    def close(self) -> dict[str, int | None]:
        """Stop every process and the bringup's own node; returns the exit codes."""
        import rclpy

        codes = stop_all(self.children)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        return codes


def _note(note: str) -> None:
    print(f"{PROG}: {note}", file=sys.stderr)


def finish(args: argparse.Namespace, plan: Plan, outputs: NodeOutputs) -> str:
    """After a bag: ``ptm-run``'s outputs from what the nodes made (``outputs.write_outputs`` on the map
    publisher's ptm.json, map and trajectory, the detector's surprise trace and the bag's odometry and
    scans): ptm.json with the trajectory errors and the map's quality when a ground truth is known,
    config.yaml, route_graph.geojson and (unless ``--no-report``) the report; returns ``ptm-run``'s
    summary lines."""
    from ptm_ros.io.bag import read_run
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.ptm import load_ptm
    from ptm_ros.tools.outputs import OUTPUT_FILES, provenance, saved_map, write_outputs
    from ptm_ros.tools.run import format_summary, skipped_warning

    ptm = load_ptm(plan.out / OUTPUT_FILES["ptm"])
    extra = {**provenance(args.bag, plan.config), **ptm.extra}
    if outputs.input_counts is not None:  # the detector's counts of the input, under ptm-run's keys
        extra["diagnostics"] = {**dict(extra.get("diagnostics") or {}), **outputs.input_counts}
    ptm = replace(ptm, extra=extra)
    t = plan.config.topics
    run = read_run(args.bag, odom_topic=t.odom, scan_topic=t.scan, image_topic=None, require=(t.odom,))
    result = write_outputs(
        plan.out,
        ptm,
        plan.config,
        run,
        saved_map(run, outputs.map_files, outputs.trajectory),
        truth=load_ground_truth(plan.truth) if plan.truth is not None else None,
        truth_file=plan.truth,
        surprise=outputs.surprise,
        write_report=not args.no_report,
        title=f"PTM of {args.bag.name} (node suite over DDS)",
        log=_note,
    )
    warning = skipped_warning(result.diagnostics)
    if warning:
        print(f"{PROG}: warning: {warning}", file=sys.stderr)
    return format_summary(result, args.top)


def run(args: argparse.Namespace) -> int:
    """Validate, start, supervise, stop; then, after a bag, report."""
    from ptm_ros.errors import PtmError

    try:
        plan = make_plan(args)
    except PtmError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    suite = Bringup(plan)

    def request_stop(signum: int, frame: Any) -> None:
        suite.stop_requested = True

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        code = suite.execute(child_env())
    finally:
        codes = suite.close()
        suite.log(f"stopped: exit codes {codes}")
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if suite.error is not None:
        print(f"{PROG}: error: {args.bag}: {suite.error}", file=sys.stderr)
    ptm_path = plan.out / "ptm.json"
    if code == 0 and args.bag is not None and not suite.stop_requested and ptm_path.is_file():
        try:
            print(finish(args, plan, suite.outputs), flush=True)
        except (PtmError, OSError) as err:
            print(f"{PROG}: error: cannot write the outputs beside {ptm_path}: {err}", file=sys.stderr)
            return 1
    return code


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not args.rate >= 0.0:
        print(f"{PROG}: error: --rate must be >= 0, got {args.rate}", file=sys.stderr)
        return 2
    for name in ("respawn", "autosave"):
        if getattr(args, name) < 0:
            print(f"{PROG}: error: --{name} must be >= 0, got {getattr(args, name)}", file=sys.stderr)
            return 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
