"""``ptm-eval DIR/ptm.json --ground-truth FILE``: score a PTM against a ground truth, print JSON.

Each landmark's true position is the ground-truth trajectory (``ptm_ros.io.groundtruth``) interpolated
at the landmark's stamp (:func:`true_positions_for`). A landmark stamped more than ``--max-extrapolation``
seconds outside the ground truth's time span has no truth: its pairs are unscored (CARMEN ground truth
starts and ends a few seconds inside the raw log). When the ground truth lists places (the simulator's)
and every landmark lies within ``--same-radius`` of one, the nearest place is its true place and the
mass of the exactly-true topology is reported too. Definitions: :mod:`ptm_ros.scoring.evaluation`.

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
* ``pair_calibration`` — how often the pairs stated at each ``P(i ~ j)`` are one place (below);
* ``topologies`` (unless ``--no-topologies``) — per listed topology: ``rank`` (0 = MAP),
  ``probability``, ``num_places``, ``tp``, ``fp``, ``fn``, ``tn``, ``precision``, ``recall``, ``f1``,
  ``consistent``;
* ``map_quality`` — the occupancy map (``--map``, default the ``map.yaml`` beside the ``ptm.json``)
  against the bag's scans placed at the ground truth's poses (:func:`map_quality_of_run`:
  :mod:`ptm_ros.maps.map_quality`'s ``leak``, ``wall_precision``, ``wall_recall``, ``free_area_ratio`` and
  their counts), ``null`` when the run has no map, no scans or no recorded alignment.

``ptm-eval --calibration RUN [RUN ...] [--plot FILE]`` scores many runs at once, simulated or real (issue
#23): each RUN is a ``ptm.json``, a run directory holding one, or a directory searched recursively for
them; each run's ground truth is ``--ground-truth`` when given, else the ``ground_truth.json`` beside
the ``ptm.json``, else the file ``ptm-run --ground-truth`` scored it against (a real run's), else the one
in the bag named by the ``ptm.json`` (``bag``). It prints (schema
``ptm_ros.calibration/1``): ``runs`` (per run: ``ptm``, ``ground_truth``, and :func:`calibration_record`'s
keys), ``n_runs``, ``n_runs_without_true_topology`` (visits not all within ``--same-radius`` of a place:
no exact truth, left out of the calibration figures) and ``calibration``
(:meth:`ptm_ros.scoring.evaluation.CalibrationSummary.as_dict`: ``ece``, ``chance_ece``, ``chance_ece_p95``,
``brier``, ``map_right_rate``, ``mean_map_probability``, ``overconfident_failures``,
``mean_true_topology_mass``, ``bins``; ``null`` when no run has an exact truth, e.g. real runs) and
``pair_calibration``: the runs' pair tables pooled (below); ``--plot FILE`` writes the reliability
diagram (PNG) of the MAP, or of the pairs when no run has an exact truth.

``pair_calibration`` (in both modes; :class:`ptm_ros.scoring.evaluation.PairReliability`, definitions in
:mod:`ptm_ros.scoring.evaluation`, "Pair calibration"): ``pairs``, ``doubtful_pairs`` (stated between
0.02 and 0.98), ``doubtful_gap`` (their ECE), ``confident_false_merges`` (different pairs stated
≥ 0.98), ``confident_misses`` (same pairs stated < 0.02) and ``bins`` (``lo``, ``hi``, ``count``,
``probability_sum``, ``same``, ``mean_probability``, ``share_same``). Unlike the MAP calibration it
needs no exact places: a real run's trajectory is enough.

Exit status: 0 on success, 2 on bad input (unreadable or invalid ptm.json or ground truth, landmark
no landmark inside the ground truth's time span, bad thresholds), with the reason on stderr.
"""

from __future__ import annotations

import argparse
import functools
import json
import operator
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from ptm_ros.io.groundtruth import GroundTruthTrajectory
    from ptm_ros.model.ptm import Ptm
    from ptm_ros.scoring.evaluation import CalibrationSummary, EvalConfig, OdometryFit, PairReliability, Score

