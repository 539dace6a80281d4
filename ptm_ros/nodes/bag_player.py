"""``ptm-bag-player BAG [--rate R] [--topics T ...]``: replay a rosbag2 over DDS, losslessly.

Publishes the bag's messages as stored (raw CDR bytes: no decoding, so the subscribers see exactly the
recorded values) on their recorded topics, with reliable, keep-all QoS, in log-time order, and the
bag's log time on ``/clock`` (for nodes with ``use_sim_time``). Before the first message it waits until
every replayed topic has a matched subscriber (``--wait`` s, then it fails). ``--rate R`` paces the
replay at R × the recorded speed; ``--rate 0`` publishes as fast as the subscribers keep up (reliable
keep-all publishers block while the readers' queues are full, so nothing is dropped).

At the end it waits until every subscriber has acknowledged every message, then publishes the number of
messages per topic on ``end_of_input`` (std_msgs/String ``ptm_ros.end_of_input/1``, latched) — the
landmark detector completes its last visits once it has received that many — and exits 0.
Exit codes: 0 done, 1 no subscriber matched or delivery unconfirmed, 2 bad arguments or bag, 130 SIGINT.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PROG = "ptm-bag-player"
POLL_S = 0.02
PUBLISH_RETRY_S = 0.05


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="Replay a rosbag2 over DDS without losing messages.")
    p.add_argument("bag", type=Path, help="rosbag2 directory (or .mcap / .db3 file)")
    p.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="speed factor (1 = recorded speed; 0 = as fast as the subscribers keep up; "
        "default: %(default)s)",
    )
    p.add_argument("--topics", nargs="+", default=None, help="replay only these topics (default: all)")
    p.add_argument(
        "--wait", type=float, default=30.0, help="s to wait for subscribers (default: %(default)s)"
    )
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    return p


@dataclass(frozen=True)
class BagTopic:
    """A topic of a bag: name, ROS type (``nav_msgs/msg/Odometry``; None when the topic's connections
    disagree on it) and message count."""

    name: str
    msgtype: str | None
    count: int


def bag_topics(path: Path) -> dict[str, BagTopic]:
    """The topics of a rosbag2 (from its metadata).

    Raises:
        BagError: the bag cannot be opened.
    """
    from rosbags.rosbag2 import Reader

    from ptm_ros.errors import BagError

    if not path.exists():
        msg = f"bag {path} does not exist"
        raise BagError(msg)
    try:
        with Reader(path) as reader:
            return {
                name: BagTopic(name, info.msgtype, int(info.msgcount)) for name, info in reader.topics.items()
            }
    except Exception as err:  # rosbags raises many types on unreadable input
        msg = f"cannot open bag {path}: {type(err).__name__}: {err}"
        raise BagError(msg) from err


def message_class(msgtype: str | None) -> Any:
    """The rclpy message class of a ROS type name (``pkg/msg/Name``).

    Raises:
        BagError: the type is not installed, or None (:class:`BagTopic`: a topic of several types).
    """
    from ptm_ros.errors import BagError

    if msgtype is None:
        msg = "a topic whose connections have different message types cannot be replayed"
        raise BagError(msg)
    pkg, _, name = msgtype.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError, ValueError) as err:
        msg = f"message type {msgtype} is not available to rclpy ({err})"
        raise BagError(msg) from err


def select_topics(available: dict[str, BagTopic], wanted: Collection[str] | None) -> list[BagTopic]:
    """The topics to replay (all when ``wanted`` is None).

    Raises:
        BagError: a wanted topic the bag lacks.
    """
    from ptm_ros.errors import BagError

    if wanted is None:
        return sorted(available.values(), key=lambda t: t.name)
    missing = sorted(set(wanted) - set(available))
    if missing:
        msg = f"the bag has no topic {', '.join(missing)} (topics: {sorted(available)})"
        raise BagError(msg)
    return [available[t] for t in sorted(set(wanted))]


class BagPlayer:
    """Publishers for the replayed topics, ``/clock`` and ``end_of_input`` on ``node``."""

    def __init__(self, node: Any, bag: Path, topics: Sequence[BagTopic], *, clock: bool = True) -> None:
        from rosgraph_msgs.msg import Clock
        from std_msgs.msg import String

        from ptm_ros.nodes.common import LATCHED_QOS, REPLAY_QOS

        self.node = node
        self.bag = bag
        self.topics = list(topics)
        self.publishers = {
            t.name: node.create_publisher(message_class(t.msgtype), t.name, REPLAY_QOS) for t in topics
        }
        self.clock_pub = node.create_publisher(Clock, "/clock", 10) if clock else None
        self.end_pub = node.create_publisher(String, "end_of_input", LATCHED_QOS)
        self.counts = {t.name: 0 for t in topics}

    def unmatched(self) -> list[str]:
        """Replayed topics without a matched subscriber."""
        return [name for name, pub in self.publishers.items() if pub.get_subscription_count() == 0]

    def wait_for_subscribers(self, timeout: float) -> list[str]:
        """Wait until every replayed topic has a subscriber; returns the topics still without one."""
        deadline = time.monotonic() + timeout
        while (missing := self.unmatched()) and time.monotonic() < deadline:
            time.sleep(POLL_S)
        return missing

    def _publish(self, pub: Any, data: Any, timeout: float) -> None:
        """Publish, retrying while the publisher's history is full (slow subscribers)."""
        from rclpy._rclpy_pybind11 import RCLError

        deadline = time.monotonic() + timeout
        while True:
            try:
                pub.publish(data)
                return
            except RCLError:
                if not self.node.context.ok():
                    raise KeyboardInterrupt from None  # rclpy shut down (SIGINT) while publishing
                if time.monotonic() > deadline:
                    raise
                time.sleep(PUBLISH_RETRY_S)

    def play(self, rate: float, timeout: float = 30.0) -> int:
        """Publish every message (paced at ``rate``; 0 = unpaced); returns the number published."""
        from builtin_interfaces.msg import Time
        from rosgraph_msgs.msg import Clock

        from ptm_ros.io.bag import NS_PER_S, iter_raw

        start_wall = time.monotonic()
        start_ns: int | None = None
        last_clock = -1
        total = 0
        for raw in iter_raw(self.bag, [t.name for t in self.topics]):
            if start_ns is None:
                start_ns = raw.log_time_ns
            if rate > 0.0:
                delay = start_wall + (raw.log_time_ns - start_ns) / NS_PER_S / rate - time.monotonic()
                if delay > 0.0:
                    time.sleep(delay)
            if self.clock_pub is not None and raw.log_time_ns > last_clock:
                last_clock = raw.log_time_ns
                stamp = Time(sec=raw.log_time_ns // NS_PER_S, nanosec=raw.log_time_ns % NS_PER_S)
                self.clock_pub.publish(Clock(clock=stamp))
            self._publish(self.publishers[raw.topic], raw.rawdata, timeout)
            self.counts[raw.topic] += 1
            total += 1
        return total

    def finish(self, timeout: float) -> bool:
        """Wait for every message to be acknowledged, then announce the end; True when all were."""
        from rclpy.duration import Duration
        from std_msgs.msg import String

        from ptm_ros.nodes.messages import END_OF_INPUT_SCHEMA

        deadline = time.monotonic() + timeout
        acked = True
        for pub in self.publishers.values():
            left = max(deadline - time.monotonic(), 0.0)
            acked &= bool(pub.wait_for_all_acked(Duration(seconds=left)))
        while self.end_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(POLL_S)
        doc = {"schema": END_OF_INPUT_SCHEMA, "bag": str(self.bag), "counts": self.counts}
        self.end_pub.publish(String(data=json.dumps(doc)))
        if self.end_pub.get_subscription_count() > 0:
            left = max(deadline - time.monotonic(), 1.0)
            acked &= bool(self.end_pub.wait_for_all_acked(Duration(seconds=left)))
        return acked


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``ptm-bag-player``."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.utilities import remove_ros_args

    from ptm_ros.errors import PtmError

    full = [PROG, *(sys.argv[1:] if argv is None else argv)]
    args = build_parser().parse_args(remove_ros_args(full)[1:])
    if not args.rate >= 0.0:
        print(f"{PROG}: error: --rate must be >= 0, got {args.rate}", file=sys.stderr)
        return 2
    try:
        topics = select_topics(bag_topics(args.bag), args.topics)
        for t in topics:
            message_class(t.msgtype)
    except PtmError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    rclpy.init(args=full)
    node = rclpy.create_node("ptm_bag_player")
    log = node.get_logger()
    try:
        player = BagPlayer(node, args.bag, topics, clock=not args.no_clock)
        missing = player.wait_for_subscribers(args.wait)
        if missing:
            log.error(f"no subscriber for {', '.join(missing)} after {args.wait:g} s; nothing published")
            return 1
        log.info(f"playing {args.bag} ({sum(t.count for t in topics)} messages) at rate {args.rate:g}")
        t0 = time.monotonic()
        total = player.play(args.rate, timeout=max(args.wait, 1.0))
        acked = player.finish(timeout=max(args.wait, 1.0))
        log.info(f"published {total} messages in {time.monotonic() - t0:.2f} s: {player.counts}")
        if not acked:
            log.error("not every message was acknowledged by the subscribers")
            return 1
        return 0
    except PtmError as err:
        log.error(str(err))
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
