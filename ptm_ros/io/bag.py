"""rosbag2 reading and writing (ROS 2 Jazzy message types) on top of ``rosbags``.

Writing: :class:`BagWriter` stores ``nav_msgs/msg/Odometry``, ``sensor_msgs/msg/LaserScan`` and
``sensor_msgs/msg/Image`` messages (and raw CDR bytes of any Jazzy type) in an mcap (default) or sqlite3
rosbag2, version 9. Frames follow REP 105: odometry in ``odom`` with child ``base_link``.

Reading: :func:`read_run` loads odometry, scans and images into numpy arrays (:class:`RunData`);
:func:`iter_raw` yields the raw messages in log-time order for a player.

Exactness rules (the whole pipeline keeps CARMEN stamps and poses unchanged):

* **Stamps.** A stamp ``t`` in seconds (float) becomes the integer ``ns = round(t · 10⁹)`` computed on the
  exact binary value of ``t`` (ties to even), split into ``sec = ns // 10⁹`` and ``nanosec = ns % 10⁹``;
  the bag's log time is the same ``ns``. Reading gives back ``ns / 10⁹`` correctly rounded, which equals
  ``t`` bit for bit whenever ``t`` is a decimal with at most 9 fractional digits (every CARMEN stamp) or
  ``|t| ≥ 2²² s`` (epoch stamps). :func:`stamp_to_ns` and :func:`ns_to_stamp` implement the rule.
* **Poses.** ``x``, ``y`` are float64 fields, stored as is. The yaw travels as the quaternion
  ``(0, 0, sin(θ/2), cos(θ/2))``, nudged by at most a few ulps so that :func:`quaternion_to_yaw` (which
  other modules must use to decode) returns ``θ`` bit for bit for every normal float ``|θ| ≤ 2π``
  (CARMEN corrected logs hold yaws slightly beyond π). Larger yaws come back reduced to ``[−π, π]``.
* **Scans.** ``LaserScan`` fields are float32: ranges and angles come back as the float32 nearest to
  what was written.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from functools import cache
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import BagError, ConfigError
from ptm_ros.model.geometry import FloatArray

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.rosbag2 import Writer
    from rosbags.typesys.store import Typestore

    from ptm_ros.model.appearance import AppearanceConfig

IntArray = NDArray[np.int64]

ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
SCAN_TYPE = "sensor_msgs/msg/LaserScan"
IMAGE_TYPE = "sensor_msgs/msg/Image"
#: The extractor's name of each stream (the prefix of its skip reasons).
STREAM_NAMES = {ODOMETRY_TYPE: "odometry", SCAN_TYPE: "scan", IMAGE_TYPE: "image"}
HEADER_TYPE = "std_msgs/msg/Header"
STORAGES = ("mcap", "sqlite3")
NS_PER_S = 1_000_000_000
_MAX_NS = (2**31 - 1) * NS_PER_S + NS_PER_S - 1  # builtin_interfaces/Time.sec is int32
# Encodings read_run decodes: name -> (numpy dtype, channels).
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    "mono8": ("u1", 1),
    "8UC1": ("u1", 1),
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "8UC3": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
    "mono16": ("u2", 1),
    "16UC1": ("u2", 1),
}
# Exceptions rosbags and its storage back-ends raise on unreadable or corrupt input.
_READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError,
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    AssertionError,
    ArithmeticError,
    EOFError,
    struct.error,
)


@cache
def typestore() -> Typestore:
    """The ROS 2 Jazzy typestore (built once)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _reader_errors() -> tuple[type[BaseException], ...]:
    from rosbags.rosbag2 import ReaderError
    from rosbags.serde import SerdeError

    errors: tuple[type[BaseException], ...] = (ReaderError, SerdeError, *_READ_ERRORS)
    try:
        import apsw
    except ImportError:  # pragma: no cover - apsw ships with rosbags
        return errors
    return (*errors, apsw.Error)


# --------------------------------------------------------------------------------------------- stamps