PROG = "ptm-eval"
#: Schema tag of the JSON printed by ``ptm-eval --calibration``.
CALIBRATION_SCHEMA = "ptm_ros.calibration/1"


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
    from ptm_ros.io.groundtruth import interpolate_pose, within_span

    stamps = np.array([lm.stamp for lm in ptm.landmarks], dtype=float)
    t0, t1 = float(np.min(ground_truth.stamps)), float(np.max(ground_truth.stamps))
    inside = within_span(ground_truth, stamps, max_extrapolation)
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


def odometry_fit_against(
    ptm: Ptm, truth: GroundTruthTrajectory, *, max_extrapolation: float = 0.5
) -> OdometryFit:
    """How well the landmarks' odometry poses (``ptm.json``'s ``pose``) fit the ground truth at their stamps
    (:func:`ptm_ros.io.groundtruth.odometry_fit_at`, the rule ``ptm-run`` applies to the bag's odometry)."""
    from ptm_ros.io.groundtruth import odometry_fit_at

    stamps = [lm.stamp for lm in ptm.landmarks]
    odom = [lm.pose[:2] for lm in ptm.landmarks]
    return odometry_fit_at(truth, stamps, odom, max_extrapolation=max_extrapolation)


def another_runs_problem(score: Score, fit: OdometryFit, *, raw: bool) -> str | None:
    """Why the ground truth looks like another run's, with the figures (None: it does not): most landmarks
    had no ground truth (their stamps outside its span: another run's, or part of this one), or their
    odometry does not fit it (``fit``; ``raw``: against its raw odometry). The shared rule of
    :mod:`ptm_ros.io.groundtruth`, as ``ptm-run`` applies it before the work."""
    from ptm_ros.io.groundtruth import coverage_problem, odometry_fit_problem

    return coverage_problem(
        score.n_visits_without_truth, score.n_visits, "landmarks"
    ) or odometry_fit_problem(fit, raw=raw, what="the landmarks' odometry")


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
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.scoring.evaluation import EvalConfig, score_ptm

    config = config or EvalConfig()
    truth = load_ground_truth(ground_truth) if isinstance(ground_truth, str | Path) else ground_truth
    xy, places = true_place_ids(ptm, truth, config=config, max_extrapolation=max_extrapolation)
    return score_ptm(ptm, xy, true_places=None if places is None else places.tolist(), config=config)


def true_place_ids(
    ptm: Ptm, truth: GroundTruthTrajectory, *, config: EvalConfig, max_extrapolation: float = 0.5
) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
    """Each landmark's true position (:func:`true_positions_for`) and true place id: the nearest of the
    ground truth's places within ``config.same_radius``, or None (no exact truth) when one is farther."""
    from ptm_ros.errors import ConfigError
    from ptm_ros.scoring.evaluation import place_ids_from_positions

    if not max_extrapolation >= 0.0:
        msg = f"max_extrapolation must be >= 0 s, got {max_extrapolation}"
        raise ConfigError(msg)
    xy = true_positions_for(ptm, truth, max_extrapolation=max_extrapolation)
    places = None
    if truth.places:
        places = place_ids_from_positions(xy, [(pl.x, pl.y) for pl in truth.places], config.same_radius)
    return xy, places


