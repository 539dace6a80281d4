"""Issue #9: the nodes under a storm of malformed messages (seeded random), fed straight to their callbacks
(the topology filter's: to its rclpy-free :class:`~ptm_ros.nodes.filter_inbox.FilterInbox`).

Two kinds of storm per node:

* *neutral*: only messages the node must reject (every one of a known kind) between the messages of a
  valid stream. The node's counters must equal the number of each kind sent, and its output must equal
  that of a clean node fed the valid stream alone — bit for bit: nothing bad leaks into the map.
* *wild*: random mutations of valid messages (extreme, non-finite, wrongly typed or shaped values,
  random bytes), some of which are plausible and used. Then a fresh valid stream in a new session: its
  output must equal a clean node's on the same stream.

Every storm asserts zero ``internal_errors`` (no exception reached a callback's last-resort guard; the
inbox has no guard, so any exception fails its storms), and
that the counters account for every message received. In all, each message kind (odometry, scan,
panorama, end_of_input, landmark visit, ptm_graph) gets at least ``2 * N_STORM`` malformed messages.
"""

from __future__ import annotations

import array
import base64
import json
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
from ros_helpers import ros_context

from ptm_ros.io.simulator import SimConfig, simulate
from ptm_ros.io.worlds import get_world
from ptm_ros.model.partitions import enumerate_partitions
from ptm_ros.model.ptm import Landmark, make_ptm
from ptm_ros.model.visits import Visit
from ptm_ros.nodes import common
from ptm_ros.nodes.messages import END_OF_INPUT_SCHEMA, END_SCHEMA
from ptm_ros.perception.landmarks import visit_to_json

pytestmark = pytest.mark.dds  # the nodes run in an rclpy context on its own ROS domain

N_STORM = 5_000  # malformed messages per kind and storm (two storms per kind: >= 10,000 per kind)


class Recorder:
    """Stands in for a publisher: keeps what the node publishes."""

    def __init__(self) -> None:
        self.items: list[Any] = []

    def publish(self, msg: Any) -> None:
        self.items.append(msg)


@pytest.fixture(scope="module")
def ros():
    with ros_context() as session:
        yield session


# ------------------------------------------------------------------------------------- sensor messages


@dataclass(frozen=True)
class Base:
    """One valid message of the simulated run: its stream, stamp and content."""

    stream: str  # odometry | scan | image
    stamp: float
    data: Any


@pytest.fixture(scope="module")
def sim_stream() -> list[Base]:
    """The t-junction run's odometry, scans and panoramas in stamp order (odometry first on ties)."""
    run = simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(4), visits=5)
    laser = run.config.laser
    geometry = (laser.angle_min, laser.angle_increment, laser.range_min, laser.range_max)
    events = [
        (float(t), 0, Base("odometry", float(t), p))
        for t, p in zip(run.odom_stamps, run.odom_poses, strict=True)
    ]
    events += [
        (float(t), 1, Base("scan", float(t), (r, *geometry)))
        for t, r in zip(run.scan_stamps, run.scan_ranges, strict=True)
    ]
    events += [
        (float(t), 2, Base("image", float(t), im)) for t, im in zip(run.image_stamps, run.images, strict=True)
    ]
    return [e for _, _, e in sorted(events, key=lambda e: e[:2])]


def set_stamp(msg: Any, stamp: float) -> Any:
    msg.header.stamp = common.time_msg(stamp)
    return msg


def odom_msg(stamp: float, pose: Any) -> Any:
    from nav_msgs.msg import Odometry

    msg = set_stamp(Odometry(), stamp)
    msg.header.frame_id = "odom"
    msg.pose.pose = common.pose_msg(*pose)
    return msg


def scan_msg(stamp: float, ranges: Any, amin: float, ainc: float, rmin: float, rmax: float) -> Any:
    from sensor_msgs.msg import LaserScan

    r = np.asarray(ranges, dtype=np.float32)
    msg = set_stamp(LaserScan(), stamp)
    msg.angle_min, msg.angle_increment = float(amin), float(ainc)
    msg.angle_max = float(amin) + (r.size - 1) * float(ainc)
    msg.range_min, msg.range_max = float(rmin), float(rmax)
    msg.ranges = array.array("f", r.tobytes())
    return msg


def image_msg(stamp: float, pixels: Any, encoding: str = "mono8") -> Any:
    from sensor_msgs.msg import Image

    im = np.ascontiguousarray(pixels, dtype=np.uint8)
    msg = set_stamp(Image(), stamp)
    msg.height, msg.width = im.shape[0], im.shape[1]
    msg.encoding = encoding
    msg.step = im.shape[1] * (im.shape[2] if im.ndim == 3 else 1)
    msg.data = im.tobytes()
    return msg


def message(b: Base, stamp: float | None = None) -> Any:
    t = b.stamp if stamp is None else stamp
    if b.stream == "odometry":
        return odom_msg(t, b.data)
    if b.stream == "scan":
        return scan_msg(t, *b.data)
    return image_msg(t, b.data)


#: The subscription topics a detector node has by default (its inbox counts messages per topic name).
TOPICS = {"odom": "/odom", "scan": "/scan", "panorama": "/panorama"}


