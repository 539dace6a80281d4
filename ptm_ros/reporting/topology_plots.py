"""The figures of a PTM's topologies (after the thesis' Fig. 56–57), each written to the path given:

* :func:`draw_histogram` — the PTM as a histogram: one bar per topology (most probable first, at most
  ``max_bars``), height = posterior mass, tick = the compact label string
  (:func:`ptm_ros.reporting.plots.label_string`). With a score, consistent topologies (no scored pair wrong)
  are green, the others red.
* :func:`draw_topologies` — the ``top_k`` most probable topologies drawn over the trajectory (Fig. 56c,
  57b): visits at their odometry poses coloured by place, each place at its position
  (``Topology.positions`` when present, else the mean of its visits' poses) joined to its visits by
  faint spokes, and an edge between the places of consecutive visits.
* :func:`draw_scores` — precision / recall / F1 of the MAP topology and of the posterior against a ground
  truth, and the masses.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.maps.routes import place_means
from ptm_ros.model.partitions import IntSequence, num_places
from ptm_ros.model.ptm import Ptm, Topology
from ptm_ros.reporting.plots import ReportConfig, _new_figure, label_string
from ptm_ros.scoring.evaluation import Score

if TYPE_CHECKING:
    from matplotlib.axes import Axes

_GOLDEN = 0.618033988749895


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
