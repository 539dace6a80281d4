"""The ROS 2 nodes: parameters from the config dataclasses, message conversions, the streaming filter
session against the offline pipeline, the graph / marker / path content, and the nodes over real DDS
(in-process nodes on a private domain, plus start-up failures of node processes)."""

from __future__ import annotations

import faulthandler
import io
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from ros_helpers import Inbox, dds_env, next_domain_id, ros_context, wait_for

from ptm_ros.config import PtmConfig, load_config
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.factories import make_extractor
from ptm_ros.io.bag import BagWriter, iter_raw, read_run, yaw_to_quaternion
from ptm_ros.io.validation import scan_payload, valid_stamp
from ptm_ros.maps.occupancy import load_map, to_ros_data, trinary
from ptm_ros.model.partitions import enumerate_partitions
from ptm_ros.model.ptm import Landmark, Topology, from_json_dict, make_ptm
from ptm_ros.nodes import common, stream_guard
from ptm_ros.nodes.filter_inbox import visit_line
from ptm_ros.nodes.map_publisher import map_path
from ptm_ros.nodes.messages import (
    END_OF_INPUT_SCHEMA,
    END_SCHEMA,
    edge_probabilities,
    graph_document,
    parse_graph,
    parse_visit_message,
)
from ptm_ros.nodes.topology_filter import ensemble_markers, topology_alpha
from ptm_ros.perception.landmarks import (
    ExtractorDiagnostics,
    diagnostics_dict,
    visit_to_json,
    with_input_skips,
)
from ptm_ros.session import FilterSession
from ptm_ros.settings import Settings, setting
from ptm_ros.tools.pipeline import detect_visits

# --------------------------------------------------------------------------------------------- fixtures


def no_laser() -> PtmConfig:
    return load_config(None, {"model": {"use_laser": False}, "inference": {"particles": 30}})


# ------------------------------------------------------------------------------------------- parameters


def filter_and_map_publisher(ros, overrides, out_dir, map_overrides=()):
    """A topology filter node (``overrides``) and a map publisher writing to ``out_dir`` (and
    ``map_overrides``), in ``ros``."""
    from rclpy.parameter import Parameter

    from ptm_ros.nodes.map_publisher import MapPublisherNode
    from ptm_ros.nodes.topology_filter import TopologyFilterNode

    flt = ros.add(TopologyFilterNode(context=ros.context, parameter_overrides=overrides))
    mine = [Parameter("out_dir", value=str(out_dir)), *map_overrides]
    mp = ros.add(MapPublisherNode(context=ros.context, parameter_overrides=mine))
    return flt, mp


def scan_msgs(sc):
    """The ``LaserScan`` messages of a run's scans, in order."""
    from sensor_msgs.msg import LaserScan

    for k, t in enumerate(sc.stamps):
        msg = LaserScan()
        msg.header.stamp = common.time_msg(t)
        msg.angle_min, msg.angle_increment = float(sc.angle_min[k]), float(sc.angle_increment[k])
        msg.angle_max = msg.angle_min + (len(sc.ranges[k]) - 1) * msg.angle_increment
        msg.range_min, msg.range_max = float(sc.range_min[k]), float(sc.range_max[k])
        msg.ranges = [float(r) for r in sc.ranges[k]]
        yield msg


def test_every_config_leaf_is_a_typed_parameter():
    from rcl_interfaces.msg import ParameterType as T

    specs = {p.name: p for p in common.config_parameters()}
    assert specs["inference.particles"].type == T.PARAMETER_INTEGER
    assert specs["model.odometry.a_xy"].type == T.PARAMETER_DOUBLE
    assert specs["model.use_laser"].type == T.PARAMETER_BOOL
    assert specs["model.prior.kind"].type == T.PARAMETER_STRING
    assert specs["model.appearance.models"].type == T.PARAMETER_STRING_ARRAY
    assert specs["detector.kind"].optional and specs["detector.kind"].type == T.PARAMETER_NOT_SET
    assert specs["model.appearance.nig_kappa"].optional
    assert all(not p.description.startswith("(") for p in specs.values())  # every parameter is described
    # the defaults rebuild the default configuration, and every leaf of the YAML file is a parameter
    defaults = {p.name: p.default for p in specs.values()}
    assert common.config_from_parameters(defaults) == PtmConfig()

    def leaves(d, prefix=""):
        for k, v in d.items():
            yield from leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]

    import yaml

    doc = yaml.safe_load((Path(__file__).parents[1] / "config" / "ptm.yaml").read_text())
    assert set(leaves(doc["/**"]["ros__parameters"])) <= set(specs)


@dataclass(frozen=True)
class Inner(Settings):
    """A section."""

    alpha: float = setting(1.0, gt=0, doc="the first parameter")
    beta: int = setting(2, ge=1, le=10, doc="counts things")
    gamma: str | None = setting(None, doc="a name, or none")


@dataclass(frozen=True)
class Root(Settings):
    """The root."""

    inner: Inner = setting(factory=Inner, doc="the section")
    names: tuple[str, ...] = setting(("a", "b"), choices=("a", "b", "c"), doc="some names")
    flag: bool = setting(False, doc="a switch")


def test_parameters_of_a_dataclass_tree():
    from rcl_interfaces.msg import ParameterType as T

    specs = {p.name: p for p in common.config_parameters(Root)}
    assert list(specs) == ["inner.alpha", "inner.beta", "inner.gamma", "names", "flag"]
    assert [specs[n].type for n in specs] == [
        T.PARAMETER_DOUBLE,
        T.PARAMETER_INTEGER,
        T.PARAMETER_NOT_SET,
        T.PARAMETER_STRING_ARRAY,
        T.PARAMETER_BOOL,
    ]
    assert specs["inner.alpha"].description == "the first parameter (Inner.alpha: float)"
    assert specs["inner.beta"].description.startswith("counts things")
    assert specs["names"].description.startswith("some names; one of a, b, c")
    assert specs["flag"].description.startswith("a switch")
    assert specs["inner.gamma"].optional and specs["inner.gamma"].default is None
    assert specs["names"].default == ["a", "b"]
    got = common.config_from_parameters({"inner.gamma": "x", "names": ["c"], "inner.beta": 5}, Root)
    assert got == Root(inner=Inner(beta=5, gamma="x"), names=("c",))
    assert common.config_from_parameters({"inner.gamma": "null"}, Root) == Root()
    with pytest.raises(ConfigError, match=r"Inner.beta must be an integer in \[1, 10\], got 11"):
        common.config_from_parameters({"inner.beta": 11}, Root)
    with pytest.raises(ConfigError, match=r"Root.names must be a list of one of \('a', 'b', 'c'\)"):
        common.config_from_parameters({"names": ["d"]}, Root)


def test_parameter_descriptors_carry_the_declared_ranges():
    """The ROS descriptor of a bounded field carries its range (an exclusive bound as inclusive, an open
    end as the type's extreme, ±inf for a double), so a parameter tool shows and enforces it."""
    specs = {p.name: p for p in common.config_parameters(Root)}
    beta = common._descriptor(specs["inner.beta"]).integer_range[0]
    assert (beta.from_value, beta.to_value) == (1, 10)
    alpha = common._descriptor(specs["inner.alpha"]).floating_point_range[0]
    assert (alpha.from_value, alpha.to_value) == (0.0, math.inf)
    assert not common._descriptor(specs["flag"]).floating_point_range
    real = {p.name: p for p in common.config_parameters()}
    assert sum(p.range is not None for p in real.values()) > len(real) // 2  # most parameters are bounded
    particles = common._descriptor(real["inference.particles"]).integer_range[0]
    assert particles.from_value == 1 and particles.to_value == 2**63 - 1


