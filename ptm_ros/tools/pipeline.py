"""The offline pipeline behind ``ptm-run``: bag → landmark visits → PTM → ptm.json, maps, report, score.

The science is in the core modules and the orchestration in :mod:`ptm_ros.session` (the filter session,
the estimators, the ptm.json content) and :mod:`ptm_ros.factories` (detector, extractor, registrar);
this module only loops over a recorded run, times, checkpoints and writes files (kiss-icp's
``pipeline.py`` plays the same role). The detector and filter nodes drive the same core code on live
messages.

Files :func:`run_offline` writes into ``DIR`` (:data:`OUTPUT_FILES` names them; all but the map and the
state through :func:`write_outputs`, which ``ptm-bringup`` calls on what the nodes published, so that both
tools write one set of outputs, issue #24):

* ``ptm.json`` (CONTRACT.md schema) and ``config.yaml`` (the parameters used);
* ``route_graph.geojson`` — the PTM as a nav2 route graph (:mod:`ptm_ros.maps.routes`), always; with a map,
  its nodes on the map's trajectory and its edges kept off the map's walls (:func:`write_route_graph`);
* ``map.pgm`` (``map_scale.png`` with ``occupancy.mode: scale``) + ``map.yaml`` (nav2 ``map_server``) and
  ``map.png`` — the occupancy grid
  (:mod:`ptm_ros.maps.occupancy`, parameters ``occupancy``) of the bag's scans placed along the smoothed
  trajectory of the MAP topology (:func:`map_trajectory`, interpolated at the scan stamps); only when the
  bag has scans and maps are wanted (``ptm-run --no-map`` skips them);
* ``report.{md,html}`` with figures (the map, and the detector's surprise trace for a surprise detector);
* ``mcmc_trace.json`` — with ``write_trace`` (``ptm-run --trace``) and MCMC: the cold chains' full
  states (:func:`ptm_ros.reporting.report.split_chain_trace`; ``ptm.json`` keeps their summary);
* ``filter_state.npz`` — the RBPF's state, with a :class:`RunCheckpoint` that saves (``ptm-run
  --autosave N``; its ``path`` may lie elsewhere); a checkpoint that resumes continues from it
  (:func:`run_offline`);
* ``ground_truth.json`` — with the ``ground-truth`` detector (landmarks fixed along the true path, the
  thesis' Intel protocol, :func:`ground_truth_landmarks`): the ground truth with the landmarks it placed
  and their visits (simulator schema), so that ``ptm-eval DIR/ptm.json --ground-truth DIR`` scores the
  mass on the true topology as ``ptm-run`` did.

With a ground truth, ``ptm.json`` carries ``extra["trajectory_error"]`` (:func:`trajectory_errors`):
``ate_smoothed_m`` and ``ate_odometry_m``, the absolute trajectory errors
(:func:`ptm_ros.scoring.evaluation.absolute_trajectory_error`, RMSE after the best rigid 2-D alignment) of the
smoothed MAP trajectory and of the bag's raw odometry, both at the odometry stamps inside the ground
truth's time span (``poses`` of them), the rigid alignment of the former onto the ground truth
(``alignment``: ``theta``, ``x``, ``y``) and the ground-truth file; with a map, ``extra["map_quality"]``
(:func:`map_quality_against`): the map against the same scans placed at the true poses
(:mod:`ptm_ros.maps.map_quality`: free-space leak, wall precision and recall, free-area ratio). ``timing``
adds ``smoothing_s`` and ``map_s`` to ``wall_s`` (bag reading, detection and inference).
"""

from __future__ import annotations

import functools
import heapq
import json
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from multiprocessing.connection import wait
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from ptm_ros.config import PtmConfig, save_config
from ptm_ros.configio import to_dict
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.factories import cached, detector_kind, make_extractor, make_registrar, with_detector_kind
from ptm_ros.io.bag import OdometryData, RunData, read_run
from ptm_ros.io.groundtruth import (
    SIM_FILENAME,
    GroundTruthTrajectory,
    interpolate_pose,
    load_ground_truth,
    run_ground_truth_problem,
    save_sim_gt,
    with_placed_landmarks,
)
from ptm_ros.maps.occupancy import MAP_STEM
from ptm_ros.maps.refinement import Mapper, RegistrationJob
from ptm_ros.model.partitions import Labels
from ptm_ros.model.ptm import Ptm, save_ptm
from ptm_ros.model.visits import Visit
from ptm_ros.nodes.filter_inbox import NODE_NAME, NODE_STATE_SCHEMA
from ptm_ros.perception.landmarks import IMAGE, ODOM, SCAN, VisitExtractor, diagnostics_dict, with_input_skips
from ptm_ros.perception.laser import Registration, WorkerPool
from ptm_ros.perception.surprise import surprise_trace
from ptm_ros.reporting.doubts import doubt_lines, find_doubts
from ptm_ros.reporting.report import save_chain_trace, split_chain_trace
from ptm_ros.session import (
    RUN_STATE_TOOL,
    SESSION_STATE_SCHEMA,
    VERSUS_KEY,
    FilterSession,
    Progress,
    build_ptm,
    filter_visits,
    infer,
    require_rbpf,
)
from ptm_ros.tools.progress import Phases