def stamp_to_ns(stamp_s: float) -> int:
    """Seconds → integer nanoseconds, rounding the exact binary value of ``stamp_s`` to the nearest ns."""
    t = float(stamp_s)
    if not math.isfinite(t):
        msg = f"stamp {stamp_s!r} is not finite"
        raise BagError(msg)
    ns = round(Fraction(t) * NS_PER_S)
    if not 0 <= ns <= _MAX_NS:
        msg = f"stamp {stamp_s!r} s is outside [0, 2^31) s, the range of a ROS 2 time"
        raise BagError(msg)
    return ns


def ns_to_stamp(ns: int) -> float:
    """Integer nanoseconds → seconds, correctly rounded (the inverse of :func:`stamp_to_ns`)."""
    return int(ns) / NS_PER_S


# ------------------------------------------------------------------------------------------------ yaw


def quaternion_to_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw of a quaternion; the bit-exact inverse of :func:`yaw_to_quaternion`.

    A planar quaternion (``x = y = 0``) decodes as ``2·atan2(z, w) ∈ [−2π, 2π]`` (outside ``[−π, π]``
    exactly when ``w < 0``: wrap it if you need the principal angle); any other one as
    ``atan2(2(wz + xy), 1 − 2(y² + z²)) ∈ [−π, π]``.
    """
    if x == 0.0 and y == 0.0:
        return 2.0 * math.atan2(z, w)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _ulp_steps(v: float, k: int) -> list[float]:
    """``v`` moved by ``-k … k`` ulps, ordered by distance from ``v``."""
    out = [v]
    up = down = v
    for _ in range(k):
        up = math.nextafter(up, math.inf)
        down = math.nextafter(down, -math.inf)
        out += [up, down]
    return out


def yaw_to_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``yaw`` about z such that :func:`quaternion_to_yaw` returns ``yaw``.

    Starts from ``(0, 0, sin(yaw/2), cos(yaw/2))`` and, when rounding spoils the round trip, searches
    ``z`` and ``w`` within ±3 ulps (the quaternion's norm moves by < 1e-15). Exact for every normal
    ``|yaw| ≤ 2π`` (``w < 0`` when ``|yaw| > π``); larger yaws are first reduced to ``[−π, π]``; subnormal
    yaws (no exact encoding exists) get the nearest one.
    """
    yaw = float(yaw)
    if not math.isfinite(yaw):
        msg = f"yaw {yaw!r} is not finite"
        raise BagError(msg)
    if not -2.0 * math.pi <= yaw <= 2.0 * math.pi:
        yaw = math.remainder(yaw, 2.0 * math.pi)
    half = 0.5 * yaw
    z, w = math.sin(half), math.cos(half)
    if quaternion_to_yaw(0.0, 0.0, z, w) == yaw:
        return 0.0, 0.0, z, w
    for zz in _ulp_steps(z, 3):
        for ww in _ulp_steps(w, 3):
            if quaternion_to_yaw(0.0, 0.0, zz, ww) == yaw:
                return 0.0, 0.0, zz, ww
    return 0.0, 0.0, z, w


# --------------------------------------------------------------------------------------------- writer


def _pose_tuple(pose: ArrayLike, name: str, n: int) -> tuple[float, ...]:
    values = np.asarray(pose, dtype=float).reshape(-1)
    if values.shape != (n,) or not np.all(np.isfinite(values)):
        msg = f"{name} must be {n} finite numbers, got {pose!r}"
        raise BagError(msg)
    return tuple(float(v) for v in values)


