"""Streaming parser for CARMEN logs (``.clf`` / ``.log``, plain or gzip-compressed).

Parsed line kinds (fields after the tag; ``ts`` = ``ipc_timestamp ipc_hostname logger_timestamp``)::

    FLASER      n r_1..r_n  x y θ  odom_x odom_y odom_θ  ts
    ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
                n r_1..r_n  m e_1..e_m  laser_x laser_y laser_θ  robot_x robot_y robot_θ
                tv rv forward_safety_dist side_safety_dist turn_axis  ts
    ODOM        x y θ tv rv accel  ts

Every other kind (``PARAM``, ``NEFF``, ``SYNC``, ``RLASER``, ``TRUEPOS``, …), comments (``#``) and blank
lines are ignored and counted by kind in :class:`ParseReport`; ``PARAM name value`` pairs are kept in
``ParseReport.params``. A parsed line with the wrong number of fields, a non-numeric number or a
non-finite pose or timestamp is *malformed*: recorded with its line number (``strict=False``) or raised
as :class:`~ptm_ros.errors.DataError` (``strict=True``).

FLASER beam geometry (the line carries none): the beams cover 180° counter-clockwise from −90° (right)
to +90° (left). An odd count includes both ends (``n = 181, 361`` → step ``π/(n−1)``: 1°, 0.5°); an even
count starts at −90° and stops one step short of +90° (``n = 180, 360`` → step ``π/n``: 1°, 0.5°), the
convention of the Intel and ACES logs. FLASER has no maximum range (``LaserRecord.max_range`` is
``None``); CARMEN loggers write "no return" as the sensor's largest reading (81.91 m MIT, 81.83 m Intel,
50 m ACES).
"""

from __future__ import annotations

import gzip
import math
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptm_ros.errors import DataError
from ptm_ros.model.geometry import FloatArray

Pose = tuple[float, float, float]

FLASER = "FLASER"
ROBOTLASER1 = "ROBOTLASER1"
ODOM = "ODOM"
COMMENT = "comment"
BLANK = "blank"
_TS_FIELDS = 3  # ipc_timestamp ipc_hostname logger_timestamp


@dataclass(frozen=True)
class LaserRecord:
    """One FLASER or ROBOTLASER1 line. ``pose`` is the laser pose, ``odom_pose`` the robot odometry."""

    line: int
    kind: str
    ranges: FloatArray
    angle_min: float
    angle_increment: float
    max_range: float | None
    pose: Pose
    odom_pose: Pose
    ipc_timestamp: float
    hostname: str
    logger_timestamp: float


@dataclass(frozen=True)
class OdomRecord:
    """One ODOM line: odometry pose ``(x, y, theta)``, velocities ``tv`` (m/s) ``rv`` (rad/s), ``accel``."""

    line: int
    x: float
    y: float
    theta: float
    tv: float
    rv: float
    accel: float
    ipc_timestamp: float
    hostname: str
    logger_timestamp: float

    @property
    def pose(self) -> Pose:
        return (self.x, self.y, self.theta)


Record = LaserRecord | OdomRecord


@dataclass(frozen=True)
class Malformed:
    """A line that could not be parsed: 1-based ``line`` number, its ``kind`` tag and why."""

    line: int
    kind: str
    reason: str


@dataclass
class ParseReport:
    """Filled while a log streams by: ``counts`` of well-formed lines per kind (parsed or ignored),
    the ``malformed`` lines, and the ``PARAM`` name/value pairs."""

    path: str
    lines: int = 0
    counts: dict[str, int] = field(default_factory=dict)
    malformed: list[Malformed] = field(default_factory=list)
    params: dict[str, str] = field(default_factory=dict)

    def ignored(self) -> dict[str, int]:
        """Counts of the kinds that were skipped (everything but FLASER, ROBOTLASER1 and ODOM)."""
        return {k: v for k, v in self.counts.items() if k not in (FLASER, ROBOTLASER1, ODOM)}


@dataclass(frozen=True)
class CarmenLog:
    """A whole log: laser and odometry records in file order, and the parse report."""

    path: Path
    lasers: tuple[LaserRecord, ...]
    odometry: tuple[OdomRecord, ...]
    report: ParseReport


@dataclass(frozen=True)
class OdometryTrack:
    """Odometry of a log: ``stamps (T,)`` logger timestamps, ``poses (T, 3)``, ``twists (T, 2)``
    (tv, rv); ``source`` is ``"ODOM"`` or ``"laser odom pose"``."""

    stamps: FloatArray
    poses: FloatArray
    twists: FloatArray
    source: str


class _MalformedLineError(Exception):
    """Internal: carries the reason a line is malformed."""


def flaser_angles(n: int) -> tuple[float, float]:
    """``(angle_min, angle_increment)`` of an ``n``-beam FLASER (see the module docstring)."""
    if n < 1:
        msg = f"a FLASER needs at least one beam, got n={n}"
        raise DataError(msg)
    step = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / n
    return -0.5 * math.pi, step