if TYPE_CHECKING:
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.routes import RouteConfig
    from ptm_ros.model.geometry import Registrar
    from ptm_ros.perception.surprise import SurpriseTrace

_T = TypeVar("_T")

#: Names of the files :func:`run_offline` writes (keys of :attr:`RunResult.files`).
OUTPUT_FILES = {
    "ptm": "ptm.json",
    "config": "config.yaml",
    "route_graph": "route_graph.geojson",
    "map_image": f"{MAP_STEM}.pgm",  # the map_server image: MAP_IMAGES[occupancy.mode]
    "map_yaml": f"{MAP_STEM}.yaml",
    "map_png": f"{MAP_STEM}.png",
    "state": "filter_state.npz",
    "ground_truth": SIM_FILENAME,
    "mcmc_trace": "mcmc_trace.json",
}
#: Key of ``Ptm.extra`` holding the absolute trajectory errors (module docstring).
TRAJECTORY_ERROR_KEY = "trajectory_error"
#: Key of ``Ptm.extra`` holding the map's quality against the ground truth (module docstring).
MAP_QUALITY_KEY = "map_quality"


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


def run_odometry(run: RunData) -> OdometryData:
    """The run's odometry stream; :class:`DataError` when the bag has none."""
    odom = run.odometry
    if odom is None or len(odom.stamps) == 0:
        msg = f"bag {run.path} has no odometry"
        raise DataError(msg)
    return odom


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


@dataclass(frozen=True)
class RunResult:
    """What ``run_offline`` wrote: ``files`` maps the keys of :data:`OUTPUT_FILES` to the files written;
    ``trajectory_error`` is ``ptm.extra["trajectory_error"]`` (None without a ground truth);
    ``trajectory`` the ``(T, 3)`` smoothed MAP trajectory at the run's odometry stamps that the map was
    drawn along (None when none was drawn), so that a caller can redraw or rescore the map."""

    ptm: Ptm
    ptm_path: Path
    report_path: Path | None
    score: Any | None
    diagnostics: dict[str, Any]
    files: Mapping[str, Path] = field(default_factory=dict)
    trajectory_error: Mapping[str, Any] | None = None
    resumed_visits: int = 0
    trajectory: np.ndarray | None = None


@dataclass(frozen=True)
class RunCheckpoint:
    """Saving and resuming :func:`run_offline`'s RBPF (``ptm-run --autosave/--resume``, issue #8).

    Attributes:
        path: the state file (:func:`ptm_ros.inference.persistence.save_filter_state`, written atomically).
        every: save after every ``every``-th visit and after the last one; 0: never save.
        resume: continue from ``path`` when it exists, once :func:`check_run_state` accepts it (else
            start afresh).
    """

    path: Path
    every: int = 0
    resume: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 0:
            msg = f"RunCheckpoint.every must be an integer >= 0 (visits between saves), got {self.every!r}"
            raise ConfigError(msg)
        if self.every == 0 and not self.resume:
            msg = "RunCheckpoint neither saves (every >= 1) nor resumes: nothing to do"
            raise ConfigError(msg)


def run_state_meta(used: PtmConfig, bag: Path, visits: Sequence[Visit]) -> dict[str, Any]:
    """What :func:`run_offline`'s state file records about its run: the configuration used (as written
    to ``config.yaml``), the bag, the number of visits and their fingerprint."""
    from ptm_ros.inference.persistence import visits_fingerprint

    return {
        "tool": RUN_STATE_TOOL,
        "config": to_dict(used),
        "bag": str(bag),
        "n_visits": len(visits),
        "visits_sha256": visits_fingerprint(visits),
    }


def check_state_config(meta: Mapping[str, Any], used: PtmConfig, path: Path) -> None:
    """Refuse a state file that neither ``ptm-run`` nor the ``topology_filter`` node wrote, or that was
    written with another configuration.

    Raises:
        DataError: written by another program.
        ConfigError: made with another configuration (the differing parameters are named).
    """
    from ptm_ros.inference.persistence import differences

    if meta.get("tool") != RUN_STATE_TOOL and meta.get("node") != NODE_NAME:
        writer = meta.get("tool") or meta.get("node") or "an unknown program"
        msg = f"cannot resume from {path}: written by {writer}, not {RUN_STATE_TOOL} or the {NODE_NAME} node"
        raise DataError(msg)
    if not isinstance(meta.get("config"), Mapping):
        msg = f"cannot resume from {path}: its meta data lack the configuration"
        raise DataError(msg)
    diff = differences(meta["config"], to_dict(used))
    if diff:
        more = f" and {len(diff) - 5} more" if len(diff) > 5 else ""
        msg = (
            f"cannot resume from {path}: it was made with other parameters (differing: "
            f"{', '.join(diff[:5])}{more}); use the same ones, or start afresh without resuming"
        )
        raise ConfigError(msg)