class BagWriter:
    """Writes a new rosbag2 (version 9, Jazzy types) at ``path``; use as a context manager.

    ``path`` must not exist (rosbag2 directories are never overwritten). Every ``write_*`` takes the stamp
    in seconds; the header stamp and the log time are both ``stamp_to_ns(stamp_s)``. On an exception
    inside the ``with`` block the bag is aborted (left without ``metadata.yaml``).
    """

    def __init__(self, path: str | Path, storage: Literal["mcap", "sqlite3"] = "mcap") -> None:
        if storage not in STORAGES:
            msg = f"storage must be one of {STORAGES}, got {storage!r}"
            raise ConfigError(msg)
        self.path = Path(path)
        self.storage = storage
        self._writer: Writer | None = None
        self._connections: dict[str, Connection] = {}
        self.counts: dict[str, int] = {}

    # -- lifecycle
    def open(self) -> BagWriter:
        """Create the bag directory and its storage file."""
        from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

        if self.path.exists():
            msg = f"cannot write bag {self.path}: the path exists already (rosbag2 never overwrites)"
            raise BagError(msg)
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        try:
            writer = Writer(self.path, version=9, storage_plugin=plugin)
            writer.open()
        except (WriterError, OSError) as err:
            msg = f"cannot create bag {self.path}: {err}"
            raise BagError(msg) from err
        self._writer = writer
        return self

    def close(self) -> None:
        """Write the index and ``metadata.yaml``."""
        from rosbags.rosbag2 import WriterError

        writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.close()
        except (WriterError, OSError) as err:
            msg = f"cannot finish bag {self.path}: {err}"
            raise BagError(msg) from err

    def abort(self) -> None:
        """Stop writing without an index or metadata (the directory is left behind)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.abort()

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # -- raw
    def _connection(self, topic: str, msgtype: str) -> Connection:
        from rosbags.rosbag2 import WriterError

        if self._writer is None:
            msg = f"bag {self.path} is not open for writing (use `with BagWriter(...)`)"
            raise BagError(msg)
        conn = self._connections.get(topic)
        if conn is not None:
            if conn.msgtype != msgtype:
                msg = f"topic {topic} already carries {conn.msgtype}, cannot write {msgtype} on it"
                raise BagError(msg)
            return conn
        if msgtype not in typestore().fielddefs:
            msg = f"message type {msgtype!r} is not a ROS 2 Jazzy type known to rosbags"
            raise BagError(msg)
        try:
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore())
        except WriterError as err:
            msg = f"cannot add topic {topic} ({msgtype}) to {self.path}: {err}"
            raise BagError(msg) from err
        self._connections[topic] = conn
        self.counts[topic] = 0
        return conn

    def write_raw(self, topic: str, msgtype: str, stamp_ns: int, cdr_bytes: bytes | memoryview) -> None:
        """Append already CDR-serialized bytes of a Jazzy ``msgtype`` with log time ``stamp_ns``."""
        from rosbags.rosbag2 import WriterError

        if int(stamp_ns) < 0:
            msg = f"log time {stamp_ns} ns is negative"
            raise BagError(msg)
        conn = self._connection(topic, msgtype)
        assert self._writer is not None
        try:
            self._writer.write(conn, int(stamp_ns), bytes(cdr_bytes))
        except (WriterError, OSError) as err:
            msg = f"cannot write to {topic} in {self.path}: {err}"
            raise BagError(msg) from err
        self.counts[topic] += 1

    def _write_msg(self, topic: str, msgtype: str, stamp_ns: int, message: object) -> None:
        self.write_raw(topic, msgtype, stamp_ns, typestore().serialize_cdr(message, msgtype))

    @staticmethod
    def _header(stamp_ns: int, frame_id: str) -> Any:
        types = typestore().types
        stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // NS_PER_S, nanosec=stamp_ns % NS_PER_S)
        return types[HEADER_TYPE](stamp=stamp, frame_id=frame_id)

    # -- typed
    def write_odometry(
        self,
        stamp_s: float,
        pose: ArrayLike,
        twist: ArrayLike = (0.0, 0.0),
        *,
        frame_id: str = "odom",
        child_frame_id: str = "base_link",
        topic: str = "/odom",
    ) -> None:
        """``nav_msgs/Odometry``: ``pose = (x, y, yaw)`` in ``frame_id``, ``twist = (vx, wz)`` in the child
        frame; covariances zero (unknown)."""
        x, y, yaw = _pose_tuple(pose, "pose", 3)
        vx, wz = _pose_tuple(twist, "twist", 2)
        ns = stamp_to_ns(stamp_s)
        t = typestore().types
        qx, qy, qz, qw = yaw_to_quaternion(yaw)
        zeros36 = np.zeros(36, dtype=np.float64)
        vec3 = t["geometry_msgs/msg/Vector3"]
        msg = t[ODOMETRY_TYPE](
            header=self._header(ns, frame_id),
            child_frame_id=child_frame_id,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                    orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
                covariance=zeros36,
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=vec3(x=vx, y=0.0, z=0.0), angular=vec3(x=0.0, y=0.0, z=wz)
                ),
                covariance=zeros36.copy(),
            ),
        )
        self._write_msg(topic, ODOMETRY_TYPE, ns, msg)

    def write_scan(  # noqa: PLR0917 - the six scan quantities read best positionally
        self,
        stamp_s: float,
        ranges: ArrayLike,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
        *,
        frame_id: str = "base_laser",
        topic: str = "/scan",
    ) -> None:
        """``sensor_msgs/LaserScan`` with ``angle_max = angle_min + (n − 1)·angle_increment``; no
        intensities, ``time_increment = scan_time = 0``."""
        r = np.asarray(ranges, dtype=np.float32).reshape(-1)
        if r.size == 0:
            msg = "a scan needs at least one range"
            raise BagError(msg)
        ns = stamp_to_ns(stamp_s)
        scan = typestore().types[SCAN_TYPE](
            header=self._header(ns, frame_id),
            angle_min=float(angle_min),
            angle_max=float(angle_min) + (r.size - 1) * float(angle_increment),
            angle_increment=float(angle_increment),
            time_increment=0.0,
            scan_time=0.0,
            range_min=float(range_min),
            range_max=float(range_max),
            ranges=r,
            intensities=np.zeros(0, dtype=np.float32),
        )
        self._write_msg(topic, SCAN_TYPE, ns, scan)

    def write_image(
        self,
        stamp_s: float,
        image: ArrayLike,
        *,
        frame_id: str = "camera",
        topic: str = "/panorama",
    ) -> None:
        """``sensor_msgs/Image``: a ``(H, W)`` uint8 array as ``mono8``, ``(H, W, 3)`` uint8 as ``rgb8``."""
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
            msg = f"image must be (H, W) or (H, W, 3) uint8, got {img.shape} {img.dtype}"
            raise BagError(msg)
        height, width = img.shape[:2]
        channels = 1 if img.ndim == 2 else 3
        ns = stamp_to_ns(stamp_s)
        message = typestore().types[IMAGE_TYPE](
            header=self._header(ns, frame_id),
            height=height,
            width=width,
            encoding="mono8" if channels == 1 else "rgb8",
            is_bigendian=0,
            step=width * channels,
            data=np.ascontiguousarray(img).reshape(-1),
        )
        self._write_msg(topic, IMAGE_TYPE, ns, message)


# -------------------------------------------------------------------------------------------- readers


@dataclass(frozen=True)
class OdometryData:
    """``/odom`` in log-time order: ``stamps (T,)`` s, ``stamps_ns (T,)``, ``poses (T, 3)`` x y yaw,
    ``twists (T, 2)`` vx wz."""

    stamps: FloatArray
    stamps_ns: IntArray
    poses: FloatArray
    twists: FloatArray
    frame_id: str
    child_frame_id: str


@dataclass(frozen=True)
class ScanData:
    """``/scan`` in log-time order. ``ranges`` is ``(S, N)`` float32 when every scan has N beams, else a
    list of ``(N_i,)`` arrays; the angle and range parameters are per scan, ``(S,)``."""

    stamps: FloatArray
    stamps_ns: IntArray
    ranges: NDArray[np.float32] | list[NDArray[np.float32]]
    angle_min: FloatArray
    angle_increment: FloatArray
    range_min: FloatArray
    range_max: FloatArray
    frame_id: str


@dataclass(frozen=True)
class ImageData:
    """Decoded images in log-time order; ``skipped`` counts messages with unsupported encodings."""

    stamps: FloatArray
    stamps_ns: IntArray
    images: list[NDArray[Any]]
    encodings: list[str]
    frame_id: str
    skipped: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class RunData:
    """A recorded run; a stream is ``None`` when its topic is absent (or its topic name was ``None``);
    ``skipped`` counts the messages :func:`read_run` skipped, by reason."""

    path: Path
    topics: dict[str, str]
    odometry: OdometryData | None
    scans: ScanData | None
    images: ImageData | None
    skipped: dict[str, int] = field(default_factory=dict)  # messages skipped by reason (read_run)


class RawMessage(NamedTuple):
    """One message as stored: ``header_stamp_ns`` is ``None`` for types without a leading Header."""

    topic: str
    msgtype: str
    log_time_ns: int
    header_stamp_ns: int | None
    rawdata: bytes


def _open_reader(path: Path) -> Any:
    from rosbags.rosbag2 import Reader

    if not path.exists():
        msg = f"bag {path} does not exist"
        raise BagError(msg)
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        found = sorted(p.name for p in path.glob("*") if p.suffix in {".mcap", ".db3"})
        hint = f" (it holds {', '.join(found[:3])}: pass that file)" if found else ""
        msg = f"{path} is not a rosbag2 directory: it has no metadata.yaml{hint}"
        raise BagError(msg)
    try:
        reader = Reader(path)
        reader.open()
    except FileNotFoundError as err:
        msg = f"{path} is not a rosbag2 (a directory with metadata.yaml, or a .mcap / .db3 file): {err}"
        raise BagError(msg) from err
    except _reader_errors() as err:
        hint = ""
        if "end magic" in str(err):
            hint = " (the .mcap file ends early: an interrupted recording? `mcap recover` rebuilds it)"
        msg = f"cannot open bag {path}: {type(err).__name__}: {err}{hint}"
        raise BagError(msg) from err
    return reader


def _has_header(msgtype: str) -> bool:
    fields = typestore().fielddefs.get(msgtype)
    if not fields or not fields[1]:
        return False
    _, (_, target) = fields[1][0]
    return target == HEADER_TYPE


def _cdr_header_stamp_ns(raw: bytes) -> int:
    """``header.stamp`` of a CDR message whose first field is a Header (8 bytes after the 4-byte
    encapsulation: int32 sec, uint32 nanosec)."""
    if len(raw) < 12:
        msg = f"CDR message of {len(raw)} bytes is too short to hold a header stamp"
        raise BagError(msg)
    endian = "<" if raw[1] else ">"
    sec, nanosec = struct.unpack_from(f"{endian}iI", raw, 4)
    return sec * NS_PER_S + nanosec


def iter_raw(path: str | Path, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
    """Every message of the bag (or of ``topics``) as :class:`RawMessage`, ordered by log time (ties in
    write order); the order across the files of a split bag is rosbags' (file by file)."""
    bag = Path(path)
    reader = _open_reader(bag)
    try:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        if topics is not None:
            missing = sorted(set(topics) - {c.topic for c in conns})
            if missing:
                msg = f"bag {bag} has no topic {', '.join(missing)} (topics: {sorted(reader.topics)})"
                raise BagError(msg)
        headers = {c.msgtype: _has_header(c.msgtype) for c in conns}
        if not conns:
            return
        try:
            for conn, log_ns, raw in reader.messages(connections=conns):
                data = bytes(raw)
                stamp = _cdr_header_stamp_ns(data) if headers[conn.msgtype] else None
                yield RawMessage(conn.topic, conn.msgtype, int(log_ns), stamp, data)
        except _reader_errors() as err:
            msg = f"corrupt bag {bag}: {type(err).__name__}: {err}"
            raise BagError(msg) from err
    finally:
        reader.close()


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def decode_image(msg: Any) -> NDArray[Any] | None:
    """``(H, W)`` or ``(H, W, C)`` array of an Image message; ``None`` for unsupported encodings."""
    spec = IMAGE_ENCODINGS.get(msg.encoding)
    if spec is None:
        return None
    kind, channels = spec
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row or data.size < h * step:
        err = f"image {h}x{w} {msg.encoding} with step {step} has {data.size} bytes, needs {h * step}"
        raise BagError(err)
    rows = data[: h * step].reshape(h, step)[:, :row]
    img = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
    return img.reshape(h, w) if channels == 1 else img.reshape(h, w, channels)


