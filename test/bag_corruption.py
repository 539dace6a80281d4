"""Corrupted copies of a rosbag2, for the bag fuzz test (``test_bag_fuzz.py``) and its bench
(``bench/bench_fuzz.py``).

A :class:`Plan` lists what to do to a clean bag's messages; :func:`corrupt` writes the corrupted copy
and returns what it wrote. Corruptions come in two families:

* *inserted* bad messages (:class:`Insert`, ``Plan.duplicate_every``): a duplicate, a copy stamped
  back or far ahead, a scan filled with NaN / inf, an empty or over-long scan, a panorama with a wrong
  encoding, a header stamp that is no ROS time. Each is written just after the message it copies (log
  time + 1 ns). The reader must skip every one of them, so a bag with only these gives the clean bag's
  result exactly.
* *damage* to the messages themselves (:class:`Stretch`, :class:`Replace`, ``Plan.missing_from``,
  ``Plan.truncate``, ``Plan.smash``): stamps of a stretch moved back or forward, scans replaced by NaN /
  inf / empty ones, a topic that stops midway, a storage file cut short or overwritten in places. These
  cost good data, so only the accounting and the survival of the tools can be checked.
"""

from __future__ import annotations

import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptm_ros.io.bag import NS_PER_S, BagWriter, iter_raw, typestore

TOPIC_STREAMS = {"/odom": "odometry", "/scan": "scan", "/panorama": "image"}

#: Inserted kinds: (topic or None for any, the reason the reader counts it under; None: by stamp order).
INSERTED = {
    "duplicate": (None, None),
    "back-copy": (None, None),
    "far-copy": (None, None),
    "bad-stamp": (None, "bad-stamp"),
    "nan-scan": ("/scan", "scan-non-finite"),
    "inf-scan": ("/scan", "scan-non-finite"),
    "empty-scan": ("/scan", "scan-empty"),
    "long-scan": ("/scan", "scan-length-mismatch"),
    "jpeg-image": ("/panorama", "image-unsupported-encoding"),
    "float-image": ("/panorama", "image-unsupported-encoding"),
    "rgb-image": ("/panorama", "image-malformed"),  # mono8 data said to be rgb8: rows too short
}
REPLACED = {"nan": "scan-non-finite", "inf": "scan-non-finite", "empty": "scan-empty"}


@dataclass(frozen=True)
class Insert:
    """An extra bad message of ``kind`` (:data:`INSERTED`) after the message at fraction ``at`` of
    ``topic``'s messages (never after the last two: a copy stamped ahead there would tie with them)."""

    kind: str
    topic: str
    at: float
    shift_s: float = 1.0  # back-copy / far-copy: how far the copy's stamp moves


@dataclass(frozen=True)
class Stretch:
    """``length`` messages of ``topic`` from fraction ``at`` with their header stamps moved by
    ``shift_s`` (negative: back in time)."""

    topic: str
    at: float
    length: int
    shift_s: float


@dataclass(frozen=True)
class Replace:
    """The scan at fraction ``at`` replaced by a ``kind`` one (:data:`REPLACED`)."""

    kind: str
    at: float


@dataclass(frozen=True)
class Plan:
    """What to do to a bag; ``missing_from``: topic -> fraction of its messages after which it stops;
    ``truncate``: the fraction of the storage file kept (None: intact)."""

    inserts: tuple[Insert, ...] = ()
    stretches: tuple[Stretch, ...] = ()
    replaces: tuple[Replace, ...] = ()
    missing_from: tuple[tuple[str, float], ...] = ()
    truncate: float | None = None
    duplicate_every: int | None = None  # every k-th message of the bag (log order) written twice
    storage: str = "mcap"  # of the corrupted copy
    smash: float | None = None  # 64 bytes of the storage file from this fraction on overwritten

    @property
    def neutral(self) -> bool:
        """Only inserted bad messages: the result must equal the clean bag's."""
        damaged = self.truncate is not None or self.smash is not None
        return not (self.stretches or self.replaces or self.missing_from or damaged)


@dataclass
class Written:
    """What :func:`corrupt` wrote: messages per stream, and per skip reason the messages that must be
    counted under it at least (content rejections; the stamp-order reasons are not predicted)."""

    path: Path
    messages: Counter[str] = field(default_factory=Counter)
    at_least: Counter[str] = field(default_factory=Counter)


def _index(n: int, at: float, *, spare: int = 0) -> int:
    return min(int(at * n), max(n - 1 - spare, 0))


def _with_stamp(msg: object, ns: int) -> object:
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // NS_PER_S, ns % NS_PER_S  # type: ignore[attr-defined]
    return msg