class Detector:
    """The landmark detector's logic (its rclpy-free :class:`~ptm_ros.nodes.detector_inbox.DetectorInbox`;
    laser surprise on scans, panoramas on, replay timing: ``stall_s`` 0) and what it published, by kind."""

    def __init__(self) -> None:
        import logging

        from ptm_ros.config import load_config
        from ptm_ros.factories import detector_kind
        from ptm_ros.nodes.detector_inbox import DetectorInbox

        config = load_config(None, {"model": {"use_laser": False}, "detector": {"kind": "laser-surprise"}})
        kind = detector_kind(config, has_scans=True, has_images=True)
        self.inbox = DetectorInbox(
            config, logging.getLogger("detector"), kind=kind, topics=TOPICS, stall_s=0.0
        )
        self.out: list[Any] = []

    def __getattr__(self, name: str) -> Any:  # the inbox's counters, diagnostics, session ids, finish
        return getattr(self.inbox, name)

    def feed(self, b: Base, msg: Any | None = None) -> None:
        getattr(self.inbox, b.stream)(message(b) if msg is None else msg)
        self.out += self.inbox.take()

    def finish(self) -> int:
        n = self.inbox.finish()
        self.out += self.inbox.take()
        return n

    def of(self, kind: type) -> list[Any]:
        return [o for o in self.out if isinstance(o, kind)]


def detector() -> Detector:
    return Detector()


def feed(node: Detector, b: Base, msg: Any | None = None) -> None:
    node.feed(b, msg)


def published_visits(node: Detector, session: str | None = None) -> list[Visit]:
    from ptm_ros.nodes.detector_inbox import VisitOut

    return [o.visit for o in node.of(VisitOut) if session is None or o.session == session]


def assert_same_visits(got: list[Visit], expected: list[Visit]) -> None:
    assert got == expected  # index, stamp, pose, travel, rotation
    for a, b in zip(got, expected, strict=True):
        for name in ("signature", "words", "patch"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None and y is None) or np.array_equal(x, y)


def assert_accounted(node: Any) -> dict[str, Any]:
    """Every message received was skipped (by the node, under one named counter), is held, or was fed to
    the extractor; the extractor received exactly what was fed; no internal error."""
    from ptm_ros.nodes.detector_inbox import SUBSCRIPTIONS

    d = node.diagnostics()
    for sub, stream in SUBSCRIPTIONS.items():
        topic = TOPICS[sub]
        skipped = sum(n for reason, n in node.skipped.items() if reason.startswith(f"{stream}-"))
        assert d["received"][topic] == skipped + d["fed"][stream] + d["held"][stream], (stream, d)
        assert d["fed"][stream] == d["extractor"]["received"][stream], (stream, d)
    assert d["internal_errors"] == 0 and d["extractor_errors"] == 0
    return d


# -------------------------------------------------------------------------------------- neutral storm


def _bad_stamp(msg: Any, rng: np.random.Generator) -> Any:
    if rng.random() < 0.5:
        msg.header.stamp.sec = -int(rng.integers(1, 2**31 - 1))
    else:
        msg.header.stamp.nanosec = int(rng.integers(1_000_000_000, 2**32))
    return msg


