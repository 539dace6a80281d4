"""Figures and a one-page report of a PTM (after the thesis' Fig. 56–57).

:func:`write_report` writes into ``out_dir``, always under the same file names:

* ``ptm_histogram.png`` — the PTM as a histogram: one bar per topology (most probable first, at most
  ``max_bars``), height = posterior mass, tick = the compact label string (:func:`label_string`). With a
  score, consistent topologies (no scored pair wrong) are green, the others red.
* ``ptm_topologies.png`` — the ``top_k`` most probable topologies drawn over the trajectory (Fig. 56c,
  57b): visits at their odometry poses coloured by place, each place at its position
  (``Topology.positions`` when present, else the mean of its visits' poses) joined to its visits by
  faint spokes, and an edge between the places of consecutive visits.
* ``ptm_scores.png`` (only with a score) — precision / recall / F1 of the MAP topology and of the
  posterior, and the masses.
* ``ptm_surprise.png`` (only with a surprise trace) — the landmark detector's Bayesian surprise (thesis
  Ch. 4.7.3, Fig. 62): actual surprise per measurement against time, the predicted surprise mean with
  its band ``mean ± k·std`` shaded (the upper edge is the detector's threshold), the surprise maxima
  that fired a landmark ringed (above the band, by the detector's rule) and the landmarks as declared
  (dotted lines: a laser detector places each at the most open scan near its maximum).
* ``ptm_timeline.png`` (only when ``ptm.inference`` holds the particle filter's timeline,
  :func:`ptm_ros.model.ptm.ptm_timeline`) — how the mass moved as the visits arrived
  (:func:`timeline_figure`): after each visit the mass of the most probable topology (bars), of the true
  topology of the visits so far (with a ground truth) and of the greedy baseline's answer (when ptm.json has
  one), each cut to the visits so far (:func:`ptm_ros.scoring.evaluation.timeline_masses`); without a truth,
  the two most probable.
* ``ptm_srq.png`` (only when ``ptm.inference[SRQ_KEY]`` holds MCMC cold-chain states) — the scaled
  regeneration quantile plot of every chain (thesis Ch. 3.6, Fig. 42; :mod:`ptm_ros.inference.convergence`),
  all chains at one atom: the state most visited over all chains.
* the occupancy map (only when ``occupancy_map`` is given: ``ptm-run`` passes its ``map.png``, the grid
  of the scans placed along the smoothed trajectory of the MAP topology, :mod:`ptm_ros.maps.occupancy`).
* ``map_comparison.png`` (only with a :class:`MapComparison`) — the map side by side with what it should
  be read against (issue #24): with a reference (the same scans at the ground-truth poses,
  :mod:`ptm_ros.maps.map_quality`), the map carried onto it by the ATE alignment, its leaked free cells
  (more than ``LEAK_RADIUS`` from anything the reference saw) in red, next to the reference; without one, the
  map next to the MAP topology's route graph drawn over it (places, waypoints and edges as a route server
  reads them, :mod:`ptm_ros.maps.routes`, the edges coloured by probability).
* ``report.md`` and ``report.html`` — the summary (plus the caller's ``notes``, e.g. trajectory errors),
  the score table, the figures (relative links, the map and extra figures copied beside them unless
  already there) and the top topologies as a table.

``ptm.inference["cold_chain_states"]`` (:data:`SRQ_KEY`): one list per independent chain of the cold
(``β = 1``) replica's state after each sweep, thinned by a fixed stride (every ``k``-th sweep, ``k`` in
``ptm.inference["cold_chain_thin"]`` when known), states as integers (ids of topologies, the same id
for the same topology in every chain) or label lists. A thinned chain is again a Markov chain with the
same atoms, so its SRQ plot is valid.

Matplotlib is imported lazily and drawn through its Agg canvas (no display, no pyplot state); large
PTMs stay quick because bars, tables and panels are capped and points/lines are drawn as collections.
"""

from __future__ import annotations

import html
import json
import math
import shutil
from collections.abc import Callable, Hashable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ConfigError, DataError, ModelError
from ptm_ros.inference.convergence import most_visited, srq_deviation, srq_points
from ptm_ros.maps.map_quality import ClassGrid, leaked_cells
from ptm_ros.maps.occupancy import FREE, OCCUPIED, UNKNOWN
from ptm_ros.maps.routes import place_means
from ptm_ros.model.partitions import IntSequence, Labels, num_places
from ptm_ros.model.ptm import Ptm, TimelineStep, Topology, ptm_greedy, ptm_timeline
from ptm_ros.perception.laser import WorkerPool
from ptm_ros.reporting.figures import ess_fraction, sig
from ptm_ros.scoring.evaluation import Score, first_wrong_visit, timeline_masses, unlisted_bound

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from ptm_ros.perception.surprise import SurpriseTrace

HISTOGRAM = "ptm_histogram.png"
TOPOLOGIES = "ptm_topologies.png"
SCORES = "ptm_scores.png"
SURPRISE = "ptm_surprise.png"
SRQ = "ptm_srq.png"
MAP_COMPARISON = "map_comparison.png"
TIMELINE = "ptm_timeline.png"
#: Caption of the timeline figure.
TIMELINE_CAPTION = "How the mass moved as the visits arrived (the particle filter's PTM after each visit)"
REPORT_MD = "report.md"
REPORT_HTML = "report.html"
#: Key of ``Ptm.inference`` holding the MCMC cold-chain states drawn as the SRQ plot (module docstring):
#: in memory, and in a ptm.json written before issue #25; ``ptm-run`` moves them to :data:`TRACE`.
SRQ_KEY = "cold_chain_states"
#: Key of ``Ptm.inference`` holding the thinning stride of those states (sweeps per kept state).
SRQ_THIN_KEY = "cold_chain_thin"
#: Key of ``Ptm.inference`` holding the topology (labels) of each state id in :data:`SRQ_KEY` (in memory).
SRQ_LABELS_KEY = "cold_chain_labels"
#: Key of ``Ptm.inference`` holding the summary of the cold chains that ptm.json keeps
#: (:func:`split_chain_trace`).
CHAINS_KEY = "cold_chains"
#: The file of the full cold-chain states beside ptm.json (``ptm-run --trace``) and its schema tag.
TRACE = "mcmc_trace.json"
TRACE_SCHEMA = "ptm_ros.mcmc_trace/1"
#: Caption of the occupancy map figure.
MAP_CAPTION = "Occupancy grid of the scans along the smoothed trajectory of the most probable topology"
#: Captions of the side-by-side map figure, with a reference and without one.
REFERENCE_CAPTION = (
    "The map (aligned as for the ATE; red: free cells more than 0.3 m from anything the reference saw) "
    "next to the reference: the same scans at the ground-truth poses"
)
ROUTES_CAPTION = "The map next to the most probable topology's route graph drawn over it"
#: Grey levels of the map figures: free, seen by a beam without being free (reference), unknown, wall.
_SHADES = {"free": 1.0, "seen": 0.85, "unknown": 0.62, "wall": 0.0}
_LEAK_RGB = (0.85, 0.1, 0.1)

_DIGITS = "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"
_GOLDEN = 0.618033988749895