def session_state_of(state: Mapping[str, Any], path: Path) -> Mapping[str, Any]:
    """The filter session's state in a state file: the file's content for ``ptm-run``'s, its ``session``
    for the ``topology_filter`` node's (one session schema, :data:`~ptm_ros.session.SESSION_STATE_SCHEMA`).

    Raises:
        DataError: a node state without a session.
    """
    if state.get("schema") != NODE_STATE_SCHEMA:
        return state
    session = state.get("session")
    if not isinstance(session, Mapping):
        msg = f"cannot resume from {path}: a {NODE_NAME} state without its filter session"
        raise DataError(msg)
    return session


def check_run_state(
    state: Mapping[str, Any], meta: Mapping[str, Any], visits: Sequence[Visit], path: Path
) -> list[Visit]:
    """Check that a state belongs to this run: its saved visits equal to the first ones extracted now
    (extraction is deterministic, offline and in the detector node alike); for ``ptm-run``'s own state
    also the same number of visits and the same visit fingerprint.

    Returns:
        The saved visits.

    Raises:
        DataError: another run's state, or a malformed one.
    """
    from ptm_ros.inference.persistence import first_different_visit, visit_from_state, visits_fingerprint

    where = f"cannot resume from {path}"
    if meta.get("tool") == RUN_STATE_TOOL:  # ptm-run's own state also records the whole run's visits
        if meta.get("n_visits") != len(visits):
            msg = (
                f"{where}: it belongs to a run of {meta.get('n_visits')} landmark visits, this one has "
                f"{len(visits)} (another bag or detector?)"
            )
            raise DataError(msg)
        if meta.get("visits_sha256") != visits_fingerprint(visits):
            msg = f"{where}: its visits differ from this bag's (another bag?)"
            raise DataError(msg)
    if state.get("schema") != SESSION_STATE_SCHEMA:
        schema = state.get("schema")
        msg = f"{where}: not a filter session state (schema {schema!r}, not {SESSION_STATE_SCHEMA!r})"
        raise DataError(msg)
    try:
        saved = [visit_from_state(d) for d in state["visits"]]
    except (KeyError, TypeError) as err:
        msg = f"{where}: malformed state ({type(err).__name__}: {err})"
        raise DataError(msg) from err
    if len(saved) > len(visits):
        msg = f"{where}: it holds {len(saved)} visits, this run has {len(visits)} (another bag?)"
        raise DataError(msg)
    k = first_different_visit(saved, visits)
    if k is not None:
        msg = f"{where}: its visit {k} differs from this run's"
        raise DataError(msg)
    return saved


def _load_run_state(
    checkpoint: RunCheckpoint, log: Callable[[str], None] | None
) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """``(state, meta)`` of the checkpoint's file when resuming from an existing one, else None."""
    from ptm_ros.inference.persistence import load_filter_state

    if not checkpoint.resume:
        return None
    if not checkpoint.path.exists():
        if log is not None:
            log(f"no state file {checkpoint.path} yet: starting afresh")
        return None
    return load_filter_state(checkpoint.path)


def provenance(bag: Path, used: PtmConfig) -> dict[str, str]:
    """What ``ptm.json`` says about where its run came from: the bag (as given) and the detector used."""
    return {"bag": str(bag), "detector": str(used.detector.kind)}


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

    MCMC's cold chains: ``ptm.json`` keeps their summary (:func:`ptm_ros.reporting.report.split_chain_trace`);
    ``write_trace`` also writes their full states to ``mcmc_trace.json``, from which the report draws the
    SRQ plot.

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


@dataclass(frozen=True)
class MetricMap:
    """The metric map that goes with a PTM, however it was made (``ptm-run`` draws it from the bag, the
    map publisher online from what the detector sent it).

    Attributes:
        trajectory: ``(T, 3)`` the smoothed MAP trajectory at the run's odometry stamps
            (:func:`map_trajectory`); None when none was drawn.
        walls: the classes of ``map.pgm`` (:func:`class_grid`, :func:`map_classes`); None without a map.
        files: the map files written (keys ``map_image``, ``map_yaml``, ``map_png`` of :data:`OUTPUT_FILES`).
    """

    trajectory: np.ndarray | None = None
    walls: ClassGrid | None = None
    files: Mapping[str, Path] = field(default_factory=dict)