def neutral_corruption(b: Base, last: Base, rng: np.random.Generator) -> tuple[Any, str]:
    """A message of ``b``'s stream that the detector must reject, and the counter that must count it.
    ``last`` is the stream's previous valid message (``b`` the next one)."""
    s = b.stream
    far = float(rng.choice([-1.0, 1.0]) * rng.uniform(100.0, 1e6))
    back = float(rng.uniform(1e-3, 10.0))  # a small step back: the extractor's backwards counter
    kinds = ["stamp", "duplicate", "far", "back", "content"]
    kind = kinds[int(rng.integers(len(kinds)))]
    if kind == "stamp":
        return _bad_stamp(message(b), rng), f"{s}-bad-stamp"
    if kind == "duplicate":
        return message(last), f"{s}-duplicate"
    if kind == "far" and last.stamp + far >= 0.0:
        return message(last, last.stamp + far), f"{s}-outlier"
    if kind in ("back", "far"):
        return message(b, last.stamp - back), f"extractor.{s}-stamp-backwards"
    # content the node rejects
    if s == "odometry":
        msg = message(b)
        q, p = msg.pose.pose.orientation, msg.pose.pose.position
        case = int(rng.integers(6))
        if case == 0:
            p.x = float(rng.choice([math.nan, math.inf, -math.inf]))
            return msg, "odometry-non-finite"
        if case == 1:
            p.y = float(rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(7.1, 300))
            return msg, "odometry-out-of-range"
        if case == 2:
            q.x = q.y = q.z = q.w = 0.0
            return msg, "odometry-bad-quaternion"
        if case == 3:
            setattr(q, "xyzw"[int(rng.integers(4))], float(rng.choice([math.nan, math.inf])))
            return msg, "odometry-bad-quaternion"
        if case == 4:  # a teleport at the next stamp, refuted by the next valid message
            msg = message(b, last.stamp + 1e-3 * rng.uniform(0.0, 1.0))
            msg.pose.pose.position.x += float(rng.choice([-1.0, 1.0]) * rng.uniform(50.0, 1e5))
            return msg, "odometry-outlier"
        q.w = 1e200  # the norm overflows
        return msg, "odometry-bad-quaternion"
    if s == "scan":
        ranges, amin, ainc, rmin, rmax = b.data
        case = int(rng.integers(8))
        if case == 0:
            return scan_msg(b.stamp, [], amin, ainc, rmin, rmax), "scan-empty"
        if case == 1:
            return scan_msg(
                b.stamp, ranges, amin, float(rng.choice([0.0, math.nan, math.inf])), rmin, rmax
            ), ("scan-malformed")
        if case == 2:
            return scan_msg(b.stamp, ranges, math.nan, ainc, rmin, rmax), "scan-malformed"
        if case == 3:
            bad_min = float(rng.choice([-1.0, math.nan, -math.inf]))
            return scan_msg(b.stamp, ranges, amin, ainc, bad_min, rmax), "scan-malformed"
        if case == 4:
            bad_max = float(rng.choice([0.0, rmin, math.nan, -5.0]))
            return scan_msg(b.stamp, ranges, amin, ainc, rmin, bad_max), "scan-malformed"
        if case == 5:  # ranges of another length than angle_max implies
            msg = scan_msg(b.stamp, ranges, amin, ainc, rmin, rmax)
            msg.ranges = array.array(
                "f", np.asarray(ranges[: int(rng.integers(2, len(ranges) - 2))]).tobytes()
            )
            return msg, "scan-length-mismatch"
        if case == 6:
            msg = scan_msg(b.stamp, ranges, amin, ainc, rmin, rmax)
            msg.angle_max = float(rng.choice([math.nan, math.inf, amin + 5.0 * len(ranges) * ainc]))
            return msg, "scan-malformed" if not math.isfinite(msg.angle_max) else "scan-length-mismatch"
        msg = scan_msg(b.stamp, ranges, amin, ainc, rmin, rmax)
        msg.angle_max = amin - 3.0 * ainc  # a negative beam count
        return msg, "scan-length-mismatch"
    msg = message(b)
    case = int(rng.integers(5))
    if case == 0:
        msg.encoding = str(rng.choice(["32FC1", "jpeg", "", "mono12", "rgb16", "yuv422"]))
        return msg, "image-unsupported-encoding"
    if case == 1:
        msg.step = int(rng.integers(0, msg.width))  # shorter than a row
        return msg, "image-malformed"
    if case == 2:
        msg.data = bytes(rng.integers(0, 256, int(rng.integers(0, len(msg.data))), dtype=np.uint8))
        return msg, "image-malformed"
    if case == 3:
        msg.height = int(rng.integers(msg.height + 1, 2**32))  # more rows than the data holds
        return msg, "image-malformed"
    return image_msg(b.stamp, b.data[:, : int(rng.integers(0, 16))]), "image-too-small"


@pytest.fixture(scope="module")
def clean_visits(sim_stream) -> list[Visit]:
    """The visits of a detector fed the simulated run alone."""
    clean = detector()
    for b in sim_stream:
        feed(clean, b)
    clean.finish()
    visits = published_visits(clean)
    assert len(visits) >= 5
    return visits


