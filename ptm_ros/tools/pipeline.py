"""The offline pipeline behind ``ptm-run``: bag → landmark visits → PTM → ptm.json, maps, report, score.

The science is in the core modules and the orchestration in :mod:`ptm_ros.session` (the filter session,
the estimators, the ptm.json content) and :mod:`ptm_ros.factories` (detector, extractor, registrar);
this module only loops over a recorded run (:func:`detect_visits`), times it and smooths the MAP
trajectory (:func:`map_trajectory`); it checkpoints through :mod:`ptm_ros.tools.checkpoint`, writes files
through :mod:`ptm_ros.tools.outputs` and matches scans in the worker processes of
:mod:`ptm_ros.tools.workers` (kiss-icp's ``pipeline.py`` plays the same role). The detector and filter
nodes drive the same core code on live messages.

Files :func:`run_offline` writes into ``DIR``: those of :mod:`ptm_ros.tools.outputs`
(:data:`~ptm_ros.tools.outputs.OUTPUT_FILES` names them; all but the map and the state through
:func:`~ptm_ros.tools.outputs.write_outputs`, which ``ptm-bringup`` calls on what the nodes published, so
that both tools write one set of outputs, issue #24). The map is drawn along the smoothed trajectory of the
MAP topology (:func:`map_trajectory`); ``filter_state.npz`` is the RBPF's state, with a
:class:`~ptm_ros.tools.checkpoint.RunCheckpoint` that saves (``ptm-run --autosave N``; its ``path`` may lie
elsewhere); a checkpoint that resumes continues from it (:func:`run_offline`). ``timing`` adds
``smoothing_s`` and ``map_s`` to ``wall_s`` (bag reading, detection and inference).
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ptm_ros.config import PtmConfig
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.factories import cached, detector_kind, make_extractor, make_registrar, with_detector_kind
from ptm_ros.io.bag import OdometryData, RunData, read_run
from ptm_ros.io.groundtruth import (
    SIM_FILENAME,
    GroundTruthTrajectory,
    load_ground_truth,
    run_ground_truth_problem,
    with_placed_landmarks,
)
from ptm_ros.maps.refinement import Mapper
from ptm_ros.model.partitions import Labels
from ptm_ros.model.visits import Visit
from ptm_ros.perception.landmarks import IMAGE, ODOM, SCAN, VisitExtractor, diagnostics_dict, with_input_skips
from ptm_ros.perception.laser import WorkerPool
from ptm_ros.perception.surprise import surprise_trace
from ptm_ros.reporting.chain_trace import split_chain_trace
from ptm_ros.session import FilterSession, Progress, build_ptm, filter_visits, infer, require_rbpf
from ptm_ros.tools.checkpoint import (
    RunCheckpoint,
    _checkpoint,
    _load_run_state,
    check_state_config,
    run_state_meta,
)
from ptm_ros.tools.outputs import (
    OUTPUT_FILES,
    MetricMap,
    RunResult,
    class_grid,
    occupancy_grid,
    provenance,
    run_odometry,
    write_occupancy_map,
    write_outputs,
)
from ptm_ros.tools.progress import Phases
from ptm_ros.tools.workers import RegistrationPool

if TYPE_CHECKING:
    from ptm_ros.model.geometry import Registrar


def run_sensors(run: RunData) -> dict[str, bool]:
    """Which sensor streams a recorded run has (keyword arguments of :func:`detector_kind`)."""
    return {
        "has_scans": run.scans is not None and len(run.scans.stamps) > 0,
        "has_images": run.images is not None and len(run.images.images) > 0,
    }


def merged_messages(run: RunData) -> Iterator[tuple[float, int, int]]:
    """(stamp, topic, index) of every message of a run in stamp order (odometry first on ties), the
    order in which a live robot's messages arrive."""
    streams = []
    for topic, data in ((ODOM, run.odometry), (SCAN, run.scans), (IMAGE, run.images)):
        if data is not None and len(data.stamps):
            streams.append([(float(t), topic, k) for k, t in enumerate(data.stamps)])
    return heapq.merge(*streams)


