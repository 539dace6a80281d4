"""The side-by-side map figure of the report (:func:`draw_map_comparison`, input :class:`MapComparison`).

The map side by side with what it should be read against (issue #24): with a reference (the same scans at
the ground-truth poses, :mod:`ptm_ros.maps.map_quality`), the map carried onto it by the ATE alignment, its
leaked free cells (more than ``LEAK_RADIUS`` from anything the reference saw) in red, next to the reference;
without one, the map next to the MAP topology's route graph drawn over it (places, waypoints and edges as a
route server reads them, :mod:`ptm_ros.maps.routes`, the edges coloured by probability:
:func:`draw_route_graph`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ptm_ros.maps.map_quality import ClassGrid, leaked_cells
from ptm_ros.maps.occupancy import FREE, OCCUPIED, UNKNOWN
from ptm_ros.reporting.figures import sig
from ptm_ros.reporting.plots import ReportConfig, _new_figure

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Grey levels of the map figures: free, seen by a beam without being free (reference), unknown, wall.
_SHADES = {"free": 1.0, "seen": 0.85, "unknown": 0.62, "wall": 0.0}
_LEAK_RGB = (0.85, 0.1, 0.1)


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