def saved_map(
    run: RunData, files: Mapping[str, Path], trajectory: tuple[np.ndarray, np.ndarray] | None
) -> MetricMap:
    """The :class:`MetricMap` of a map drawn elsewhere (the map publisher's, saved by its ``~/save_map``):
    its ``files`` (keys ``map_image``, ``map_yaml``, ``map_png``; none without a map), the classes of
    ``map.yaml`` read back (:func:`map_classes`), and the ``trajectory`` ``(stamps (K,), poses (K, 3))``
    it was drawn along at the run's odometry stamps (:func:`ptm_ros.model.geometry.interpolate_poses`: exact
    where the run's stamps are among the trajectory's, as when the map was drawn from every sample)."""
    from ptm_ros.model.geometry import interpolate_poses

    traj = None
    if trajectory is not None and len(trajectory[0]):
        traj = interpolate_poses(trajectory[0], trajectory[1], run_odometry(run).stamps)
    walls = map_classes(files["map_yaml"]) if "map_yaml" in files else None
    return MetricMap(trajectory=traj, walls=walls, files=dict(files))


def map_classes(yaml_path: Path) -> ClassGrid:
    """The classes of a saved map (``map.yaml`` + its image, :func:`ptm_ros.maps.occupancy.load_map`): the
    :func:`class_grid` of the grid it was saved from, in either map_server mode."""
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.occupancy import load_map

    saved = load_map(yaml_path)
    return ClassGrid(saved.classes(), saved.origin, saved.resolution)


def write_outputs(
    out: Path,
    ptm: Ptm,
    used: PtmConfig,
    run: RunData,
    metric: MetricMap,
    *,
    truth: GroundTruthTrajectory | None = None,
    truth_file: Path | None = None,
    save_truth: bool = False,
    surprise: SurpriseTrace | None = None,
    write_report: bool = True,
    title: str,
    log: Callable[[str], None] | None = None,
    chain_trace: Mapping[str, Any] | None = None,
    phases: Phases | None = None,
    workers: WorkerPool | None = None,
) -> RunResult:
    """Everything ``ptm-run`` and ``ptm-bringup`` write beside a PTM, from the PTM, the configuration
    ``used``, the recorded run and the run's metric map (files of the module docstring):

    * with a ground truth ``truth`` (read from ``truth_file``) and a trajectory, ``ptm.extra`` gains
      :data:`TRAJECTORY_ERROR_KEY` (:func:`trajectory_errors`) and, with a map, :data:`MAP_QUALITY_KEY`
      (:func:`map_quality_against`);
    * ``ptm.json``, ``config.yaml``, ``route_graph.geojson`` (:func:`write_route_graph`, on the map's
      walls and trajectory when there is a map), ``ground_truth.json`` when ``save_truth`` (the
      ``ground-truth`` detector's landmarks);
    * with ``write_report``, the report: the score against ``truth``, the detector's ``surprise`` trace
      (:func:`ptm_ros.perception.surprise.surprise_trace`), the map image and the notes (doubts, trajectory
      errors, map quality, inference), the trajectory drawn under the topologies (the raw odometry without
      one).

    * ``mcmc_trace.json``: the MCMC ``chain_trace`` (:func:`ptm_ros.reporting.report.split_chain_trace`), if
    given,
      from which the report draws its SRQ plot.

    ``phases`` shows the map quality, the route graph and the report as progress bars (none by default);
    ``workers`` (optional) draws the report's figures.
    ``RunResult.diagnostics`` is ``ptm.extra["diagnostics"]`` (callers with the extractor's replace it).
    """
    ph = phases if phases is not None else Phases(quiet=True)
    extra = dict(ptm.extra)
    traj, walls = metric.trajectory, metric.walls
    reference, alignment = None, None
    if truth is not None and traj is not None:
        ate = trajectory_errors(run, traj, truth)
        if ate is not None:
            extra[TRAJECTORY_ERROR_KEY] = {**ate, "ground_truth": str(truth_file)}
            if walls is not None:
                with ph.step("map quality"):
                    alignment = ate["alignment"]
                    reference = reference_classes(run, truth, used)
                    quality = map_quality_against(run, walls, truth, alignment, used, reference=reference)
                if quality is not None:
                    extra[MAP_QUALITY_KEY] = quality
    ptm = replace(ptm, extra=extra)
    files = dict(metric.files)
    files["ptm"] = save_ptm(ptm, out / OUTPUT_FILES["ptm"])
    files["config"] = save_config(used, out / OUTPUT_FILES["config"])
    if chain_trace is not None:
        files["mcmc_trace"] = save_chain_trace(chain_trace, out / OUTPUT_FILES["mcmc_trace"])
    with ph.step("route graph"):
        files["route_graph"] = write_route_graph(
            ptm,
            out / OUTPUT_FILES["route_graph"],
            grid=walls,
            trajectory=(run_odometry(run).stamps, traj) if walls is not None and traj is not None else None,
            config=used.routes,
            log=log,
        )
    if save_truth and truth is not None:
        files["ground_truth"] = save_sim_gt(truth, out / OUTPUT_FILES["ground_truth"])
    score = score_against(ptm, truth) if truth is not None else None
    report = None
    if write_report:
        from ptm_ros.reporting.report import write_report as _write_report

        with ph.step("report"):
            report = _write_report(
                out,
                ptm,
                trajectory=traj if traj is not None else run_odometry(run).poses,
                score=score,
                surprise_trace=surprise,
                occupancy_map=files.get("map_png"),
                map_comparison=map_comparison(walls, reference, alignment, extra, files["route_graph"]),
                notes=doubt_lines(find_doubts(ptm))
                + greedy_notes(ptm, score.true_labels if score is not None else None)
                + ate_notes(extra.get(TRAJECTORY_ERROR_KEY))
                + map_quality_notes(extra.get(MAP_QUALITY_KEY))
                + inference_notes(ptm.inference),
                title=title,
                chain_trace=chain_trace,
                workers=workers,
            )
    return RunResult(
        ptm=ptm,
        ptm_path=files["ptm"],
        report_path=report,
        score=score,
        diagnostics=dict(extra.get("diagnostics") or {}),
        files=files,
        trajectory_error=extra.get(TRAJECTORY_ERROR_KEY),
        trajectory=traj,
    )