def _inserted(kind: str, msgtype: str, msg: object, stamp_ns: int, shift_s: float) -> object:
    shift = round(shift_s * NS_PER_S)
    if kind == "back-copy":
        return _with_stamp(msg, max(stamp_ns - shift, 0))
    if kind == "far-copy":
        return _with_stamp(msg, stamp_ns + shift)
    if kind == "bad-stamp":
        msg.header.stamp.nanosec = NS_PER_S + 7  # type: ignore[attr-defined]
        return msg
    if kind in ("nan-scan", "inf-scan"):
        msg.ranges = np.full_like(msg.ranges, np.nan if kind == "nan-scan" else np.inf)  # type: ignore[attr-defined]
    elif kind == "empty-scan":
        msg.ranges = np.zeros(0, dtype=np.float32)  # type: ignore[attr-defined]
    elif kind == "long-scan":
        msg.ranges = np.concatenate([msg.ranges, msg.ranges])  # type: ignore[attr-defined]
    elif kind == "jpeg-image":
        msg.encoding = "jpeg"  # type: ignore[attr-defined]
    elif kind == "float-image":
        msg.encoding = "32FC1"  # type: ignore[attr-defined]
    elif kind == "rgb-image":
        msg.encoding = "rgb8"  # type: ignore[attr-defined]
    return msg


def corrupt(src: Path, dst: Path, plan: Plan) -> Written:
    """Write the corrupted copy of bag ``src`` (with its ``ground_truth.json``) at ``dst``."""
    store = typestore()
    raw = list(iter_raw(src))
    positions: dict[str, list[int]] = {}
    for i, m in enumerate(raw):
        positions.setdefault(m.topic, []).append(i)
    extra: dict[int, list[tuple[str, float]]] = {}
    for ins in plan.inserts:
        own = positions.get(ins.topic, [])
        if own:
            extra.setdefault(own[_index(len(own), ins.at, spare=2)], []).append((ins.kind, ins.shift_s))
    moved: dict[int, int] = {}
    for st in plan.stretches:
        own = positions.get(st.topic, [])
        start = _index(len(own), st.at)
        for i in own[start : start + st.length]:
            moved[i] = moved.get(i, 0) + round(st.shift_s * NS_PER_S)
    replaced = {positions["/scan"][_index(len(positions["/scan"]), r.at)]: r.kind for r in plan.replaces}
    stop = {t: positions[t][_index(len(positions[t]), f)] for t, f in plan.missing_from if positions.get(t)}
    written = Written(dst)
    with BagWriter(dst, storage=plan.storage) as bag:  # type: ignore[arg-type]
        for i, m in enumerate(raw):
            if m.topic in stop and i > stop[m.topic]:
                continue
            data = m.rawdata
            if i in moved or i in replaced:
                msg = store.deserialize_cdr(data, m.msgtype)
                if i in moved:
                    _with_stamp(msg, max(m.header_stamp_ns + moved[i], 0))
                if i in replaced:
                    msg = _inserted(f"{replaced[i]}-scan", m.msgtype, msg, m.header_stamp_ns, 0.0)
                    written.at_least[REPLACED[replaced[i]]] += 1
                data = store.serialize_cdr(msg, m.msgtype)
            bag.write_raw(m.topic, m.msgtype, m.log_time_ns, data)
            written.messages[TOPIC_STREAMS[m.topic]] += 1
            duplicates = (
                [("duplicate", 0.0)] if plan.duplicate_every and i % plan.duplicate_every == 0 else []
            )
            for kind, shift in extra.get(i, []) + duplicates:
                topic, reason = INSERTED[kind]
                if topic is not None and topic != m.topic:
                    continue
                copy = store.deserialize_cdr(m.rawdata, m.msgtype)
                copy = _inserted(kind, m.msgtype, copy, m.header_stamp_ns, shift)
                bag.write_raw(m.topic, m.msgtype, m.log_time_ns + 1, store.serialize_cdr(copy, m.msgtype))
                written.messages[TOPIC_STREAMS[m.topic]] += 1
                if reason is not None:
                    prefix = "" if topic is not None else f"{TOPIC_STREAMS[m.topic]}-"
                    written.at_least[prefix + reason] += 1
    shutil.copy(src / "ground_truth.json", dst / "ground_truth.json")
    for storage in sorted(dst.glob("*.mcap")) + sorted(dst.glob("*.db3")):
        size = storage.stat().st_size
        with storage.open("r+b") as fh:
            if plan.smash is not None:
                fh.seek(int(size * plan.smash))
                fh.write(np.random.default_rng(int(plan.smash * 1e6)).bytes(64))
            if plan.truncate is not None:
                fh.truncate(int(size * plan.truncate))
    return written