def run_extractor(
    run: RunData,
    config: PtmConfig,
    schedule: Sequence[float] | None = None,
    patches: WorkerPool | None = None,
) -> VisitExtractor:
    """A fresh visit extractor for a recorded run: the configured detector or the default for its
    sensors (:func:`detector_kind`), scans and panoramas used when the run has them (``schedule``: the
    ``ground-truth`` detector's stamps; ``patches``: where the patches are built, here by default)."""
    sensors = run_sensors(run)
    return make_extractor(
        config,
        detector_kind(config, **sensors),
        use_scans=sensors["has_scans"],
        use_images=sensors["has_images"],
        record_corrections=True,
        schedule=schedule,
        patches=patches,
    )


def ground_truth_landmarks(
    truth: GroundTruthTrajectory | None, config: PtmConfig, span: tuple[float, float]
) -> GroundTruthTrajectory:
    """The ground truth of a ``ground-truth`` detector run, with its landmarks and their visits within
    the odometry's time ``span`` (:func:`ptm_ros.io.groundtruth.with_placed_landmarks`; the visit stamps
    are its passages').

    Raises:
        ConfigError: no ground truth.
        DataError: no visit within ``span`` (a ground truth of another run, or on another clock).
    """
    if truth is None:
        msg = (
            "detector 'ground-truth' needs the run's ground truth: pass --ground-truth FILE "
            "(a simulated bag's ground_truth.json is found by itself)"
        )
        raise ConfigError(msg)
    placed = with_placed_landmarks(truth, config.detector.ground_truth)
    inside = tuple(p for p in placed.passages if span[0] <= p.stamp <= span[1])
    if not inside:
        first, last = placed.passages[0].stamp, placed.passages[-1].stamp
        msg = (
            f"the ground truth's landmark visits ({first:.3f} … {last:.3f} s) all lie outside the bag's "
            f"odometry ({span[0]:.3f} … {span[1]:.3f} s): wrong ground-truth file or stamps on another clock?"
        )
        raise DataError(msg)
    return replace(placed, passages=inside)


def corrected_odometry(run: RunData, extractor: VisitExtractor) -> np.ndarray:
    """The run's odometry as the visits saw it: wheel odometry carried by the extractor's laser-odometry
    corrections (:func:`ptm_ros.perception.laser_odometry.apply_corrections`); the wheel odometry without
    them."""
    from ptm_ros.perception.laser_odometry import apply_corrections, scan_time_poses

    odom = run_odometry(run)
    wheel = scan_time_poses(odom.stamps, odom.poses, extractor.time_offset)
    if not extractor.corrections:
        return wheel
    stamps = [t for t, _ in extractor.corrections]
    return apply_corrections(odom.stamps, wheel, stamps, [c for _, c in extractor.corrections])


def detect_visits(
    run: RunData,
    config: PtmConfig,
    diagnostics: dict[str, Any] | None = None,
    *,
    extractor: VisitExtractor | None = None,
    progress: Progress | None = None,
) -> list[Visit]:
    """Landmark visits of a recorded run, with their appearance signatures and laser patches.

    Feeds the run's messages in stamp order through :class:`ptm_ros.perception.landmarks.VisitExtractor`, the
    same object the detector node uses (``extractor``, a fresh one, else :func:`run_extractor`; pass one to
    read its detector's state afterwards); ``diagnostics`` (if given) receives the extractor's counters;
    ``progress`` wraps the messages (it receives their iterator and number).
    """
    odom = run_odometry(run)
    if extractor is None:
        extractor = run_extractor(run, config)
    visits: list[Visit] = []
    messages: Iterable[tuple[float, int, int]] = merged_messages(run)
    if progress is not None:
        total = sum(len(d.stamps) for d in (run.odometry, run.scans, run.images) if d is not None)
        messages = progress(messages, total)
    scans, images = run.scans, run.images  # merged_messages yields a topic only when its stream exists
    for _, topic, k in messages:
        if topic == ODOM:
            visits += extractor.on_odometry(odom.stamps[k], odom.poses[k])
        elif topic == SCAN and scans is not None:
            sc = scans
            visits += extractor.on_scan(
                sc.stamps[k],
                sc.ranges[k],
                sc.angle_min[k],
                sc.angle_increment[k],
                sc.range_min[k],
                sc.range_max[k],
            )
        elif topic == IMAGE and images is not None:
            visits += extractor.on_image(images.stamps[k], images.images[k])
    visits += extractor.flush()
    if diagnostics is not None:
        diagnostics.update(run_diagnostics(run, extractor))
    return visits