def _as_ranges(ranges: list[NDArray[np.float32]]) -> NDArray[np.float32] | list[NDArray[np.float32]]:
    if ranges and len({r.size for r in ranges}) == 1:
        return np.stack(ranges)
    return ranges


def read_run(
    path: str | Path,
    *,
    odom_topic: str | None = "/odom",
    scan_topic: str | None = "/scan",
    image_topic: str | None = "/panorama",
    require: Sequence[str] = (),
    appearance: AppearanceConfig | None = None,
    progress: Callable[[Iterable[Any], int], Iterable[Any]] | None = None,
) -> RunData:
    """Load odometry, scans and images of a rosbag2 into arrays (stamps from the message headers).

    A topic absent from the bag gives ``None`` unless it is listed in ``require`` (then :class:`BagError`);
    a topic of the wrong message type is a :class:`BagError`, and so is a storage file that cannot be read.
    Bad messages are skipped and counted in ``RunData.skipped`` by reason, as the nodes count them
    (:mod:`ptm_ros.io.validation`): undecodable bytes (``<stream>-undecodable``), a header stamp that is
    no ROS time, unusable content (non-finite odometry, empty or non-finite scans, unsupported image
    encodings, panoramas too small for ``appearance``), and stamps out of order on their topic (only the
    longest strictly increasing run is kept: :func:`ptm_ros.io.validation.stamp_order`). Every stream of
    the result therefore has strictly increasing stamps. Images with an encoding outside
    :data:`IMAGE_ENCODINGS` are also counted by encoding in ``ImageData.skipped``. ``progress`` (e.g. a
    progress bar) wraps the messages read: it receives their iterator and their number.
    """
    bag = Path(path)
    wanted = {
        topic: msgtype
        for topic, msgtype in (
            (odom_topic, ODOMETRY_TYPE),
            (scan_topic, SCAN_TYPE),
            (image_topic, IMAGE_TYPE),
        )
        if topic is not None
    }
    reader = _open_reader(bag)
    try:
        topics = {name: info.msgtype for name, info in reader.topics.items()}
        missing = [t for t in require if t not in topics]
        if missing:
            msg = f"bag {bag} lacks required topic {', '.join(missing)} (topics: {sorted(topics)})"
            raise BagError(msg)
        for topic, expected in wanted.items():
            if topic in topics and topics[topic] != expected:
                msg = f"topic {topic} in {bag} has type {topics[topic]}, expected {expected}"
                raise BagError(msg)
        conns = [c for c in reader.connections if c.topic in wanted]
        rows: dict[str, list[Any]] = {t: [] for t in wanted}
        skipped: dict[str, int] = {}
        if conns:
            store = typestore()
            try:
                messages: Iterable[Any] = reader.messages(connections=conns)
                if progress is not None:
                    messages = progress(messages, sum(c.msgcount for c in conns))
                for conn, _, raw in messages:
                    try:
                        rows[conn.topic].append(store.deserialize_cdr(raw, conn.msgtype))
                    except _reader_errors():
                        reason = f"{STREAM_NAMES[conn.msgtype]}-undecodable"
                        skipped[reason] = skipped.get(reason, 0) + 1
            except _reader_errors() as err:
                msg = f"corrupt bag {bag}: {type(err).__name__}: {err}"
                raise BagError(msg) from err
    finally:
        reader.close()

    def present(topic: str | None) -> list[Any] | None:
        return rows[topic] if topic is not None and topic in topics else None

    return RunData(
        path=bag,
        topics=topics,
        odometry=_odometry(msgs, skipped) if (msgs := present(odom_topic)) is not None else None,
        scans=_scans(msgs, skipped) if (msgs := present(scan_topic)) is not None else None,
        images=_images(msgs, skipped, appearance) if (msgs := present(image_topic)) is not None else None,
        skipped=skipped,
    )


