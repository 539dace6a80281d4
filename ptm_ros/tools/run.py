"""``ptm-run BAG --out DIR``: the offline pipeline (same core code as the nodes, no DDS).

Writes ``DIR/ptm.json`` (CONTRACT.md schema), ``DIR/config.yaml`` (the parameters used),
``DIR/route_graph.geojson`` (nav2 route graph, its edges kept off the map's walls), for a bag with scans
the occupancy map ``DIR/map.pgm`` + ``DIR/map.yaml`` (nav2 map_server) and ``DIR/map.png`` (unless
``--no-map``), and ``DIR/report.{md,html}`` with figures (unless ``--no-report``); see
:mod:`ptm_ros.tools.pipeline` and :mod:`ptm_ros.tools.outputs`.
Prints the most probable topologies and, when the bag carries a ground truth (``BAG/ground_truth.json``)
or ``--ground-truth`` is given, their score and the absolute trajectory errors of the smoothed MAP
trajectory and of the raw odometry (also in ``ptm.json`` under ``trajectory_error``), and the map's
quality against the same scans at the true poses (``map_quality``, :mod:`ptm_ros.maps.map_quality`).
A ground truth that looks like another run's is refused right after the bag is read, before the work,
with exit code 2 and one line naming the figures: ``ptm-eval``'s rule and thresholds applied to the bag's
odometry (:func:`ptm_ros.io.groundtruth.run_ground_truth_problem`); ``--force`` uses it anyway.

Persistence (``--method rbpf``, issue #8): ``--autosave N`` writes the filter's state every N visits and
after the last one to ``DIR/filter_state.npz`` (``--state-file`` elsewhere; atomic writes, checksummed);
``--resume`` continues from that file when it exists — after checking it was made with the same
parameters on the same visits, else exit code 2 and a one-line reason — and writes the same ``ptm.json``
as an uninterrupted run (timings aside); without the file it starts afresh.

``--detector ground-truth`` replays the protocol of the thesis' Intel experiment (Ch. 4.5, Fig. 57:
landmarks placed in the environment 5 m from each other): landmarks fixed along the ground truth's path
(``detector.ground_truth`` parameters; a simulated bag's own places), visits where the robot passes them;
it needs the ground truth, scores the mass on the true topology, and writes ``DIR/ground_truth.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ptm_ros.model.partitions import Labels
    from ptm_ros.model.ptm import Ptm, TimelineStep
    from ptm_ros.tools.checkpoint import RunCheckpoint

PROG = "ptm-run"


def build_parser() -> argparse.ArgumentParser:
    from ptm_ros.config import DETECTORS, InferenceConfig
    from ptm_ros.tools.paths import add_params_option

    inf = InferenceConfig()
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Compute a probabilistic topological map from a bag.",
        epilog="A run saved with --autosave N and stopped (killed, crashed) continues with the same "
        "command plus --resume, and writes the same ptm.json as an uninterrupted run (timings aside). "
        "A state file made with other parameters, on another bag, or damaged is refused (exit code 2).",
    )
    p.add_argument("bag", type=Path, help="rosbag2 directory with /odom (and /scan, /panorama)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument(
        "--method",
        choices=("rbpf", "mcmc", "exact"),
        default=None,
        help=f"estimator (default: inference.method of --params, else {inf.method})",
    )
    p.add_argument(
        "--detector",
        choices=DETECTORS,
        default=None,
        help="landmark detector (default: the default for the bag's sensors; ground-truth: landmarks "
        "fixed along the ground truth's path, the thesis' Intel protocol, needs --ground-truth or a "
        "simulated bag)",
    )
    p.add_argument(
        "--particles",
        type=int,
        default=None,
        help=f"particles of the RBPF (default: inference.particles of --params, else {inf.particles})",
    )
    add_params_option(p)
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help=f"random seed (default: inference.seed of --params, else {inf.seed})",
    )
    p.add_argument(
        "--ground-truth",
        type=Path,
        default=None,
        help="score against this ground truth: a CARMEN *-gt-*.txt file or a ground_truth.json (default: "
        "the bag's own ground_truth.json, if any)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="use the ground truth even when it looks like another run's (most of the bag's odometry "
        "outside its time span, or the odometry not moving as it does; checked before the work; default: "
        "off, refused)",
    )
    p.add_argument("--top", type=int, default=5, help="topologies to print (default: %(default)s)")
    p.add_argument("--no-report", action="store_true", help="skip the figures and report")
    p.add_argument("--no-map", action="store_true", help="skip the occupancy map (map.pgm/.yaml/.png)")
    p.add_argument("--quiet", action="store_true", help="no progress bars (one per phase, on stderr)")
    p.add_argument(
        "--trace",
        action="store_true",
        help="mcmc: also write the cold chains' full states to DIR/mcmc_trace.json, for the report's SRQ "
        "plot (default: off; ptm.json keeps their summary)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="worker processes for the scan matching (the visits' patches, the filter's registrations, the "
        "map's refinement) and the report's figures (default: the machine's CPUs); the same results",
    )
    p.add_argument(
        "--autosave",
        type=int,
        default=None,
        metavar="N",
        help="rbpf: save the filter state every N visits and at the end (to DIR/filter_state.npz; "
        "default: off)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="rbpf: continue from the saved state if it exists (it must come from the same bag and "
        "parameters: else an error); without one, start afresh",
    )
    p.add_argument(
        "--state-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="the state file of --autosave/--resume (default: DIR/filter_state.npz)",
    )
    return p


def _overrides(args: argparse.Namespace) -> dict:
    inference = {
        k: v
        for k, v in (("method", args.method), ("particles", args.particles), ("seed", args.seed))
        if v is not None
    }
    out: dict = {}
    if inference:
        out["inference"] = inference
    if args.detector is not None:
        out["detector"] = {"kind": args.detector}
    return out


def jobs_of(args: argparse.Namespace) -> int:
    """``--jobs``, or the machine's CPUs.

    Raises:
        ConfigError: ``--jobs`` below 1.
    """
    from ptm_ros.errors import ConfigError

    if args.jobs is None:
        return os.cpu_count() or 1
    if args.jobs < 1:
        msg = f"--jobs N needs N >= 1 (worker processes), got {args.jobs}"
        raise ConfigError(msg)
    return int(args.jobs)


def checkpoint_of(args: argparse.Namespace) -> RunCheckpoint | None:
    """The :class:`~ptm_ros.tools.checkpoint.RunCheckpoint` of ``--autosave/--resume/--state-file``, or None.

    Raises:
        ConfigError: ``--autosave`` below 1, or ``--state-file`` without ``--autosave``/``--resume``.
    """
    from ptm_ros.errors import ConfigError
    from ptm_ros.tools.checkpoint import RunCheckpoint
    from ptm_ros.tools.outputs import OUTPUT_FILES

    if args.autosave is not None and args.autosave < 1:
        msg = f"--autosave N needs N >= 1 (visits between saves), got {args.autosave}"
        raise ConfigError(msg)
    if args.autosave is None and not args.resume:
        if args.state_file is not None:
            msg = "--state-file needs --autosave N or --resume"
            raise ConfigError(msg)
        return None
    path = args.state_file if args.state_file is not None else args.out / OUTPUT_FILES["state"]
    return RunCheckpoint(path, every=args.autosave or 0, resume=args.resume)


#: Rows of the printed timeline: a longer one shows only the visits where the mass moved (:func:`eventful`).
TIMELINE_ROWS = 20
#: A visit where the most probable topology holds less than this is one where the mass is split.
SURE_MASS = 0.95


def eventful(steps: Sequence[TimelineStep], greedy_wrong: int | None = None) -> list[int]:
    """Indices of the timeline steps worth a row when there are too many: the first and last visits,
    those after which the most probable topology held less than :data:`SURE_MASS` or was not the
    previous one extended (the mass moved), and the greedy baseline's first wrong decision."""
    keep = {0, len(steps) - 1} | ({greedy_wrong} if greedy_wrong is not None else set())
    for k, st in enumerate(steps):
        best, p = st.topologies[0] if st.topologies else ((), 0.0)
        before = steps[k - 1].topologies[0][0] if k > 0 and steps[k - 1].topologies else None
        if p < SURE_MASS or (before is not None and best[:-1] != before):
            keep.add(k)
    return sorted(keep)