def test_parameter_values_build_the_same_config_as_ptm_run():
    values = {
        "inference.particles": 7,
        "model.appearance.models": ["fourier", "words"],
        "model.appearance.nig_kappa": 2,
        "detector.kind": "equidistant",
        "model.appearance.dcm_alpha": "null",  # how a ROS parameter file spells None
    }
    expected = load_config(
        None,
        {
            "inference": {"particles": 7},
            "model": {"appearance": {"models": ["fourier", "words"], "nig_kappa": 2.0}},
            "detector": {"kind": "equidistant"},
        },
    )
    assert common.config_from_parameters(values) == expected
    assert common.config_from_parameters({"detector.kind": "~"}).detector.kind is None
    with pytest.raises(ConfigError, match=r"InferenceConfig\.particles must be an integer >= 1, got 0"):
        common.config_from_parameters({"inference.particles": 0})
    with pytest.raises(ConfigError, match=r"inference.particles: expected an integer"):
        common.config_from_parameters({"inference.particles": "many"})
    with pytest.raises(ConfigError, match=r"unknown parameter\(s\) \['inference.particlez'\]"):
        common.config_from_parameters({"inference.particlez": 3})


def test_sensor_qos_choices():
    from rclpy.qos import ReliabilityPolicy

    assert common.sensor_qos("reliable").reliability == ReliabilityPolicy.RELIABLE
    assert common.sensor_qos("sensor_data").reliability == ReliabilityPolicy.BEST_EFFORT
    with pytest.raises(ConfigError, match="sensor_qos must be one of"):
        common.sensor_qos("fast")


# ------------------------------------------------------------------------------------------ conversions


def test_odometry_and_scan_conversions_match_the_bag_reader(tmp_path):
    """The node's decoding of rclpy messages equals read_run's decoding of the same CDR bytes."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image, LaserScan

    rng = np.random.default_rng(3)
    stamps = [1.0, 13.123456789, 1_700_000_000.25, 2.000000001]
    yaws = [0.0, math.pi, -math.pi, 3.5, -6.2, 1e-3]
    bag = tmp_path / "b"
    with BagWriter(bag) as w:
        for s, yaw in zip(stamps, yaws, strict=False):
            w.write_odometry(s, (rng.normal(), rng.normal(), yaw))
        for s in stamps:
            w.write_scan(
                s,
                rng.uniform(0.1, 20.0, 31).astype(np.float32),
                angle_min=-1.5,
                angle_increment=0.1,
                range_min=0.05,
                range_max=25.0,
            )
        w.write_image(5.0, rng.integers(0, 255, (4, 6), dtype=np.uint8))
        w.write_image(6.0, rng.integers(0, 255, (3, 5, 3), dtype=np.uint8))
    run = read_run(bag)
    types = {"/odom": Odometry, "/scan": LaserScan, "/panorama": Image}
    got: dict[str, list] = {k: [] for k in types}
    for raw in iter_raw(bag):
        got[raw.topic].append(deserialize_message(raw.rawdata, types[raw.topic]))
    for k, msg in enumerate(got["/odom"]):
        stamp, pose = common.odometry_sample(msg)
        assert stamp == run.odometry.stamps[k]
        assert pose == tuple(run.odometry.poses[k])  # bit for bit, yaws beyond pi included
    for k, msg in enumerate(got["/scan"]):
        stamp, ranges, amin, ainc, rmin, rmax = common.scan_fields(msg)
        assert stamp == run.scans.stamps[k] and np.array_equal(ranges, run.scans.ranges[k])
        assert (amin, ainc, rmin, rmax) == (
            run.scans.angle_min[k],
            run.scans.angle_increment[k],
            run.scans.range_min[k],
            run.scans.range_max[k],
        )
    for k, msg in enumerate(got["/panorama"]):
        assert np.array_equal(common.image_array(msg), run.images.images[k])
    msg = got["/panorama"][0]
    msg.encoding = "32FC1"
    assert common.image_array(msg) is None


def test_time_and_pose_messages_round_trip():
    from types import SimpleNamespace

    for s in (0.0, 13.12, 1_700_000_000.123456789, 2.5e-9):
        assert common.header_stamp(SimpleNamespace(stamp=common.time_msg(s))) == pytest.approx(s, abs=5e-10)
    assert common.time_msg(-1.0).sec == 0 and common.time_msg(math.nan).sec == 0
    for yaw in np.linspace(-2 * math.pi, 2 * math.pi, 17):
        q = common.pose_msg(1.0, 2.0, float(yaw)).orientation
        assert (q.x, q.y, q.z, q.w) == yaw_to_quaternion(float(yaw))


# ---------------------------------------------------------------------------------------- bad input


def test_valid_stamp_rejects_what_is_no_ros_time():
    from types import SimpleNamespace

    def header(sec, nanosec):
        return SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec))

    assert valid_stamp(header(5, 999_999_999)) == 5.999999999
    assert valid_stamp(header(0, 0)) == 0.0
    assert valid_stamp(header(-1, 0)) is None
    assert valid_stamp(header(3, 1_000_000_000)) is None
    assert valid_stamp(header(3, 2**32 - 1)) is None


def test_guard_config_is_validated():
    for kwargs, match in [
        ({"stamp_jump_s": 0.0}, "stamp_jump_s must be finite and > 0"),
        ({"stamp_jump_s": math.nan}, "stamp_jump_s must be finite and > 0"),
        ({"confirm": 0}, "jump_confirm must be >= 1"),
        ({"max_speed": 0.0}, "max_speed must be > 0"),
        ({"max_speed": math.nan}, "max_speed must be > 0"),
    ]:
        with pytest.raises(ConfigError, match=match):
            stream_guard.GuardConfig(**kwargs)
    assert stream_guard.GuardConfig(max_speed=math.inf).max_speed == math.inf  # no teleport check


def point_guard(**kwargs):
    return stream_guard.StreamGuard(
        stream_guard.GuardConfig(**kwargs), equal=lambda a, b: a == b, position=lambda p: p
    )


def test_stream_guard_passes_a_timeline_and_drops_every_isolated_bad_message():
    """Random bad messages (far stamps either way, teleports, repeats) between the messages of a 10 Hz
    odometry timeline: exactly the timeline is released, in order; each bad message is counted once."""
    rng = np.random.default_rng(3)
    guard = point_guard()
    timeline = [(100.0 + 0.1 * k, (0.05 * k, 0.01 * k)) for k in range(3000)]
    released, outliers, duplicates, bad = [], 0, 0, 0
    for k, (t, p) in enumerate(timeline):
        if k > 3:
            for _ in range(int(rng.poisson(0.7))):
                t0, p0 = timeline[k - 1]
                kind = int(rng.integers(3))
                if kind == 0:
                    adm = guard.admit(t0 + float(rng.choice([-1, 1]) * rng.uniform(30.5, 1e5)), p0)
                elif kind == 1:
                    jump = rng.uniform(2.0, 1e4)  # farther than max_speed * dt + 1 m
                    adm = guard.admit(t0 + float(rng.uniform(0.0, 0.09)), (p0[0] + jump, p0[1]))
                else:
                    adm = guard.admit(t0, p0)
                    assert adm.duplicate
                    duplicates += 1
                bad += kind != 2
                assert adm.released == ()
                outliers += adm.outliers
        adm = guard.admit(t, p)
        assert adm.event in (None, stream_guard.START) and not adm.duplicate
        released += adm.released
        outliers += adm.outliers
    assert released == timeline
    assert outliers == bad and duplicates > 100 and bad > 1000
    assert guard.held == 0 and guard.last_stamp == timeline[-1][0]


def test_stream_guard_confirms_jumps_resets_and_teleports():
    guard = point_guard(confirm=3)
    t = [float(k) for k in range(5)]
    assert guard.admit(0.0, (0.0, 0.0)).released == () and guard.held == 1
    guard.admit(1e6, (0.0, 0.0))  # a lone bad first message: its own run
    assert guard.admit(0.5, (0.1, 0.0)).released == ()
    adm = guard.admit(1.0, (0.2, 0.0))
    assert (
        adm.event == stream_guard.START
        and [s for s, _ in adm.released] == [0.0, 0.5, 1.0]
        and adm.outliers == 1
    )
    for s in t[2:]:
        assert guard.admit(s, (0.2 * s, 0.0)).released == ((s, (0.2 * s, 0.0)),)
    # a pause of 100 s: held until three messages confirm it, a bad one in between changes nothing
    assert guard.admit(104.0, (1.0, 0.0)).released == ()
    assert guard.admit(4.0, (0.8, 0.0)).duplicate
    assert guard.admit(-5.0 + 1e3 * 7, (0.0, 0.0)).released == ()
    assert guard.admit(104.1, (1.0, 0.0)).released == ()
    adm = guard.admit(104.2, (1.0, 0.0))
    assert adm.event == stream_guard.FORWARD_JUMP and len(adm.released) == 3 and adm.outliers == 1
    # the clock goes back (a looped bag)
    for s in (10.0, 10.1):
        assert guard.admit(s, (0.0, 0.0)).released == ()
    adm = guard.admit(10.2, (0.0, 0.0))
    assert adm.event == stream_guard.CLOCK_RESET and guard.last_stamp == 10.2
    # odometry jumps 100 m in 0.1 s and goes on from there
    for s in (10.3, 10.4):
        assert guard.admit(s, (100.0, 0.0)).released == ()
    adm = guard.admit(10.5, (100.1, 0.0))
    assert adm.event == stream_guard.TELEPORT and [p for _, p in adm.released][-1] == (100.1, 0.0)
    # at the end of input: a held pause is used, a held reset or teleport is dropped
    guard.admit(200.0, (100.1, 0.0))
    adm = guard.settle()
    assert adm.event == stream_guard.FORWARD_JUMP and adm.released == ((200.0, (100.1, 0.0)),)
    guard.admit(50.0, (100.1, 0.0))
    assert guard.settle() == stream_guard.Admission(outliers=1)
    # at most MAX_RUNS runs are held: the oldest goes first
    for k in range(stream_guard.StreamGuard.MAX_RUNS + 1):
        adm = guard.admit(1000.0 + 100.0 * k * (-1) ** k, (100.1, 0.0))
    assert adm.outliers == 1 and guard.held == stream_guard.StreamGuard.MAX_RUNS


def test_stream_guard_keeps_a_good_message_held_with_a_bad_one():
    """A copy stamped 30 s ahead arrives right after the stream's first message and joins its run (it
    continues it within stamp_jump_s): the messages that follow continue the first message, not the
    copy, and their run keeps it, so only the copy is an outlier (ptm-run's reader too keeps the longest
    increasing run); the same inside a held forward jump."""
    guard = point_guard(confirm=3)
    guard.admit(0.0, (0.0, 0.0))
    guard.admit(30.0, (0.0, 0.0))  # a far copy of the first message
    assert guard.held == 2
    assert guard.admit(0.1, (0.05, 0.0)).released == () and guard.held == 3  # the first one shared
    adm = guard.admit(0.2, (0.1, 0.0))
    assert adm.event == stream_guard.START and adm.outliers == 1
    assert adm.released == ((0.0, (0.0, 0.0)), (0.1, (0.05, 0.0)), (0.2, (0.1, 0.0)))
    for s in (0.3, 0.4, 0.5):
        guard.admit(s, (0.5 * s, 0.0))
    guard.admit(100.0, (1.0, 0.0))  # a pause: held
    guard.admit(125.0, (1.0, 0.0))  # a bad copy ahead of it, continuing it
    guard.admit(100.1, (1.0, 0.0))
    adm = guard.admit(100.2, (1.0, 0.0))
    assert adm.event == stream_guard.FORWARD_JUMP and [t for t, _ in adm.released] == [100.0, 100.1, 100.2]
    assert adm.outliers == 1 and guard.held == 0


def test_params_files_are_checked_before_rclpy_reads_them(tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text("/**:\n  ros__parameters:\n    inference:\n      particles: 3\n")
    common.check_params_files(["prog", "--ros-args", "--params-file", str(good)])
    cases = {
        "broken.yaml": (
            "/**:\n  ros__parameters: {inference: [1, 2\n",
            r"^malformed YAML in \S+broken.yaml, line \d+, column \d+: [^\n]+$",
        ),
        "string.yaml": ("just a string\n", "expected a mapping of node names"),
        "empty.yaml": ("", "expected a mapping of node names"),
        "section.yaml": ("/**:\n  ros__parameters: 5\n", "'ros__parameters' must be a mapping"),
        "nested.yaml": ("/**:\n  ns:\n    other: 3\n", r"nested.yaml, at /\*\*.ns.other: expected a mapping"),
    }
    for name, (text, match) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ConfigError, match=match):
            common.check_params_files(["--ros-args", "--params-file", str(tmp_path / name)])
    with pytest.raises(ConfigError, match="cannot read parameter file"):
        common.check_params_files(["--params-file", str(tmp_path / "missing.yaml")])


@pytest.fixture
def node_domain(monkeypatch):
    """A private domain, localhost discovery, for a node run in this process by run_node.

    run_node is a process's entry point: it leaves a faulthandler watchdog armed that prints every
    thread's stack STOP_REPORT_S later. In the pytest process that dump would strike during a later test
    while its executor threads run (faulthandler reads their frames without the GIL: a suspect for a
    segmentation fault of the suite in CI), so it is disarmed here."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(next_domain_id()))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.mark.dds
