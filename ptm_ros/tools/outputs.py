"""What ``ptm-run`` and ``ptm-bringup`` write beside a PTM (:func:`write_outputs`, issue #24), and the
notes on it in the report and the console summary (the ``*_notes`` functions); with :class:`RunResult` (what
was written), :func:`provenance` and :func:`run_odometry`, which ``ptm-run`` and ``ptm-bringup`` share.

Files (:data:`OUTPUT_FILES` names them; ``ptm-run``, :func:`ptm_ros.tools.pipeline.run_offline`, writes the
map with :func:`write_occupancy_map`, the state with :mod:`ptm_ros.tools.checkpoint` and the rest with
:func:`write_outputs`, which ``ptm-bringup`` calls on what the nodes published):

* ``ptm.json`` (CONTRACT.md schema) and ``config.yaml`` (the parameters used);
* ``route_graph.geojson`` — the PTM as a nav2 route graph (:mod:`ptm_ros.maps.routes`), always; with a map,
  its nodes on the map's trajectory and its edges kept off the map's walls (:func:`write_route_graph`);
* ``map.pgm`` (``map_scale.png`` with ``occupancy.mode: scale``) + ``map.yaml`` (nav2 ``map_server``) and
  ``map.png`` — the occupancy grid
  (:mod:`ptm_ros.maps.occupancy`, parameters ``occupancy``) of the bag's scans placed along the smoothed
  trajectory of the MAP topology (:func:`ptm_ros.tools.pipeline.map_trajectory`, interpolated at the scan
  stamps); only when the bag has scans and maps are wanted (``ptm-run --no-map`` skips them);
* ``report.{md,html}`` with figures (the map, and the detector's surprise trace for a surprise detector);
* ``mcmc_trace.json`` — with ``write_trace`` (``ptm-run --trace``) and MCMC: the cold chains' full
  states (:func:`ptm_ros.reporting.chain_trace.split_chain_trace`; ``ptm.json`` keeps their summary);
* ``filter_state.npz`` — the RBPF's state (:class:`ptm_ros.tools.checkpoint.RunCheckpoint`);
* ``ground_truth.json`` — with the ``ground-truth`` detector (landmarks fixed along the true path, the
  thesis' Intel protocol, :func:`ptm_ros.tools.pipeline.ground_truth_landmarks`): the ground truth with the
  landmarks it placed and their visits (simulator schema), so that ``ptm-eval DIR/ptm.json --ground-truth
  DIR`` scores the mass on the true topology as ``ptm-run`` did.

With a ground truth, ``ptm.json`` carries ``extra["trajectory_error"]`` (:func:`trajectory_errors`):
``ate_smoothed_m`` and ``ate_odometry_m``, the absolute trajectory errors
(:func:`ptm_ros.scoring.evaluation.absolute_trajectory_error`, RMSE after the best rigid 2-D alignment) of the
smoothed MAP trajectory and of the bag's raw odometry, both at the odometry stamps inside the ground
truth's time span (``poses`` of them), the rigid alignment of the former onto the ground truth
(``alignment``: ``theta``, ``x``, ``y``) and the ground-truth file; with a map, ``extra["map_quality"]``
(:func:`map_quality_against`): the map against the same scans placed at the true poses
(:mod:`ptm_ros.maps.map_quality`: free-space leak, wall precision and recall, free-area ratio).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ptm_ros.config import PtmConfig, save_config
from ptm_ros.errors import DataError
from ptm_ros.io.bag import OdometryData, RunData
from ptm_ros.io.groundtruth import SIM_FILENAME, GroundTruthTrajectory, interpolate_pose, save_sim_gt
from ptm_ros.maps.occupancy import MAP_STEM
from ptm_ros.model.partitions import Labels
from ptm_ros.model.ptm import Ptm, save_ptm
from ptm_ros.perception.laser import WorkerPool
from ptm_ros.reporting.chain_trace import save_chain_trace
from ptm_ros.reporting.doubts import doubt_lines, find_doubts
from ptm_ros.session import VERSUS_KEY
from ptm_ros.tools.progress import Phases

if TYPE_CHECKING:
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.routes import RouteConfig
    from ptm_ros.perception.surprise import SurpriseTrace

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


def run_odometry(run: RunData) -> OdometryData:
    """The run's odometry stream; :class:`DataError` when the bag has none."""
    odom = run.odometry
    if odom is None or len(odom.stamps) == 0:
        msg = f"bag {run.path} has no odometry"
        raise DataError(msg)
    return odom


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


def provenance(bag: Path, used: PtmConfig) -> dict[str, str]:
    """What ``ptm.json`` says about where its run came from: the bag (as given) and the detector used."""
    return {"bag": str(bag), "detector": str(used.detector.kind)}


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

    * ``mcmc_trace.json``: the MCMC ``chain_trace`` (:func:`ptm_ros.reporting.chain_trace.split_chain_trace`),
      if given, from which the report draws its SRQ plot.

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
    """The report's side-by-side map figure (:class:`ptm_ros.reporting.map_plots.MapComparison`): the map
    next to its ``reference`` carried by the ATE ``alignment`` when there is one, else next to the route graph
    written to ``route_graph``; None without a map."""
    from ptm_ros.reporting.map_plots import MapComparison

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
    from ptm_ros.reporting.plots import label_string
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


def score_against(ptm: Ptm, ground_truth: str | Path | GroundTruthTrajectory) -> Any:
    """Score a PTM against a ground-truth file (simulator JSON or CARMEN ``*-gt-*.txt``) or a loaded
    :class:`ptm_ros.io.groundtruth.GroundTruthTrajectory`."""
    from ptm_ros.tools.evaluate import score_against_ground_truth

    return score_against_ground_truth(ptm, ground_truth)
