"""``ptm-sim OUT_BAG [--seed N] [--world NAME] [--landmarks N] [--storage mcap|sqlite3] [--no-images]``.

Simulates a run through one of the worlds of :mod:`ptm_ros.io.worlds` (:mod:`ptm_ros.io.simulator`)
and writes a rosbag2 with ``/odom`` (``nav_msgs/Odometry``, noisy wheel odometry at 20 Hz), ``/scan``
(``sensor_msgs/LaserScan``, 10 Hz) and ``/panorama`` (``sensor_msgs/Image``, mono8 360-degree panoramas
every metre), plus the ground truth in ``OUT_BAG/ground_truth.json`` (schema ``ptm_ros.ground_truth/1``:
true poses at the odometry stamps, the world's places and the passages through them).
``--landmarks N`` is the number of place visits: the world's route is cycled until N visits.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

DEFAULT_WORLD = "two-loop"


def build_parser() -> argparse.ArgumentParser:
    from ptm_ros.io.worlds import WORLDS

    parser = argparse.ArgumentParser(
        prog="ptm-sim",
        description="Simulate a robot run (odometry, laser, panoramas) through a corridor world and write "
        "it as a rosbag2 with OUT_BAG/ground_truth.json.",
    )
    parser.add_argument("out_bag", type=Path, help="rosbag2 directory to create (must not exist)")
    parser.add_argument(
        "--seed",
        type=_seed,
        default=0,
        help="random seed of the sensor noise, an integer >= 0 (default: %(default)s)",
    )
    parser.add_argument(
        "--world",
        choices=sorted(WORLDS),
        default=DEFAULT_WORLD,
        help="the world to drive through (default: %(default)s)",
    )
    parser.add_argument(
        "--landmarks",
        type=int,
        default=None,
        metavar="N",
        help="number of place visits, cycling the world's route (default: the world's own)",
    )
    parser.add_argument(
        "--storage",
        choices=("mcap", "sqlite3"),
        default="mcap",
        help="rosbag2 storage (default: %(default)s)",
    )
    parser.add_argument("--no-images", action="store_true", help="write no /panorama topic")
    return parser


def _seed(text: str) -> int:
    """An argparse type: an integer >= 0 (numpy's generators take no negative seed)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        msg = f"expected an integer >= 0, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 usage or bad input)."""
    args = build_parser().parse_args(argv)
    import dataclasses

    import numpy as np

    from ptm_ros.errors import PtmError
    from ptm_ros.io.simulator import CameraConfig, SimConfig, simulate, write_run
    from ptm_ros.io.worlds import get_world
    from ptm_ros.tools.paths import new_output

    try:
        new_output(args.out_bag)
        world = get_world(args.world)
        config = SimConfig(camera=dataclasses.replace(CameraConfig(), enabled=not args.no_images))
        run = simulate(world, config, np.random.default_rng(args.seed), visits=args.landmarks)
        out = write_run(run, args.out_bag, storage=args.storage)
    except (PtmError, OSError) as err:
        print(f"ptm-sim: error: {err}", file=sys.stderr)
        return 2
    drift = float(np.hypot(*run.odometry_error()[-1, :2]))
    shape = (
        f" ({run.images.shape[1]}x{run.images.shape[2]} {config.camera.encoding})" if len(run.images) else ""
    )
    print(
        f"Simulated {len(run.passages)} place visits ({len(set(run.route))} distinct places) in world "
        f"{world.name!r}, seed {args.seed}: {run.duration:.1f} s, {run.path_length:.1f} m travelled, "
        f"final odometry position error {drift:.2f} m.\n"
        f"Wrote {out} ({args.storage}, {_size(out) / 1e6:.1f} MB): {len(run.odom_stamps)} /odom, "
        f"{len(run.scan_stamps)} /scan, {len(run.image_stamps)} /panorama{shape}, "
        f"ground truth in {out / 'ground_truth.json'}."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