def _usable(
    name: str,
    msgs: list[Any],
    check: Callable[[Any], tuple[Any, tuple[str, str] | None]],
    skipped: dict[str, int],
) -> tuple[list[Any], list[Any], list[int]]:
    """The messages of one stream that pass ``check`` (content) and the stamp rules of
    :mod:`ptm_ros.io.validation`, with their checked content and stamps (ns); the others counted in
    ``skipped``."""
    from ptm_ros.io.validation import header_stamp_ns, stamp_order

    def count(reason: str) -> None:
        skipped[reason] = skipped.get(reason, 0) + 1

    good: list[tuple[Any, Any, int]] = []
    for m in msgs:
        ns = header_stamp_ns(m.header)
        if ns is None:
            count(f"{name}-bad-stamp")
            continue
        content, rejected = check(m)
        if rejected is not None:
            count(rejected[0])
            continue
        good.append((m, content, ns))
    kept, reasons = stamp_order([ns for _, _, ns in good])
    for reason in reasons:
        count(f"{name}-{reason}")
    chosen = [good[i] for i in kept]
    return [m for m, _, _ in chosen], [c for _, c, _ in chosen], [ns for _, _, ns in chosen]


def _stamps(stamps_ns: list[int]) -> tuple[FloatArray, IntArray]:
    return np.array([ns_to_stamp(n) for n in stamps_ns], dtype=float), np.array(stamps_ns, dtype=np.int64)