def test_a_signal_during_a_callback_lets_it_finish_and_exits_0(node_domain):
    """run_node: SIGINT while a callback runs (say, one writing ptm.json) is a stop request: the callback
    completes, no other callback starts, the node is destroyed, rclpy shut down, exit code 0, and the
    handlers are put back (rclpy's own handler raised KeyboardInterrupt inside the callback)."""
    import rclpy
    from rclpy.node import Node

    events = []

    class Probe(Node):
        def __init__(self) -> None:
            super().__init__("probe")
            self.create_timer(0.01, self.tick)

        def tick(self) -> None:
            events.append("tick")
            os.kill(os.getpid(), signal.SIGINT)
            total = sum(range(10_000))  # bytecodes after the signal: where a KeyboardInterrupt would strike
            events.append(f"tick done {total}")

        def destroy_node(self) -> None:
            events.append("destroyed")
            super().destroy_node()

    handlers = {sig: signal.getsignal(sig) for sig in common.STOP_SIGNALS}
    assert common.run_node(Probe, ["probe"], "probe") == 0
    assert events == ["tick", f"tick done {sum(range(10_000))}", "destroyed"]
    assert not rclpy.ok()
    assert {sig: signal.getsignal(sig) for sig in common.STOP_SIGNALS} == handlers


@pytest.mark.dds
def test_a_signal_while_the_node_is_built_stops_it_cleanly(node_domain):
    """run_node: SIGTERM before the node is fully built (rclpy's signal thread used to shut the context
    down under the construction: RCLError, exit code 1) builds it, never spins it, destroys it: 0."""
    from rclpy.node import Node

    events = []

    class Probe(Node):
        def __init__(self) -> None:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)  # a signal thread shutting the context down has all the time it needs
            super().__init__("probe")
            self.create_timer(0.001, lambda: events.append("tick"))
            events.append("built")

        def destroy_node(self) -> None:
            events.append("destroyed")
            super().destroy_node()

    assert common.run_node(Probe, ["probe"], "probe") == 0
    assert events == ["built", "destroyed"]


@pytest.mark.dds
def test_run_node_ends_cleanly_when_the_context_is_shut_down_and_propagates_bugs(node_domain):
    """run_node: a context shut down by someone else (rclpy.shutdown() in process) ends the spin with 0 and
    destroys the node; an error raised by a callback with the context alive is a bug: it propagates after
    the node is destroyed and rclpy shut down."""
    import rclpy
    from rclpy.node import Node

    destroyed = []

    def probe(callback):
        class Probe(Node):
            def __init__(self) -> None:
                super().__init__("probe")
                self.create_timer(0.01, callback)

            def destroy_node(self) -> None:
                destroyed.append(True)
                super().destroy_node()

        return Probe

    assert common.run_node(probe(rclpy.shutdown), ["probe"], "probe") == 0
    assert destroyed == [True]

    def bug() -> None:
        raise RuntimeError("a bug in a callback")

    with pytest.raises(RuntimeError, match="a bug"):
        common.run_node(probe(bug), ["probe"], "probe")
    assert destroyed == [True, True] and not rclpy.ok()