def run_diagnostics(run: RunData, extractor: VisitExtractor) -> dict[str, Any]:
    """The input counters of a recorded run (ptm.json's ``diagnostics``): the extractor's, with the
    messages the bag reader skipped added to ``skipped`` under the same reasons as the nodes'
    (:func:`ptm_ros.io.bag.read_run`), and ``read_skipped`` the reader's share of them."""
    diag = with_input_skips(diagnostics_dict(extractor.diagnostics), run.skipped)
    if extractor.time_offset_estimate is not None:
        diag["time_offset"] = extractor.time_offset_estimate.as_dict()
    return diag


def find_ground_truth(bag: Path) -> Path | None:
    """The simulator's ground truth stored beside or inside the bag directory, if any."""
    for cand in (bag / SIM_FILENAME, bag.parent / f"{bag.name}.{SIM_FILENAME}"):
        if cand.is_file():
            return cand
    return None


def run_offline(
    bag: str | Path,
    out_dir: str | Path,
    config: PtmConfig,
    *,
    ground_truth: str | Path | None = None,
    progress: Progress | None = None,
    write_report: bool = True,
    write_map: bool = True,
    checkpoint: RunCheckpoint | None = None,
    log: Callable[[str], None] | None = None,
    write_trace: bool = False,
    phases: Phases | None = None,
    jobs: int = 1,
    force: bool = False,
) -> RunResult:
    """Bag in, the files of the module docstring out (the score when a ground truth is known: the
    ``ground_truth`` file, else the simulator's beside the bag); ``write_map=False`` skips the
    occupancy map files. ``jobs`` > 1: the visits' patches, the filter's registrations, the refinement's
    scan matches and the report's figures are made in that many worker processes
    (:class:`RegistrationPool`; the same files).

    ``checkpoint`` (RBPF only) saves the filter's state along the way and/or resumes from it: the state
    is the filter session's (:meth:`ptm_ros.session.FilterSession.state_dict`: the filter, the
    registration cache and its counters); its meta data :func:`run_state_meta`. A resumed run extracts
    the visits again, refuses a state of another run (:func:`check_state_config`,
    :func:`check_run_state`), fits the models on all visits as an uninterrupted run does, and continues
    the filter with the visits not yet seen: the same ``ptm.json`` but for the timings. ``log`` receives
    progress notes (resumed, started afresh) and the route graph's rerouted and dropped edges
    (:func:`route_notes`).

    ``phases`` (:class:`ptm_ros.tools.progress.Phases`) shows a progress bar per phase: reading the bag,
    the landmark visits, the inference (the filter's visits or the enumeration's topologies, and MCMC's
    sweeps), the smoothing, the scores, the map, the route graph and the report; ``progress``, when
    given, replaces its bar over the filter's visits.

    MCMC's cold chains: ``ptm.json`` keeps their summary
    (:func:`ptm_ros.reporting.chain_trace.split_chain_trace`); ``write_trace`` also writes their full states
    to ``mcmc_trace.json``, from which the report draws the SRQ plot.

    The ground truth is judged right after the bag is read, before the heavy work: one that looks like
    another run's (:func:`ptm_ros.io.groundtruth.run_ground_truth_problem`: less than half of the bag's
    odometry inside its time span, or the odometry not moving as it does; ``ptm-eval``'s rule and
    thresholds) is refused with a :class:`DataError` naming the figures, unless ``force`` (then ``log``
    receives the problem and the run goes on with it).
    """
    with RegistrationPool(jobs) as pool:
        return _run_offline(
            bag,
            out_dir,
            config,
            ground_truth=ground_truth,
            progress=progress,
            write_report=write_report,
            write_map=write_map,
            checkpoint=checkpoint,
            log=log,
            write_trace=write_trace,
            phases=phases,
            force=force,
            pool=pool,
        )