def timeline_lines(ptm: Ptm, truth: Labels | None = None) -> list[str]:
    """The printed timeline: after each visit the mass of the most probable topologies of the visits so
    far (``*`` the true one, ``g`` the greedy baseline's answer so far) and, with the true topology
    ``truth``, its mass and whether the greedy answer so far is right; at most :data:`TIMELINE_ROWS` rows
    (the :func:`eventful` ones when more); no lines without a timeline in ptm.json."""
    from ptm_ros.model.ptm import ptm_greedy, ptm_timeline
    from ptm_ros.reporting.plots import label_string
    from ptm_ros.scoring.evaluation import cut, first_wrong_visit, timeline_masses, unlisted_bound

    steps = ptm_timeline(ptm)
    if not steps:
        return []
    greedy = ptm_greedy(ptm)
    wrong = first_wrong_visit(greedy, truth) if greedy is not None and truth is not None else None
    rows = list(range(len(steps))) if len(steps) <= TIMELINE_ROWS else eventful(steps, wrong)[:TIMELINE_ROWS]
    masses = timeline_masses(steps, truth) if truth is not None else ()
    marks = "* the true one, g the greedy baseline's answer" if truth is not None else "g the greedy answer"
    lines = [
        "how the mass moved as the visits arrived (the particle filter's PTM after each visit: its most "
        f"probable topologies of the visits so far, {marks}):",
        "  visit  "
        + ("truth   " if truth is not None else "")
        + ("greedy  " if truth is not None and greedy is not None else "")
        + "topologies",
    ]
    shown = -1
    for k in rows:
        st = steps[k]
        if k > shown + 1:
            lines.append(f"  … {k - shown - 1} visits with one topology holding >= {SURE_MASS} of the mass")
        shown = k
        head = f"  {st.visits - 1:5d}  "
        if truth is not None:
            m = masses[k]
            head += (f"{m:.3f}" if m is not None else f"<{unlisted_bound(st):.3f}").ljust(8)
            if greedy is not None:
                head += ("wrong" if wrong is not None and st.visits > wrong else "right").ljust(8)
        cells = []
        for lab, p in st.topologies:
            mark = "*" if truth is not None and lab == cut(truth, st.visits) else ""
            mark += "g" if greedy is not None and lab == cut(greedy, st.visits) else ""
            cells.append(f"{p:.3f} {label_string(lab, 24)}{mark}")
        lines.append(head + "  ".join(cells))
    if shown < len(steps) - 1:
        lines.append(f"  … {len(steps) - 1 - shown} more visits: ptm.json's inference.timeline")
    return lines