# ------------------------------------------------------------------------------------- graph and markers
# ------------------------------------------------------------------------------------- graph and markers


def random_ptm(rng, n=5, k=12):
    parts = list(enumerate_partitions(n))
    chosen = [parts[i] for i in rng.choice(len(parts), size=k, replace=False)]
    w = rng.dirichlet(np.ones(k)) * 0.9
    landmarks = [Landmark(i, 10.0 + i, (float(rng.normal()), float(rng.normal()), 0.3 * i)) for i in range(n)]
    positions = {tuple(lab): rng.normal(size=(max(lab) + 1, 2)) for lab in chosen}
    return make_ptm(landmarks, dict(zip(map(tuple, chosen), w, strict=True)), positions=positions)


def test_visit_log_line_gives_the_ess_as_a_share_of_the_particles():
    """The filter node's line after a visit: ``1/Σw²`` over the particles held, with their number, and the
    mass of the most probable topology that explains an ESS near 1 (issue #25: every line said "ESS 1.0"
    although the figure is a share of 100 particles)."""
    from ptm_ros.inference.rbpf import FilterState

    peaked = FilterState(n_visits=8, n_topologies=100, ess=1.45554, log_evidence_increment=0.0, update_s=0.05)
    line = visit_line(7, peaked, 0.805802, how="updated", ms=56.3)
    assert line == (
        "visit 7: ESS 1.46/100 particles (each a distinct topology; the most probable holds 0.806), "
        "updated in 56 ms"
    )
    spread = replace(peaked, ess=37.24, n_topologies=52)
    assert "ESS 37.2/52 particles" in visit_line(4, spread, 0.12, how="replayed", ms=1700.0)
    assert "replayed in 1700 ms" in visit_line(4, spread, 0.12, how="replayed", ms=1700.0)
    sure = replace(peaked, ess=1.0000039)
    assert "ESS 1.00/100 particles" in visit_line(9, sure, 0.999998, how="updated", ms=3.0)
    assert "holds 1.000" in visit_line(9, sure, 0.999998, how="updated", ms=3.0)


def test_edge_probabilities_against_adjacency_sums():
    rng = np.random.default_rng(0)
    ptm = random_ptm(rng)
    m = 5
    expected = np.zeros((m, m))
    for t in ptm.topologies:  # brute force: any consecutive pair of visits joining places a and b
        adj = np.zeros((m, m), dtype=bool)
        for i in range(len(t.labels) - 1):
            a, b = t.labels[i], t.labels[i + 1]
            adj[a, b] = adj[b, a] = a != b
        expected += t.probability * adj
    got = np.zeros((m, m))
    for e in edge_probabilities(ptm.topologies):
        a, b = e["places"]
        assert a < b and 0.0 <= e["probability"] <= 1.0
        got[a, b] = got[b, a] = e["probability"]
    assert np.allclose(got, expected, atol=1e-15)
    one = edge_probabilities([Topology(labels=(0, 1, 0, 2, 2), probability=1.0)])
    assert one == [{"places": [0, 1], "probability": 1.0}, {"places": [0, 2], "probability": 1.0}]


def test_graph_document_is_a_valid_ptm_json():
    ptm = random_ptm(np.random.default_rng(1))
    doc = json.loads(json.dumps(graph_document(ptm, complete=True)))
    back = from_json_dict(doc)
    assert back.topologies == ptm.topologies and back.landmarks == ptm.landmarks
    assert doc["graph_schema"] == "ptm_ros.ptm_graph/1" and doc["stream"] == {"visits": 5, "complete": True}
    assert parse_graph(json.dumps(doc))[1].topologies == ptm.topologies
    with pytest.raises(DataError, match="not JSON"):
        parse_graph("{")
    with pytest.raises(DataError, match=r"invalid ptm\.json"):
        parse_graph(json.dumps({**doc, "schema": "x"}))


def check_markers(array, ptm, count):
    from visualization_msgs.msg import Marker

    assert array.markers[0].action == Marker.DELETEALL
    by_ns = {}
    for mk in array.markers[1:]:
        by_ns.setdefault(mk.ns, {})[mk.id] = mk
    assert sorted(by_ns) == [f"topology_{r}" for r in range(min(count, len(ptm.topologies)))]
    for r, t in enumerate(ptm.topologies[:count]):
        mk = by_ns[f"topology_{r}"]
        m = max(t.labels) + 1
        visits, places, edges = mk[0], mk[1], mk[2]
        assert len(visits.points) == len(t.labels) == len(visits.colors)
        assert len(places.points) == m
        # each visit has its place's colour; edges join places of consecutive visits
        assert all(visits.colors[i] == places.colors[t.labels[i]] for i in range(len(t.labels)))
        place_xy = {(p.x, p.y) for p in places.points}
        assert all((p.x, p.y) in place_xy for p in edges.points) and len(edges.points) % 2 == 0
        pairs = {tuple(sorted((t.labels[i], t.labels[i + 1]))) for i in range(len(t.labels) - 1)}
        assert len(edges.points) == 2 * sum(a != b for a, b in pairs)
        assert visits.colors[0].a == pytest.approx(topology_alpha(t.probability))
        if t.positions is not None:
            assert [(p.x, p.y) for p in places.points] == list(t.positions)


def test_markers_reference_valid_places_and_start_with_deleteall():
    ptm = random_ptm(np.random.default_rng(2))
    check_markers(ensemble_markers(ptm, 3, 12.0), ptm, 3)
    assert topology_alpha(0.9) > topology_alpha(0.1) > 0.0
    empty = ensemble_markers(replace(ptm, topologies=()), 3, 0.0)
    assert len(empty.markers) == 1


def test_map_path_has_one_pose_per_visit_at_its_place():
    ptm = random_ptm(np.random.default_rng(3))
    path = map_path(ptm)
    top = ptm.topologies[0]
    assert len(path.poses) == len(ptm.landmarks)
    for ps, lm, label in zip(path.poses, ptm.landmarks, top.labels, strict=True):
        assert (ps.pose.position.x, ps.pose.position.y) == top.positions[label]
        assert common.header_stamp(ps.header) == pytest.approx(lm.stamp, abs=1e-9)
    bare = replace(ptm, topologies=(replace(top, positions=None),))
    assert [(p.pose.position.x, p.pose.position.y) for p in map_path(bare).poses] == [
        lm.pose[:2] for lm in ptm.landmarks
    ]
    assert map_path(replace(ptm, topologies=())).poses == []


def test_visit_messages_are_parsed_or_rejected(sim_visits):
    v = sim_visits[1]
    back = parse_visit_message(visit_to_json(v))
    assert back == v and np.array_equal(back.patch, v.patch)
    assert parse_visit_message(json.dumps({"schema": END_SCHEMA, "visits": 4})) == 4
    for bad, match in [
        ("{", "not JSON"),
        ("[1]", "schema must be"),
        (json.dumps({"schema": "ptm_ros.visit/1", "index": 0}), "malformed visit"),
        (json.dumps({"schema": END_SCHEMA, "visits": -1}), "bad count"),
    ]:
        with pytest.raises(DataError, match=match):
            parse_visit_message(bad)


def test_scan_payloads_are_accepted_or_rejected_with_a_reason():
    from types import SimpleNamespace

    def scan(ranges, amin=-1.0, amax=1.0, ainc=1.0, rmin=0.1, rmax=30.0):
        angles = {"angle_min": amin, "angle_max": amax, "angle_increment": ainc}
        return SimpleNamespace(ranges=ranges, range_min=rmin, range_max=rmax, **angles)

    payload, rejected = scan_payload(scan([1.0, math.inf, 2.0]))
    assert rejected is None
    ranges, amin, ainc, rmin, rmax = payload
    assert ranges.dtype == np.float32 and ranges.tolist() == [1.0, math.inf, 2.0]
    assert (amin, ainc, rmin, rmax) == (-1.0, 1.0, 0.1, 30.0)
    for msg, reason in [
        (scan([]), "scan-empty"),
        (scan([1.0, 2.0, 3.0], amax=math.nan), "scan-malformed"),
        (scan([1.0, 2.0, 3.0], ainc=0.0), "scan-malformed"),
        (scan([1.0, 2.0, 3.0], rmin=5.0, rmax=5.0), "scan-malformed"),
        (scan([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]), "scan-length-mismatch"),
    ]:
        payload, rejected = scan_payload(msg)
        assert payload is None and rejected[0] == reason, (msg, rejected)