@dataclass(frozen=True)
class ReportConfig:
    """Sizes of the report.

    Attributes:
        top_k: topologies drawn over the trajectory.
        max_bars: topologies in the histogram.
        max_rows: topologies in the markdown/HTML table.
        max_label_chars: longest label string shown before it is shortened with "…".
        dpi: resolution of the PNGs.
        surprise_log_scale: draw the surprise on a log axis (it spans orders of magnitude: the band
            sits near the predicted mean while a change of place can be 10-100 times above it).
    """

    top_k: int = 4
    max_bars: int = 20
    max_rows: int = 20
    max_label_chars: int = 40
    dpi: int = 100
    surprise_log_scale: bool = True

    def __post_init__(self) -> None:
        for name in ("top_k", "max_bars", "max_rows", "dpi"):
            if getattr(self, name) < 1:
                msg = f"ReportConfig.{name} must be >= 1, got {getattr(self, name)}"
                raise ConfigError(msg)
        if self.max_label_chars < 4:
            msg = f"ReportConfig.max_label_chars must be >= 4, got {self.max_label_chars}"
            raise ConfigError(msg)


def label_string(labels: Sequence[int], max_chars: int | None = None) -> str:
    """Compact label string: one character per visit (``0-9a-zA-Z``) up to 62 places, else dotted.

    ``(0, 1, 2, 0)`` → ``"0120"``; shortened to ``max_chars`` with a middle "…" when given.
    """
    if not labels:
        text = "∅"
    elif max(labels) < len(_DIGITS):
        text = "".join(_DIGITS[v] for v in labels)
    else:
        text = ".".join(str(v) for v in labels)
    if max_chars is not None and len(text) > max_chars:
        head = (max_chars - 1) // 2
        text = text[:head] + "…" + text[len(text) - (max_chars - 1 - head) :]
    return text


