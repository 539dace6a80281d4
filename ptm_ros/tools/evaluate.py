"""``ptm-eval DIR/ptm.json --ground-truth FILE``: score a PTM against a ground truth, print JSON.

Each landmark's true position is the ground-truth trajectory (``ptm_ros.io.groundtruth``) interpolated
at the landmark's stamp (:func:`true_positions_for`). A landmark stamped more than ``--max-extrapolation``
seconds outside the ground truth's time span has no truth: its pairs are unscored (CARMEN ground truth
starts and ends a few seconds inside the raw log). When the ground truth lists places (the simulator's)
and every landmark lies within ``--same-radius`` of one, the nearest place is its true place and the
mass of the exactly-true topology is reported too. Definitions: :mod:`ptm_ros.evaluation`.

Printed JSON (schema ``ptm_ros.eval/1``; key names are stable):

* ``schema``, ``same_radius_m``, ``different_radius_m`` — the schema tag and thresholds (m);
* ``n_visits``, ``n_topologies``, ``listed_mass`` — the PTM's size and its listed probability;
  ``n_visits_without_truth`` — landmarks outside the ground truth's time span (not scored);
* ``n_true_places``, ``true_places_from`` (``"single-linkage"`` or ``"place-ids"``);
* ``n_pairs``, ``n_scored_pairs``, ``n_same_pairs``, ``n_different_pairs`` — visit pairs;
* ``map_probability``, ``map_num_places``, ``map_tp``, ``map_fp``, ``map_fn``, ``map_tn``,
  ``map_precision``, ``map_recall``, ``map_f1`` — the most probable topology;
* ``posterior_tp``, ``posterior_fp``, ``posterior_fn``, ``posterior_tn``, ``posterior_precision``,
  ``posterior_recall``, ``posterior_f1`` — expected counts over the listed topologies (masses
  renormalised over ``listed_mass``) and their precision/recall/F1 (``posterior_f1`` is the headline);
  ``posterior_mean_f1`` — the mass-weighted mean of the topologies' F1;
* ``consistent_mass`` — posterior mass of listed topologies with no scored pair wrong;
* ``true_topology_mass`` — mass of the exactly-true topology, ``null`` without true place ids;
* ``n_contradictory_pairs`` — scored pairs inside a single-linkage cluster spanning more than the
  different-place radius (no topology scores them all right); ``attainable_consistent_mass`` — mass of
  listed topologies with no wrong scored pair outside them;
* ``topologies`` (unless ``--no-topologies``) — per listed topology: ``rank`` (0 = MAP),
  ``probability``, ``num_places``, ``tp``, ``fp``, ``fn``, ``tn``, ``precision``, ``recall``, ``f1``,
  ``consistent``.

Exit status: 0 on success, 2 on bad input (unreadable or invalid ptm.json or ground truth, landmark
no landmark inside the ground truth's time span, bad thresholds), with the reason on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from ptm_ros.evaluation import EvalConfig, Score
    from ptm_ros.io.groundtruth import GroundTruthTrajectory
    from ptm_ros.ptm import Ptm

PROG = "ptm-eval"


def true_positions_for(
    ptm: Ptm, ground_truth: GroundTruthTrajectory, *, max_extrapolation: float = 0.5
) -> NDArray[np.float64]:
    """``(N, 2)`` true position of each landmark: the ground truth interpolated at its stamp.

    Stamps up to ``max_extrapolation`` s outside the ground truth's span take its end pose; farther ones
    get a NaN row (no truth). Raises :class:`DataError` when no landmark stamp lies within the span
    (wrong file, or stamps on another clock).
    """
    import numpy as np

    from ptm_ros.errors import DataError
    from ptm_ros.io.groundtruth import interpolate_pose

    stamps = np.array([lm.stamp for lm in ptm.landmarks], dtype=float)
    t0, t1 = float(np.min(ground_truth.stamps)), float(np.max(ground_truth.stamps))
    inside = (stamps >= t0 - max_extrapolation) & (stamps <= t1 + max_extrapolation)
    if stamps.size and not np.any(inside):
        msg = (
            f"no landmark stamp ({stamps[0]:.3f} … {stamps[-1]:.3f} s) lies within the ground truth's "
            f"span [{t0:.3f}, {t1:.3f}] s: wrong ground-truth file or stamps on another clock?"
        )
        raise DataError(msg)
    xy = np.full((stamps.size, 2), np.nan)
    if np.any(inside):
        poses = interpolate_pose(ground_truth, stamps[inside], tolerance=max_extrapolation)
        xy[inside] = poses[:, :2]
    return xy


def score_against_ground_truth(
    ptm: Ptm,
    ground_truth: str | Path | GroundTruthTrajectory,
    *,
    config: EvalConfig | None = None,
    max_extrapolation: float = 0.5,
) -> Score:
    """Score ``ptm`` against a ground-truth file (or a loaded one): the glue used by ``ptm-eval`` and
    ``ptm-run``. True positions by :func:`true_positions_for`; true place ids from the ground truth's
    places when every landmark lies within ``config.same_radius`` of one."""
    from ptm_ros.errors import ConfigError
    from ptm_ros.evaluation import EvalConfig, place_ids_from_positions, score_ptm
    from ptm_ros.io.groundtruth import load_ground_truth

    config = config or EvalConfig()
    if not max_extrapolation >= 0.0:
        msg = f"max_extrapolation must be >= 0 s, got {max_extrapolation}"
        raise ConfigError(msg)
    truth = load_ground_truth(ground_truth) if isinstance(ground_truth, str | Path) else ground_truth
    xy = true_positions_for(ptm, truth, max_extrapolation=max_extrapolation)
    places = None
    if truth.places:
        places = place_ids_from_positions(xy, [(pl.x, pl.y) for pl in truth.places], config.same_radius)
    return score_ptm(ptm, xy, true_places=None if places is None else places.tolist(), config=config)


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``ptm-eval``."""
    from ptm_ros.evaluation import EvalConfig

    d = EvalConfig()
    p = argparse.ArgumentParser(prog=PROG, description="Score a PTM (ptm.json) against a ground truth.")
    p.add_argument("ptm", type=Path, help="the ptm.json to score")
    p.add_argument("--ground-truth", type=Path, required=True, help="ground-truth file (see io.groundtruth)")
    p.add_argument("--same-radius", type=float, default=d.same_radius, help="same place below (m)")
    p.add_argument("--different-radius", type=float, default=d.different_radius, help="different above (m)")
    p.add_argument(
        "--max-extrapolation",
        type=float,
        default=0.5,
        help="how far (s) a landmark stamp may lie outside the ground-truth span",
    )
    p.add_argument("--no-topologies", action="store_true", help="leave out the per-topology list")
    p.add_argument("--report", type=Path, default=None, help="also write the report with the score here")
    p.add_argument("--indent", type=int, default=2, help="JSON indentation (default 2)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ptm-eval``; returns the exit status."""
    args = build_parser().parse_args(argv)

    from ptm_ros.errors import PtmError
    from ptm_ros.evaluation import EvalConfig
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.ptm import load_ptm

    try:
        config = EvalConfig(args.same_radius, args.different_radius)
        ptm = load_ptm(args.ptm)
        truth = load_ground_truth(args.ground_truth)
        extrapolation = args.max_extrapolation
        score = score_against_ground_truth(ptm, truth, config=config, max_extrapolation=extrapolation)
        if args.report is not None:
            from ptm_ros.report import write_report

            write_report(
                args.report,
                ptm,
                trajectory=truth.poses_raw,  # raw odometry (CARMEN), the frame of the landmark poses
                score=score,
                title=f"{args.ptm} vs {args.ground_truth.name}",
            )
    except (PtmError, OSError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(score.as_dict(per_topology=not args.no_topologies), indent=args.indent))
    return 0


if __name__ == "__main__":
    sys.exit(main())