# --------------------------------------------------------------------------------------- nodes over DDS


def odometry_msg(stamp, pose, frame="odom"):
    from nav_msgs.msg import Odometry

    msg = Odometry()
    msg.header.stamp = common.time_msg(stamp)
    msg.header.frame_id = frame
    msg.pose.pose = common.pose_msg(*pose)
    return msg


@pytest.mark.dds
def test_filter_and_map_publisher_over_dds(sim_bag, sim_visits, sim_odometry, tmp_path, monkeypatch, capfd):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import OccupancyGrid as GridMsg
    from nav_msgs.msg import Odometry
    from nav_msgs.msg import Path as PathMsg
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import LaserScan
    from std_msgs.msg import String
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    config = no_laser()
    overrides = [
        Parameter("model.use_laser", value=False),
        Parameter("inference.particles", value=30),
        Parameter("marker_topologies", value=3),
        Parameter("out_dir", value=str(tmp_path / "filter")),
    ]
    with ros_context(monkeypatch) as ros:
        flt, mp = filter_and_map_publisher(ros, overrides, tmp_path)
        probe = ros.node("probe")
        graph = Inbox(probe, String, "ptm_graph", common.LATCHED_QOS)
        markers = Inbox(probe, MarkerArray, "ptm_markers", common.LATCHED_QOS)
        path = Inbox(probe, PathMsg, "ptm_path", common.LATCHED_QOS)
        diagnostics = Inbox(probe, DiagnosticArray, "/diagnostics", 10)
        pub = probe.create_publisher(String, "landmark_visits", common.STREAM_QOS)
        ros.spin(flt, mp, probe)
        wait_for(lambda: pub.get_subscription_count() > 0)
        pub.publish(String(data="{not json"))
        pub.publish(String(data=json.dumps({"schema": "ptm_ros.visit/9"})))
        for v in sim_visits:
            pub.publish(String(data=visit_to_json(v)))
        pub.publish(String(data=visit_to_json(sim_visits[2])))  # a duplicate
        pub.publish(String(data=json.dumps({"schema": END_SCHEMA, "visits": len(sim_visits)})))

        def final_graph():
            msg = graph.last()
            return msg is not None and json.loads(msg.data)["stream"]["complete"] and json.loads(msg.data)

        doc = wait_for(final_graph, timeout=60.0)
        ptm = from_json_dict(doc)
        session = FilterSession(config)
        for v in sim_visits:
            session.add(v)
        assert [t.labels for t in ptm.topologies] == list(session.inference().probabilities)
        assert [t.probability for t in ptm.topologies] == list(session.inference().probabilities.values())
        assert all(0.0 <= e["probability"] <= 1.0 for e in doc["edges"])
        assert doc["diagnostics"]["invalid"] == 2 and doc["diagnostics"]["duplicates"] == 1
        assert capfd.readouterr().err.count("dropped a malformed landmark_visits message") == 1  # logged once

        wait_for(lambda: markers.last() is not None and len(markers.last().markers) == 1 + 4 * 3)
        check_markers(markers.last(), ptm, 3)
        wait_for(lambda: path.last() is not None and len(path.last().poses) == len(sim_visits))

        def statuses():
            names = {s.name: s for msg in diagnostics.items for s in msg.status}
            ok = any("topology_filter" in n for n in names) and any("map_publisher" in n for n in names)
            return ok and names

        names = wait_for(statuses, timeout=10.0)
        filt = next(s for n, s in names.items() if "topology_filter" in n)
        assert {kv.key for kv in filt.values} >= {"visits", "particles", "ess", "update_ms", "invalid"}

        reply = ros.call(probe, Trigger, "/map_publisher/save_ptm")
        assert reply.success and json.loads(reply.message)["complete"] is True
        assert json.loads((tmp_path / "ptm.json").read_text()) == doc
        # The metric map: the visits' odometry (laser-corrected, as the detector publishes it) and the scans.
        reply = ros.call(probe, Trigger, "/map_publisher/save_map")
        assert not reply.success and "no map yet" in reply.message  # no odometry or scan yet
        run, odom = read_run(sim_bag), sim_odometry
        odom_pub = probe.create_publisher(Odometry, "landmark_odom", common.MAP_STREAM_QOS)
        scan_pub = probe.create_publisher(LaserScan, "landmark_scans", common.MAP_STREAM_QOS)
        wait_for(lambda: odom_pub.get_subscription_count() > 0 and scan_pub.get_subscription_count() > 0)
        for t, pose in zip(run.odometry.stamps, odom, strict=True):
            odom_pub.publish(odometry_msg(t, pose))
        sc = run.scans
        for msg in scan_msgs(sc):
            scan_pub.publish(msg)
        counters = mp.inbox.online.counters  # every sample received: the map drawn next is the last one
        wait_for(lambda: (counters.poses, counters.scans) == (len(odom), len(sc.stamps)), timeout=30.0)
        reply = ros.call(probe, Trigger, "/map_publisher/save_map")  # draws everything received
        info = json.loads(reply.message)
        assert reply.success and info["complete"] is False  # no bag player announced the scans
        assert info["input"]["keyframes"] == info["scans"] > 0 and info["input"]["resets"] == 0
        late = Inbox(probe, GridMsg, "map", common.LATCHED_QOS)  # subscribes after the map was drawn
        trajectory = Inbox(probe, PathMsg, "ptm_trajectory", common.LATCHED_QOS)
        expected = to_ros_data(mp.map.grid, mp.config.occupancy)
        grid = wait_for(
            lambda: late.last() is not None and np.array_equal(late.last().data, expected) and late.last()
        )
        assert (grid.info.width, grid.info.height) == (mp.map.grid.width, mp.map.grid.height)
        assert grid.info.resolution == pytest.approx(0.05) and grid.header.frame_id == ptm.frame_id
        assert np.sum(expected == 100) > 100 and np.sum(expected == 0) > 1000  # walls, free
        saved = load_map(tmp_path / "map.yaml")  # the map_server files: the map's trinary classes
        assert np.array_equal(saved.data, trinary(mp.map.grid))
        # the smoothed trajectory the map was drawn along: a pose per odometry sample
        assert info["trajectory"] == len(odom)
        wait_for(lambda: trajectory.last() is not None and len(trajectory.last().poses) == len(odom))

        reply = ros.call(probe, Trigger, "/topology_filter/save_ptm")
        assert reply.success and load_config(tmp_path / "filter" / "config.yaml") == config
        saved = from_json_dict(json.loads((tmp_path / "filter" / "ptm.json").read_text()))
        assert saved.topologies == ptm.topologies
        reply = ros.call(probe, Trigger, "/topology_filter/reset")
        assert reply.success and "forgot" in reply.message
        assert not flt.inbox.session.visits


#: nav2_costmap_2d's costs (cost_values.hpp) and its static layer's reading of a map cell
#: (StaticLayer::interpretValue) with the documented defaults ``lethal_cost_threshold: 100``,
#: ``unknown_cost_value: -1`` and ``track_unknown_space: true``; ``trinary_costmap: true`` (the default)
#: reads every other value as free, ``false`` (for scale maps) as ``value / 100 * 254``, truncated.
NAV2_FREE, NAV2_LETHAL, NAV2_NO_INFORMATION = 0, 254, 255


def nav2_static_layer_costs(data: np.ndarray, *, trinary_costmap: bool = True) -> np.ndarray:
    value = np.asarray(data, dtype=np.int16)
    other = NAV2_FREE if trinary_costmap else (value / 100.0 * NAV2_LETHAL).astype(np.int16)
    return np.where(value == -1, NAV2_NO_INFORMATION, np.where(value >= 100, NAV2_LETHAL, other))