def place_colors(n: int) -> NDArray[np.float64]:
    """``(n, 3)`` RGB colours of places 0..n-1: tab10 up to 10 places, golden-ratio hues beyond."""
    from matplotlib import colormaps
    from matplotlib.colors import hsv_to_rgb

    if n <= 10:
        return np.asarray(colormaps["tab10"](np.arange(n))[:, :3], dtype=float)
    k = np.arange(n)
    hsv = np.stack([(k * _GOLDEN) % 1.0, 0.55 + 0.4 * (k % 2), 0.95 - 0.25 * ((k // 2) % 2)], axis=1)
    return np.asarray(hsv_to_rgb(hsv), dtype=float)


def place_positions(topology: Topology, visit_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(M, 2)`` place positions: ``topology.positions`` when it has one per place, else visit means."""
    m = num_places(topology.labels)
    if topology.positions is not None and len(topology.positions) == m:
        return np.asarray(topology.positions, dtype=float).reshape(m, 2)
    if m == 0:
        return np.zeros((0, 2))
    return place_means(topology.labels, visit_xy)


def place_edges(labels: IntSequence) -> NDArray[np.intp]:
    """``(E, 2)`` distinct undirected edges between the places of consecutive visits (sorted)."""
    lab = np.asarray(labels, dtype=np.intp)
    if lab.size < 2:
        return np.zeros((0, 2), dtype=np.intp)
    pairs = np.sort(np.stack([lab[:-1], lab[1:]], axis=1), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    return np.unique(pairs, axis=0).reshape(-1, 2)


def _new_figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _visit_xy(ptm: Ptm) -> NDArray[np.float64]:
    return np.array([lm.map_pose[:2] for lm in ptm.landmarks], dtype=float).reshape(-1, 2)


def _tick(rank: int, topology: Topology, config: ReportConfig) -> str:
    """The full label string when it fits, else the rank and number of places."""
    text = label_string(topology.labels)
    if len(text) <= min(config.max_label_chars, 24):
        return text
    return f"#{rank + 1}: {num_places(topology.labels)} places"


def draw_histogram(ptm: Ptm, path: Path, *, score: Score | None, config: ReportConfig) -> Path:
    """Write the PTM histogram (top ``config.max_bars`` topologies) to ``path``."""
    tops = ptm.topologies[: config.max_bars]
    probs = np.array([t.probability for t in tops], dtype=float)
    fig = _new_figure(max(5.0, 0.45 * len(tops) + 2.0), 4.5)
    ax = fig.add_subplot()
    if score is None:
        colors: Any = "tab:blue"
    else:
        colors = ["tab:green" if s.consistent else "tab:red" for s in score.topologies[: len(tops)]]
    x = np.arange(len(tops))
    ax.bar(x, probs, color=colors, edgecolor="black", linewidth=0.5)
    ax.set_xticks(x, [_tick(k, t, config) for k, t in enumerate(tops)], rotation=60, ha="right")
    ax.set_ylabel("posterior probability")
    ax.set_ylim(0.0, 1.05 * max(1e-9, float(probs.max(initial=0.0))))
    listed = sum(t.probability for t in ptm.topologies)
    rest = len(ptm.topologies) - len(tops)
    note = f"{len(ptm.landmarks)} visits, {len(ptm.topologies)} topologies, listed mass {listed:.3f}"
    if rest > 0:
        note += f" ({rest} not shown)"
    if score is not None:
        note += "\ngreen: no scored pair wrong; red: at least one"
    ax.set_title(f"PTM histogram\n{note}", fontsize=9)
    fig.savefig(path, dpi=config.dpi)
    return path


def _draw_topology(
    ax: Axes,
    topology: Topology,
    visit_xy: NDArray[np.float64],
    trajectory: NDArray[np.float64] | None,
    title: str,
) -> None:
    from matplotlib.collections import LineCollection

    labels = np.asarray(topology.labels, dtype=np.intp)
    places = place_positions(topology, visit_xy)
    colors = place_colors(len(places))
    path_xy = trajectory[:, :2] if trajectory is not None else visit_xy
    if len(path_xy) > 1:
        ax.plot(path_xy[:, 0], path_xy[:, 1], color="0.75", linewidth=0.8, zorder=1)
    if labels.size:
        spokes = np.stack([visit_xy, places[labels]], axis=1)
        ax.add_collection(
            LineCollection(list(spokes), colors=colors[labels], linewidths=0.6, alpha=0.5, zorder=2)
        )
        edges = place_edges(labels)
        if len(edges):
            ax.add_collection(LineCollection(list(places[edges]), colors="black", linewidths=1.0, zorder=3))
        size = 60.0 * min(1.0, 30.0 / len(places))  # shrink markers when there are many places
        ax.scatter(visit_xy[:, 0], visit_xy[:, 1], s=size / 4, c=colors[labels], edgecolors="none", zorder=4)
        ax.scatter(places[:, 0], places[:, 1], s=size, c=colors, edgecolors="black", linewidths=0.6, zorder=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)


def draw_topologies(
    ptm: Ptm,
    path: Path,
    *,
    trajectory: NDArray[np.float64] | None,
    score: Score | None,
    config: ReportConfig,
) -> Path:
    """Write the ``config.top_k`` most probable topologies drawn over the trajectory to ``path``."""
    tops = ptm.topologies[: config.top_k]
    ncols = min(2, max(1, len(tops)))
    nrows = max(1, math.ceil(len(tops) / ncols))
    fig = _new_figure(5.0 * ncols, 4.6 * nrows)
    visit_xy = _visit_xy(ptm)
    for k, t in enumerate(tops):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        title = f"#{k + 1}  p = {t.probability:.3f}  {num_places(t.labels)} places"
        if score is not None:
            c = score.topologies[k].counts
            title += f"\nP {c.precision:.2f}  R {c.recall:.2f}  F1 {c.f1:.2f}"
        _draw_topology(ax, t, visit_xy, trajectory, title)
        ax.set_xlabel(f"x [m] ({ptm.frame_id})", fontsize=8)
        ax.set_ylabel("y [m]", fontsize=8)
    fig.savefig(path, dpi=config.dpi)
    return path


@dataclass(frozen=True)
class MapComparison:
    """The side-by-side map figure's input (:func:`draw_map_comparison`).

    Attributes:
        product: the run's map (trinary classes) in its own frame.
        reference: the reference map in the ground truth's frame (its ``seen`` cells set), or None.
        theta: rotation (rad) of the rigid motion ``x ↦ R_theta x + t`` carrying the product onto the
            reference (the ATE alignment).
        t: its translation (m).
        quality: the map's quality figures (:meth:`ptm_ros.maps.map_quality.MapQuality.as_dict`), for the
        title. route_graph: the GeoJSON route graph (:func:`ptm_ros.maps.routes.route_graph`) drawn over the
        map when
            there is no reference.
    """

    product: ClassGrid
    reference: ClassGrid | None = None
    theta: float = 0.0
    t: tuple[float, float] = (0.0, 0.0)
    quality: Mapping[str, Any] | None = None
    route_graph: Mapping[str, Any] | None = None


def _class_rgba(
    grid: ClassGrid, *, leak: NDArray[np.bool_] | None = None, faded: bool = False
) -> NDArray[np.float64]:
    """``(H, W, 4)`` colours of a class grid (row 0 = lowest y): walls black, free white, seen but not
    free light grey (a grid with ``seen``), ``leak`` cells red, unknown transparent (the axes show the
    unknown grey); ``faded`` lifts walls to grey (a background)."""
    classes = np.asarray(grid.classes)
    grey = np.full(classes.shape, _SHADES["unknown"])
    known = classes != UNKNOWN
    if grid.seen is not None:
        seen = np.asarray(grid.seen, dtype=bool)
        grey[seen] = _SHADES["seen"]
        known |= seen
    grey[classes == FREE] = _SHADES["free"]
    grey[classes == OCCUPIED] = 0.55 if faded else _SHADES["wall"]
    rgba = np.concatenate([np.repeat(grey[..., None], 3, axis=2), known[..., None].astype(float)], axis=2)
    if leak is not None:
        rgba[leak, :3] = _LEAK_RGB
    return rgba


def _show_grid(
    ax: Axes, rgba: NDArray[np.float64], grid: ClassGrid, motion: tuple[float, float, float] | None = None
) -> NDArray[np.float64]:
    """Draw ``rgba`` at the grid's place (carried by ``motion = (theta, tx, ty)`` when given) on the
    unknown grey; returns the ``(n, 2)`` centres of its drawn (not transparent) cells in the axes' frame."""
    from matplotlib.transforms import Affine2D

    x0, y0 = grid.origin[0], grid.origin[1]
    w, h = rgba.shape[1] * grid.resolution, rgba.shape[0] * grid.resolution
    ax.set_facecolor(str(_SHADES["unknown"]))
    image = ax.imshow(rgba, origin="lower", extent=(x0, x0 + w, y0, y0 + h), interpolation="antialiased")
    drawn = grid.centres(rgba[..., 3] > 0)
    if motion is not None:
        theta, tx, ty = motion
        move = Affine2D().rotate(theta).translate(tx, ty)
        image.set_transform(move + ax.transData)
        drawn = move.transform(drawn)
    return np.asarray(drawn, dtype=np.float64)


def draw_route_graph(ax: Axes, doc: Mapping[str, Any]) -> tuple[int, int]:
    """The route graph's edges (from yellow, improbable, to blue, certain) and nodes (places with their
    ids, waypoints small); returns the numbers of places and of (directed) edges drawn."""
    from matplotlib.collections import LineCollection

    places: list[tuple[Any, Sequence[float]]] = []
    waypoints: list[tuple[Any, Sequence[float]]] = []
    segments: list[NDArray[np.float64]] = []
    probs: list[float] = []
    edges = 0
    for feature in doc.get("features", ()):
        geometry, props = feature.get("geometry") or {}, feature.get("properties") or {}
        meta = props.get("metadata") or {}
        if geometry.get("type") == "Point":
            (waypoints if meta.get("waypoint") else places).append((props.get("id"), geometry["coordinates"]))
        elif geometry.get("type") == "MultiLineString":
            edges += 1
            for line in geometry["coordinates"]:
                segments.append(np.asarray(line, dtype=float)[:, :2])
                probs.append(float(meta.get("probability", 1.0)))
    if segments:
        shade = np.clip(np.asarray(probs), 0.0, 1.0)
        colors = np.column_stack(
            [0.9 * (1 - shade), 0.3 + 0.4 * (1 - shade), 0.9 * shade + 0.1 * (1 - shade)]
        )
        ax.add_collection(LineCollection(segments, colors=colors, linewidths=1.2, zorder=3))
    if waypoints:
        xy = np.asarray([c for _, c in waypoints], dtype=np.float64)
        ax.scatter(xy[:, 0], xy[:, 1], s=7, c="white", edgecolors="black", linewidths=0.4, zorder=4)
    if places:
        xy = np.asarray([c for _, c in places], dtype=np.float64)
        ax.scatter(xy[:, 0], xy[:, 1], s=22, c="tab:blue", edgecolors="black", linewidths=0.5, zorder=5)
        if len(places) <= 60:
            for node, (x, y) in places:
                ax.annotate(
                    str(node), (x, y), fontsize=6, xytext=(2, 2), textcoords="offset points", zorder=6
                )
    return len(places), edges


def draw_map_comparison(comparison: MapComparison, path: Path, *, config: ReportConfig) -> Path:
    """Write the side-by-side map figure (module docstring) to ``path``: both panels share one frame and
    window (the reference's with a reference, the map's without)."""
    product, reference = comparison.product, comparison.reference
    fig: Figure = _new_figure(12.0, 7.0)
    left = fig.add_subplot(1, 2, 1)
    right = fig.add_subplot(1, 2, 2, sharex=left, sharey=left)
    q = comparison.quality or {}

    def fig_of(key: str) -> str:
        v = q.get(key)
        return "–" if v is None else sig(float(v))

    if reference is not None:
        leak = leaked_cells(product, reference, theta=comparison.theta, t=comparison.t)
        motion = (comparison.theta, float(comparison.t[0]), float(comparison.t[1]))
        drawn = _show_grid(left, _class_rgba(product, leak=leak), product, motion)
        drawn = np.vstack([drawn, _show_grid(right, _class_rgba(reference), reference)])
        left.set_title(
            f"map, aligned onto the ground truth: leak {fig_of('leak')} ({int(leak.sum())} red cells), "
            f"free area {fig_of('free_area_ratio')} x the reference's\nwall precision "
            f"{fig_of('wall_precision')}, wall recall {fig_of('wall_recall')}",
            fontsize=8,
        )
        right.set_title(
            "reference: the same scans at the ground-truth poses\n(light grey: seen, not free)", fontsize=8
        )
    else:
        drawn = _show_grid(left, _class_rgba(product), product)
        _show_grid(right, _class_rgba(product, faded=True), product)
        n_places, n_edges = draw_route_graph(right, comparison.route_graph or {})
        left.set_title("map", fontsize=8)
        right.set_title(
            f"most probable topology as a route graph: {n_places} places, {n_edges} directed edges\n"
            "(blue: places; white: waypoints around walls; edges blue when certain, yellow when improbable)",
            fontsize=8,
        )
    if len(drawn):  # the window: everything either panel knows, and a metre around it
        lo, hi = drawn.min(axis=0) - 1.0, drawn.max(axis=0) + 1.0
        left.set_xlim(lo[0], hi[0])
        left.set_ylim(lo[1], hi[1])
        fig.set_size_inches(12.0, float(np.clip(5.6 * (hi[1] - lo[1]) / (hi[0] - lo[0]) + 1.4, 3.5, 13.0)))
    for ax in (left, right):
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)", fontsize=8)
        ax.tick_params(labelsize=7)
    left.set_ylabel("y (m)", fontsize=8)
    fig.savefig(path, dpi=config.dpi)
    return path


def draw_scores(score: Score, path: Path, *, config: ReportConfig) -> Path:
    """Write a bar chart of the MAP and posterior-weighted precision / recall / F1 to ``path``."""
    fig = _new_figure(6.5, 3.8)
    ax = fig.add_subplot()
    names = ("precision", "recall", "F1")
    m, e = score.map.counts, score.expected
    x = np.arange(3)
    for offset, vals, name in (
        (-0.2, (m.precision, m.recall, m.f1), "MAP topology"),
        (0.2, (e.precision, e.recall, e.f1), "posterior (expected counts)"),
    ):
        bars = ax.bar(x + offset, vals, width=0.4, label=name)
        ax.bar_label(bars, fmt="%.3f", fontsize=8)
    ax.set_xticks(x, names)
    ax.set_ylim(0.0, 1.3)
    ax.legend(loc="upper center", ncols=2, fontsize=8)
    truth = "—" if score.true_topology_mass is None else f"{score.true_topology_mass:.3f}"
    ax.set_title(
        f"consistent mass {score.consistent_mass:.3f}   true-topology mass {truth}   "
        f"mean F1 {score.mean_f1:.3f}\n{score.n_scored_pairs} scored pairs ({score.n_same_pairs} same), "
        f"{score.n_true_places} true places, MAP {score.map.num_places} places",
        fontsize=8,
    )
    fig.savefig(path, dpi=config.dpi)
    return path


def fired_indices(trace: SurpriseTrace) -> NDArray[np.intp]:
    """``(L,)`` indices of the trace's measurements at which its landmarks were declared.

    Among measurements sharing a landmark's stamp the most surprising one is taken.

    Raises:
        DataError: a landmark stamp that is not the stamp of any measurement of the trace.
    """
    return _indices(trace, trace.landmarks, "landmark")


def trigger_indices(trace: SurpriseTrace) -> NDArray[np.intp]:
    """Indices of the trace's measurements whose surprise fired a landmark: the maxima above the band
    (:class:`ptm_ros.perception.surprise.BandTrigger`, ``trace.triggers``); the landmarks' own measurements
    for a trace without triggers. Raises :class:`DataError` as :func:`fired_indices` does."""
    if trace.triggers is None:
        return fired_indices(trace)
    return _indices(trace, trace.triggers, "trigger")


def _indices(trace: SurpriseTrace, at: ArrayLike, what: str) -> NDArray[np.intp]:
    stamps = np.asarray(trace.stamps, dtype=float)
    surprise = np.asarray(trace.surprise, dtype=float)
    wanted = np.asarray(at, dtype=float).reshape(-1)
    out = np.empty(len(wanted), dtype=np.intp)
    for k, stamp in enumerate(wanted.tolist()):
        tol = 1e-9 * max(1.0, abs(stamp))
        lo = int(np.searchsorted(stamps, stamp - tol, side="left"))
        hi = int(np.searchsorted(stamps, stamp + tol, side="right"))
        if hi <= lo:
            msg = f"{what} stamp {stamp:.9f} is not the stamp of a measurement of the surprise trace"
            raise DataError(msg)
        out[k] = lo + int(np.argmax(surprise[lo:hi]))
    return out


def _check_trace(trace: SurpriseTrace) -> None:
    n = len(trace.stamps)
    if n == 0:
        msg = "the surprise trace is empty"
        raise DataError(msg)
    fields = ("surprise", "predicted_mean", "predicted_std", "upper")
    shapes = {name: np.shape(getattr(trace, name)) for name in ("stamps", *fields)}
    if any(shape != (n,) for shape in shapes.values()):
        msg = f"surprise trace fields must all be (T,) arrays, got shapes {shapes}"
        raise DataError(msg)
    stamps = np.asarray(trace.stamps, dtype=float)
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) < 0.0):
        msg = "surprise trace stamps must be finite and non-decreasing"
        raise DataError(msg)


def _band_sigmas(trace: SurpriseTrace) -> float | None:
    """``k`` of the band ``upper = mean + k·std`` (median over measurements with ``std > 0``)."""
    std = np.asarray(trace.predicted_std, dtype=float)
    ok = std > 0.0
    if not ok.any():
        return None
    width = np.asarray(trace.upper, dtype=float) - np.asarray(trace.predicted_mean, dtype=float)
    return float(np.median(width[ok] / std[ok]))


def surprise_figure(trace: SurpriseTrace, *, config: ReportConfig) -> Figure:
    """The surprise figure (thesis Fig. 62) of a detector's trace, not yet saved.

    Time runs from the first measurement. The band is ``[max(0, mean - k·std), mean + k·std]``; its top
    (dashed) is the detector's threshold. The detector's rule
    (:class:`ptm_ros.perception.surprise.BandTrigger`): a landmark fires at the first maximum of each run of
    measurements above the band; these maxima are ringed (so every ring lies above the band). A laser detector
    then places the landmark at the most open scan within ``localize_distance`` of travel (usually inside the
    band): dotted vertical lines at the declared landmarks (through the rings when nothing was moved). On a
    log axis (:attr:`ReportConfig.surprise_log_scale`) values are floored at half the smallest positive one.
    Artists carry ids for inspection (``gid``): ``"surprise"`` (actual), ``"predicted_mean"``,
    ``"upper"``, ``"band"``, ``"triggers"`` (a scatter at ``(time, surprise)`` of
    :func:`trigger_indices`) and ``"landmarks"`` (vertical lines at the times of :func:`fired_indices`).
    """
    _check_trace(trace)
    stamps = np.asarray(trace.stamps, dtype=float)
    surprise = np.asarray(trace.surprise, dtype=float)
    mean = np.asarray(trace.predicted_mean, dtype=float)
    upper = np.asarray(trace.upper, dtype=float)
    lower = 2.0 * mean - upper  # mean - k·std
    placed = fired_indices(trace)
    fired = trigger_indices(trace)
    moved = placed.shape != fired.shape or bool(np.any(stamps[placed] != stamps[fired]))
    t = stamps - stamps[0]
    positive = np.concatenate([surprise, mean, upper])
    positive = positive[np.isfinite(positive) & (positive > 0.0)]
    log_scale = config.surprise_log_scale and positive.size > 0
    floor = 0.5 * float(positive.min()) if log_scale else -math.inf

    def shown(v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.maximum(v, floor)

    fig = _new_figure(10.0, 4.4)
    ax = fig.add_subplot()
    k = _band_sigmas(trace)
    band = "band: predicted mean ± " + (f"{k:.3g}σ" if k is not None else "k·σ")
    ax.fill_between(
        t,
        shown(np.maximum(lower, 0.0)),
        shown(upper),
        color="tab:orange",
        alpha=0.25,
        lw=0,
        label=band,
        gid="band",
    )
    ax.plot(t, shown(upper), color="tab:orange", lw=0.6, ls="--", label="threshold (band top)", gid="upper")
    ax.plot(
        t, shown(mean), color="tab:orange", lw=1.0, label="predicted surprise (mean)", gid="predicted_mean"
    )
    ax.plot(t, shown(surprise), color="tab:blue", lw=0.8, label="actual surprise", gid="surprise")
    top = float(shown(np.concatenate([surprise, upper])).max())
    ax.vlines(
        t[placed],
        floor if log_scale else 0.0,
        top,
        color="tab:red",
        lw=0.8,
        ls=":",
        label=f"landmarks ({placed.size})" + (": where placed" if moved else ""),
        gid="landmarks",
    )
    ax.scatter(
        t[fired],
        shown(surprise[fired]),
        s=30,
        marker="o",
        facecolors="none",
        edgecolors="tab:red",
        linewidths=1.2,
        zorder=5,
        label=f"surprise maxima that fired ({fired.size})",
        gid="triggers",
    )
    if log_scale:
        ax.set_yscale("log")
        ax.set_ylim(bottom=floor)
    else:
        ax.set_ylim(bottom=0.0)
    ax.set_xlim(float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1.0)
    ax.set_xlabel(f"time [s] since the first measurement (stamp {stamps[0]:.3f})")
    ax.set_ylabel("surprise KL(after ‖ before) [nats]")
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    rule = "a landmark fires at the first maximum of each run above the band (rings)"
    if moved:
        rule += ",\nthen is placed at the most open scan nearby (dotted lines: the landmarks)"
    ax.set_title(
        f"Bayesian surprise (thesis Fig. 62): {len(t)} measurements, {placed.size} landmarks\n{rule}",
        fontsize=9,
    )
    return fig


def draw_surprise(trace: SurpriseTrace, path: Path, *, config: ReportConfig) -> Path:
    """Write the surprise figure (:func:`surprise_figure`) of a detector's trace to ``path``."""
    fig = surprise_figure(trace, config=config)
    fig.savefig(path, dpi=config.dpi)
    return path


def _mass_track(
    steps: Sequence[TimelineStep], labels: IntSequence
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Per visit the listed mass of ``labels`` cut to the visits so far, and whether it was listed (an
    unlisted one is drawn at :func:`ptm_ros.scoring.evaluation.unlisted_bound`, the most it can hold)."""
    masses = timeline_masses(steps, labels)
    listed = np.array([m is not None for m in masses])
    values = np.array([unlisted_bound(st) if m is None else m for st, m in zip(steps, masses, strict=True)])
    return values, listed


def timeline_figure(
    steps: Sequence[TimelineStep], *, truth: Labels | None = None, greedy: Labels | None = None
) -> Figure:
    """The timeline figure (module docstring), not yet saved: x = the newest visit's index. Artists carry
    ids (``gid``): ``"top"`` (the bars), ``"truth"``, ``"greedy"`` or ``"second"`` (lines), ``"commit"``
    (the greedy baseline's first wrong decision)."""
    if not steps:
        msg = "the timeline figure needs at least one step"
        raise DataError(msg)
    fig = _new_figure(max(6.0, 0.35 * len(steps) + 3.0), 4.2)
    ax = fig.add_subplot()
    x = np.array([st.visits - 1 for st in steps])
    top = np.array([st.topologies[0][1] if st.topologies else 0.0 for st in steps])
    ax.bar(
        x,
        top,
        width=0.8,
        color="0.85",
        edgecolor="0.6",
        linewidth=0.5,
        label="most probable topology",
        gid="top",
    )
    tracks: list[tuple[str, IntSequence, str, str, str]] = []
    if greedy is not None:
        tracks.append(("greedy baseline's answer so far", greedy, "tab:red", "s", "greedy"))
    if truth is not None:
        tracks.append(("true topology of the visits so far", truth, "tab:green", "o", "truth"))
    else:
        second = [st.topologies[1][1] if len(st.topologies) > 1 else 0.0 for st in steps]
        ax.plot(
            x, second, color="tab:blue", marker="o", linewidth=1.2, label="second most probable", gid="second"
        )
    unlisted = False
    for z, (name, labels, color, marker, gid) in enumerate(tracks, start=2):
        values, listed = _mass_track(steps, labels)
        ax.plot(x, values, color=color, linewidth=1.5, label=name, zorder=z, gid=gid)
        ax.scatter(x[listed], values[listed], color=color, marker=marker, zorder=z)
        ax.scatter(x[~listed], values[~listed], facecolors="white", edgecolors=color, marker=marker, zorder=z)
        unlisted |= not listed.all()
    if greedy is not None and truth is not None:
        wrong = first_wrong_visit(greedy, truth)
        if wrong is not None:
            ax.axvline(wrong, color="tab:red", linestyle=":", linewidth=1.0, gid="commit")
            ax.annotate(
                f" greedy commits, wrongly (visit {wrong})", (wrong, 0.02), fontsize=7, color="tab:red"
            )
    ax.set_xticks(x)
    ax.tick_params(labelsize=7)
    ax.set_xlim(x[0] - 0.6, x[-1] + 0.6)
    ax.set_ylim(0.0, 1.05)
    ax.set_xlabel("visit (the newest one)")
    ax.set_ylabel("posterior probability")
    hollow = "\n(hollow marker: not among the listed topologies, at most this)" if unlisted else ""
    ax.set_title(f"How the mass moved as the visits arrived{hollow}", fontsize=9)
    ax.legend(loc="center left", fontsize=7)
    return fig


def draw_timeline(ptm: Ptm, path: Path, *, truth: Labels | None, config: ReportConfig) -> Path:
    """Write the timeline figure (:func:`timeline_figure`) of a PTM's timeline to ``path``, with the
    greedy baseline's answer when ptm.json has one."""
    fig = timeline_figure(ptm_timeline(ptm), truth=truth, greedy=ptm_greedy(ptm))
    fig.savefig(path, dpi=config.dpi)
    return path


SrqPoints = tuple[ArrayLike, ArrayLike]


def srq_figure(points_by_chain: Mapping[str, SrqPoints], *, note: str = "") -> Figure:
    """The SRQ plot (thesis Fig. 42) of several chains, not yet saved.

    ``points_by_chain``: chain name → ``(x, y)`` from :func:`ptm_ros.inference.convergence.srq_points`. Each
    chain is a line from the origin through its points (``gid`` = the chain's name), the unit-slope
    line is dashed (``gid`` ``"diagonal"``); ``note`` is added to the title.
    """
    if not points_by_chain:
        msg = "the SRQ plot needs at least one chain"
        raise DataError(msg)
    fig = _new_figure(6.0, 6.0)
    ax = fig.add_subplot()
    ax.plot([0.0, 1.0], [0.0, 1.0], color="black", ls="--", lw=0.8, label="unit slope", gid="diagonal")
    for name, (x, y) in points_by_chain.items():
        dev = srq_deviation(x, y)
        xs = np.concatenate([[0.0], np.asarray(x, dtype=float)])
        ys = np.concatenate([[0.0], np.asarray(y, dtype=float)])
        marker = "." if len(xs) <= 200 else None
        ax.plot(
            xs,
            ys,
            lw=1.0,
            marker=marker,
            ms=3,
            label=f"{name}: R = {len(xs) - 1}, max |y − x| = {dev:.3f}",
            gid=name,
        )
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_aspect("equal")
    ax.set_xlabel(r"regeneration count  $i\,/\,R$")
    ax.set_ylabel(r"regeneration time  $T_i\,/\,T_R$")
    ax.legend(loc="upper left", fontsize=8)
    title = "Scaled regeneration quantiles (thesis Fig. 42)\nnear the unit slope: the chain mixes"
    ax.set_title(title + (f"\n{note}" if note else ""), fontsize=9)
    return fig


def draw_srq(
    points_by_chain: Mapping[str, SrqPoints], path: Path, *, config: ReportConfig, note: str = ""
) -> Path:
    """Write the SRQ plot (:func:`srq_figure`) of several chains to ``path``."""
    fig = srq_figure(points_by_chain, note=note)
    fig.savefig(path, dpi=config.dpi)
    return path


def _hashable(state: Any) -> Hashable:
    if isinstance(state, np.ndarray):
        return tuple(state.tolist())
    return tuple(state) if isinstance(state, list) else state


def chain_states(ptm: Ptm, trace: Mapping[str, Any] | None = None) -> list[list[Hashable]] | None:
    """The MCMC cold-chain states (one list per chain) of ``trace`` (:func:`load_chain_trace`) when given,
    else of ``ptm.inference[SRQ_KEY]``; None if absent.

    Label lists become tuples (hashable); numpy arrays are accepted as from an in-memory result.

    Raises:
        DataError: the states are something other than non-empty sequences of states, one per chain.
    """
    raw = trace["chains"] if trace is not None else ptm.inference.get(SRQ_KEY)
    if raw is None:
        return None
    rows = raw.tolist() if isinstance(raw, np.ndarray) else raw
    if isinstance(rows, str | bytes) or not isinstance(rows, Sequence) or not rows:
        msg = f"ptm.inference[{SRQ_KEY!r}] must be a non-empty list with one state list per chain"
        raise DataError(msg)
    chains = []
    for k, row in enumerate(rows):
        seq = row.tolist() if isinstance(row, np.ndarray) else row
        if isinstance(seq, str | bytes) or not isinstance(seq, Sequence) or not seq:
            got = type(seq).__name__
            msg = f"ptm.inference[{SRQ_KEY!r}][{k}] must be a non-empty list of states, got {got}"
            raise DataError(msg)
        chains.append([_hashable(s) for s in seq])
    return chains


def chain_srq(chains: Sequence[Sequence[Hashable]]) -> tuple[dict[str, SrqPoints], list[int]]:
    """SRQ points (``"chain k"`` → ``(x, y)``) of every chain at one atom, the state most visited over
    all chains, and the chains that never visit it (trapped away from the mode: no points)."""
    atom = most_visited([s for chain in chains for s in chain])
    points: dict[str, SrqPoints] = {}
    missing = []
    for k, chain in enumerate(chains):
        if atom in set(chain):
            points[f"chain {k}"] = srq_points(chain, atom)
        else:
            missing.append(k)
    return points, missing


def split_chain_trace(ptm: Ptm, *, trace_file: str | None = None) -> tuple[Ptm, dict[str, Any] | None]:
    """``(ptm, trace)``: the PTM whose ``inference`` keeps only a summary of MCMC's cold chains, and the
    chains' full states as a trace document (None when ``ptm`` holds none).

    The summary (:data:`CHAINS_KEY`) holds ``chains``, ``states`` (kept per chain), ``thin`` (sweeps per
    kept state), ``srq_max_deviation`` (per chain, the SRQ plot's ``max |y − x|`` at the atom most
    visited over all chains; null for a chain that never visits it) and ``trace`` (``trace_file``: where
    the caller writes the trace, null when nowhere). The trace (:data:`TRACE_SCHEMA`) holds ``thin``,
    ``chains`` (the states, one list per chain: topology ids, or label lists) and ``topologies`` (the
    labels of each id, when known).

    Raises:
        DataError: malformed states (:func:`chain_states`).
    """
    inf = dict(ptm.inference)
    chains = chain_states(ptm)
    if chains is None:
        return ptm, None
    raw = inf.pop(SRQ_KEY)
    rows = raw.tolist() if isinstance(raw, np.ndarray) else [list(np.asarray(c).tolist()) for c in raw]
    thin = int(inf.pop(SRQ_THIN_KEY, 1))
    labels = inf.pop(SRQ_LABELS_KEY, None)
    points, _ = chain_srq(chains)
    devs = [points.get(f"chain {k}") for k in range(len(chains))]
    inf[CHAINS_KEY] = {
        "chains": len(chains),
        "states": [len(c) for c in chains],
        "thin": thin,
        "srq_max_deviation": [None if p is None else srq_deviation(*p) for p in devs],
        "trace": trace_file,
    }
    trace = {"schema": TRACE_SCHEMA, "thin": thin, "chains": rows, "topologies": labels}
    return replace(ptm, inference=inf), trace


def save_chain_trace(trace: Mapping[str, Any], path: str | Path) -> Path:
    """Write a trace document (:func:`split_chain_trace`) as compact JSON; returns the path."""
    path = Path(path)
    path.write_text(json.dumps(trace, separators=(",", ":")), encoding="utf-8")
    return path


def load_chain_trace(path: str | Path, ptm: Ptm) -> dict[str, Any]:
    """The trace document at ``path``, checked against ``ptm``'s chain summary (:data:`CHAINS_KEY`: the
    same number of chains, states per chain and thinning).

    Raises:
        DataError: not a trace, malformed, or the trace of another run.
        OSError: the file cannot be read.
    """
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        msg = f"{path} is not a JSON document: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict) or doc.get("schema") != TRACE_SCHEMA:
        msg = f"{path} is not an MCMC trace (schema {TRACE_SCHEMA})"
        raise DataError(msg)
    summary = ptm.inference.get(CHAINS_KEY)
    chains = chain_states(ptm, doc)
    got = {"states": [len(c) for c in chains or ()], "thin": doc.get("thin")}
    if not isinstance(summary, Mapping) or {k: summary.get(k) for k in got} != got:
        msg = f"{path} is the trace of another run (its chains do not match the PTM's {CHAINS_KEY})"
        raise DataError(msg)
    return doc


def find_chain_trace(ptm: Ptm, directory: str | Path) -> dict[str, Any] | None:
    """The trace that ``ptm``'s chain summary names (``trace``, a file in ``directory``, the directory of
    its ptm.json), loaded and checked (:func:`load_chain_trace`); None when it names none or the file is
    missing."""
    summary = ptm.inference.get(CHAINS_KEY)
    name = summary.get("trace") if isinstance(summary, Mapping) else None
    if not isinstance(name, str) or not (Path(directory) / name).is_file():
        return None
    return load_chain_trace(Path(directory) / name, ptm)


def srq_summary_line(summary: Mapping[str, Any]) -> str:
    """The report line of a chain summary (:data:`CHAINS_KEY`) without the states: the SRQ figures, and
    that the plot needs the trace."""
    devs = summary.get("srq_max_deviation") or []
    shown = [f"chain {k} {'–' if d is None else f'{d:.3f}'}" for k, d in enumerate(devs)]
    trapped = [str(k) for k, d in enumerate(devs) if d is None]
    line = f"SRQ max |y − x| (0 = ideal mixing): {', '.join(shown)}" if shown else "SRQ"
    if trapped:
        line += f"; atom never visited by chain {', '.join(trapped)}"
    return line + f"; the SRQ plot needs the chains' states: run ptm-run with --trace (they go to {TRACE})"


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.3f}"


#: The scalar figures of ``ptm.inference`` that :func:`inference_line` shows, per method, in words:
#: key -> (label, unit). MCMC's convergence figures have their own line (``ptm-run``'s inference notes).
INFERENCE_WORDS: dict[str, dict[str, tuple[str, str]]] = {
    "rbpf": {
        "particles": ("particles", ""),
        "seed": ("seed", ""),
        "resample": ("resampling", ""),
        "n_topologies": ("distinct topologies held", ""),
        "ess": ("ESS", ""),
        "log_evidence": ("log evidence", " nats"),
        "update_ms_median": ("update time median", " ms"),
        "update_ms_p95": ("95th percentile", " ms"),
    },
    "exact": {"n_topologies_evaluated": ("topologies enumerated", "")},
    "mcmc": {"seed": ("seed", ""), "estimate": ("estimate", ""), "samples": ("samples", "")},
}
#: One sentence on the consistent mass, wherever it is shown.
CONSISTENT_MASS_MEANING = (
    "consistent mass = the posterior mass of the topologies that put no scored visit pair wrong; on long "
    "real runs it is often 0, because every listed topology gets at least one of hundreds of pairs wrong, "
    "even at an F1 of 0.98"
)


def _value(value: Any) -> str:
    """A scalar for a reader: yes/no, whole numbers as they are, other numbers to 3 significant digits."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return sig(float(value))
    return str(value)


def inference_line(inference: Mapping[str, Any]) -> str:
    """``method: rbpf (particles 100, seed 0, …, ESS 1.00/100, log evidence 278.9 nats, …)``: the estimator
    with its scalar figures (:data:`INFERENCE_WORDS` for the known methods, every scalar for others),
    rounded for reading (:func:`ptm_ros.reporting.figures.sig`; the ESS as a share of the topologies held)."""
    inf = dict(inference)
    method = str(inf.pop("method", "unknown"))
    words = INFERENCE_WORDS.get(method)
    if words is None:
        words = {
            k: (k.replace("_", " "), "") for k, v in inf.items() if isinstance(v, int | float | str | bool)
        }
    parts = []
    for key, (label, unit) in words.items():
        v = inf.get(key)
        if v is None or not isinstance(v, int | float | str | bool):
            continue
        if key == "ess" and isinstance(inf.get("n_topologies"), int):
            text = ess_fraction(float(v), inf["n_topologies"])
        elif key == "log_evidence":
            text = f"{float(v):.1f}"
        else:
            text = _value(v)
        parts.append(f"{label} {text}{unit}")
    return f"method: {method}" + (f" ({', '.join(parts)})" if parts else "")


def visits_line(ptm: Ptm, declared: int | None = None) -> str:
    """``visits: 10; topologies listed: 50, listed mass 1.000``, and how the visits reconcile with the
    landmarks the detector declared (``declared``, else the drops counted in ``diagnostics.skipped``:
    :func:`ptm_ros.perception.landmarks.landmark_accounting`)."""
    from ptm_ros.perception.landmarks import landmark_accounting

    line = (
        f"visits: {len(ptm.landmarks)}; topologies listed: {len(ptm.topologies)}, "
        f"listed mass {sum(t.probability for t in ptm.topologies):.3f}"
    )
    diag = ptm.extra.get("diagnostics")
    skipped = diag.get("skipped") if isinstance(diag, Mapping) else None
    accounting = landmark_accounting(
        len(ptm.landmarks), skipped if isinstance(skipped, Mapping) else {}, declared
    )
    return line + (f" ({accounting})" if accounting else "")


def _summary(ptm: Ptm, notes: Sequence[str] = (), declared: int | None = None) -> list[str]:
    top = ptm.topologies[0] if ptm.topologies else None
    lines = [inference_line(ptm.inference), visits_line(ptm, declared)]
    if top is not None:
        lines.append(f"most probable topology: p = {top.probability:.3f}, {num_places(top.labels)} places")
    wall = ptm.timing.get("wall_s")
    if isinstance(wall, (int, float)):
        lines.append(f"wall time: {wall:.2f} s")
    return lines + list(notes)


def _score_rows(score: Score) -> list[tuple[str, str, str]]:
    m, e = score.map.counts, score.expected
    return [
        ("precision", _fmt(m.precision), _fmt(e.precision)),
        ("recall", _fmt(m.recall), _fmt(e.recall)),
        ("F1", _fmt(m.f1), _fmt(e.f1)),
        ("TP / FP / FN", f"{m.tp:.0f} / {m.fp:.0f} / {m.fn:.0f}", f"{e.tp:.2f} / {e.fp:.2f} / {e.fn:.2f}"),
        ("places", str(score.map.num_places), f"true: {score.n_true_places} ({score.true_places_from})"),
    ]


def _score_notes(score: Score) -> list[str]:
    return [
        f"consistent mass: {score.consistent_mass:.3f} ({CONSISTENT_MASS_MEANING.split(' = ', 1)[1]})",
        f"mass of the exactly-true topology: {_fmt(score.true_topology_mass)}",
        f"mass-weighted mean F1: {score.mean_f1:.3f}",
        f"scored pairs: {score.n_scored_pairs} of {score.n_pairs} ({score.n_same_pairs} same, "
        f"{score.n_different_pairs} different; same < {score.config.same_radius} m, "
        f"different > {score.config.different_radius} m)",
    ] + (
        [f"visits without ground truth (unscored): {score.n_visits_without_truth}"]
        if score.n_visits_without_truth
        else []
    )


def _topology_rows(ptm: Ptm, score: Score | None, config: ReportConfig) -> list[tuple[str, ...]]:
    rows: list[tuple[str, ...]] = []
    for k, t in enumerate(ptm.topologies[: config.max_rows]):
        row: tuple[str, ...] = (str(k + 1), f"{t.probability:.4f}", str(num_places(t.labels)))
        if score is not None:
            row += (f"{score.topologies[k].counts.f1:.3f}", "yes" if score.topologies[k].consistent else "no")
        rows.append((*row, label_string(t.labels, config.max_label_chars)))
    return rows


def _table_head(score: Score | None) -> list[str]:
    scored = ["F1", "consistent"] if score is not None else []
    return ["rank", "probability", "places", *scored, "labels"]


def _table_title(ptm: Ptm, config: ReportConfig) -> str:
    return f"Top topologies ({min(config.max_rows, len(ptm.topologies))} of {len(ptm.topologies)})"


def _markdown(
    title: str,
    ptm: Ptm,
    score: Score | None,
    figures: list[tuple[str, str]],
    config: ReportConfig,
    *,
    notes: Sequence[str] = (),
    declared: int | None = None,
) -> str:
    out = [f"# {title}", ""]
    out += [f"- {line}" for line in _summary(ptm, notes, declared)]
    if score is not None:
        out += ["", "## Ground truth", "", "| | MAP topology | posterior |", "|---|---|---|"]
        out += [f"| {a} | {b} | {c} |" for a, b, c in _score_rows(score)]
        out += [""] + [f"- {line}" for line in _score_notes(score)]
    out += ["", "## Figures", ""]
    out += [f"![{caption}]({name})" + "\n" for caption, name in figures]
    head = _table_head(score)
    out += [f"## {_table_title(ptm, config)}", ""]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r[:-1]) + f" | `{r[-1]}` |" for r in _topology_rows(ptm, score, config)]
    return "\n".join(out) + "\n"


def _html(
    title: str,
    ptm: Ptm,
    score: Score | None,
    figures: list[tuple[str, str]],
    config: ReportConfig,
    *,
    notes: Sequence[str] = (),
    declared: int | None = None,
) -> str:
    e = html.escape
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #999;padding:2px 8px}"
        "img{max-width:100%}code{font-size:90%}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        "<ul>" + "".join(f"<li>{e(line)}</li>" for line in _summary(ptm, notes, declared)) + "</ul>",
    ]
    if score is not None:
        out.append("<h2>Ground truth</h2><table><tr><th></th><th>MAP topology</th><th>posterior</th></tr>")
        out += [f"<tr><td>{e(a)}</td><td>{e(b)}</td><td>{e(c)}</td></tr>" for a, b, c in _score_rows(score)]
        out.append("</table><ul>" + "".join(f"<li>{e(line)}</li>" for line in _score_notes(score)) + "</ul>")
    out.append("<h2>Figures</h2>")
    out += [
        f'<p><a href="{e(name)}"><img src="{e(name)}" alt="{e(caption)}"></a><br>{e(caption)}</p>'
        for caption, name in figures
    ]
    head = _table_head(score)
    out.append(f"<h2>{e(_table_title(ptm, config))}</h2>")
    out.append("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>")
    for r in _topology_rows(ptm, score, config):
        cells = "".join(f"<td>{e(c)}</td>" for c in r[:-1])
        out.append(f"<tr>{cells}<td><code>{e(r[-1])}</code></td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out) + "\n"


def _place_extra(src: str | Path, out_dir: Path, taken: set[str], prefix: str) -> str:
    """Copy a figure into ``out_dir`` (unless it is there already) under a name not yet ``taken``."""
    src = Path(src)
    if not src.is_file():
        msg = f"figure {src} does not exist"
        raise DataError(msg)
    name = src.name if src.name not in taken else f"{prefix}_{src.name}"
    if src.resolve() != (out_dir / name).resolve():
        shutil.copyfile(src, out_dir / name)
    taken.add(name)
    return name


def write_report(
    out_dir: str | Path,
    ptm: Ptm,
    *,
    trajectory: ArrayLike | None = None,
    score: Score | None = None,
    surprise_trace: SurpriseTrace | None = None,
    occupancy_map: str | Path | None = None,
    map_comparison: MapComparison | None = None,
    extra_figures: Sequence[str | Path] = (),
    notes: Sequence[str] = (),
    title: str = "Probabilistic topological map",
    config: ReportConfig | None = None,
    chain_trace: Mapping[str, Any] | None = None,
    workers: WorkerPool | None = None,
) -> Path:
    """Write the figures, ``report.md`` and ``report.html`` into ``out_dir``; returns the HTML path.

    ``trajectory`` ``(T, 3)`` (or ``(T, 2)``) odometry or smoothed poses drawn under the topologies;
    ``score`` from :func:`ptm_ros.scoring.evaluation.score_ptm` on this PTM; ``surprise_trace`` the landmark
    detector's :attr:`~ptm_ros.perception.surprise.LaserSurpriseDetector.trace` (drawn unless empty); the SRQ
    plot is drawn from ``chain_trace`` (:func:`load_chain_trace`) or, without it, from the states in
    ``ptm.inference[SRQ_KEY]``; a PTM with only the chains' summary (:data:`CHAINS_KEY`) gets its SRQ
    figures as a line and a note that the plot needs ``ptm-run --trace``; ``occupancy_map`` an image of
    the metric map (shown with :data:`MAP_CAPTION`) and ``extra_figures`` image files to include (both
    copied into ``out_dir`` unless already there); ``map_comparison`` the map side by side with its
    reference or its route graph (:func:`draw_map_comparison`); ``notes`` extra summary lines;
    ``workers`` (optional) draws the figures while the pages are written.
    """
    config = config or ReportConfig()
    if not ptm.topologies:
        msg = "cannot report a PTM without topologies"
        raise DataError(msg)
    traj = None
    if trajectory is not None:
        traj = np.asarray(trajectory, dtype=float)
        if traj.ndim != 2 or traj.shape[1] not in (2, 3) or not np.all(np.isfinite(traj)):
            msg = f"trajectory must be finite (T, 3) or (T, 2) poses, got shape {traj.shape}"
            raise ModelError(msg)
    if score is not None and (
        len(score.topologies) != len(ptm.topologies) or score.n_visits != len(ptm.landmarks)
    ):
        msg = (
            f"the score is of another PTM ({score.n_visits} visits, {len(score.topologies)} topologies; "
            f"this PTM has {len(ptm.landmarks)} and {len(ptm.topologies)})"
        )
        raise DataError(msg)
    chains = chain_states(ptm, chain_trace)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drawn: list[Future[Path]] = []

    def draw(fn: Callable[..., Path], *args: Any, **kwargs: Any) -> None:
        if workers is None:
            fn(*args, **kwargs)
        else:
            drawn.append(workers.submit(fn, *args, **kwargs))

    draw(draw_histogram, ptm, out / HISTOGRAM, score=score, config=config)
    draw(draw_topologies, ptm, out / TOPOLOGIES, trajectory=traj, score=score, config=config)
    figures = [
        ("PTM histogram", HISTOGRAM),
        (f"Top {min(config.top_k, len(ptm.topologies))} topologies", TOPOLOGIES),
    ]
    if score is not None:
        draw(draw_scores, score, out / SCORES, config=config)
        figures.append(("Scores against ground truth", SCORES))
    if ptm_timeline(ptm):
        truth = score.true_labels if score is not None else None
        draw(draw_timeline, ptm, out / TIMELINE, truth=truth, config=config)
        figures.append((TIMELINE_CAPTION, TIMELINE))
    notes = list(notes)
    declared = None
    if surprise_trace is not None and len(surprise_trace.stamps):
        declared = len(surprise_trace.landmarks)
        draw(draw_surprise, surprise_trace, out / SURPRISE, config=config)
        figures.append(("Bayesian surprise of the landmark detector (thesis Fig. 62)", SURPRISE))
        notes.append(
            f"landmark detector: {len(surprise_trace.stamps)} measurements, "
            f"{len(surprise_trace.landmarks)} landmarks declared by surprise"
        )
    if chains is not None:
        points, missing = chain_srq(chains)
        trapped = f"never visited by chain {', '.join(map(str, missing))}" if missing else ""
        thin = ptm.inference.get(SRQ_THIN_KEY)
        every = f"states, one per {thin} sweeps" if isinstance(thin, int) and thin > 1 else "states"
        note = f"atom: the state most visited over all chains ({sum(map(len, chains))} {every})"
        draw(draw_srq, points, out / SRQ, config=config, note=note + (f"; {trapped}" if trapped else ""))
        figures.append(("Scaled regeneration quantiles of the MCMC chains (thesis Fig. 42)", SRQ))
        devs = ", ".join(f"{name} {srq_deviation(x, y):.3f}" for name, (x, y) in points.items())
        notes.append(f"SRQ max |y − x| (0 = ideal mixing): {devs}" + (f"; atom {trapped}" if trapped else ""))
    elif isinstance(summary := ptm.inference.get(CHAINS_KEY), Mapping):
        notes.append(srq_summary_line(summary))
    taken = {HISTOGRAM, TOPOLOGIES, SCORES, SURPRISE, SRQ, TIMELINE, MAP_COMPARISON, REPORT_MD, REPORT_HTML}
    if occupancy_map is not None:
        figures.append((MAP_CAPTION, _place_extra(occupancy_map, out, taken, "map")))
    if map_comparison is not None:
        caption = REFERENCE_CAPTION if map_comparison.reference is not None else ROUTES_CAPTION
        draw(draw_map_comparison, map_comparison, out / MAP_COMPARISON, config=config)
        figures.append((caption, MAP_COMPARISON))
    figures += [(Path(f).stem, _place_extra(f, out, taken, f"extra{k}")) for k, f in enumerate(extra_figures)]
    md = _markdown(title, ptm, score, figures, config, notes=notes, declared=declared)
    (out / REPORT_MD).write_text(md, encoding="utf-8")
    html_path = out / REPORT_HTML
    page = _html(title, ptm, score, figures, config, notes=notes, declared=declared)
    html_path.write_text(page, encoding="utf-8")
    for future in drawn:
        future.result()  # a figure's error is the report's
    return html_path
