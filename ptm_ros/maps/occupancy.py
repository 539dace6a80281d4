"""Occupancy grid of a run from laser scans at known poses, and its nav2 ``map_server`` files.

Not part of the topology inference (the thesis only names occupancy grids as the metric-map
alternative, Ch. 0.1, Fig. 2): this module draws the metric map that goes with a PTM, from the scans and
the poses of one trajectory (ground truth, a smoothed trajectory of a topology, or raw odometry).

Model (binary Bayes filter in log odds, cells independent, prior ``l = 0``). For each scan, every
cell a beam passes through receives ``l_free`` and the cell holding a beam's return receives ``l_occ``,
each cell at most once per scan, a return winning over a pass of another beam of the same scan; the
log odds are clamped to ``[-clamp, clamp]`` after every scan:

.. math::
    l_t(c) = \\operatorname{clip}\\bigl(l_{t-1}(c) + l_\\text{occ}\\,[c \\in H_t]
             + l_\\text{free}\\,[c \\in F_t \\setminus H_t],\\; -\\text{clamp}, \\text{clamp}\\bigr)

Hits weigh more than misses, as in the mature mappers (Cartographer's ``hit_probability`` 0.55 /
``miss_probability`` 0.49, a hit worth 5 misses; GMapping's counting model with ``occ_thresh`` 0.25, a
hit worth 3): ``l_occ = logit(0.7) ≈ 0.85`` and ``l_free = logit(0.45) ≈ -0.2``, so a cell that holds
returns stays occupied until beams pass through it more than about 4 times as often as they end there;
the beams that graze a wall at a shallow angle, crossing its cells on their way to a farther part of it,
no longer erase it. The clamp bounds how long a cell remembers (a door opened later can still clear).

A beam of range ``r`` is used up to ``min(r, max_range)``; it has a return (a hit) only when
``r < range_max`` and ``r <= max_range``: a return beyond ``max_range`` is clipped there, clearing
without a hit. A beam at or beyond ``range_max`` is "no return" (a CARMEN log's 81.9 m readings): it says
nothing about where the next obstacle is, only that the sensor saw none close by, so it clears
``min(missing_ray_length, max_range, range_max)`` (Cartographer's ``missing_data_ray_length``), no hit.
NaN, ±inf, non-positive and below-``range_min`` ranges are skipped and counted
(:attr:`OccupancyGrid.skipped`). Ray casting is the exact traversal of the cells a
segment's interior meets (the cells Amanatides–Woo visits), vectorised over the beams of a scan
(:func:`grid_traversal`).

Layout: ``log_odds[row, col]``, row 0 = lowest y, column 0 = lowest x; ``origin`` is the world pose of
the lower-left corner of cell (0, 0) (yaw always 0). This is the ``nav_msgs/OccupancyGrid`` data order
(:func:`to_ros_data`). The nav2 ``map_server`` image is the same grid flipped vertically (image row 0
= highest y). Map files (docs.ros.org map_server "Map format"; nav2 ``nav2_map_server/src/map_io.cpp``,
``loadMapFromFile``): a YAML with ``image, mode, resolution, origin [x, y, yaw], negate,
occupied_thresh, free_thresh`` and an image; with ``negate: 0`` a pixel of grey level ``v`` reads as
occupancy ``p = (255 - v) / 255``, then by ``mode`` (``OccupancyConfig.mode``):

* ``trinary`` (the default; a binary PGM): 100 when ``p > occupied_thresh``, 0 when ``p < free_thresh``,
  -1 otherwise. :func:`save_map` writes occupied 0, free 254 and unknown as the grey level in the middle
  of the unknown band of *these* thresholds (140 for the defaults): nav2's own saver writes unknown as
  205, which reads back as free whenever ``free_thresh > 50/255``, as with nav2's default 0.25.
* ``scale`` (an RGBA PNG: the mode needs transparency, and nav2's saver writes it as true colour with
  alpha): -1 for a pixel that is not opaque, else 100 / 0 as in trinary mode and
  ``rint(100 (p - free_thresh) / (occupied_thresh - free_thresh))`` in between. :func:`save_map` writes
  each observed cell as ``v = round(255 (1 - P(occupied)))``, opaque, and never observed cells
  transparent, so the grey levels between the thresholds keep how sure the map is.

The published ``/map`` (:func:`to_ros_data`) is what map_server publishes after loading the saved files
(:func:`map_cells`, the one reading of a pixel :func:`load_map` uses too), so a subscriber sees exactly
the cells of the saved map in either mode.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import expit

from ptm_ros.errors import ConfigError, DataError
from ptm_ros.model.geometry import FloatArray
from ptm_ros.settings import Settings, setting

IntArray = NDArray[np.int64]

OCCUPIED = 100
FREE = 0
UNKNOWN = -1
PIXEL_OCCUPIED = 0
PIXEL_FREE = 254
#: Names of the map files :func:`save_map_files` writes (``map.pgm``, ``map.yaml``, ``map.png``).
MAP_STEM = "map"
#: map_server modes :func:`save_map` writes, with the name of the image beside ``STEM.yaml``
#: (scale mode needs an image with transparency: a PNG, and ``STEM.png`` is the figure of the map).
MAP_IMAGES = {"trinary": "{stem}.pgm", "scale": "{stem}_scale.png"}
OPAQUE = 255


#: map_server modes :func:`save_map` writes (``OccupancyConfig.mode``).
MAP_MODES = tuple(MAP_IMAGES)
#: Occupancy of a free pixel (grey level 254): ``free_thresh`` must lie above it for the pixel to read free.
FREE_PIXEL_OCCUPANCY = 1.0 / 255.0


@dataclass(frozen=True)
class OccupancyConfig(Settings):
    """Occupancy grid parameters."""

    resolution: float = setting(0.05, gt=0, doc="cell size [m].")
    max_range: float = setting(
        20.0, gt=0, doc="usable beam length [m]; longer returns are truncated to free space without a hit."
    )
    missing_ray_length: float = setting(
        2.0,
        ge=0,
        doc=(
            "a no-return beam (range at or beyond the scan's ``range_max``) clears this far [m] (0: not at "
            "all), as Cartographer's ``missing_data_ray_length``."
        ),
    )
    l_occ: float = setting(
        0.85, gt=0, doc="log-odds increment of a cell holding a return (evidence for occupied; logit(0.7))."
    )
    l_free: float = setting(
        -0.2,
        lt=0,
        doc=(
            "log-odds increment of a cell a beam passes through (evidence for free; logit(0.45): a hit "
            "outweighs about 4 passes, module docstring)."
        ),
    )
    clamp: float = setting(5.0, gt=0, doc="log odds are kept in ``[-clamp, clamp]``.")
    margin: float = setting(1.0, ge=0, doc="unknown border around the data [m].")
    occupied_thresh: float = setting(
        0.65,
        gt=FREE_PIXEL_OCCUPANCY,
        lt=1,
        doc=(
            "map_server threshold: occupancy above it is occupied (below 1, the occupancy of the occupied "
            "pixel 0; above ``free_thresh``)."
        ),
    )
    free_thresh: float = setting(
        0.25,
        gt=FREE_PIXEL_OCCUPANCY,
        lt=1,
        doc=(
            "map_server threshold: occupancy below it is free (above 1/255, the occupancy of the free pixel "
            "254; below ``occupied_thresh``, with a grey level between the two for unknown)."
        ),
    )
    max_cells: int = setting(
        50_000_000, ge=1, doc="largest grid built (a guard against a stray pose far away)."
    )
    mode: str = setting(
        "trinary",
        choices=MAP_MODES,
        doc=(
            "map_server mode of the saved map and of ``/map`` (module docstring): ``trinary`` (``map.pgm``; "
            "100 / 0 / -1) or ``scale`` (``map_scale.png``; 100 / 0 / -1 and the occupancy between the "
            "thresholds as 1..99)."
        ),
    )

    def check(self) -> None:
        """``free_thresh < occupied_thresh``, with an 8-bit grey level between them for unknown."""
        if self.free_thresh >= self.occupied_thresh:
            msg = (
                "OccupancyConfig thresholds must satisfy 1/255 < free_thresh < occupied_thresh < 1 "
                f"(free pixel 254, occupied pixel 0), got free_thresh={self.free_thresh}, "
                f"occupied_thresh={self.occupied_thresh}"
            )
            raise ConfigError(msg)
        v = unknown_pixel(self.free_thresh, self.occupied_thresh)
        if not (self.free_thresh <= (255 - v) / 255.0 <= self.occupied_thresh):
            msg = (
                f"OccupancyConfig: no 8-bit grey level reads as unknown between free_thresh="
                f"{self.free_thresh} and occupied_thresh={self.occupied_thresh}; widen the band"
            )
            raise ConfigError(msg)


@dataclass(frozen=True)
class OccupancyGrid:
    """A built grid: ``log_odds (H, W)`` and ``observed (H, W)`` (row 0 = lowest y), the world pose
    ``origin (x, y, yaw=0)`` of cell (0, 0)'s lower-left corner, ``resolution`` (m); ``scans`` and
    ``beams`` used, ``skipped`` invalid ranges (NaN, ±inf, <= 0 or below range_min)."""

    log_odds: FloatArray = field(repr=False)
    observed: NDArray[np.bool_] = field(repr=False)
    origin: tuple[float, float, float]
    resolution: float
    scans: int = 0
    beams: int = 0
    skipped: int = 0

    @property
    def height(self) -> int:
        return int(self.log_odds.shape[0])

    @property
    def width(self) -> int:
        return int(self.log_odds.shape[1])


@dataclass(frozen=True)
class MapFile:
    """A map read back from map_server files: ``data (H, W)`` as map_server publishes it (row 0 = lowest
    y, the ``nav_msgs/OccupancyGrid`` order; {-1, 0, 100} in trinary mode, -1 and 0..100 in scale mode),
    and the YAML fields."""

    data: NDArray[np.int8] = field(repr=False)
    origin: tuple[float, float, float]
    resolution: float
    occupied_thresh: float
    free_thresh: float
    negate: bool
    image: Path
    mode: str = "trinary"

    def classes(self) -> NDArray[np.int8]:
        """``(H, W)`` trinary classes of the cells (:func:`classes_of`)."""
        return classes_of(self.data)


def unknown_pixel(free_thresh: float, occupied_thresh: float) -> int:
    """Grey level whose occupancy ``(255 - v) / 255`` is the middle of ``[free_thresh, occupied_thresh]``."""
    return round(255.0 * (1.0 - 0.5 * (free_thresh + occupied_thresh)))


def grid_traversal(starts: ArrayLike, ends: ArrayLike) -> tuple[IntArray, IntArray, IntArray]:
    """Cells whose interior each segment meets, in cell units (cell (i, j) = ``[i, i+1) × [j, j+1)``).

    ``starts`` and ``ends`` are ``(B, 2)`` (or ``(2,)`` broadcast) points ``(u, v)``. Returns flat arrays
    ``(ix, iy, ray)``: one entry per (segment, cell), cells of a segment in no particular order; the
    start and end cells are always included. Column by column: inside column ``i`` the segment spans
    ``v`` between its entry and exit values, so it meets the rows ``floor(min) .. floor(max)``. The set
    is the one Amanatides–Woo walks (up to measure-zero ties at exact corners).
    """
    p0 = np.asarray(starts, dtype=float)
    p1 = np.asarray(ends, dtype=float)
    p0, p1 = np.broadcast_arrays(p0.reshape(-1, 2), p1.reshape(-1, 2))
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(p1))):
        msg = "grid_traversal needs finite segment end points"
        raise DataError(msg)
    u0, v0, u1, v1 = p0[:, 0], p0[:, 1], p1[:, 0], p1[:, 1]
    du = u1 - u0
    c0 = np.floor(u0).astype(np.int64)
    c1 = np.floor(u1).astype(np.int64)
    step = np.where(c1 >= c0, 1, -1)
    ncol = np.abs(c1 - c0) + 1
    ray = np.repeat(np.arange(len(u0)), ncol)
    k = np.arange(int(ncol.sum())) - np.repeat(np.cumsum(ncol) - ncol, ncol)
    s = step[ray]
    col = c0[ray] + s * k
    first = k == 0
    last = k == ncol[ray] - 1
    safe = np.where(du != 0.0, du, 1.0)[ray]  # du == 0 only with a single column (first and last)
    b_in = np.where(s > 0, col, col + 1).astype(float)
    b_out = np.where(s > 0, col + 1, col).astype(float)
    t_in = np.where(first, 0.0, np.clip((b_in - u0[ray]) / safe, 0.0, 1.0))
    t_out = np.where(last, 1.0, np.clip((b_out - u0[ray]) / safe, 0.0, 1.0))
    dv = (v1 - v0)[ray]
    y_in = np.where(first, v0[ray], v0[ray] + t_in * dv)
    y_out = np.where(last, v1[ray], v0[ray] + t_out * dv)
    r_lo = np.floor(np.minimum(y_in, y_out)).astype(np.int64)
    r_hi = np.floor(np.maximum(y_in, y_out)).astype(np.int64)
    nrow = r_hi - r_lo + 1
    seg = np.repeat(np.arange(len(col)), nrow)
    j = np.arange(int(nrow.sum())) - np.repeat(np.cumsum(nrow) - nrow, nrow)
    return col[seg], r_lo[seg] + j, ray[seg]


def _per_scan(value: ArrayLike, n: int, name: str) -> FloatArray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    arr = arr.reshape(-1)
    if len(arr) != n:
        msg = f"{name} must be a scalar or have one value per scan ({n}), got {len(arr)}"
        raise DataError(msg)
    return arr


@dataclass(frozen=True)
class Beams:
    """The usable beams of one scan in world coordinates."""

    origin: FloatArray  # (2,)
    ends: FloatArray  # (B, 2)
    hit: NDArray[np.bool_]  # (B,)


def scan_beams(
    pose: FloatArray,
    ranges: FloatArray,
    *,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    max_range: float,
    missing_ray_length: float,
) -> tuple[Beams, int]:
    """Beam end points of one scan (module docstring: returns truncated at ``max_range``, no-return beams
    at ``missing_ray_length``; zero-length beams dropped) and the number of skipped ranges."""
    angles = angle_min + angle_increment * np.arange(len(ranges))
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & (ranges > 0.0) & (ranges >= range_min)
    r = ranges[valid]
    no_return = r >= range_max
    length = np.where(no_return, min(missing_ray_length, max_range, range_max), np.minimum(r, max_range))
    hit = ~no_return & (r <= max_range)
    used = length > 0.0
    heading = pose[2] + angles[valid][used]
    ends = pose[:2] + length[used, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    return Beams(pose[:2].copy(), ends, hit[used]), int(len(ranges) - valid.sum())


def build_grid(
    poses: ArrayLike,
    ranges: Sequence[ArrayLike] | NDArray[Any],
    angle_min: ArrayLike,
    angle_increment: ArrayLike,
    range_max: ArrayLike,
    *,
    config: OccupancyConfig | None = None,
    range_min: ArrayLike = 0.0,
) -> OccupancyGrid:
    """Occupancy grid of ``T`` scans taken at the world ``poses (T, 3)`` of the scanner.

    ``ranges`` holds one range array per scan (lengths may differ); ``angle_min``, ``angle_increment``,
    ``range_max`` and ``range_min`` are scalars or ``(T,)`` (LaserScan fields). The grid covers every
    sensor position and used beam end point plus ``config.margin``; its origin is a multiple of the
    resolution. Raises :class:`DataError` on inconsistent shapes, non-finite poses or an oversized grid.
    """
    cfg = config if config is not None else OccupancyConfig()
    P = np.asarray(poses, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        msg = f"poses must be (T, 3), got shape {P.shape}"
        raise DataError(msg)
    T = len(P)
    if T == 0:
        msg = "build_grid needs at least one scan"
        raise DataError(msg)
    if not np.all(np.isfinite(P)):
        msg = "poses must be finite"
        raise DataError(msg)
    if len(ranges) != T:
        msg = f"got {len(ranges)} range arrays for {T} poses"
        raise DataError(msg)
    a0 = _per_scan(angle_min, T, "angle_min")
    da = _per_scan(angle_increment, T, "angle_increment")
    rmax = _per_scan(range_max, T, "range_max")
    rmin = _per_scan(range_min, T, "range_min")
    if not (np.all(np.isfinite(a0)) and np.all(np.isfinite(da))):
        msg = "angle_min and angle_increment must be finite"
        raise DataError(msg)
    if not np.all(rmax > 0):
        msg = "range_max must be > 0 for every scan"
        raise DataError(msg)

    def beams_of(t: int) -> tuple[Beams, int]:
        return scan_beams(
            P[t],
            np.asarray(ranges[t], dtype=float).reshape(-1),
            angle_min=a0[t],
            angle_increment=da[t],
            range_min=rmin[t],
            range_max=rmax[t],
            max_range=cfg.max_range,
            missing_ray_length=cfg.missing_ray_length,
        )

    # Two passes over the scans (the extent first, then the rays), so that memory stays that of the grid
    # and one scan however many scans there are (the map publisher redraws maps of thousands).
    lo_pt, hi_pt = P[:, :2].min(axis=0), P[:, :2].max(axis=0)
    skipped = n_beams = 0
    for t in range(T):
        beams, bad = beams_of(t)
        skipped += bad
        n_beams += len(beams.ends)
        if len(beams.ends):
            lo_pt = np.minimum(lo_pt, beams.ends.min(axis=0))
            hi_pt = np.maximum(hi_pt, beams.ends.max(axis=0))
    res = cfg.resolution
    lo = np.floor((lo_pt - cfg.margin) / res) * res
    hi = hi_pt + cfg.margin
    width, height = (np.floor((hi - lo) / res).astype(np.int64) + 1).tolist()
    if width * height > cfg.max_cells:
        msg = (
            f"the grid would be {width} x {height} cells ({(hi - lo)[0]:.1f} m x {(hi - lo)[1]:.1f} m "
            f"at {res} m), more than max_cells={cfg.max_cells}; check the poses or raise the limit"
        )
        raise DataError(msg)

    log_odds = np.zeros(height * width)
    observed = np.zeros(height * width, dtype=bool)
    for t in range(T):
        beams, _ = beams_of(t)
        if len(beams.ends) == 0:
            continue
        start = (beams.origin - lo) / res
        ends = (beams.ends - lo) / res
        ix, iy, _ = grid_traversal(start, ends)
        passed = iy * width + ix
        e = np.floor(ends[beams.hit]).astype(np.int64)
        hits = e[:, 1] * width + e[:, 0]
        before = log_odds[hits]
        # Fancy assignment writes each repeated cell once: one update per cell and scan.
        log_odds[passed] = np.clip(log_odds[passed] + cfg.l_free, -cfg.clamp, cfg.clamp)
        log_odds[hits] = np.clip(before + cfg.l_occ, -cfg.clamp, cfg.clamp)
        observed[passed] = True
    return OccupancyGrid(
        log_odds=log_odds.reshape(height, width),
        observed=observed.reshape(height, width),
        origin=(float(lo[0]), float(lo[1]), 0.0),
        resolution=res,
        scans=T,
        beams=n_beams,
        skipped=skipped,
    )


def aligned_windows(
    a: NDArray[Any], a_origin: Sequence[float], b: NDArray[Any], b_origin: Sequence[float], resolution: float
) -> tuple[NDArray[Any], NDArray[Any]]:
    """The overlapping windows of two ``(H, W)`` grids of one resolution (row 0 = lowest y) whose origins
    lie on one lattice (as :func:`build_grid` places them): cell ``[r, c]`` of both windows is the same
    place. Used to compare two maps of one run (e.g. the map publisher's and ``ptm-run``'s).

    Raises:
        DataError: the grids do not overlap.
    """
    # the (column, row) of b's cell (0, 0) in a
    d = np.rint((np.asarray(b_origin[:2]) - np.asarray(a_origin[:2])) / resolution).astype(int)
    lo = np.maximum(0, d)
    hi = np.minimum(a.shape[::-1], d + np.array(b.shape[::-1]))
    if not np.all(hi > lo):
        msg = "the grids do not overlap"
        raise DataError(msg)
    return a[lo[1] : hi[1], lo[0] : hi[0]], b[lo[1] - d[1] : hi[1] - d[1], lo[0] - d[0] : hi[0] - d[0]]


def probabilities(grid: OccupancyGrid) -> FloatArray:
    """``(H, W)`` occupancy probabilities ``1 / (1 + exp(-l))``; never observed cells read 0.5."""
    return np.asarray(expit(grid.log_odds), dtype=float)


def to_ros_data(grid: OccupancyGrid, config: OccupancyConfig | None = None) -> NDArray[np.int8]:
    """``nav_msgs/OccupancyGrid.data`` as map_server publishes the files of :func:`save_map`: ``(H*W,)``
    int8, row-major from row 0 = lowest y (:func:`cells`), so a subscriber of ``/map`` sees the cells the
    saved map holds: only 100 / 0 / -1 in trinary mode, also 1..99 in scale mode."""
    return cells(grid, config).reshape(-1)


def cells(grid: OccupancyGrid, config: OccupancyConfig | None = None) -> NDArray[np.int8]:
    """``(H, W)`` values map_server publishes for the grid saved in ``config.mode`` (row 0 = lowest y):
    :func:`trinary` in trinary mode; in scale mode the reading (:func:`map_cells`) of the pixels
    :func:`save_map` writes, quantisation included."""
    cfg = config if config is not None else OccupancyConfig()
    if cfg.mode == "trinary":
        return trinary(grid, cfg)
    grey, alpha = _scale_pixels(grid)
    read = map_cells(
        grey, alpha, mode="scale", occupied_thresh=cfg.occupied_thresh, free_thresh=cfg.free_thresh
    )
    return read[::-1].copy()


def classes_of(values: ArrayLike) -> NDArray[np.int8]:
    """Trinary classes of map_server cell values: 100 stays occupied, 0 free, everything else (-1 and a
    scale map's 1..99, cells between the thresholds) unknown."""
    v = np.asarray(values)
    return np.where(v == OCCUPIED, OCCUPIED, np.where(v == FREE, FREE, UNKNOWN)).astype(np.int8)


def map_cells(
    grey: ArrayLike,
    alpha: ArrayLike | None = None,
    *,
    mode: str = "trinary",
    occupied_thresh: float,
    free_thresh: float,
    negate: bool = False,
) -> NDArray[np.int8]:
    """The cell values map_server (nav2 ``map_io.cpp``, ``loadMapFromFile``) reads from an image's grey
    levels ``grey (H, W)`` (the mean of its colour channels, 0..255) and its ``alpha (H, W)`` (255 =
    opaque; None: no alpha channel), in image order. Occupancy ``p = 1 - shade`` (``shade`` with
    ``negate``), ``shade = grey / 255``; trinary mode averages the alpha into the shade as a fourth
    channel when there is one; scale mode reads a pixel that is not opaque as unknown (module
    docstring)."""
    g = np.asarray(grey, dtype=float)
    a = None if alpha is None else np.asarray(alpha, dtype=float)
    if mode == "trinary" and a is not None:
        g = (3.0 * g + a) / 4.0
    shade = g / 255.0
    occ = shade if negate else 1.0 - shade
    out = np.full(g.shape, UNKNOWN, dtype=np.int8)
    between = (occ >= free_thresh) & (occ <= occupied_thresh)
    if mode == "scale":
        level = np.rint((occ - free_thresh) / (occupied_thresh - free_thresh) * 100.0)
        out[between] = level[between].astype(np.int8)
    elif mode != "trinary":
        msg = f"map_server mode {mode!r} is not supported (trinary, scale)"
        raise DataError(msg)
    out[occ > occupied_thresh] = OCCUPIED
    out[occ < free_thresh] = FREE
    if mode == "scale" and a is not None:
        out[a != OPAQUE] = UNKNOWN
    return out


def trinary(grid: OccupancyGrid, config: OccupancyConfig | None = None) -> NDArray[np.int8]:
    """``(H, W)`` map_server trinary classes of the grid: 100 when ``p > occupied_thresh``, 0 when
    ``p < free_thresh``, -1 otherwise and for never observed cells (row 0 = lowest y)."""
    cfg = config if config is not None else OccupancyConfig()
    p = probabilities(grid)
    out = np.full(p.shape, UNKNOWN, dtype=np.int8)
    out[(p < cfg.free_thresh) & grid.observed] = FREE
    out[(p > cfg.occupied_thresh) & grid.observed] = OCCUPIED
    return out


def _pixels(classes: NDArray[np.int8], config: OccupancyConfig) -> NDArray[np.uint8]:
    pix = np.full(classes.shape, unknown_pixel(config.free_thresh, config.occupied_thresh), dtype=np.uint8)
    pix[classes == FREE] = PIXEL_FREE
    pix[classes == OCCUPIED] = PIXEL_OCCUPIED
    return pix[::-1]  # image row 0 = highest y


def _scale_pixels(grid: OccupancyGrid) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Grey levels ``round(255 (1 - p))`` and alpha (opaque where observed, else transparent) of the
    scale-mode image, image row 0 = highest y."""
    grey = np.rint(255.0 * (1.0 - probabilities(grid))).astype(np.uint8)
    alpha = np.where(grid.observed, OPAQUE, 0).astype(np.uint8)
    return grey[::-1], alpha[::-1]


def write_png(path: Path, grey: NDArray[np.uint8], alpha: NDArray[np.uint8]) -> Path:
    """An 8-bit RGBA PNG (colour type 6, as nav2's saver writes scale maps) of ``(H, W)`` grey levels
    (R = G = B) and alpha, row 0 at the top; written with zlib, every row unfiltered."""
    h, w = grey.shape
    rgba = np.stack([grey, grey, grey, alpha], axis=-1).astype(np.uint8).reshape(h, 4 * w)
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), rgba], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    header = struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6))
    path.write_bytes(png + chunk(b"IEND", b""))
    return path


def read_image(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Grey levels (mean of the colour channels, 0..255) and alpha (0..255, None without an alpha
    channel) of a map image, ``(H, W)`` each, image row 0 first: a binary PGM (:func:`read_pgm`) or an
    8-bit PNG (read with matplotlib)."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        return read_pgm(path).astype(float), None
    from matplotlib.image import imread

    try:
        img = np.rint(np.asarray(imread(path), dtype=float) * 255.0)
    except (OSError, ValueError, SyntaxError) as err:
        msg = f"cannot read the PNG {path}: {err}"
        raise DataError(msg) from err
    if img.ndim == 2:
        return img, None
    channels = img.shape[2]
    if channels in (2, 4):
        return img[..., : channels - 1].mean(axis=2), img[..., channels - 1]
    return img.mean(axis=2), None


def save_map(
    grid: OccupancyGrid, stem: str | Path, config: OccupancyConfig | None = None
) -> tuple[Path, Path]:
    """Write the map_server image and ``STEM.yaml`` for nav2's map_server in ``config.mode``; returns
    both paths. Trinary: ``STEM.pgm`` (binary P5); scale: ``STEM_scale.png`` (RGBA, :data:`MAP_IMAGES`).

    Loading them with map_server's rule (``negate: 0``) gives back :func:`cells`.
    """
    cfg = config if config is not None else OccupancyConfig()
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    image = stem.with_name(MAP_IMAGES[cfg.mode].format(stem=stem.name))
    yml = stem.with_name(stem.name + ".yaml")
    if cfg.mode == "scale":
        write_png(image, *_scale_pixels(grid))
    else:
        pix = _pixels(trinary(grid, cfg), cfg)
        header = f"P5\n# ptm_ros occupancy grid, {grid.resolution} m/cell\n{grid.width} {grid.height}\n255\n"
        image.write_bytes(header.encode("ascii") + np.ascontiguousarray(pix).tobytes())
    x, y, yaw = grid.origin
    yml.write_text(
        f"image: {json.dumps(image.name)}\n"
        f"mode: {cfg.mode}\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{x!r}, {y!r}, {yaw!r}]\n"
        "negate: 0\n"
        f"occupied_thresh: {cfg.occupied_thresh!r}\n"
        f"free_thresh: {cfg.free_thresh!r}\n"
    )
    return image, yml


_PGM_HEADER = re.compile(rb"\AP5(?:\s+|#[^\n]*\n)+?(\d+)(?:\s+|#[^\n]*\n)+?(\d+)(?:\s+|#[^\n]*\n)+?(\d+)\s")


def read_pgm(path: str | Path) -> NDArray[np.uint8]:
    """An 8-bit binary (P5) PGM as an ``(H, W)`` array, image row 0 first (the top)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        msg = f"cannot read {path}: {err}"
        raise DataError(msg) from err
    m = _PGM_HEADER.match(raw)
    if m is None:
        msg = f"{path} is not a binary (P5) PGM"
        raise DataError(msg)
    w, h, maxval = (int(g) for g in m.groups())
    if maxval != 255:
        msg = f"{path}: only 8-bit PGMs (maxval 255) are supported, got maxval {maxval}"
        raise DataError(msg)
    body = raw[m.end() :]
    if len(body) < w * h:
        msg = f"{path}: expected {w * h} pixels, got {len(body)} bytes"
        raise DataError(msg)
    return np.frombuffer(body[: w * h], dtype=np.uint8).reshape(h, w)


def load_map(yaml_path: str | Path) -> MapFile:
    """Read a map_server YAML and its image (a binary PGM or a PNG) the way nav2 does in trinary or scale
    mode (:func:`map_cells`; the round trip of :func:`save_map`)."""
    import yaml

    yaml_path = Path(yaml_path)
    try:
        doc: Any = yaml.safe_load(yaml_path.read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f"cannot read map YAML {yaml_path}: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict):
        msg = f"{yaml_path}: a map YAML must be a mapping"
        raise DataError(msg)
    try:
        image = Path(str(doc["image"]))
        resolution = float(doc["resolution"])
        origin = tuple(float(v) for v in doc["origin"])
        occ_th = float(doc["occupied_thresh"])
        free_th = float(doc["free_thresh"])
        negate = bool(int(doc["negate"]))
    except (KeyError, TypeError, ValueError) as err:
        msg = f"{yaml_path}: missing or malformed map field: {err!r}"
        raise DataError(msg) from err
    mode = str(doc.get("mode", "trinary"))
    if mode not in MAP_IMAGES:
        msg = f"{yaml_path}: only modes {sorted(MAP_IMAGES)} are supported, got {mode!r}"
        raise DataError(msg)
    if len(origin) != 3:
        msg = f"{yaml_path}: origin must have 3 elements, got {len(origin)}"
        raise DataError(msg)
    if not image.is_absolute():
        image = yaml_path.parent / image
    grey, alpha = read_image(image)
    data = map_cells(grey, alpha, mode=mode, occupied_thresh=occ_th, free_thresh=free_th, negate=negate)
    return MapFile(
        data=data[::-1].copy(),
        origin=(origin[0], origin[1], origin[2]),
        resolution=resolution,
        occupied_thresh=occ_th,
        free_thresh=free_th,
        negate=negate,
        image=image,
        mode=mode,
    )


def save_png(
    grid: OccupancyGrid,
    path: str | Path,
    *,
    trajectory: ArrayLike | None = None,
    title: str | None = None,
    dpi: int = 150,
) -> Path:
    """Figure of the grid for reports: occupancy probability in grey (black = occupied, never observed =
    mid grey), metres on the axes, equal aspect; an optional ``(T, >=2)`` trajectory drawn over it."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    x0, y0, _ = grid.origin
    extent = (x0, x0 + grid.width * grid.resolution, y0, y0 + grid.height * grid.resolution)
    aspect = grid.height / max(grid.width, 1)
    fig = Figure(figsize=(7.0, max(3.0, min(14.0, 7.0 * aspect + 0.8))), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.imshow(
        probabilities(grid),
        cmap="gray_r",
        vmin=0.0,
        vmax=1.0,
        origin="lower",
        extent=extent,
        interpolation="nearest",
    )
    if trajectory is not None:
        xy = np.asarray(trajectory, dtype=float)
        ax.plot(xy[:, 0], xy[:, 1], color="tab:red", linewidth=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"occupancy grid ({grid.resolution:g} m cells, {grid.scans} scans)", fontsize=9)
    fig.savefig(path, dpi=dpi)
    return path


def save_map_files(
    grid: OccupancyGrid, out_dir: str | Path, config: OccupancyConfig, *, trajectory: ArrayLike | None = None
) -> tuple[Path, Path, Path]:
    """The map files of a run in ``out_dir``: the map_server image (``map.pgm``, or ``map_scale.png`` in
    scale mode) + ``map.yaml`` (:func:`save_map`) and ``map.png`` (:func:`save_png`, with the
    ``(T, >=2)`` ``trajectory`` the scans were placed along drawn over it). ``ptm-run`` and the map
    publisher both write their maps with it; returns the three paths (image, YAML, figure)."""
    out = Path(out_dir)
    image, yml = save_map(grid, out / MAP_STEM, config)
    title = f"occupancy grid ({grid.resolution:g} m cells, {grid.scans} scans), smoothed MAP trajectory"
    png = save_png(grid, out / f"{MAP_STEM}.png", trajectory=trajectory, title=title)
    return image, yml, png