def format_summary(result, top: int, total_s: float | None = None) -> str:
    """Human-readable lines: visits, the most probable topologies, the score if any, how the mass moved as
    the visits arrived (:func:`timeline_lines`), the greedy baseline's answer beside it, and
    (``total_s``) the run's whole wall time with its phases."""
    from ptm_ros.model.translation_noise import TRANSLATION_KEY
    from ptm_ros.perception.landmarks import landmark_accounting
    from ptm_ros.reporting.doubts import doubt_lines, find_doubts
    from ptm_ros.reporting.plots import label_string
    from ptm_ros.reporting.report import CONSISTENT_MASS_MEANING, inference_line, translation_check_line
    from ptm_ros.tools.outputs import MAP_QUALITY_KEY, greedy_notes, inference_notes, map_quality_notes

    ptm = result.ptm
    lines = [f"{len(ptm.landmarks)} landmark visits, {ptm.timing.get('wall_s', 0.0):.2f} s to the PTM"]
    diag = result.diagnostics or ptm.extra.get("diagnostics")
    skipped = diag.get("skipped") if isinstance(diag, dict) else None
    accounting = landmark_accounting(len(ptm.landmarks), skipped if isinstance(skipped, dict) else {})
    if accounting:
        lines.append(accounting)
    lines.append(inference_line(ptm.inference))
    check = translation_check_line(ptm.inference.get(TRANSLATION_KEY))
    lines += [*([check] if check else []), "most probable topologies:"]
    for rank, t in enumerate(ptm.topologies[:top]):
        places = len(set(t.labels))
        lines.append(f"  #{rank + 1} p = {t.probability:.4f}  places = {places:3d}  {label_string(t.labels)}")
    if result.score is not None:
        s = result.score.as_dict(per_topology=False)
        lines.append(
            "score vs ground truth: MAP F1 = {map_f1:.3f} (P {map_precision:.3f}, R {map_recall:.3f}), "
            "posterior F1 = {posterior_f1:.3f}, consistent mass = {consistent_mass:.3f}, "
            "true places = {n_true_places}".format(**s)
        )
        lines.append(f"  ({CONSISTENT_MASS_MEANING})")
        if s.get("true_topology_mass") is not None:
            lines.append(f"mass on the true topology = {s['true_topology_mass']:.3f}")
        if result.score.pairs is not None:
            lines.append(result.score.pairs.summary())
    truth = result.score.true_labels if result.score is not None else None
    lines.extend(timeline_lines(ptm, truth))
    lines.extend(greedy_notes(ptm, truth))
    ate = result.trajectory_error
    if ate:
        lines.append(
            f"trajectory error (ATE, {ate['poses']} poses): smoothed MAP {ate['ate_smoothed_m']:.3f} m, "
            f"odometry {ate['ate_odometry_m']:.3f} m"
        )
    lines.extend(map_quality_notes(ptm.extra.get(MAP_QUALITY_KEY)))
    lines.extend(doubt_lines(find_doubts(ptm), most=5))
    lines.extend(inference_notes(ptm.inference))
    written = [str(p) for p in result.files.values()] or [str(result.ptm_path)]
    if result.report_path:
        written.append(str(result.report_path))
    lines.append("wrote " + ", ".join(written))
    if total_s is not None:
        phases = {"to the PTM": "wall_s", "smoothing": "smoothing_s", "map": "map_s"}
        parts = [f"{name} {ptm.timing[key]:.1f} s" for name, key in phases.items() if key in ptm.timing]
        lines.append(f"done in {total_s:.1f} s of wall time ({', '.join(parts)}; the rest: files, report)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    start = time.perf_counter()
    args = build_parser().parse_args(argv)
    from ptm_ros.config import load_config
    from ptm_ros.errors import PtmError
    from ptm_ros.tools.paths import output_dir
    from ptm_ros.tools.pipeline import run_offline
    from ptm_ros.tools.progress import Phases

    phases = Phases(quiet=args.quiet)
    try:
        config = load_config(args.params, _overrides(args))
        checkpoint = checkpoint_of(args)
        jobs = jobs_of(args)
        output_dir(args.out)  # fails now, not after the inference
        result = run_offline(
            args.bag,
            args.out,
            config,
            ground_truth=args.ground_truth,
            phases=phases,
            write_report=not args.no_report,
            write_map=not args.no_map,
            checkpoint=checkpoint,
            log=lambda note: phases.note(f"{PROG}: {note}"),
            write_trace=args.trace,
            jobs=jobs,
            force=args.force,
        )
    except (PtmError, OSError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    warning = skipped_warning(result.diagnostics)
    if warning:
        print(f"{PROG}: warning: {warning}", file=sys.stderr)
    print(format_summary(result, args.top, total_s=time.perf_counter() - start))
    return 0


def skipped_warning(diagnostics: dict) -> str:
    """One line naming the input messages the extractor skipped, by reason (``''`` when none): bad input
    is reported, never dropped silently (the counts are also in ptm.json's ``diagnostics``)."""
    from ptm_ros.perception.landmarks import LANDMARK_DROPS

    items = (diagnostics.get("skipped") or {}).items()
    skipped = {k: int(v) for k, v in items if v and k not in LANDMARK_DROPS}  # landmarks: in the summary
    if not skipped:
        return ""
    reasons = ", ".join(f"{k} {v}" for k, v in sorted(skipped.items()))
    return f"skipped {sum(skipped.values())} input messages ({reasons}); see diagnostics in ptm.json"


if __name__ == "__main__":
    sys.exit(main())