def _count(tokens: list[str], i: int, what: str) -> int:
    try:
        n = int(tokens[i])
    except (ValueError, IndexError) as err:
        tok = tokens[i] if i < len(tokens) else "<missing>"
        msg = f"field {i} ({what}) must be a non-negative integer, got {tok!r}"
        raise _MalformedLineError(msg) from err
    if n < 0:
        msg = f"field {i} ({what}) must be a non-negative integer, got {n}"
        raise _MalformedLineError(msg)
    return n


def _numbers(tokens: list[str], start: int, stop: int) -> FloatArray:
    """Fields ``tokens[start:stop]`` as floats (field numbers counted from the tag = field 0)."""
    chunk = tokens[start:stop]
    try:
        return np.array([float(t) for t in chunk], dtype=np.float64)
    except ValueError:
        bad = next(i for i, t in enumerate(chunk) if not _is_number(t))
        msg = f"field {start + bad} is not a number: {chunk[bad]!r}"
        raise _MalformedLineError(msg) from None


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _expect(tokens: list[str], n_fields: int, layout: str) -> None:
    got = len(tokens) - 1
    if got != n_fields:
        msg = f"expected {n_fields} fields after the tag ({layout}), got {got}"
        raise _MalformedLineError(msg)


def _finite(values: FloatArray, what: str) -> None:
    if not np.all(np.isfinite(values)):
        msg = f"non-finite {what}: {values.tolist()}"
        raise _MalformedLineError(msg)


def _pose(v: FloatArray) -> Pose:
    return (float(v[0]), float(v[1]), float(v[2]))


def _timestamps(tokens: list[str]) -> tuple[float, str, float]:
    """The trailing ``ipc_timestamp ipc_hostname logger_timestamp``."""
    ipc = _numbers(tokens, len(tokens) - 3, len(tokens) - 2)
    logger = _numbers(tokens, len(tokens) - 1, len(tokens))
    _finite(np.concatenate([ipc, logger]), "timestamp")
    return float(ipc[0]), tokens[-2], float(logger[0])


def _parse_flaser(tokens: list[str], lineno: int) -> LaserRecord:
    n = _count(tokens, 1, "num_readings")
    if n < 1:
        msg = "num_readings must be at least 1"
        raise _MalformedLineError(msg)
    _expect(tokens, 1 + n + 6 + _TS_FIELDS, f"n={n}: n ranges, 6 pose values, 3 timestamp fields")
    ranges = _numbers(tokens, 2, 2 + n)
    poses = _numbers(tokens, 2 + n, 8 + n)
    _finite(poses, "pose")
    ipc, host, logger = _timestamps(tokens)
    angle_min, step = flaser_angles(n)
    return LaserRecord(
        line=lineno,
        kind=FLASER,
        ranges=ranges,
        angle_min=angle_min,
        angle_increment=step,
        max_range=None,
        pose=_pose(poses[:3]),
        odom_pose=_pose(poses[3:]),
        ipc_timestamp=ipc,
        hostname=host,
        logger_timestamp=logger,
    )


def _parse_robotlaser(tokens: list[str], lineno: int) -> LaserRecord:
    n = _count(tokens, 8, "num_readings")
    if n < 1:
        msg = "num_readings must be at least 1"
        raise _MalformedLineError(msg)
    m = _count(tokens, 9 + n, "num_remissions")
    _expect(tokens, n + m + 23, f"n={n}, m={m}: 7 laser params, ranges, remissions, 11 values, 3 ts")
    # laser_type start_angle fov angular_resolution max_range accuracy remission_mode
    params = _numbers(tokens, 1, 8)
    _finite(params, "laser parameter")
    ranges = _numbers(tokens, 9, 9 + n)
    _numbers(tokens, 10 + n, 10 + n + m)  # remissions: checked, not kept
    poses = _numbers(tokens, 10 + n + m, 16 + n + m)
    _finite(poses, "pose")
    _numbers(tokens, 16 + n + m, 21 + n + m)  # tv rv forward_safety side_safety turn_axis
    ipc, host, logger = _timestamps(tokens)
    return LaserRecord(
        line=lineno,
        kind=ROBOTLASER1,
        ranges=ranges,
        angle_min=float(params[1]),
        angle_increment=float(params[3]),
        max_range=float(params[4]),
        pose=_pose(poses[:3]),
        odom_pose=_pose(poses[3:]),
        ipc_timestamp=ipc,
        hostname=host,
        logger_timestamp=logger,
    )


def _parse_odom(tokens: list[str], lineno: int) -> OdomRecord:
    _expect(tokens, 6 + _TS_FIELDS, "x y theta tv rv accel and 3 timestamp fields")
    v = _numbers(tokens, 1, 7)
    _finite(v, "odometry value")
    ipc, host, logger = _timestamps(tokens)
    x, y, theta, tv, rv, accel = (float(a) for a in v)
    return OdomRecord(lineno, x, y, theta, tv, rv, accel, ipc, host, logger)