@pytest.mark.dds
@pytest.mark.parametrize("mode", ["trinary", "scale"])
def test_map_reaches_a_nav2_static_layer_with_the_saved_maps_cells(
    mode, sim_bag, sim_visits, sim_odometry, tmp_path, monkeypatch
):
    """A subscriber with nav2's static-layer QoS (reliable, transient local, depth 1) joining after the
    map was drawn reads walls as lethal, unseen cells as no-information, and exactly the cells of the
    saved map as map_server loads it: in trinary mode (``trinary_costmap: true``) map.pgm's classes, in
    scale mode (``trinary_costmap: false``) also map_scale.png's occupancy between the thresholds."""
    from nav_msgs.msg import OccupancyGrid as GridMsg
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import LaserScan
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    nav2_qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    overrides = [Parameter("model.use_laser", value=False), Parameter("inference.particles", value=30)]
    with ros_context(monkeypatch) as ros:
        flt, mp = filter_and_map_publisher(
            ros, overrides, tmp_path, [Parameter("occupancy.mode", value=mode)]
        )
        probe = ros.node("probe")
        visits = probe.create_publisher(String, "landmark_visits", common.STREAM_QOS)
        odom_pub = probe.create_publisher(Odometry, "landmark_odom", common.MAP_STREAM_QOS)
        scan_pub = probe.create_publisher(LaserScan, "landmark_scans", common.MAP_STREAM_QOS)
        ros.spin(flt, mp, probe)
        wait_for(lambda: min(p.get_subscription_count() for p in (visits, odom_pub, scan_pub)) > 0)
        for v in sim_visits:
            visits.publish(String(data=visit_to_json(v)))
        run = read_run(sim_bag)
        for t, pose in zip(run.odometry.stamps, sim_odometry, strict=True):
            odom_pub.publish(odometry_msg(t, pose))
        sc = run.scans
        for msg in scan_msgs(sc):
            scan_pub.publish(msg)
        # every odometry sample too (another topic: it may still be in flight when the scans are in)
        counters = mp.inbox.online.counters
        n_odom = len(run.odometry.stamps)
        wait_for(lambda: counters.scans == len(sc.stamps) and counters.poses == n_odom, timeout=30.0)
        wait_for(
            lambda: mp.inbox.ptm is not None and len(mp.inbox.ptm.landmarks) == len(sim_visits), timeout=60.0
        )
        assert ros.call(probe, Trigger, "/map_publisher/save_map").success  # draws and publishes everything
        saved = load_map(tmp_path / "map.yaml")
        static_layer = Inbox(probe, GridMsg, "map", nav2_qos)  # joins late, as a costmap started later does

        def the_saved_map():
            msg = static_layer.last()
            return msg is not None and (msg.info.width, msg.info.height) == saved.data.shape[::-1] and msg

        grid = wait_for(the_saved_map)
        data = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
        assert saved.mode == mode
        trinary_costmap = mode == "trinary"
        costs = nav2_static_layer_costs(data, trinary_costmap=trinary_costmap)
        if trinary_costmap:
            assert set(np.unique(data).tolist()) <= {-1, 0, 100}  # map_server's trinary values only
            expected = np.select(
                [saved.data == 100, saved.data == 0], [NAV2_LETHAL, NAV2_FREE], NAV2_NO_INFORMATION
            )
        else:  # the saved occupancy between the thresholds, as map_server's scale mode reads it
            between = (saved.data > 0) & (saved.data < 100)
            assert np.count_nonzero(between) > 100
            expected = np.select(
                [saved.data == -1, saved.data == 100, between],
                [NAV2_NO_INFORMATION, NAV2_LETHAL, (saved.data / 100.0 * NAV2_LETHAL).astype(np.int16)],
                NAV2_FREE,
            )
            assert np.any((costs > NAV2_FREE) & (costs < NAV2_LETHAL))
        np.testing.assert_array_equal(costs, expected)  # the same occupied, free and unknown cells
        assert np.sum(costs == NAV2_LETHAL) > 100 and np.sum(costs == NAV2_FREE) > 1000
        assert np.sum(costs == NAV2_NO_INFORMATION) > 0  # the margin and the unseen outside
        assert (grid.info.origin.position.x, grid.info.origin.position.y) == pytest.approx(saved.origin[:2])
        assert grid.info.resolution == pytest.approx(saved.resolution)


def test_input_counts_read_the_detectors_status_as_ptm_run_writes_its_diagnostics():
    """The detector's /diagnostics values (flattened to dotted keys) back into ptm.json's ``diagnostics``
    under ptm-run's keys: the extractor's counters, and the node's input-check skips added to ``skipped``
    and kept apart as ``read_skipped`` (ptm-run: the bag reader's), as pipeline.run_diagnostics does."""
    from types import SimpleNamespace

    from ptm_ros.nodes.landmark_detector import SKIP_REASONS, input_counts
    from ptm_ros.tools.pipeline import run_diagnostics

    ext = ExtractorDiagnostics(
        received={"odometry": 900, "scan": 441, "image": 0},
        skipped={"scan-stamp-backwards": 1, "landmark-at-same-odometry-sample": 2},
        scan_beams_dropped=17,
        visits=9,
        visits_without_panorama=9,
        laser_odometry={"matched": 400, "rejected": 3},
    )
    node_skips = {**dict.fromkeys(SKIP_REASONS, 0), "scan-empty": 2, "scan-non-finite": 3}
    status = {
        "received": {"/odom": 900, "/scan": 446, "/panorama": 0},
        "published_visits": 9,
        "finished": True,
        "extractor": diagnostics_dict(ext),
        "time_offset": -0.15,
        **node_skips,
        "sessions": 1,
        "odometry-quaternion-normalized": 4,
    }
    values = {kv.key: kv.value for kv in common.key_values(status)}
    counts = input_counts(values)
    reader = SimpleNamespace(skipped={"scan-empty": 2, "scan-non-finite": 3})
    extractor = SimpleNamespace(diagnostics=ext, time_offset_estimate=None)
    assert counts == run_diagnostics(reader, extractor)  # ptm-run's, had its reader skipped those scans
    assert counts["read_skipped"] == {"scan-empty": 2, "scan-non-finite": 3}
    assert counts["skipped"] == {
        "scan-stamp-backwards": 1,
        "landmark-at-same-odometry-sample": 2,
        "scan-empty": 2,
        "scan-non-finite": 3,
    }
    assert counts["laser_odometry"] == {"matched": 400, "rejected": 3} and counts["scan_beams_dropped"] == 17
    # values that are no counts are left out: the extractor's defaults stand, nothing raises
    broken = {**values, "extractor.visits": "many", "scan-empty": "-1", "extractor.received.scan": "4.5"}
    counts = input_counts(broken)
    assert (
        counts["visits"] == 0
        and counts["received"]["scan"] == 0
        and counts["read_skipped"] == {"scan-non-finite": 3}
    )
    assert (
        input_counts({})["skipped"] == {} and input_counts({})["received"] == ExtractorDiagnostics().received
    )


