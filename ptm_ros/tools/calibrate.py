"""``ptm-calibrate BAG``: estimate the laser's time offset from the bag itself (no ground truth).

Some laser drivers stamp a scan when it has been read out, not when it was taken: the scans then lag
the odometry, and during every turn the scan-to-map matching of the laser odometry must undo the
heading the odometry already turned. ``ptm-calibrate`` runs the laser odometry over the bag once per
candidate offset (:func:`ptm_ros.perception.laser_odometry.time_offset_scores`) and picks the one whose
heading corrections are smallest (:func:`ptm_ros.perception.laser_odometry.best_time_offset`: it must beat
offset 0 by ``--min-gain``). Prints JSON (schema ``ptm_ros.calibration/1``: ``offsets`` with each candidate's
``median_yaw_correction`` / ``rms_yaw_correction`` in rad and the matched / rejected scan counts,
``time_offset`` the choice); ``--out FILE`` writes the parameters (``--params`` or the defaults) with
``laser_odometry.time_offset`` set, ready for ``ptm-run --params`` and ``ptm-bringup --params``.

Exit status: 0 on success, 2 on bad input (unreadable bag, no scans, bad parameters or offsets).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from ptm_ros.errors import ConfigError, DataError, PtmError
from ptm_ros.tools.paths import add_params_option

if TYPE_CHECKING:
    from ptm_ros.config import PtmConfig
    from ptm_ros.io.bag import RunData
    from ptm_ros.perception.laser_odometry import OffsetScore

PROG = "ptm-calibrate"
DEFAULT_OFFSETS = (0.0, -0.05, -0.1, -0.15, -0.2, -0.25, -0.3)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0].split(": ", 1)[1])
    p.add_argument("bag", type=Path, help="rosbag2 directory with /odom and /scan")
    add_params_option(p)
    p.add_argument(
        "--offsets",
        type=float,
        nargs="+",
        default=list(DEFAULT_OFFSETS),
        metavar="S",
        help="candidate offsets in [-1, 0] s (0 is always tried; default: %(default)s)",
    )
    p.add_argument(
        "--min-gain",
        type=float,
        default=0.05,
        help="relative RMS gain over offset 0 needed (default: %(default)s)",
    )
    p.add_argument("--max-scans", type=int, default=None, help="use only the first N scans (default: all)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="write the parameters with the offset here (default: print only)",
    )
    return p


@dataclass(frozen=True)
class Calibration:
    """What :func:`calibrate_run` found: the scans used, every candidate's score, the chosen offset."""

    scans: int
    scores: list[OffsetScore]
    time_offset: float

    def applied(self, config: PtmConfig) -> PtmConfig:
        """``config`` with ``laser_odometry.time_offset`` set to the chosen offset (and its learning off)."""
        lo = replace(config.laser_odometry, time_offset=self.time_offset, learn_time_offset=False)
        return replace(config, laser_odometry=lo)

    def as_dict(self) -> dict:
        """JSON-able (a non-finite score, at an offset where no scan matched, is None)."""
        return {
            "scans": self.scans,
            "offsets": [s.as_dict() for s in self.scores],
            "time_offset": self.time_offset,
        }


def calibrate_run(
    run: RunData,
    config: PtmConfig,
    offsets: Sequence[float] = DEFAULT_OFFSETS,
    *,
    min_gain: float = 0.05,
    max_scans: int | None = None,
) -> Calibration:
    """The scores of ``offsets`` (0 added, largest first) on a run read with its scans, and the chosen
    offset (module docstring); ``max_scans``: only the first scans.

    Raises:
        DataError: the run has no usable scan points.
        ModelError: an offset outside [-1, 0], or a bad ``min_gain``.
    """
    from ptm_ros.maps.mapping import scan_points
    from ptm_ros.perception.laser_odometry import best_time_offset, time_offset_scores

    if run.scans is None:
        msg = f"no scans in {run.path}"
        raise DataError(msg)
    odom = run.odometry
    if odom is None:
        msg = f"no odometry in {run.path}"
        raise DataError(msg)
    stamps, points = scan_points(run.scans, config.laser)
    stamps, points = stamps[:max_scans], points[:max_scans]
    if not any(len(p) for p in points):
        msg = f"no usable scan points in {run.path}"
        raise DataError(msg)
    scores = time_offset_scores(
        odom.stamps,
        odom.poses,
        stamps,
        points,
        sorted({0.0, *offsets}, reverse=True),
        config.laser_odometry,
        config.laser,
    )
    return Calibration(scans=len(stamps), scores=scores, time_offset=best_time_offset(scores, min_gain))


def calibrate(args: argparse.Namespace) -> dict:
    """The calibration report of the parsed arguments (module docstring); writes ``--out``."""
    from ptm_ros.config import load_config, save_config
    from ptm_ros.io.bag import read_run

    config = load_config(args.params)
    if args.max_scans is not None and args.max_scans < 2:
        msg = f"--max-scans needs at least 2 scans, got {args.max_scans}"
        raise ConfigError(msg)
    topics = config.topics
    run = read_run(
        args.bag,
        odom_topic=topics.odom,
        scan_topic=topics.scan,
        image_topic=None,
        require=(topics.odom, topics.scan),
    )
    cal = calibrate_run(run, config, args.offsets, min_gain=args.min_gain, max_scans=args.max_scans)
    report = {"schema": "ptm_ros.calibration/1", "bag": str(args.bag), "min_gain": args.min_gain}
    report.update(cal.as_dict())
    if args.out is not None:
        report["params"] = str(save_config(cal.applied(config), args.out))
    return report


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        report = calibrate(args)
    except (PtmError, OSError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(report, indent=2, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
