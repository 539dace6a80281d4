"""``ptm-convert LOG.clf[.gz] OUT_BAG [--storage mcap|sqlite3]``: a CARMEN log to a rosbag2.

The bag holds ``/odom`` (``nav_msgs/Odometry``, frame ``odom`` → ``base_link``) from the log's ODOM lines,
or from the odometry pose of every laser line when the log has none, and ``/scan``
(``sensor_msgs/LaserScan``, frame ``base_laser``) from its FLASER / ROBOTLASER1 lines. Every message is
stamped with its line's last field (the logger timestamp) and poses are copied unchanged (see
:mod:`ptm_ros.io.bag` for the exactness rules). FLASER lines carry no maximum range: ``range_max`` is
``--max-range``, else the log's ``robot_front_laser_max`` PARAM, else the largest reading in the log
(the value CARMEN loggers write for "no return"); ``range_min`` is 0.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from ptm_ros.io.carmen import CarmenLog, ParseReport

MAX_LISTED = 5  # malformed line numbers named in the summary


@dataclass(frozen=True)
class ConvertSummary:
    """What :func:`convert` wrote."""

    log: Path
    bag: Path
    storage: str
    scans: int
    odometry: int
    odometry_source: str
    range_max: float | None
    first_stamp: float | None
    last_stamp: float | None
    laser_offset_lines: int
    report: ParseReport


def default_max_range(log: CarmenLog) -> float | None:
    """``robot_front_laser_max`` from the log's PARAM lines, else its largest finite FLASER reading."""
    import numpy as np

    value = log.report.params.get("robot_front_laser_max")
    if value is not None:
        try:
            return float(value)
        except ValueError:
            pass
    readings = [r.ranges[np.isfinite(r.ranges)] for r in log.lasers if r.max_range is None]
    finite = [float(r.max()) for r in readings if r.size]
    return max(finite) if finite else None


def convert(
    log_path: str | Path,
    bag_path: str | Path,
    *,
    storage: Literal["mcap", "sqlite3"] = "mcap",
    max_range: float | None = None,
    strict: bool = False,
) -> ConvertSummary:
    """Parse ``log_path`` completely, check every stamp, then write the bag at ``bag_path`` (which must
    not exist; nothing is created when the log cannot be converted)."""
    import math

    import numpy as np

    from ptm_ros.errors import BagError, ConfigError, DataError
    from ptm_ros.io.bag import BagWriter, stamp_to_ns
    from ptm_ros.io.carmen import LaserRecord, odometry_track, read_log

    if max_range is not None and not (math.isfinite(max_range) and max_range > 0):
        msg = f"max_range must be a positive finite number, got {max_range!r}"
        raise ConfigError(msg)
    if Path(bag_path).exists():
        msg = f"output {bag_path} exists already; choose a new path (rosbag2 never overwrites)"
        raise BagError(msg)
    log = read_log(log_path, strict=strict)
    if not log.lasers and not log.odometry:
        msg = f"{log_path} has no FLASER, ROBOTLASER1 or ODOM records"
        raise DataError(msg)
    track = odometry_track(log)
    flaser_max = max_range if max_range is not None else default_max_range(log)
    offsets = sum(1 for r in log.lasers if r.pose != r.odom_pose)
    stamps = np.concatenate([track.stamps, [r.logger_timestamp for r in log.lasers]])
    for t in stamps:
        stamp_to_ns(t)  # raises BagError on a stamp a ROS time cannot hold, before the bag exists

    # Interleave odometry and scans in file order (odometry first on equal lines).
    events: list[tuple[int, int, int]] = []  # (line, 0 = odom / 1 = scan, index)
    odom_lines = [r.line for r in log.odometry] if log.odometry else [r.line for r in log.lasers]
    events += [(line, 0, i) for i, line in enumerate(odom_lines)]
    events += [(r.line, 1, i) for i, r in enumerate(log.lasers)]
    events.sort()

    with BagWriter(bag_path, storage=storage) as writer:
        for _, what, i in events:
            if what == 0:
                writer.write_odometry(track.stamps[i], track.poses[i], track.twists[i])
                continue
            rec: LaserRecord = log.lasers[i]
            rmax = rec.max_range if rec.max_range is not None else flaser_max
            writer.write_scan(
                rec.logger_timestamp,
                rec.ranges,
                rec.angle_min,
                rec.angle_increment,
                0.0,
                float(rmax) if rmax is not None else float("inf"),
            )
    return ConvertSummary(
        log=Path(log_path),
        bag=Path(bag_path),
        storage=storage,
        scans=len(log.lasers),
        odometry=len(track.stamps),
        odometry_source=track.source,
        range_max=flaser_max if any(r.max_range is None for r in log.lasers) else None,
        first_stamp=float(stamps.min()) if stamps.size else None,
        last_stamp=float(stamps.max()) if stamps.size else None,
        laser_offset_lines=offsets,
        report=log.report,
    )


def summary_text(s: ConvertSummary) -> str:
    """One paragraph for the terminal."""
    rep = s.report
    ignored = ", ".join(f"{n} {k}" for k, n in sorted(rep.ignored().items())) or "none"
    parts = [
        f"Converted {s.log} ({rep.lines} lines) to {s.bag} ({s.storage}):",
        f"{s.scans} scans on /scan, {s.odometry} odometry messages on /odom (from {s.odometry_source});",
    ]
    if s.first_stamp is not None and s.last_stamp is not None:
        parts.append(f"logger stamps {s.first_stamp:.6f} to {s.last_stamp:.6f} s;")
    if s.range_max is not None:
        parts.append(f"FLASER range_max {s.range_max:g} m;")
    if s.laser_offset_lines:
        parts.append(f"{s.laser_offset_lines} laser lines have a laser pose differing from the odometry;")
    parts.append(f"ignored lines: {ignored};")
    if rep.malformed:
        listed = ", ".join(str(m.line) for m in rep.malformed[:MAX_LISTED])
        more = ", …" if len(rep.malformed) > MAX_LISTED else ""
        parts.append(f"{len(rep.malformed)} malformed lines skipped (lines {listed}{more}).")
    else:
        parts.append("no malformed lines.")
    return " ".join(parts)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ptm-convert",
        description="Convert a CARMEN log (.clf/.log, plain or .gz) into a rosbag2 with /odom and /scan "
        "(ROS 2 Jazzy types), stamped with the logger timestamps.",
    )
    parser.add_argument("log", type=Path, help="CARMEN log file")
    parser.add_argument("out_bag", type=Path, help="rosbag2 directory to create (must not exist)")
    parser.add_argument(
        "--storage",
        choices=("mcap", "sqlite3"),
        default="mcap",
        help="rosbag2 storage (default: %(default)s)",
    )
    parser.add_argument(
        "--max-range",
        type=float,
        default=None,
        help="LaserScan range_max for FLASER lines (default: robot_front_laser_max PARAM, else the "
        "largest reading in the log)",
    )
    parser.add_argument("--strict", action="store_true", help="fail on the first malformed line")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 usage or bad input)."""
    args = build_parser().parse_args(argv)
    from ptm_ros.errors import PtmError
    from ptm_ros.tools.paths import new_output

    try:
        new_output(args.out_bag)
        summary = convert(
            args.log, args.out_bag, storage=args.storage, max_range=args.max_range, strict=args.strict
        )
    except (PtmError, OSError) as err:
        print(f"ptm-convert: error: {err}", file=sys.stderr)
        return 2
    print(summary_text(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