@pytest.mark.dds
def test_detector_counts_bad_odometry_and_flushes_at_the_announced_end(monkeypatch, capfd):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from ptm_ros.nodes.landmark_detector import LandmarkDetectorNode, input_counts

    stamps = (5_000_000_000 + np.arange(200) * 100_000_000) / 1e9  # whole ns, as messages carry them
    poses = [(0.1 * k, 0.02 * math.sin(0.1 * k), 0.05) for k in range(200)]
    bad = {30: (math.nan, 0.0, 0.0), 77: (1.0, math.inf, 0.0)}
    stream = [(s, bad.get(k, p)) for k, (s, p) in enumerate(zip(stamps, poses, strict=True))]
    offline = make_extractor(PtmConfig(), "equidistant", use_scans=False, use_images=False)
    expected = [v for s, p in stream for v in offline.on_odometry(float(s), p)] + offline.flush()
    assert len(expected) >= 5

    overrides = [Parameter("use_scans", value=False), Parameter("use_images", value=False)]
    with ros_context(monkeypatch) as ros:
        det = ros.add(LandmarkDetectorNode(context=ros.context, parameter_overrides=overrides))
        probe = ros.node("probe")
        visits = Inbox(probe, String, "landmark_visits", common.STREAM_QOS)
        poses_in = Inbox(probe, PoseStamped, "landmark_poses", common.DISPLAY_QOS)
        diagnostics = Inbox(probe, DiagnosticArray, "/diagnostics", 10)
        odom = probe.create_publisher(Odometry, "odom", common.REPLAY_QOS)
        end = probe.create_publisher(String, "end_of_input", common.LATCHED_QOS)
        ros.spin(det, probe)
        wait_for(lambda: odom.get_subscription_count() > 0 and end.get_subscription_count() > 0)
        for s, p in stream:
            odom.publish(odometry_msg(float(s), p, frame="wheel_odom"))
        counts = {"/odom": len(stream), "/imu": 4}  # a topic the detector does not read is ignored
        end.publish(String(data=json.dumps({"schema": END_OF_INPUT_SCHEMA, "counts": counts})))
        wait_for(lambda: visits.items and json.loads(visits.items[-1].data)["schema"] == END_SCHEMA)
        got = [parse_visit_message(m.data) for m in visits.items]
        assert got[-1] == len(expected)
        assert got[:-1] == expected  # the offline extractor's visits, poses and stamps bit for bit
        wait_for(lambda: len(poses_in.items) == len(expected))
        for ps, v in zip(poses_in.items, expected, strict=True):
            assert ps.header.frame_id == "wheel_odom" and common.header_stamp(ps.header) == v.stamp
            assert (ps.pose.position.x, ps.pose.position.y) == v.pose[:2]
        diag = det.inbox.diagnostics()
        assert diag["odometry-non-finite"] == 2 and diag["extractor"]["skipped"] == {}
        assert diag["fed"]["odometry"] == len(stream) - 2 and diag["held"]["odometry"] == 0
        assert diag["received"] == {"/odom": len(stream), "/scan": 0, "/panorama": 0} and diag["finished"]

        def detector_status():
            for msg in diagnostics.items:
                for st in msg.status:
                    values = {kv.key: kv.value for kv in st.values}
                    if "landmark_detector" in st.name and values.get("finished") == "True":
                        return values
            return None

        values = wait_for(detector_status, timeout=10.0)
        assert values["odometry-non-finite"] == "2" and values["published_visits"] == str(len(got) - 1)
        # the same counts as ptm-run's ptm.json diagnostics (what ptm-bringup writes): its reader drops the
        # two bad messages, its extractor sees the rest
        read = make_extractor(PtmConfig(), "equidistant", use_scans=False, use_images=False)
        for k, (s, p) in enumerate(stream):
            if k not in bad:
                read.on_odometry(float(s), p)
        read.flush()
        counts = input_counts(values)
        assert counts == with_input_skips(diagnostics_dict(read.diagnostics), {"odometry-non-finite": 2})
        assert counts["read_skipped"] == counts["skipped"] == {"odometry-non-finite": 2}
        assert counts["received"]["odometry"] == len(stream) - 2 and counts["visits"] == len(expected)
        # two bad messages, one warning
        assert capfd.readouterr().err.count("skipped 1 message(s): odometry-non-finite") == 1


#: The subscription topics of a detector node by default (its inbox counts messages per topic name).
DETECTOR_TOPICS = {"odom": "/odom", "scan": "/scan", "panorama": "/panorama"}


def detector_inbox(*, use_scans=False, use_images=False, kind=None, silence_s=10.0):
    """The landmark detector's logic without rclpy (:class:`ptm_ros.nodes.detector_inbox.DetectorInbox`),
    with the node's defaults but replay timing (``stall_s`` 0)."""
    import logging

    from ptm_ros.factories import detector_kind
    from ptm_ros.nodes.detector_inbox import DetectorInbox

    config = load_config(None, {} if kind is None else {"detector": {"kind": kind}})
    return DetectorInbox(
        config,
        logging.getLogger("landmark_detector"),
        kind=detector_kind(config, has_scans=use_scans, has_images=use_images),
        topics=DETECTOR_TOPICS,
        use_scans=use_scans,
        use_images=use_images,
        stall_s=0.0,
        silence_s=silence_s,
    )


@pytest.mark.dds
def test_detector_node_refuses_the_ground_truth_detector(monkeypatch):
    """The thesis' perfect detector needs the run's ground truth, which a live node does not have: a
    clear ConfigError (run_node makes it a fatal log and exit code 2), not a node that never fires."""
    from rclpy.parameter import Parameter

    from ptm_ros.nodes.landmark_detector import LandmarkDetectorNode

    params = {"use_scans": False, "use_images": False, "detector.kind": "ground-truth"}
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    with ros_context(monkeypatch) as ros, pytest.raises(ConfigError, match="only ptm-run can use it"):
        ros.add(LandmarkDetectorNode(context=ros.context, parameter_overrides=overrides))


def visits_by_session(outputs):
    """The visits a detector inbox queued, per detector session in order, and its end markers."""
    from ptm_ros.nodes.detector_inbox import EndOut, VisitOut

    out = {}
    for o in outputs:
        if isinstance(o, VisitOut):
            out.setdefault(o.session, []).append(o.visit)
    return list(out.values()), [json.loads(o.text) for o in outputs if isinstance(o, EndOut)]


def test_detector_continues_over_a_pause_and_starts_a_session_after_a_teleport():
    """Odometry pauses for 60 s (a forward jump: same session, nothing lost), then jumps 500 m (odometry
    reset: a new session, visits from 0): each session's visits are ptm-run's on its samples."""
    stamps = 5.0 + 0.1 * np.arange(400)
    stamps[150:] += 60.0
    poses = np.column_stack([0.05 * np.arange(400), np.sin(0.02 * np.arange(400)), np.full(400, 0.1)])
    poses[300:, 0] += 500.0

    def offline(part):
        ext = make_extractor(PtmConfig(), "equidistant", use_scans=False, use_images=False)
        return [v for t, p in part for v in ext.on_odometry(float(t), p)] + ext.flush()

    samples = list(zip(stamps, poses, strict=True))
    box = detector_inbox()
    for t, p in samples:
        box.odometry(odometry_msg(float(t), p))
    box.finish()
    (first, second), ends = visits_by_session(box.take())
    assert first == offline(samples[:300]) and len(first) >= 5
    assert second == offline(samples[300:]) and second[0].index == 0
    d = box.diagnostics()
    assert (d["forward_jumps"], d["teleports"], d["sessions"], d["clock_resets"]) == (1, 1, 2, 0)
    assert sum(box.skipped.values()) == 0 and d["fed"]["odometry"] == 400
    assert ends == [
        {
            "schema": END_SCHEMA,
            "visits": len(second),
            "session": box.session_id,
            "keyframes": 0,  # odometry alone: no scan to send
        }
    ]


@pytest.mark.slow
def test_detector_rejoins_a_scan_stream_whose_first_messages_were_stamped_ahead(sim_bag, tmp_path):
    """The bag's first 11 scans stamped 100 s ahead (confirmed as the stream's start), then the scans on
    the odometry's clock: the stream rejoins the session at once and what the extractor held of the
    stretch ahead is dropped, so the node's visits are those ptm-run's reader gives (it keeps the longest
    increasing run of a topic), not none (every later scan skipped as going back in time)."""
    from bag_corruption import Plan, Stretch, corrupt
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import LaserScan

    bag = corrupt(sim_bag, tmp_path / "ahead", Plan(stretches=(Stretch("/scan", 0.0, 11, 100.0),))).path
    run = read_run(bag, image_topic=None)  # ptm-run's reader: the 11 scans ahead are skipped
    expected = detect_visits(run, load_config(None, {"detector": {"kind": "laser-surprise"}}))
    assert len(expected) >= 3
    box = detector_inbox(use_scans=True, kind="laser-surprise")
    for raw in iter_raw(bag, ["/odom", "/scan"]):
        if raw.topic == "/odom":
            box.odometry(deserialize_message(raw.rawdata, Odometry))
        else:
            box.scan(deserialize_message(raw.rawdata, LaserScan))
    box.finish()
    (got,), _ = visits_by_session(box.take())
    diag = box.diagnostics()
    assert [v.stamp for v in got] == [v.stamp for v in expected]
    assert [v.input_pose for v in got] == [v.input_pose for v in expected]
    assert diag["clock_resets"] == 1 and diag["sessions"] == 1  # the scans came back: no new session
    assert diag["extractor"]["skipped"]["scan-off-clock"] > 0