def _checkpoint(
    session: FilterSession,
    checkpoint: RunCheckpoint,
    saved: tuple[dict[str, Any], dict[str, Any]] | None,
    *,
    meta: dict[str, Any],
    visits: Sequence[Visit],
) -> tuple[int, Callable[[FilterSession], None] | None]:
    """Restore ``session`` from a saved state (checked against this run's ``visits``); the number of
    visits restored, and the saver of the session's state (:data:`~ptm_ros.session.SESSION_STATE_SCHEMA`,
    with ``meta``) that ``checkpoint`` asks for (None: it only resumes)."""
    from ptm_ros.inference.persistence import save_filter_state

    resumed = 0
    if saved is not None:
        content, saved_meta = saved
        state = session_state_of(content, checkpoint.path)
        resumed = len(check_run_state(state, saved_meta, visits, checkpoint.path))
        session.load_state(state)

    def save(s: FilterSession) -> None:
        checkpoint.path.parent.mkdir(parents=True, exist_ok=True)
        save_filter_state(checkpoint.path, s.state_dict(), meta=meta)

    return resumed, (save if checkpoint.every else None)


def trajectory_errors(
    run: RunData, trajectory: np.ndarray, truth: GroundTruthTrajectory
) -> dict[str, Any] | None:
    """Absolute trajectory errors (m) of ``trajectory (T, 3)`` (at the run's odometry stamps) and of the
    raw odometry against a ground truth, at the odometry stamps inside the ground truth's time span
    (its corrected poses interpolated there); None when fewer than two lie inside."""
    from ptm_ros.scoring.evaluation import absolute_trajectory_error, rigid_alignment

    paired = _paired_with_truth(run, trajectory, truth)
    if paired is None:
        return None
    inside, est_xy, true_xy = paired
    theta, t = rigid_alignment(est_xy, true_xy)
    return {
        "ate_smoothed_m": absolute_trajectory_error(est_xy, true_xy),
        "ate_odometry_m": absolute_trajectory_error(np.asarray(run_odometry(run).poses)[inside, :2], true_xy),
        "poses": int(np.count_nonzero(inside)),
        "alignment": {"theta": theta, "x": float(t[0]), "y": float(t[1])},
    }