def _run_offline(
    bag: str | Path,
    out_dir: str | Path,
    config: PtmConfig,
    *,
    ground_truth: str | Path | None,
    progress: Progress | None,
    write_report: bool,
    write_map: bool,
    checkpoint: RunCheckpoint | None,
    log: Callable[[str], None] | None,
    write_trace: bool,
    phases: Phases | None,
    force: bool,
    pool: RegistrationPool,
) -> RunResult:
    t0 = time.perf_counter()
    ph = phases if phases is not None else Phases(quiet=True)
    bag = Path(bag)
    out = Path(out_dir)
    if checkpoint is not None:
        require_rbpf(config, "saving and resuming the filter state (--autosave/--resume)")
    saved = _load_run_state(checkpoint, log) if checkpoint is not None else None
    gt = Path(ground_truth) if ground_truth is not None else find_ground_truth(bag)
    truth = load_ground_truth(gt) if gt is not None else None  # a bad file fails before the long part
    topics = config.topics
    run = read_run(
        bag,
        odom_topic=topics.odom,
        scan_topic=topics.scan,
        image_topic=topics.panorama,
        require=(topics.odom,),
        appearance=config.model.appearance,
        progress=ph.wrap("reading the bag", "msg"),
    )
    if truth is not None:  # another run's ground truth fails now, not after the inference
        check_ground_truth_of_run(truth, run_odometry(run), force=force, log=log)
    sensors = run_sensors(run)
    used = with_detector_kind(config, **sensors)
    schedule = None
    if used.detector.kind == "ground-truth":
        odom_stamps = run_odometry(run).stamps
        truth = ground_truth_landmarks(truth, config, (float(odom_stamps[0]), float(odom_stamps[-1])))
        schedule = [p.stamp for p in truth.passages]
    if saved is not None and checkpoint is not None:
        check_state_config(saved[1], used, checkpoint.path)
    diag: dict[str, Any] = {}
    extractor = run_extractor(run, config, schedule, patches=pool.workers)
    visits = detect_visits(run, config, diag, extractor=extractor, progress=ph.wrap("landmark visits", "msg"))
    method = config.inference.method
    if progress is None:
        name, unit = {
            "exact": ("enumeration", "topology"),
            "mcmc": ("particle filter (MCMC's starts)", "visit"),
        }.get(method, ("particle filter", "visit"))
        progress = ph.wrap(name, unit)
    session, resumed = None, 0
    if config.inference.method == "rbpf":
        session = FilterSession(config, fitted_to=visits, workers=pool.workers)
        registrar = session.registrar
        if checkpoint is not None:
            resumed, save = _checkpoint(
                session, checkpoint, saved, meta=run_state_meta(used, bag, visits), visits=visits
            )
            if resumed and log is not None:
                log(f"resumed from {checkpoint.path}: {resumed} of {len(visits)} visits already filtered")
            filter_visits(session, visits, progress=progress, save=save, every=max(checkpoint.every, 1))
    else:
        registrar = cached(make_registrar(visits, config, diag)) if config.model.use_laser else None
    with ph.counter("MCMC sweeps", "sweep") as sweeps:
        result = infer(visits, config, session=session, registrar=registrar, progress=progress, sweeps=sweeps)
    wall = time.perf_counter() - t0
    frame_id = run.odometry.frame_id if run.odometry is not None else "odom"
    ptm = build_ptm(
        visits,
        result,
        used,
        frame_id=frame_id or "odom",
        wall_s=wall,
        **provenance(bag, used),
        diagnostics=diag,
    )
    ptm, chain_trace = split_chain_trace(ptm, trace_file=OUTPUT_FILES["mcmc_trace"] if write_trace else None)
    if write_trace and chain_trace is None and log is not None:
        log(f"--trace: method {config.inference.method} has no MCMC chains: no {OUTPUT_FILES['mcmc_trace']}")
    want_map = write_map and sensors["has_scans"]
    timing = dict(ptm.timing)
    traj = None
    if write_report or want_map or truth is not None:
        t1 = time.perf_counter()
        with ph.step("smoothing"):
            base = corrected_odometry(run, extractor)
            traj = map_trajectory(
                run, visits, ptm.map_topology.labels, config, registrar, odometry=base, mapper=pool
            )
        timing["smoothing_s"] = time.perf_counter() - t1
    map_files: dict[str, Path] = {}
    walls = None  # the map's classes, for the map's quality and the route graph
    if want_map and traj is not None:
        t1 = time.perf_counter()
        with ph.step("map"):
            grid = occupancy_grid(run, traj, config)
            map_files = write_occupancy_map(run, traj, out, config, grid=grid)
        timing["map_s"] = time.perf_counter() - t1
        walls = class_grid(grid, config) if grid is not None else None
    extra = dict(ptm.extra)
    if session is not None:  # the laser registrations' counters, after the smoothing's registrations
        extra["diagnostics"] = {**diag, **session.registrations}
    written = write_outputs(
        out,
        replace(ptm, timing=timing, extra=extra),
        used,
        run,
        MetricMap(trajectory=traj, walls=walls, files=map_files),
        truth=truth,
        truth_file=gt,
        save_truth=schedule is not None,  # what ptm-eval needs for the true-topology mass
        surprise=surprise_trace(extractor.detector),
        write_report=write_report,
        title=f"PTM of {bag.name}",
        log=log,
        chain_trace=chain_trace if write_trace else None,
        phases=ph,
        workers=pool.workers,
    )
    files = dict(written.files)
    if checkpoint is not None and checkpoint.every:
        files["state"] = checkpoint.path
    return replace(written, diagnostics=diag, files=files, resumed_visits=resumed)