def test_detector_neutral_storm_changes_nothing_but_counters(sim_stream, clean_visits):
    rng = np.random.default_rng(20250901)
    expected = clean_visits

    node = detector()
    streams = ("odometry", "scan", "image")
    burst = np.zeros(len(sim_stream), dtype=int)  # bad messages before each valid one, per stream
    for s in streams:
        eligible = [i for i, b in enumerate(sim_stream) if b.stream == s][4:]  # its start is confirmed
        burst[eligible] = rng.multinomial(N_STORM, np.full(len(eligible), 1.0 / len(eligible)))
    announce = set(rng.choice(len(sim_stream), size=2 * N_STORM // 40 + 1, replace=False).tolist())
    counts: dict[str, int] = {}
    sent = dict.fromkeys(streams, 0)
    last: dict[str, Base] = {}
    ends = 0
    for i, b in enumerate(sim_stream):
        for _ in range(burst[i]):
            msg, reason = neutral_corruption(b, last[b.stream], rng)
            feed(node, b, msg)
            counts[reason] = counts.get(reason, 0) + 1
            sent[b.stream] += 1
        if i in announce:  # malformed end-of-input announcements
            for text in bad_end_of_input(rng, 40):
                node.end_of_input(text)
                ends += 1
        feed(node, b)
        last[b.stream] = b
    assert min(sent.values()) >= N_STORM and ends >= 2 * N_STORM  # end_of_input: only this storm
    assert not node.finished and not node.end_announced
    node.finish()
    d = assert_accounted(node)
    for reason, n in counts.items():
        if reason.startswith("extractor."):
            assert d["extractor"]["skipped"][reason.removeprefix("extractor.")] == n, reason
        else:
            assert d[reason] == n, reason
    assert (
        sum(node.skipped.values())
        == sum(n for r, n in counts.items() if not r.startswith("extractor.")) + ends
    )
    assert d["end-of-input-invalid"] == ends
    assert d["sessions"] == 1 and d["clock_resets"] == d["teleports"] == d["forward_jumps"] == 0
    assert_same_visits(published_visits(node), expected)  # bit for bit: nothing leaked into the visits


def bad_end_of_input(rng: np.random.Generator, n: int) -> list[str]:
    """Malformed ``end_of_input`` announcements (none may end the input)."""
    schema = END_OF_INPUT_SCHEMA
    pool = [
        "",
        "{",
        "[" * 50_000,
        "1" * 5_000,
        "null",
        "[1, 2]",
        json.dumps({"schema": "ptm_ros.end_of_input/2", "counts": {"/odom": 1}}),
        json.dumps({"counts": {"/odom": 1}}),
        json.dumps({"schema": schema}),
        json.dumps({"schema": schema, "counts": 5}),
        json.dumps({"schema": schema, "counts": "abc"}),
        json.dumps({"schema": schema, "counts": {"/odom": -1}}),
        json.dumps({"schema": schema, "counts": {"/odom": 1.5}}),
        json.dumps({"schema": schema, "counts": {"/odom": True}}),
        json.dumps({"schema": schema, "counts": {"/odom": "12"}}),
        json.dumps({"schema": schema, "counts": {"/odom": None}}),
        json.dumps({"schema": schema, "counts": {"/odom": "BIG"}}).replace('"BIG"', "1e999"),
        json.dumps({"schema": schema, "counts": {"/odom": math.nan}}),
    ]
    out = [pool[int(i)] for i in rng.integers(len(pool), size=n - n // 4)]
    out += [
        bytes(rng.integers(32, 127, int(rng.integers(1, 60)), dtype=np.uint8)).decode() + "}"
        for _ in range(n // 4)
    ]
    return out


def test_detector_bag_loop_is_a_new_session_whichever_topic_restarts_first(sim_stream, clean_visits):
    """The run played twice, as a looped bag does (same stamps again), the second time with the odometry
    delivered 2 s late: scans and panoramas restart first and wait for the odometry's restart."""
    node = detector()
    for b in sim_stream:
        feed(node, b)
    late = sorted(sim_stream, key=lambda b: b.stamp + (2.0 if b.stream == "odometry" else 0.0))
    for b in late:
        feed(node, b)
    node.finish()
    d = assert_accounted(node)
    assert (d["sessions"], d["clock_resets"], d["resyncs"]) == (2, 3, 0)
    assert sum(node.skipped.values()) == 0
    nonce = node.session_id.rsplit("-", 1)[0]
    first, second = (published_visits(node, f"{nonce}-{k}") for k in (0, 1))
    assert_same_visits(first, clean_visits)
    assert_same_visits(second, clean_visits)


# ----------------------------------------------------------------------------------------- wild storm

WILD_FLOATS = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1e-300, -1e300, 1e300, 3.4e38, 1e7 + 1.0, -7.5)


def wild_message(b: Base, rng: np.random.Generator) -> Any:
    """``b`` with one to three random fields replaced by extreme, non-finite or random values."""
    msg = message(b)
    for _ in range(int(rng.integers(1, 4))):
        pick = int(rng.integers(4))
        if pick == 0:  # stamp: random, jittered, invalid
            msg.header.stamp.sec = int(rng.integers(-(2**31), 2**31))
            msg.header.stamp.nanosec = int(rng.integers(0, 2**32))
        elif pick == 1:
            msg.header.stamp = common.time_msg(max(b.stamp + float(rng.normal(0.0, 5.0)), 0.0))
        elif b.stream == "odometry":
            target = rng.choice(["x", "y", "qx", "qy", "qz", "qw", "scale"])
            value = float(rng.choice(WILD_FLOATS)) if rng.random() < 0.5 else float(rng.normal(0.0, 10.0))
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            if target == "scale":  # a non-unit quaternion
                q.x, q.y, q.z, q.w = (c * float(rng.uniform(0.01, 100.0)) for c in (q.x, q.y, q.z, q.w))
            elif target in ("x", "y"):
                setattr(p, target, value)
            else:
                setattr(q, target[1], value)
            msg.header.frame_id = str(rng.choice(["odom", "", "mäp", "x" * 300]))
        elif b.stream == "scan":
            field = str(
                rng.choice(["angle_min", "angle_max", "angle_increment", "range_min", "range_max", "ranges"])
            )
            if field == "ranges":
                r = np.array(msg.ranges, dtype=np.float32)
                if r.size < 2:  # already cut short by an earlier edit of this message
                    continue
                k = rng.integers(0, r.size, size=int(rng.integers(1, r.size)))
                r[k] = rng.choice(
                    np.array([math.nan, math.inf, -math.inf, -1.0, 0.0, 1e30, 3e38], dtype=np.float32),
                    size=k.size,
                )
                if rng.random() < 0.3:
                    r = r[: int(rng.integers(0, r.size))]
                msg.ranges = array.array("f", r.tobytes())
            else:
                setattr(
                    msg,
                    field,
                    float(rng.choice(WILD_FLOATS)) if rng.random() < 0.6 else float(rng.normal(0.0, 3.0)),
                )
        else:
            field = str(rng.choice(["encoding", "height", "width", "step", "data", "is_bigendian"]))
            if field == "encoding":
                msg.encoding = str(
                    rng.choice(["mono8", "mono16", "rgb8", "bgra8", "8UC3", "16UC1", "32FC1", "?"])
                )
            elif field == "data":
                msg.data = bytes(
                    rng.integers(0, 256, int(rng.integers(0, 2 * len(msg.data))), dtype=np.uint8)
                )
            elif field == "is_bigendian":
                msg.is_bigendian = int(rng.integers(0, 256))
            else:
                setattr(
                    msg,
                    field,
                    int(rng.integers(0, 2**32)) if rng.random() < 0.3 else int(rng.integers(0, 600)),
                )
    return msg


def test_detector_survives_a_wild_storm_and_then_maps_a_new_session_exactly(sim_stream):
    rng = np.random.default_rng(7)
    node = detector()
    sent = dict.fromkeys(("odometry", "scan", "image"), 0)
    by_stream = {s: [b for b in sim_stream if b.stream == s] for s in sent}
    rate = {s: N_STORM / len(v) for s, v in by_stream.items()}
    for b in sim_stream:
        for _ in range(int(rng.poisson(rate[b.stream]))):
            feed(node, b, wild_message(b, rng))
            sent[b.stream] += 1
        feed(node, b)
    for s, stream in by_stream.items():  # top up to N_STORM
        while sent[s] < N_STORM:
            b = stream[int(rng.integers(len(stream)))]
            feed(node, b, wild_message(b, rng))
            sent[s] += 1
    d = assert_accounted(node)
    assert sum(node.skipped.values()) > N_STORM  # most of the storm was rejected ...
    assert sum(d["fed"].values()) > len(sim_stream)  # ... some of it was plausible and used
    assert d["silent"] == ""

    # the same run again, its clock restarted 500 s earlier: a new session, mapped exactly
    shift = sim_stream[0].stamp - 500.0 - sim_stream[-1].stamp
    again = [replace(b, stamp=b.stamp + shift) for b in sim_stream]
    clean = detector()
    for b in again:
        feed(clean, b)
        feed(node, b)
    clean.finish()
    node.finish()
    d = assert_accounted(node)
    assert d["clock_resets"] >= 3 and d["sessions"] >= 2  # odometry, scans and panoramas went back
    assert_same_visits(published_visits(node, node.session_id), published_visits(clean))
    from ptm_ros.nodes.detector_inbox import EndOut, MapPose, MapScan

    ends = [json.loads(o.text) for o in node.of(EndOut)]
    assert ends == [
        {
            "schema": END_SCHEMA,
            "visits": len(published_visits(clean)),
            "session": node.session_id,
            "keyframes": len(node.of(MapScan)),
        }
    ]
    # the map stream of the new session (odometry samples, keyframe scans) is the clean run's too
    lo, hi = again[0].stamp, again[-1].stamp

    def stamps(det: Detector, kind: type) -> list[float]:
        return [o.stamp for o in det.of(kind) if lo <= o.stamp <= hi]

    assert stamps(node, MapScan) == stamps(clean, MapScan) and len(stamps(clean, MapScan)) > 20
    assert stamps(node, MapPose) == stamps(clean, MapPose) and len(stamps(clean, MapPose)) > 100


# ------------------------------------------------------------------------------------ topology filter


def synthetic_visits(rng: np.random.Generator, n: int = 10) -> list[Visit]:
    """Visits of a robot touring 4 places (pose noise 0.2 m), with 8-coefficient signatures."""
    places = rng.uniform(-8.0, 8.0, size=(4, 2))
    sigs = rng.uniform(0.01, 0.2, size=(4, 8))
    route = [0, 1, 2, 0, 3, 1, 2, 3, 0, 1, 3, 2][:n]
    out, prev = [], None
    for k, p in enumerate(route):
        xy = places[p] + rng.normal(0.0, 0.2, 2)
        pose = (float(xy[0]), float(xy[1]), float(rng.uniform(-math.pi, math.pi)))
        travel = 0.0 if prev is None else float(np.hypot(*(xy - prev)) * 1.2)
        out.append(
            Visit(
                index=k,
                stamp=100.0 + 17.0 * k,
                pose=pose,
                travel=travel,
                rotation=0.0 if prev is None else float(rng.uniform(0.0, 3.0)),
                signature=sigs[p] * rng.uniform(0.9, 1.1, 8),
            )
        )
        prev = xy
    return out


def filter_inbox(refit: int = 4) -> Any:
    """The topology filter node's logic without rclpy (the node hands it every message's text)."""
    import logging

    from ptm_ros.config import load_config
    from ptm_ros.nodes.filter_inbox import FilterInbox

    config = load_config(None, {"model": {"use_laser": False}, "inference": {"particles": 20}})
    return FilterInbox(config, logging.getLogger("filter_inbox"), refit_max_visits=refit)


def _array(a: np.ndarray) -> dict[str, Any]:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode()}


def neutral_visit_corruption(
    rng: np.random.Generator, visits: list[Visit], nxt: int, session: str
) -> tuple[str, str]:
    """A ``landmark_visits`` message the filter must drop (``nxt``: index of the next valid visit, which
    has already arrived up to ``nxt - 1``), and the counter that must count it."""
    from ptm_ros.nodes.messages import visit_message

    doc = json.loads(visit_message(visits[nxt], session))
    kind = int(rng.integers(9))
    if kind == 0:  # not JSON
        text = visit_message(visits[nxt], session)
        return str(
            rng.choice(
                [
                    text[: int(rng.integers(1, len(text) - 1))],
                    "[" * 60_000,
                    '{"a": ' * 30_000,
                    '{"schema": "ptm_ros.visit/1", "index": 1' + "0" * 5_000 + "}",
                    bytes(rng.integers(0, 256, 50, dtype=np.uint8)).decode("latin-1"),
                    "",
                ]
            )
        ), "invalid"
    if kind == 1:  # JSON, but no visit
        return str(
            rng.choice(
                ["[1, 2]", "3.5", '"visit"', "null", "true", json.dumps({**doc, "schema": "ptm_ros.visit/2"})]
            )
        ), "invalid"
    if kind == 2:  # a field of the wrong value or type
        fields = [
            ("index", -1),
            ("index", "one"),
            ("index", None),
            ("index", math.inf),
            ("stamp", math.nan),
            ("stamp", -math.inf),
            ("stamp", -1.0),
            ("stamp", "now"),
            ("stamp", [1]),
            ("pose", [1.0, 2.0]),
            ("pose", [math.nan, 0.0, 0.0]),
            ("pose", "xyz"),
            ("pose", 5),
            ("travel", -1.0),
            ("travel", math.nan),
            ("rotation", math.inf),
            ("session", 5),
            ("signature", 5),
            ("signature", "abc"),
            ("signature", {"dtype": "<f8", "shape": [8], "data": "!!!"}),
            ("signature", {"dtype": "<f8", "shape": [9], "data": doc["signature"]["data"]}),
            ("signature", {"dtype": "O", "shape": [8], "data": doc["signature"]["data"]}),
            ("signature", {"dtype": "what", "shape": [8], "data": doc["signature"]["data"]}),
            ("signature", {"dtype": "<U2", "shape": [16], "data": doc["signature"]["data"]}),
            ("signature", _array(np.array([0.1, math.nan] * 4))),
            ("signature", _array(-np.ones(8))),
            ("signature", _array(np.zeros(3))),
            ("signature", _array(np.zeros(0))),
            ("signature", _array(np.zeros((2, 4)))),
            ("patch", _array(np.zeros((4, 3)))),
            ("patch", _array(np.full((4, 2), math.inf))),
            ("words", _array(np.array([1, -2, 3]))),
            ("words", _array(np.array([0.5, 2.0]))),
        ]
        field, value = fields[int(rng.integers(len(fields)))]
        return json.dumps({**doc, field: value}), "invalid"
    if kind == 3:  # number beyond float range
        return json.dumps({**doc, "stamp": "STAMP"}).replace('"STAMP"', "1e999"), "invalid"
    if kind == 4:  # an earlier visit again
        k = int(rng.integers(0, nxt))
        return visit_message(visits[k], session), "duplicates"
    if kind == 5:  # a visit of another session, not from its start
        return visit_message(replace(visits[nxt], index=int(rng.integers(1, 50))), "other"), "foreign"
    if kind == 6:  # the next index, but older than the map's latest visit
        return visit_message(replace(visits[nxt], stamp=visits[nxt - 1].stamp - 1.0), session), "out_of_order"
    if kind == 7:  # a corrupt index far ahead
        return visit_message(
            replace(visits[nxt], index=nxt + 1001 + int(rng.integers(10**6))), session
        ), "implausible"
    count = [-1, "3", True, 2.5, None, 0][int(rng.integers(6))]
    if rng.random() < 0.3:
        return json.dumps({"schema": END_SCHEMA, "visits": nxt, "session": "other"}), "foreign"
    return json.dumps({"schema": END_SCHEMA, "visits": count, "session": session}), "invalid"


def test_filter_neutral_storm_leaves_the_ensemble_exact():
    from ptm_ros.nodes.messages import visit_message
    from ptm_ros.session import FilterSession

    rng = np.random.default_rng(11)
    visits = synthetic_visits(rng)
    node = filter_inbox()
    clean = FilterSession(node.config, refit_max_visits=4)
    counts: dict[str, int] = {}
    node.receive(visit_message(visits[0], "s"))
    clean.add(visits[0])
    per_gap = N_STORM // (len(visits) - 1) + 1
    for nxt in range(1, len(visits)):
        for _ in range(per_gap):
            text, counter = neutral_visit_corruption(rng, visits, nxt, "s")
            node.receive(text)
            counts[counter] = counts.get(counter, 0) + 1
        node.receive(visit_message(visits[nxt], "s"))
        clean.add(visits[nxt])
    node.receive(json.dumps({"schema": END_SCHEMA, "visits": len(visits), "session": "s"}))
    d = node.diagnostics()
    assert sum(counts.values()) >= N_STORM
    assert {k: d[k] for k in counts} == counts
    assert d["messages"] == sum(counts.values()) + len(visits) + 1
    assert d["gaps"] == d["rejected"] == d["resets"] == d["internal_errors"] == 0 and node.complete
    online, offline = node.session.inference(), clean.inference()
    assert online.probabilities == offline.probabilities  # bit for bit
    for lab in offline.probabilities:
        assert np.array_equal(online.positions[lab], offline.positions[lab])
    assert len(node.session.visits) == len(visits) and node.problems() == sum(counts.values())


WILD_JSON = [
    math.nan,
    math.inf,
    -math.inf,
    1e308,
    -0.0,
    0,
    -1,
    10**40,
    "",
    "x",
    None,
    True,
    [],
    {},
    [1, 2, 3],
    {"a": 1},
]


def wild_text(rng: np.random.Generator, text: str) -> str:
    """``text`` with one to five random edits: characters replaced, inserted or deleted, or a JSON value
    of a random key replaced."""
    if rng.random() < 0.4:
        try:
            doc = json.loads(text)
        except ValueError:
            doc = None
        if isinstance(doc, dict) and doc:
            key = str(rng.choice(sorted(doc)))
            doc[key] = WILD_JSON[int(rng.integers(len(WILD_JSON)))]
            return json.dumps(doc)
    chars = list(text)
    for _ in range(int(rng.integers(1, 6))):
        i = int(rng.integers(0, max(len(chars), 1)))
        op = int(rng.integers(3))
        c = chr(int(rng.choice([rng.integers(32, 127), rng.integers(0, 0x3000)])))
        if op == 0 and chars:
            chars[i] = c
        elif op == 1:
            chars.insert(i, c)
        elif chars:
            del chars[i]
    return "".join(chars)


def test_filter_survives_a_wild_storm_and_then_maps_a_new_session_exactly():
    from ptm_ros.nodes.messages import visit_message
    from ptm_ros.session import FilterSession

    rng = np.random.default_rng(12)
    visits = synthetic_visits(rng)
    node = filter_inbox()
    texts = [visit_message(v, "wild storm session") for v in visits]
    texts.append(json.dumps({"schema": END_SCHEMA, "visits": len(visits), "session": "wild storm session"}))
    for k in range(N_STORM):
        node.receive(wild_text(rng, texts[int(rng.integers(len(texts)))]))
        if k % 500 == 0:
            node.receive(texts[min(k // 500, len(texts) - 1)])
    d = node.diagnostics()
    assert d["internal_errors"] == 0 and d["invalid"] > N_STORM // 2
    taken = ("invalid", "duplicates", "implausible", "out_of_order", "foreign", "accepted", "ends")
    assert d["messages"] == sum(d[k] for k in taken) and d["accepted"] >= 1

    fresh = synthetic_visits(np.random.default_rng(13))
    clean = FilterSession(node.config, refit_max_visits=4)
    for v in fresh:
        node.receive(visit_message(v, "fresh"))
        clean.add(v)
    assert node.counters["internal_errors"] == 0 and len(node.session.visits) == len(fresh)
    assert node.session.inference().probabilities == clean.inference().probabilities


# ------------------------------------------------------------------------------------- map publisher


def graph_text(rng: np.random.Generator, n: int = 5) -> str:
    from ptm_ros.nodes.messages import graph_document

    parts = list(enumerate_partitions(n))
    chosen = [tuple(parts[i]) for i in rng.choice(len(parts), size=6, replace=False)]
    w = rng.dirichlet(np.ones(6)) * 0.95
    landmarks = [
        Landmark(i, 10.0 + i, (float(rng.normal()), float(rng.normal()), float(rng.normal())))
        for i in range(n)
    ]
    positions = {lab: rng.normal(size=(max(lab) + 1, 2)) for lab in chosen}
    ptm = make_ptm(landmarks, dict(zip(chosen, w, strict=True)), positions=positions)
    return json.dumps(graph_document(ptm, complete=bool(rng.random() < 0.5)))


def neutral_graph_corruption(rng: np.random.Generator, text: str) -> tuple[str, str]:
    """A ``ptm_graph`` message the map publisher must drop (``text``: the latest valid document)."""
    doc = json.loads(text)
    kind = int(rng.integers(5))
    if kind == 0:
        return text, "duplicates"
    if kind == 1:
        return str(
            rng.choice(
                [text[: int(rng.integers(1, len(text) - 1))], "[" * 60_000, "1" * 5_000, "", "[]", "null"]
            )
        ), "invalid"
    if kind == 2:
        key, value = [
            ("schema", "ptm_ros.ptm/2"),
            ("landmarks", 5),
            ("landmarks", [{"index": 0}]),
            ("topologies", "all"),
            ("topologies", [{"labels": [0, 2], "probability": 0.5}]),
            ("inference", 5),
            ("timing", "ab"),
            ("stream", [1]),
            ("stream", {"visits": 5, "complete": "yes"}),
        ][int(rng.integers(9))]
        return json.dumps({**doc, key: value}), "invalid"
    if kind == 3:
        lm = dict(doc["landmarks"][0])
        lm[str(rng.choice(["stamp", "pose"]))] = [math.nan, 0.0, 0.0] if rng.random() < 0.5 else math.inf
        if isinstance(lm["stamp"], list):
            lm["stamp"] = math.nan
        return json.dumps({**doc, "landmarks": [lm, *doc["landmarks"][1:]]}), "invalid"
    top = dict(doc["topologies"][0])
    change = int(rng.integers(4))
    if change == 0:
        top["positions"] = top["positions"][:-1] if len(top["positions"]) > 1 else [[0.0, 0.0], [1.0, 1.0]]
    elif change == 1:
        top["positions"] = [[math.nan, 0.0]] * len(top["positions"])
    elif change == 2:
        top["probability"] = float(rng.choice([math.nan, 1.5, -0.1]))
    else:
        top["labels"] = [1, *top["labels"][1:]]  # not canonical
    return json.dumps({**doc, "topologies": [top, *doc["topologies"][1:]]}), "invalid"


def test_map_publisher_storms():
    """The map publisher's ensemble input (its rclpy-free :class:`~ptm_ros.nodes.map_inbox.MapInbox`):
    every corrupted document dropped and counted, the latest valid one in force, and each accepted one a
    valid map whose path (one pose per visit) the node publishes."""
    import logging

    from ptm_ros.config import load_config
    from ptm_ros.nodes.map_inbox import MapInbox
    from ptm_ros.nodes.map_publisher import map_path

    rng = np.random.default_rng(14)
    inbox = MapInbox(load_config(), logging.getLogger("map_inbox"))
    counts = {"invalid": 0, "duplicates": 0}
    valid = 0
    latest = None
    for k in range(N_STORM):  # neutral: every corruption is dropped, the latest valid document stays
        if k % 250 == 0:
            latest = graph_text(rng)
            assert inbox.graph(latest) is not None
            valid += 1
        text, counter = neutral_graph_corruption(rng, latest)
        assert inbox.graph(text) is None
        counts[counter] += 1
        assert inbox.doc == json.loads(latest)
    assert {k: inbox.counters[k] for k in counts} == counts
    assert inbox.counters["messages"] == N_STORM + valid
    for k in range(N_STORM):  # wild: random edits; whatever is accepted must be a valid map
        ptm = inbox.graph(wild_text(rng, graph_text(rng) if k % 50 == 0 else latest))
        if ptm is not None:  # the path of the map: one pose per visit, if a topology
            assert ptm is inbox.ptm
            assert len(map_path(ptm).poses) == (len(ptm.landmarks) if ptm.topologies else 0)
    latest = graph_text(rng)
    ptm = inbox.graph(latest)
    assert ptm is not None and inbox.doc == json.loads(latest) and len(map_path(ptm).poses) == 5


def map_publisher(ros) -> Any:
    """A map publisher that draws on request only (``mapping.period`` large) and records what it sends."""
    from rclpy.parameter import Parameter

    from ptm_ros.nodes.map_publisher import MapPublisherNode

    params = {"out_dir": "/nonexistent", "mapping.period": 1e6}
    node = ros.add(
        MapPublisherNode(
            context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]
        )
    )
    node._path_pub, node._diag_pub, node._map_pub, node._trajectory_pub = (Recorder() for _ in range(4))
    return node


def draw(node: Any, visits: list[Visit], session: str) -> Any:
    """Give the map publisher a session's visits and an ensemble of them (each visit its own place and
    the first and last visits one place), and draw the map."""

    from ptm_ros.nodes.messages import graph_document, visit_message

    for v in visits:
        node.inbox.visit(visit_message(v, session))
    n = len(visits)
    singles, loop = tuple(range(n)), (*range(n - 1), 0)
    ptm = make_ptm([Landmark.from_visit(v) for v in visits], {singles: 0.4, loop: 0.6})
    node.inbox.graph(json.dumps(graph_document(ptm, complete=True)))
    return node.build_map()


def test_map_publisher_metric_map_survives_storms_of_its_inputs(ros, sim_stream, clean_visits):

    rng = np.random.default_rng(21)
    callback = {"odometry": "odometry_message", "scan": "scan_message"}  # the map inbox's inputs
    stream = [b for b in sim_stream if b.stream in callback]
    clean = map_publisher(ros)
    for b in stream:
        getattr(clean.inbox, callback[b.stream])(message(b))
    expected = draw(clean, clean_visits, "clean")
    assert expected is not None and expected.grid is not None and len(clean._map_pub.items) == 1
    assert clean.inbox.online.counters.resets == 0

    node = map_publisher(ros)
    sent = dict.fromkeys(callback, 0)
    for b in stream:  # the run with wild odometry samples and scans in between
        for _ in range(int(rng.poisson(2.0))):
            getattr(node.inbox, callback[b.stream])(wild_message(b, rng))
            sent[b.stream] += 1
        getattr(node.inbox, callback[b.stream])(message(b))
    texts = [wild_text(rng, visit_to_json(v)) for v in clean_visits for _ in range(200)]
    for text in texts:  # wild visit messages: dropped or taken, never a crash
        node.inbox.visit(text)
    for _ in range(200):  # and wild ensembles
        node.inbox.graph(wild_text(rng, graph_text(rng)))
    assert node.counters["internal_errors"] == 0
    c = node.inbox.online.counters
    clean_sent = {s: sum(b.stream == s for b in stream) for s in callback}
    assert c.poses + node.counters["odometry_invalid"] == clean_sent["odometry"] + sent["odometry"]
    assert c.scans + node.counters["scans_invalid"] == clean_sent["scan"] + sent["scan"]
    assert node.counters["odometry_invalid"] > 0 and node.counters["scans_invalid"] > 0
    node.build_map()  # whatever it holds now: a map or a counted refusal, no exception
    assert node.counters["internal_errors"] == 0

    # The same run again, its clock restarted 500 s earlier (a new detector session): mapped exactly.
    shift = stream[0].stamp - 500.0 - stream[-1].stamp
    for b in stream:
        getattr(node.inbox, callback[b.stream])(message(b, b.stamp + shift))
    again = [replace(v, stamp=v.stamp + shift) for v in clean_visits]
    got = draw(node, again, "again")
    assert got is not None and got.grid is not None and node.inbox.online.counters.resets >= 1
    np.testing.assert_allclose(got.trajectory, expected.trajectory, atol=1e-9)
    np.testing.assert_array_equal(got.grid.observed, expected.grid.observed)
    np.testing.assert_allclose(got.grid.log_odds, expected.grid.log_odds, atol=1e-9)
    assert node.counters["internal_errors"] == 0