def _odometry(msgs: list[Any], skipped: dict[str, int]) -> OdometryData:
    from ptm_ros.io.validation import odometry_pose

    kept, poses, ns = _usable("odometry", msgs, lambda m: odometry_pose(m)[:2], skipped)
    stamps, stamps_ns = _stamps(ns)
    twists = np.empty((len(kept), 2))
    for i, m in enumerate(kept):
        twists[i] = m.twist.twist.linear.x, m.twist.twist.angular.z
    return OdometryData(
        stamps=stamps,
        stamps_ns=stamps_ns,
        poses=np.array(poses, dtype=float).reshape(-1, 3),
        twists=twists,
        frame_id=kept[0].header.frame_id if kept else "",
        child_frame_id=kept[0].child_frame_id if kept else "",
    )


def _scans(msgs: list[Any], skipped: dict[str, int]) -> ScanData:
    from ptm_ros.io.validation import scan_payload

    kept, payloads, ns = _usable("scan", msgs, scan_payload, skipped)
    stamps, stamps_ns = _stamps(ns)

    def column(k: int) -> FloatArray:
        return np.array([float(p[k]) for p in payloads], dtype=float)

    return ScanData(
        stamps=stamps,
        stamps_ns=stamps_ns,
        ranges=_as_ranges([p[0] for p in payloads]),
        angle_min=column(1),
        angle_increment=column(2),
        range_min=column(3),
        range_max=column(4),
        frame_id=kept[0].header.frame_id if kept else "",
    )


def _images(msgs: list[Any], skipped: dict[str, int], appearance: AppearanceConfig | None) -> ImageData:
    from ptm_ros.io.validation import image_payload

    by_encoding: dict[str, int] = {}
    for m in msgs:
        if m.encoding not in IMAGE_ENCODINGS:
            by_encoding[m.encoding] = by_encoding.get(m.encoding, 0) + 1
    kept, images, ns = _usable("image", msgs, lambda m: image_payload(m, appearance), skipped)
    stamps, stamps_ns = _stamps(ns)
    return ImageData(
        stamps=stamps,
        stamps_ns=stamps_ns,
        images=images,
        encodings=[m.encoding for m in kept],
        frame_id=kept[0].header.frame_id if kept else "",
        skipped=by_encoding,
    )