def calibration_record(
    ptm: Ptm,
    ground_truth: str | Path | GroundTruthTrajectory,
    *,
    config: EvalConfig | None = None,
    max_extrapolation: float = 0.5,
) -> dict[str, Any]:
    """One run's calibration figures against its ground truth (plain JSON values).

    ``map_probability``; ``map_right`` (the MAP topology is exactly the true one, None without true place
    ids), ``map_false_merges`` / ``map_missed_merges`` (visit pairs the MAP wrongly joins / keeps apart,
    None without them); ``consistent_mass``, ``true_topology_mass``, ``overconfident_failure``
    (consistent mass < :data:`ptm_ros.scoring.evaluation.OVERCONFIDENT_MASS`); ``n_visits``,
    ``n_true_places``, ``map_num_places``, ``listed_mass``, ``posterior_f1``; ``pair_calibration``: the
    run's pair table (:class:`ptm_ros.scoring.evaluation.PairReliability`, any ground truth).
    """
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.scoring.evaluation import OVERCONFIDENT_MASS, EvalConfig, map_errors_against_truth, score_ptm

    config = config or EvalConfig()
    truth = load_ground_truth(ground_truth) if isinstance(ground_truth, str | Path) else ground_truth
    xy, places = true_place_ids(ptm, truth, config=config, max_extrapolation=max_extrapolation)
    score = score_ptm(ptm, xy, true_places=None if places is None else places.tolist(), config=config)
    merges = None if places is None else map_errors_against_truth(ptm.map_topology.labels, places)
    return {
        "n_visits": score.n_visits,
        "n_true_places": score.n_true_places,
        "map_num_places": score.map.num_places,
        "listed_mass": score.listed_mass,
        "map_probability": score.map.probability,
        "map_right": None if merges is None else merges == (0, 0),
        "map_false_merges": None if merges is None else merges[0],
        "map_missed_merges": None if merges is None else merges[1],
        "consistent_mass": score.consistent_mass,
        "true_topology_mass": score.true_topology_mass,
        "overconfident_failure": score.consistent_mass < OVERCONFIDENT_MASS,
        "posterior_f1": score.expected.f1,
        "pair_calibration": None if score.pairs is None else score.pairs.as_dict(),
    }


def summarize_records(
    records: Sequence[dict[str, Any]], rng: np.random.Generator, *, n_bins: int = 10, redraws: int = 2000
) -> CalibrationSummary | None:
    """:func:`ptm_ros.scoring.evaluation.calibration_summary` of the records with an exact truth
    (``map_right`` not None); None when there is none."""
    from ptm_ros.scoring.evaluation import calibration_summary

    scored = [r for r in records if r["map_right"] is not None]
    if not scored:
        return None
    return calibration_summary(
        [r["map_probability"] for r in scored],
        [r["map_right"] for r in scored],
        rng,
        consistent_mass=[r["consistent_mass"] for r in scored],
        true_topology_mass=[r["true_topology_mass"] for r in scored],
        n_bins=n_bins,
        redraws=redraws,
    )


def pooled_pairs(records: Sequence[dict[str, Any]]) -> PairReliability:
    """The pair calibration of all ``records`` (:func:`calibration_record`) pooled into one table."""
    from ptm_ros.errors import ConfigError
    from ptm_ros.scoring.evaluation import PairReliability

    tables = [PairReliability.from_dict(r["pair_calibration"]) for r in records if r["pair_calibration"]]
    if not tables:
        msg = "no run to score"
        raise ConfigError(msg)
    return functools.reduce(operator.add, tables)


def find_runs(paths: Sequence[Path]) -> list[Path]:
    """The ``ptm.json`` files named by ``paths``: files as given, a directory's own ``ptm.json``, else every
    ``ptm.json`` below it (sorted). Raises :class:`DataError` for a path that names none."""
    from ptm_ros.errors import DataError

    out: list[Path] = []
    for path in paths:
        if path.is_dir():
            found = [path / "ptm.json"] if (path / "ptm.json").is_file() else sorted(path.rglob("ptm.json"))
            if not found:
                msg = f"{path}: no ptm.json in or below this directory"
                raise DataError(msg)
            out += found
        else:
            out.append(path)
    return out


def map_quality_of_run(
    ptm_path: Path, ptm: Ptm, truth: GroundTruthTrajectory, *, map_yaml: Path | None = None
) -> dict[str, Any] | None:
    """The quality of a run's occupancy map (``map_yaml``, default ``map.yaml`` beside ``ptm_path``)
    against the scans of the run's bag (``ptm.json``'s ``bag``) at the ground truth's poses, carried by
    the alignment ``ptm-run`` recorded (``trajectory_error.alignment``: the map's trajectory onto the
    ground truth), with the run's ``config.yaml`` (:func:`ptm_ros.tools.outputs.map_quality_against`).
    None when the map, the bag, its scans or the alignment is missing."""
    from ptm_ros.config import load_config
    from ptm_ros.io.bag import read_run
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.occupancy import load_map
    from ptm_ros.tools.outputs import TRAJECTORY_ERROR_KEY, map_quality_against

    yml = map_yaml if map_yaml is not None else ptm_path.parent / "map.yaml"
    alignment = (ptm.extra.get(TRAJECTORY_ERROR_KEY) or {}).get("alignment")
    bag = ptm.extra.get("bag")
    if alignment is None or not yml.is_file() or not isinstance(bag, str) or not Path(bag).exists():
        return None
    saved = ptm_path.parent / "config.yaml"
    config = load_config(saved if saved.is_file() else None)
    run = read_run(bag, odom_topic=config.topics.odom, scan_topic=config.topics.scan, image_topic=None)
    if run.scans is None or len(run.scans.stamps) == 0:
        return None
    m = load_map(yml)
    return map_quality_against(run, ClassGrid(m.classes(), m.origin, m.resolution), truth, alignment, config)