def _paired_with_truth(
    run: RunData, trajectory: np.ndarray, truth: GroundTruthTrajectory
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The odometry stamps inside the ground truth's span (a mask), the trajectory's and the ground
    truth's positions there; None when fewer than two lie inside."""
    stamps = np.asarray(run_odometry(run).stamps, dtype=float)
    traj = np.asarray(trajectory, dtype=float)
    if traj.shape != (len(stamps), 3):
        msg = f"the trajectory has shape {traj.shape}, the run {len(stamps)} odometry poses"
        raise DataError(msg)
    inside = (stamps >= np.min(truth.stamps)) & (stamps <= np.max(truth.stamps))
    if np.count_nonzero(inside) < 2:
        return None
    return inside, traj[inside, :2], interpolate_pose(truth, stamps[inside])[:, :2]


def reference_grid(run: RunData, truth: GroundTruthTrajectory, config: PtmConfig) -> Any | None:
    """The map-quality reference (:mod:`ptm_ros.maps.map_quality`): the run's scans inside the ground
    truth's span placed at its poses, with ``config.occupancy`` but the beams without a return left out; None
    without a scan there."""
    from ptm_ros.maps.mapping import grid_along

    sc = run.scans
    if sc is None or len(sc.stamps) == 0:
        return None
    order = np.argsort(truth.stamps, kind="stable")
    cfg = replace(config.occupancy, missing_ray_length=0.0)
    return grid_along(truth.stamps[order], truth.poses_corrected[order], sc, cfg)


def reference_classes(run: RunData, truth: GroundTruthTrajectory, config: PtmConfig) -> ClassGrid | None:
    """:func:`reference_grid` as trinary classes (whatever ``occupancy.mode``) with its seen cells; None
    without a reference."""
    ref = reference_grid(run, truth, config)
    if ref is None:
        return None
    trinary = replace(config, occupancy=replace(config.occupancy, mode="trinary"))
    return replace(class_grid(ref, trinary), seen=ref.observed)


def map_quality_against(
    run: RunData,
    product: Any,
    truth: GroundTruthTrajectory,
    alignment: Mapping[str, float],
    config: PtmConfig,
    *,
    reference: ClassGrid | None = None,
) -> dict[str, Any] | None:
    """:func:`ptm_ros.maps.map_quality.map_quality` of a map (a
    :class:`~ptm_ros.maps.map_quality.ClassGrid` in the odometry frame) against :func:`reference_classes`
    (or ``reference``, made by it already), carried into the ground truth's frame by ``alignment`` (``theta``,
    ``x``, ``y``: :func:`trajectory_errors`' ATE alignment); None without a reference."""
    from ptm_ros.maps.map_quality import map_quality

    if reference is None:
        reference = reference_classes(run, truth, config)
    if reference is None:
        return None
    quality = map_quality(product, reference, theta=alignment["theta"], t=(alignment["x"], alignment["y"]))
    return quality.as_dict()


def map_comparison(
    walls: ClassGrid | None,
    reference: ClassGrid | None,
    alignment: Mapping[str, float] | None,
    extra: Mapping[str, Any],
    route_graph: Path,
) -> Any | None:
    """The report's side-by-side map figure (:class:`ptm_ros.reporting.report.MapComparison`): the map next to
    its ``reference`` carried by the ATE ``alignment`` when there is one, else next to the route graph written
    to ``route_graph``; None without a map."""
    from ptm_ros.reporting.report import MapComparison

    if walls is None:
        return None
    if reference is not None and alignment is not None:
        t = (float(alignment["x"]), float(alignment["y"]))
        quality = extra.get(MAP_QUALITY_KEY)
        return MapComparison(walls, reference, theta=float(alignment["theta"]), t=t, quality=quality)
    return MapComparison(walls, route_graph=json.loads(route_graph.read_text()))


def class_grid(grid: Any, config: PtmConfig) -> Any:
    """The trinary classes of an occupancy grid as its saved map reads back in ``occupancy.mode``
    (:func:`ptm_ros.maps.occupancy.cells`, :func:`~ptm_ros.maps.occupancy.classes_of`: in trinary mode
    :func:`~ptm_ros.maps.occupancy.trinary`) as a :class:`~ptm_ros.maps.map_quality.ClassGrid`."""
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.occupancy import cells, classes_of

    return ClassGrid(classes_of(cells(grid, config.occupancy)), grid.origin, grid.resolution)


def inference_notes(inference: Mapping[str, Any]) -> list[str]:
    """Report and console lines on how an estimator ended (``ptm.json``'s ``inference``): MCMC's
    convergence figures and its comparison with the particle filter; none for the other methods."""
    return mcmc_notes(inference) + versus_notes(inference.get(VERSUS_KEY))


def mcmc_notes(inference: Mapping[str, Any]) -> list[str]:
    """One line on an MCMC run's end: sweeps, evaluations, why it stopped, and the sample-doubling and
    chain-agreement figures, on the PTM (TV) and on the visit pairs' same-place probabilities."""
    if inference.get("method") != "mcmc":
        return []
    state = "converged" if inference["converged"] else f"not converged (stopped: {inference['stop_reason']})"
    chains = inference["chains"]
    fig = functools.partial(_figure, inference)
    return [
        f"MCMC: {inference['iterations']} sweeps of {chains} chain{'s' if chains != 1 else ''} from "
        f"{inference['initial']}, {inference['n_evaluated']} topologies evaluated, {state}; TV of sample "
        f"doubling {fig('doubling_tv')}, between chains {fig('chain_tv')}; largest change of a visit "
        f"pair's same-place probability: doubling {fig('doubling_pair')}, between chains {fig('chain_pair')}"
    ]


def _figure(values: Mapping[str, Any], key: str) -> str:
    """``values[key]`` to 3 decimals for a report line, "–" when missing."""
    v = values.get(key)
    return "–" if v is None else f"{v:.3f}"


def versus_notes(versus: Mapping[str, Any] | None) -> list[str]:
    """Report lines for MCMC's comparison with the particle filter it started from (``initial: rbpf``,
    :func:`compare_to_filter`); none without it."""
    if not versus:
        return []
    gain = versus["map_gain_nats"]
    same = (
        "the filter's MAP topology"
        if versus["map_equal"]
        else f"a MAP topology {gain:+.2f} nats from the filter's"
    )
    return [
        f"MCMC from the particle filter's {versus['rbpf_topologies']} topologies: {same} (batch posterior); "
        f"TV to the filter's PTM {versus['tv']:.3f} ({versus['tv_reweighted']:.3f} with the filter's "
        f"topologies re-weighted); same-place probabilities of {versus['pairs_in_play']} visit pairs "
        f"differ by {versus['pair_mean_diff']:.3f} on average, {versus['pairs_differing']} by more than 0.1"
    ]


def greedy_notes(ptm: Ptm, truth: Labels | None = None) -> list[str]:
    """A line on the greedy baseline's answer (ptm.json's ``greedy``, :func:`ptm_ros.model.ptm.ptm_greedy`):
    its topology and places and, against the true topology ``truth``, whether it is right and, if not, the
    decision where it went wrong (final: it never comes back); none without an answer."""
    from ptm_ros.model.ptm import ptm_greedy
    from ptm_ros.reporting.report import label_string
    from ptm_ros.scoring.evaluation import first_wrong_visit

    greedy = ptm_greedy(ptm)
    if greedy is None:
        return []
    line = (
        f"greedy baseline (nearest place on odometry, every decision final): {label_string(greedy, 40)}, "
        f"{max(greedy) + 1} places"
    )
    if truth is None:
        return [line]
    k = first_wrong_visit(greedy, truth)
    if k is None:
        return [f"{line}: the true topology"]
    j, t = greedy.index(greedy[k]), truth.index(truth[k])
    did = "opened a new place" if j == k else f"closed a loop onto the place of visit {j}"
    real = "a new place" if t == k else f"a return to the place of visit {t}"
    return [f"{line}: wrong, from visit {k} on: there it {did}, and visit {k} is {real}"]


def map_quality_notes(quality: Mapping[str, Any] | None) -> list[str]:
    """A report line for :func:`map_quality_against`'s figures (none without them)."""
    if not quality:
        return []
    fig = functools.partial(_figure, quality)
    return [
        f"occupancy map against the same scans at the true poses (aligned as for the ATE): free-space leak "
        f"{fig('leak')}, free-area ratio {fig('free_area_ratio')}, wall precision {fig('wall_precision')}, "
        f"wall recall {fig('wall_recall')}"
    ]


def ate_notes(ate: Mapping[str, Any] | None) -> list[str]:
    """Report lines for the trajectory errors of :func:`trajectory_errors` (none without them)."""
    if not ate:
        return []
    return [
        f"absolute trajectory error after rigid alignment, over {ate['poses']} odometry poses: smoothed "
        f"MAP trajectory {ate['ate_smoothed_m']:.3f} m, raw odometry {ate['ate_odometry_m']:.3f} m"
    ]


def occupancy_grid(run: RunData, trajectory: np.ndarray, config: PtmConfig) -> Any | None:
    """The occupancy grid of the run's scans placed along ``trajectory (T, 3)`` (at the odometry stamps):
    :func:`ptm_ros.maps.mapping.grid_along`, as the map publisher draws it online; None without a scan within
    the odometry's span."""
    from ptm_ros.maps.mapping import grid_along

    sc = run.scans
    if sc is None or len(sc.stamps) == 0:
        return None
    return grid_along(run_odometry(run).stamps, trajectory, sc, config.occupancy)


def write_occupancy_map(
    run: RunData, trajectory: np.ndarray, out: Path, config: PtmConfig, *, grid: Any | None = None
) -> dict[str, Path]:
    """The map_server image + ``map.yaml`` (nav2 map_server) and ``map.png`` (the grid with ``trajectory``
    over it) of :func:`occupancy_grid` (or of ``grid``, drawn from them already) in ``out``; nothing when the
    run has no usable scan."""
    from ptm_ros.maps.occupancy import save_map_files

    if grid is None:
        grid = occupancy_grid(run, trajectory, config)
    if grid is None:
        return {}
    image, yml, png = save_map_files(grid, out, config.occupancy, trajectory=trajectory)
    return {"map_image": image, "map_yaml": yml, "map_png": png}


def write_route_graph(
    ptm: Ptm,
    path: Path,
    *,
    grid: ClassGrid | None = None,
    trajectory: tuple[np.ndarray, np.ndarray] | None = None,
    config: RouteConfig | None = None,
    log: Callable[[str], None] | None = None,
) -> Path:
    """The PTM as a nav2 route graph (:func:`ptm_ros.maps.routes.route_graph`) at ``path``.

    ``grid``: the classes of the run's map (:func:`class_grid` of :func:`occupancy_grid`'s grid, the cells
    of ``map.pgm``) and ``trajectory`` ``(stamps, poses)`` the smoothed MAP trajectory it was drawn along
    (:func:`map_trajectory`): the nodes are the places' visits on it, in the map's frame, and edges
    crossing the map's walls are rerouted through waypoints or dropped
    (:class:`ptm_ros.maps.routes.RouteConfig` ``config``); ``log`` receives :func:`route_notes`. Without
    them (``ptm-run --no-map``, a bag without scans) the nodes are the MAP topology's place positions and
    the edges the straight segments between them, walls unchecked, as before issue #24.
    """
    from ptm_ros.maps.routes import route_graph, save_route_graph

    doc = route_graph(ptm, grid=grid, trajectory=trajectory, config=config)
    if log is not None:
        for note in route_notes(doc["metadata"]):
            log(note)
    return save_route_graph(doc, path)


def route_notes(meta: Mapping[str, Any]) -> list[str]:
    """Lines on the edges a route graph rerouted around walls or dropped (its ``metadata``)."""
    lines = []
    if meta["rerouted_edges"]:
        lines.append(
            f"route graph: {meta['rerouted_edges']} connections rerouted around the map's walls through "
            f"{meta['waypoints']} waypoints"
        )
    for d in meta["dropped_edges"]:
        a, b = d["places"]
        lines.append(
            f"route graph: dropped the edge between places {a} and {b} (p = {d['probability']:.3f}): "
            f"{d['reason']}"
        )
    return lines


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


def _exit_with_parent() -> None:
    """A worker's initializer: end the worker as soon as the process that started it has ended (a killed
    ``ptm-run`` leaves no workers behind holding its pipes)."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        wait([parent.sentinel])
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


class RegistrationPool:
    """``jobs`` worker processes for a run's independent scan matching: the visits' patches and the
    filter's registrations (:meth:`submit`, a :class:`~ptm_ros.perception.laser.WorkerPool`) and the
    refinement's (a :class:`~ptm_ros.maps.refinement.Mapper`; batches of fewer than ``min_batch``, and
    everything when ``jobs`` <= 1, run here: a pool's start-up costs more than they do). Outcomes are computed
    by the same functions and come back in order, so the files are identical whatever ``jobs``. Workers come
    from a fork server that has imported this module and matplotlib once (forking this process could copy a
    held lock of its threads), started on first use; a worker ends when this process does, even killed."""

    def __init__(self, jobs: int, min_batch: int = 32) -> None:
        self.jobs = jobs
        self.min_batch = min_batch
        self._pool: ProcessPoolExecutor | None = None

    def _workers(self) -> ProcessPoolExecutor:
        if self._pool is None:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(["ptm_ros.tools.pipeline", "matplotlib.backends.backend_agg"])
            self._pool = ProcessPoolExecutor(
                max_workers=self.jobs, mp_context=context, initializer=_exit_with_parent
            )
        return self._pool

    def __call__(
        self, fn: Callable[[RegistrationJob], Registration | None], jobs: Iterable[RegistrationJob], /
    ) -> Iterable[Registration | None]:
        batch = list(jobs)
        if self.jobs <= 1 or len(batch) < self.min_batch:
            return map(fn, batch)
        chunk = max(1, len(batch) // (4 * self.jobs))
        return self._workers().map(fn, batch, chunksize=chunk)

    @property
    def workers(self) -> RegistrationPool | None:
        """This pool as a :class:`~ptm_ros.perception.laser.WorkerPool`; None when ``jobs`` <= 1 (all work
        here)."""
        return self if self.jobs > 1 else None

    def submit(self, fn: Callable[..., _T], /, *args: Any, **kwargs: Any) -> Future[_T]:
        """``fn(*args, **kwargs)`` in a worker process."""
        return self._workers().submit(fn, *args, **kwargs)

    def __enter__(self) -> RegistrationPool:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


def score_against(ptm: Ptm, ground_truth: str | Path | GroundTruthTrajectory) -> Any:
    """Score a PTM against a ground-truth file (simulator JSON or CARMEN ``*-gt-*.txt``) or a loaded
    :class:`ptm_ros.io.groundtruth.GroundTruthTrajectory`."""
    from ptm_ros.tools.evaluate import score_against_ground_truth

    return score_against_ground_truth(ptm, ground_truth)