def check_ground_truth_of_run(
    truth: GroundTruthTrajectory,
    odometry: OdometryData,
    *,
    force: bool = False,
    log: Callable[[str], None] | None = None,
) -> None:
    """Refuse a ground truth that looks like another run's, judged on the run's ``odometry``
    (:func:`ptm_ros.io.groundtruth.run_ground_truth_problem`): a :class:`DataError` with the figures and
    the way round it; with ``force``, ``log`` receives the problem instead.

    Raises:
        DataError: the ground truth looks like another run's, and not ``force``.
    """
    _, problem = run_ground_truth_problem(truth, odometry.stamps, odometry.poses)
    if problem is None:
        return
    if not force:
        msg = f"{problem} (--force uses it anyway)"
        raise DataError(msg)
    if log is not None:
        log(f"--force: the ground truth is used although {problem}")


def map_trajectory(
    run: RunData,
    visits: Sequence[Visit],
    labels: Labels,
    config: PtmConfig,
    registrar: Registrar | None,
    *,
    odometry: np.ndarray | None = None,
    mapper: Mapper = map,
) -> np.ndarray:
    """The odometry trajectory smoothed for a topology and refined by the run's scans
    (:func:`ptm_ros.maps.mapping.topology_trajectory`, the function the map publisher's online map calls; the
    ``refinement`` section of ``config``). ``odometry`` ``(T, 3)`` at the run's odometry stamps is
    the trajectory the visits' poses come from (:func:`corrected_odometry`; default: the run's)."""
    from ptm_ros.maps.mapping import topology_trajectory

    odom = run_odometry(run)
    base = odom.poses if odometry is None else odometry
    return topology_trajectory(
        odom.stamps,
        base,
        labels,
        visits,
        config.model,
        registration=registrar,
        scans=run.scans,
        refinement=config.refinement,
        laser=config.laser,
        mapper=mapper,
    )