def ground_truth_of(ptm_path: Path) -> Path:
    """A run's ground truth: ``ground_truth.json`` beside ``ptm_path``, else the file ``ptm-run`` scored it
    against (the ptm.json's ``trajectory_error.ground_truth``: a real run's CARMEN file), else the one in
    the bag named by the ptm.json's ``bag``. Raises :class:`DataError` when none exists."""
    from ptm_ros.errors import DataError
    from ptm_ros.io.groundtruth import SIM_FILENAME

    beside = ptm_path.parent / SIM_FILENAME
    if beside.is_file():
        return beside
    try:
        doc = json.loads(ptm_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        doc = None
    doc = doc if isinstance(doc, dict) else {}
    scored = doc.get("trajectory_error")
    scored = scored.get("ground_truth") if isinstance(scored, dict) else None
    if isinstance(scored, str) and Path(scored).is_file():
        return Path(scored)
    bag = doc.get("bag")
    if isinstance(bag, str) and (Path(bag) / SIM_FILENAME).is_file():
        return Path(bag) / SIM_FILENAME
    msg = (
        f"{ptm_path}: no ground truth beside it, recorded by ptm-run nor in its bag ({bag}); "
        "give --ground-truth"
    )
    raise DataError(msg)


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``ptm-eval``."""
    from ptm_ros.scoring.evaluation import CALIBRATION_BINS, EvalConfig

    d = EvalConfig()
    p = argparse.ArgumentParser(prog=PROG, description="Score a PTM (ptm.json) against a ground truth.")
    p.add_argument(
        "ptm",
        type=Path,
        nargs="+",
        help="the ptm.json to score (with --calibration: any number of ptm.json files, run directories "
        "holding one, or directories searched for them)",
    )
    p.add_argument(
        "--ground-truth",
        type=Path,
        default=None,
        help="the ground truth: a CARMEN *-gt-*.txt file, a ground_truth.json (written by ptm-sim and by "
        "ptm-run --detector ground-truth) or a directory holding one, e.g. a simulated bag (required "
        "unless --calibration; there the default is each run's own)",
    )
    p.add_argument(
        "--calibration",
        action="store_true",
        help="score many runs and print the calibration of the MAP probability (ECE, Brier, ...)",
    )
    p.add_argument(
        "--plot",
        type=Path,
        default=None,
        help="--calibration: write the reliability diagram (PNG) here (default: none)",
    )
    p.add_argument(
        "--bins",
        type=int,
        default=CALIBRATION_BINS,
        help="--calibration: probability bins (default: %(default)s)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="--calibration: seed of the chance-level redraws (default: %(default)s)",
    )
    p.add_argument(
        "--same-radius", type=float, default=d.same_radius, help="same place below (m; default: %(default)s)"
    )
    p.add_argument(
        "--different-radius",
        type=float,
        default=d.different_radius,
        help="different places above (m; default: %(default)s)",
    )
    p.add_argument(
        "--max-extrapolation",
        type=float,
        default=0.5,
        help="how far (s) a landmark stamp may lie outside the ground-truth span (default: %(default)s)",
    )
    p.add_argument("--no-topologies", action="store_true", help="leave out the per-topology list")
    p.add_argument(
        "--map",
        type=Path,
        default=None,
        help="map_server YAML to score as the run's map (default: map.yaml beside the ptm.json)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="score even when the ground truth looks like another run's: most landmarks outside its time "
        "span, or the landmarks' odometry not moving as its poses do",
    )
    p.add_argument(
        "--report", type=Path, default=None, help="also write the report with the score here (default: none)"
    )
    p.add_argument("--indent", type=int, default=2, help="JSON indentation (default: %(default)s)")
    return p


def calibration_main(args: argparse.Namespace) -> int:
    """``ptm-eval --calibration``: score every run, print the calibration JSON, write ``--plot``."""
    import numpy as np

    from ptm_ros.errors import ConfigError, PtmError
    from ptm_ros.model.ptm import load_ptm
    from ptm_ros.scoring.evaluation import EvalConfig

    try:
        if args.bins < 1:
            msg = f"--bins must be >= 1, got {args.bins}"
            raise ConfigError(msg)
        config = EvalConfig(args.same_radius, args.different_radius)
        runs = []
        for path in find_runs(args.ptm):
            gt = args.ground_truth if args.ground_truth is not None else ground_truth_of(path)
            record = calibration_record(
                load_ptm(path), gt, config=config, max_extrapolation=args.max_extrapolation
            )
            runs.append({"ptm": str(path), "ground_truth": str(gt), **record})
        summary = summarize_records(runs, np.random.default_rng(args.seed), n_bins=args.bins)
        pairs = pooled_pairs(runs)
        if args.plot is not None:
            from ptm_ros.io.calibration_plot import write_pair_reliability_diagram, write_reliability_diagram

            if summary is not None:
                write_reliability_diagram(args.plot, {"all runs": summary})
            else:  # real runs: no exact true topology, the pairs only
                write_pair_reliability_diagram(args.plot, {"all runs": pairs})
    except (PtmError, OSError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    doc = {
        "schema": CALIBRATION_SCHEMA,
        "n_runs": len(runs),
        "n_runs_without_true_topology": sum(r["map_right"] is None for r in runs),
        "calibration": None if summary is None else summary.as_dict(),
        "pair_calibration": pairs.as_dict(),
        "runs": runs,
    }
    print(json.dumps(doc, indent=args.indent))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ptm-eval``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.calibration:
        return calibration_main(args)
    if len(args.ptm) != 1:
        parser.error("score one ptm.json at a time (or use --calibration)")
    if args.ground_truth is None:
        parser.error("the following arguments are required: --ground-truth (unless --calibration)")
    args.ptm = args.ptm[0]

    from ptm_ros.errors import DataError, PtmError
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.ptm import load_ptm
    from ptm_ros.scoring.evaluation import EvalConfig

    try:
        config = EvalConfig(args.same_radius, args.different_radius)
        ptm = load_ptm(args.ptm)
        truth = load_ground_truth(args.ground_truth)
        extrapolation = args.max_extrapolation
        score = score_against_ground_truth(ptm, truth, config=config, max_extrapolation=extrapolation)
        fit = odometry_fit_against(ptm, truth, max_extrapolation=extrapolation)
        problem = another_runs_problem(score, fit, raw=truth.poses_raw is not None)
        if problem is not None and not args.force:
            raise DataError(f"{problem} (--force scores it anyway)")
        quality = map_quality_of_run(args.ptm, ptm, truth, map_yaml=args.map)
        if args.report is not None:
            from ptm_ros.reporting.chain_trace import find_chain_trace
            from ptm_ros.reporting.report import write_report
            from ptm_ros.tools.outputs import inference_notes

            write_report(
                args.report,
                ptm,
                trajectory=truth.poses_raw,  # raw odometry (CARMEN), the frame of the landmark poses
                score=score,
                title=f"{args.ptm} vs {args.ground_truth.name}",
                chain_trace=find_chain_trace(ptm, Path(args.ptm).parent),
                notes=inference_notes(ptm.inference),  # MCMC's convergence, as ptm-run's report has it
            )
    except (PtmError, OSError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    against = "raw odometry" if truth.poses_raw is not None else "poses"
    doc = {
        **score.as_dict(per_topology=not args.no_topologies),
        "odometry_fit": {**fit.as_dict(), "against": against},
        "map_quality": quality,
    }
    print(json.dumps(doc, indent=args.indent))
    return 0


if __name__ == "__main__":
    sys.exit(main())