def test_detector_reports_a_topic_that_falls_silent(monkeypatch):
    """An expected topic silent for ``silence_s`` while others deliver is reported once per silence; a
    pause of every topic is none. Messages count as arrivals whatever they hold (these are empty)."""
    from types import SimpleNamespace

    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Image, LaserScan

    from ptm_ros.nodes import detector_inbox as module

    now = {"t": 50.0}
    monkeypatch.setattr(module, "time", SimpleNamespace(monotonic=lambda: now["t"]))

    def at(t, take, msg):
        now["t"] = t
        take(msg)

    box = detector_inbox(use_scans=True, use_images=True, silence_s=10.0)
    assert box.check_silence(100.0) == [] and not box.warns()  # nothing received yet
    at(50.0, box.odometry, Odometry())
    at(98.0, box.scan, LaserScan())
    at(99.0, box.odometry, Odometry())  # no panorama since the first message
    problems = box.problems()  # the empty messages are skipped: counted, so WARN already
    assert box.check_silence(100.0) == ["panorama"] and box.counters["silences"] == 1 and box.warns()
    assert box.check_silence(101.0) == ["panorama"] and box.counters["silences"] == 1  # same silence
    at(101.5, box.image, Image())
    assert box.check_silence(102.0) == []
    assert box.check_silence(200.0) == []  # everything stopped: a paused robot or bag, not a silence
    at(185.0, box.scan, LaserScan())
    at(199.0, box.image, Image())
    at(200.0, box.odometry, Odometry())
    assert box.check_silence(200.5) == ["scan"] and box.counters["silences"] == 2
    assert box.diagnostics()["silent"] == "scan" and problems > 0
    box.skipped = dict.fromkeys(box.skipped, 0)  # without the skips, the silence alone is a WARN
    assert box.problems() == 0 and box.warns()
    assert box.check_silence(200.6) == ["scan"] and box.warns()
    box.silence_s = 0.0
    assert box.check_silence(300.0) == [] and not box.warns()  # off


@pytest.mark.dds
def test_player_replays_the_recorded_bytes_then_announces_the_end(tmp_path, monkeypatch):
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image, LaserScan
    from std_msgs.msg import String

    rng = np.random.default_rng(5)
    bag = tmp_path / "small"
    with BagWriter(bag) as w:
        for k in range(40):
            w.write_odometry(100.0 + 0.05 * k, (0.1 * k, 0.0, 0.01 * k))
            if k % 4 == 0:
                w.write_scan(
                    100.0 + 0.05 * k + 0.01,
                    rng.uniform(0.5, 9.0, 60).astype(np.float32),
                    angle_min=-1.0,
                    angle_increment=0.03,
                    range_min=0.1,
                    range_max=10.0,
                )
        for k in range(3):
            w.write_image(100.3 + k, rng.integers(0, 255, (8, 32), dtype=np.uint8))
    recorded: dict[str, list[bytes]] = {}
    for raw in iter_raw(bag):
        recorded.setdefault(raw.topic, []).append(raw.rawdata)
    last_ns = max(raw.log_time_ns for raw in iter_raw(bag))

    with ros_context(monkeypatch) as ros:
        probe = ros.node("probe")
        got: dict[str, list[bytes]] = {t: [] for t in recorded}
        for topic, kind in (("/odom", Odometry), ("/scan", LaserScan), ("/panorama", Image)):
            probe.create_subscription(kind, topic, got[topic].append, common.REPLAY_QOS, raw=True)
        clock = Inbox(probe, Clock, "/clock", common.REPLAY_QOS)
        end = Inbox(probe, String, "end_of_input", common.LATCHED_QOS)
        ros.spin(probe)
        proc = subprocess.run(
            [sys.executable, "-m", "ptm_ros.nodes.bag_player", str(bag), "--rate", "0", "--wait", "30"],
            env=dds_env(ros.domain_id),
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert proc.returncode == 0, proc.stderr
        doc = json.loads(wait_for(end.last).data)
        assert doc["schema"] == END_OF_INPUT_SCHEMA
        assert doc["counts"] == {t: len(v) for t, v in recorded.items()}
        wait_for(lambda: all(len(got[t]) == len(recorded[t]) for t in recorded))
        assert got == recorded  # every message, in order, byte for byte
        ticks = [c.clock.sec * 1_000_000_000 + c.clock.nanosec for c in clock.items]
        assert ticks == sorted(ticks) and ticks[-1] == last_ns


# ----------------------------------------------------------------------------- node processes: start-up


@pytest.mark.dds
@pytest.mark.parametrize(
    ("node", "ros_args", "match"),
    [
        ("topology_filter", ["-p", "inference.particles:=0"], "inference.particles must be an integer >= 1"),
        ("landmark_detector", ["-p", "sensor_qos:=fast"], "sensor_qos must be one of"),
        ("map_publisher", ["-p", "out_dir:=3"], "out_dir"),
        ("map_publisher", ["-p", "inference.particlez:=3"], "unknown parameter(s) ['inference.particlez']"),
        ("landmark_detector", ["-p", "jump_confirm:=0"], "jump_confirm"),
        ("map_publisher", ["--params-file", "/nonexistent/params.yaml"], "cannot read parameter file"),
    ],
)
def test_bad_parameter_makes_the_node_exit_non_zero(node, ros_args, match):
    env = dds_env(next_domain_id())
    proc = subprocess.run(
        [sys.executable, "-m", f"ptm_ros.nodes.{node}", "--ros-args", *ros_args],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert (
        "invalid parameters" in proc.stderr or "invalid arguments" in proc.stderr
    ) and match in proc.stderr


@pytest.mark.dds
@pytest.mark.parametrize("node", ["map_publisher", "topology_filter", "landmark_detector"])
def test_a_stop_sent_while_a_node_starts_up_ends_it_with_0(node, tmp_path):
    """A node started as ptm-bringup starts it (SIGINT / SIGTERM blocked until run_node answers them) and
    sent SIGINT at once, while Python still imports its modules, stops cleanly with 0: the signal waits
    for run_node instead of raising KeyboardInterrupt inside an import (exit -2, or 1 when numpy turns it
    into an ImportError)."""
    from ptm_ros.tools.bringup import node_command, spawn, stop_all

    out = io.StringIO()
    command = node_command(node, ["-p", f"out_dir:={tmp_path}"])
    child = spawn(node, command, dds_env(next_domain_id()), out, node=True)
    try:
        os.killpg(child.popen.pid, signal.SIGINT)
        code = child.popen.wait(timeout=60)
    finally:
        stop_all([child])
    assert code == 0, out.getvalue()
    assert "Traceback" not in out.getvalue()


def test_player_rejects_bad_arguments(tmp_path, capsys, sim_bag):
    from ptm_ros.nodes import bag_player

    assert bag_player.main([str(tmp_path / "none"), "--rate", "1"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert bag_player.main([str(sim_bag), "--topics", "/nope"]) == 2
    assert "no topic /nope" in capsys.readouterr().err
    assert bag_player.main([str(sim_bag), "--rate", "-1"]) == 2
    topics = bag_player.bag_topics(sim_bag)
    counts: dict[str, int] = {}
    for raw in iter_raw(sim_bag):
        counts[raw.topic] = counts.get(raw.topic, 0) + 1
    assert {t: topics[t].count for t in topics} == counts
    assert topics["/odom"].msgtype == "nav_msgs/msg/Odometry"
    assert bag_player.message_class("nav_msgs/msg/Odometry").__name__ == "Odometry"
    with pytest.raises(DataError, match="not available"):
        bag_player.message_class("nope_msgs/msg/Nothing")