_PARSERS: dict[str, Callable[[list[str], int], Record]] = {
    FLASER: _parse_flaser,
    ROBOTLASER1: _parse_robotlaser,
    ODOM: _parse_odom,
}


def line_kind(text: str) -> str:
    """The kind of a line: its tag, ``"comment"`` or ``"blank"``."""
    stripped = text.strip()
    if not stripped:
        return BLANK
    if stripped.startswith("#"):
        return COMMENT
    return stripped.split(maxsplit=1)[0]


def parse_line(text: str, lineno: int = 0) -> Record | None:
    """Parse one line; ``None`` for kinds that are ignored. Malformed lines raise :class:`DataError`."""
    kind = line_kind(text)
    parser = _PARSERS.get(kind)
    if parser is None:
        return None
    try:
        return parser(text.split(), lineno)
    except _MalformedLineError as err:
        msg = f"line {lineno}: malformed {kind}: {err}"
        raise DataError(msg) from None


def _open_text(path: Path) -> Iterator[str]:
    """Lines of a plain or gzip-compressed text file (gzip detected by its magic bytes)."""
    with path.open("rb") as raw:
        magic = raw.read(2)
    if magic == b"\x1f\x8b":
        with gzip.open(path, "rt", encoding="utf-8", errors="replace") as f:
            yield from f
    else:
        with path.open(encoding="utf-8", errors="replace") as f:
            yield from f


def iter_records(
    path: str | Path, *, strict: bool = False, report: ParseReport | None = None
) -> Iterator[Record]:
    """Stream the FLASER / ROBOTLASER1 / ODOM records of a log in file order.

    ``report`` (if given) is filled as lines stream by. With ``strict=True`` the first malformed line
    raises :class:`DataError` naming the file and line number. An unreadable or truncated file raises
    :class:`DataError` after the records before the damage have been yielded.
    """
    p = Path(path)
    rep = report if report is not None else ParseReport(path=str(p))
    if not p.is_file():
        msg = f"CARMEN log {p} does not exist or is not a file"
        raise DataError(msg)
    lineno = 0
    try:
        for lineno, text in enumerate(_open_text(p), start=1):
            rep.lines = lineno
            kind = line_kind(text)
            parser = _PARSERS.get(kind)
            if parser is None:
                rep.counts[kind] = rep.counts.get(kind, 0) + 1
                if kind == "PARAM":
                    tokens = text.split()
                    if len(tokens) >= 3:
                        rep.params[tokens[1]] = tokens[2]
                continue
            try:
                record = parser(text.split(), lineno)
            except _MalformedLineError as err:
                if strict:
                    msg = f"{p}:{lineno}: malformed {kind}: {err}"
                    raise DataError(msg) from None
                rep.malformed.append(Malformed(lineno, kind, str(err)))
                continue
            rep.counts[kind] = rep.counts.get(kind, 0) + 1
            yield record
    except (OSError, EOFError, zlib.error, UnicodeError) as err:
        msg = f"cannot read CARMEN log {p} after line {lineno}: {type(err).__name__}: {err}"
        raise DataError(msg) from err


def read_log(path: str | Path, *, strict: bool = False) -> CarmenLog:
    """Parse a whole log into a :class:`CarmenLog` (see :func:`iter_records`)."""
    report = ParseReport(path=str(path))
    lasers: list[LaserRecord] = []
    odometry: list[OdomRecord] = []
    for record in iter_records(path, strict=strict, report=report):
        if isinstance(record, LaserRecord):
            lasers.append(record)
        else:
            odometry.append(record)
    return CarmenLog(path=Path(path), lasers=tuple(lasers), odometry=tuple(odometry), report=report)


def odometry_track(log: CarmenLog) -> OdometryTrack:
    """The log's odometry in file order, stamped with logger timestamps and otherwise unchanged: the
    ODOM lines when there are any (twist = tv, rv), else the odometry pose of every laser line (twist
    zero: the line carries none)."""
    if log.odometry:
        recs = log.odometry
        return OdometryTrack(
            stamps=np.array([r.logger_timestamp for r in recs], dtype=float),
            poses=np.array([r.pose for r in recs], dtype=float).reshape(-1, 3),
            twists=np.array([(r.tv, r.rv) for r in recs], dtype=float).reshape(-1, 2),
            source="ODOM",
        )
    lasers = log.lasers
    return OdometryTrack(
        stamps=np.array([r.logger_timestamp for r in lasers], dtype=float),
        poses=np.array([r.odom_pose for r in lasers], dtype=float).reshape(-1, 3),
        twists=np.zeros((len(lasers), 2)),
        source="laser odom pose",
    )
