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
= highest y). Map files (docs.ros.org map_server "Map format"; nav2 ``nav2_map_server/src/map_io.cpp``):
a YAML with ``image, mode, resolution, origin [x, y, yaw], negate, occupied_thresh, free_thresh`` and a
binary PGM; with ``negate: 0`` a pixel ``v`` reads as occupancy ``p = (255 - v) / 255`` and, in trinary
mode, as occupied when ``p > occupied_thresh``, free when ``p < free_thresh``, unknown otherwise.
:func:`save_map` writes occupied 0, free 254 and unknown as the grey level in the middle of the unknown
band of *these* thresholds (140 for the defaults): nav2's own saver writes unknown as 205, which
reads back as free whenever ``free_thresh > 50/255``, as with nav2's default 0.25.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import expit

from ptm_ros.errors import ConfigError, DataError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

OCCUPIED = 100
FREE = 0
UNKNOWN = -1
PIXEL_OCCUPIED = 0
PIXEL_FREE = 254
#: Names of the map files :func:`save_map_files` writes (``map.pgm``, ``map.yaml``, ``map.png``).
MAP_STEM = "map"


@dataclass(frozen=True)
class OccupancyConfig:
    """Occupancy grid parameters.

    Attributes:
        resolution: cell size (m).
        max_range: usable beam length (m); longer returns are truncated to free space without a hit.
        missing_ray_length: a no-return beam (range at or beyond the scan's ``range_max``) clears this
            far (m; 0: not at all), as Cartographer's ``missing_data_ray_length``.
        l_occ: log-odds increment of a cell holding a return (> 0; logit(0.7)).
        l_free: log-odds increment of a cell a beam passes through (< 0; logit(0.45): a hit outweighs
            about 4 passes, module docstring).
        clamp: log odds are kept in ``[-clamp, clamp]`` (> 0).
        margin: unknown border around the data (m).
        occupied_thresh: map_server threshold: occupancy above it is occupied.
        free_thresh: map_server threshold: occupancy below it is free.
        max_cells: largest grid built (a guard against a stray pose far away).
    """

    resolution: float = 0.05
    max_range: float = 20.0
    missing_ray_length: float = 2.0
    l_occ: float = 0.85
    l_free: float = -0.2
    clamp: float = 5.0
    margin: float = 1.0
    occupied_thresh: float = 0.65
    free_thresh: float = 0.25
    max_cells: int = 50_000_000

    def __post_init__(self) -> None:
        positive = {"resolution": self.resolution, "max_range": self.max_range, "clamp": self.clamp}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                msg = f"OccupancyConfig.{name} must be a positive finite number, got {value}"
                raise ConfigError(msg)
        if not (math.isfinite(self.l_occ) and self.l_occ > 0):
            msg = f"OccupancyConfig.l_occ must be > 0 (evidence for occupied), got {self.l_occ}"
            raise ConfigError(msg)
        if not (math.isfinite(self.l_free) and self.l_free < 0):
            msg = f"OccupancyConfig.l_free must be < 0 (evidence for free), got {self.l_free}"
            raise ConfigError(msg)
        if not (math.isfinite(self.missing_ray_length) and self.missing_ray_length >= 0):
            msg = f"OccupancyConfig.missing_ray_length must be >= 0, got {self.missing_ray_length}"
            raise ConfigError(msg)
        if not (math.isfinite(self.margin) and self.margin >= 0):
            msg = f"OccupancyConfig.margin must be >= 0, got {self.margin}"
            raise ConfigError(msg)
        if not (1.0 / 255.0 < self.free_thresh < self.occupied_thresh < 1.0):
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
        if self.max_cells < 1:
            msg = f"OccupancyConfig.max_cells must be >= 1, got {self.max_cells}"
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
    """A trinary map read back from map_server files: ``data (H, W)`` in {-1, 0, 100}, row 0 = lowest
    y (the ``nav_msgs/OccupancyGrid`` order), and the YAML fields."""

    data: NDArray[np.int8] = field(repr=False)
    origin: tuple[float, float, float]
    resolution: float
    occupied_thresh: float
    free_thresh: float
    negate: bool
    image: Path


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
class _Beams:
    """The usable beams of one scan in world coordinates."""

    origin: FloatArray  # (2,)
    ends: FloatArray  # (B, 2)
    hit: NDArray[np.bool_]  # (B,)


def _scan_beams(
    pose: FloatArray,
    ranges: FloatArray,
    *,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    max_range: float,
    missing_ray_length: float,
) -> tuple[_Beams, int]:
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
    return _Beams(pose[:2].copy(), ends, hit[used]), int(len(ranges) - valid.sum())


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

    def beams_of(t: int) -> tuple[_Beams, int]:
        return _scan_beams(
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
    """``nav_msgs/OccupancyGrid.data`` as map_server publishes the files of :func:`save_map` (trinary
    mode): ``(H*W,)`` int8, row-major from row 0 = lowest y, only 100 / 0 / -1 (:func:`trinary` with the
    thresholds of the saved YAML), so a subscriber of ``/map`` sees the cells ``map.pgm`` holds."""
    return trinary(grid, config).reshape(-1)


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


def save_map(
    grid: OccupancyGrid, stem: str | Path, config: OccupancyConfig | None = None
) -> tuple[Path, Path]:
    """Write ``STEM.pgm`` (binary P5, trinary) and ``STEM.yaml`` for nav2's map_server; returns both paths.

    Loading them with map_server's rule (``negate: 0``, ``mode: trinary``) gives back :func:`trinary`.
    """
    cfg = config if config is not None else OccupancyConfig()
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    pgm = stem.with_name(stem.name + ".pgm")
    yml = stem.with_name(stem.name + ".yaml")
    pix = _pixels(trinary(grid, cfg), cfg)
    header = f"P5\n# ptm_ros occupancy grid, {grid.resolution} m/cell\n{grid.width} {grid.height}\n255\n"
    pgm.write_bytes(header.encode("ascii") + np.ascontiguousarray(pix).tobytes())
    x, y, yaw = grid.origin
    yml.write_text(
        f"image: {json.dumps(pgm.name)}\n"
        "mode: trinary\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{x!r}, {y!r}, {yaw!r}]\n"
        "negate: 0\n"
        f"occupied_thresh: {cfg.occupied_thresh!r}\n"
        f"free_thresh: {cfg.free_thresh!r}\n"
    )
    return pgm, yml


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
    """Read a map_server YAML and its PGM the way nav2 does in trinary mode (the round trip of
    :func:`save_map`)."""
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
    if mode != "trinary":
        msg = f"{yaml_path}: only mode 'trinary' is supported, got {mode!r}"
        raise DataError(msg)
    if len(origin) != 3:
        msg = f"{yaml_path}: origin must have 3 elements, got {len(origin)}"
        raise DataError(msg)
    if not image.is_absolute():
        image = yaml_path.parent / image
    pix = read_pgm(image).astype(float)
    occ = pix / 255.0 if negate else (255.0 - pix) / 255.0
    data = np.full(pix.shape, UNKNOWN, dtype=np.int8)
    data[occ < free_th] = FREE
    data[occ > occ_th] = OCCUPIED
    return MapFile(
        data=data[::-1].copy(),
        origin=(origin[0], origin[1], origin[2]),
        resolution=resolution,
        occupied_thresh=occ_th,
        free_thresh=free_th,
        negate=negate,
        image=image,
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
    """The map files of a run in ``out_dir``: ``map.pgm`` + ``map.yaml`` (:func:`save_map`) and ``map.png``
    (:func:`save_png`, with the ``(T, >=2)`` ``trajectory`` the scans were placed along drawn over it).
    ``ptm-run`` and the map publisher both write their maps with it; returns the three paths."""
    out = Path(out_dir)
    pgm, yml = save_map(grid, out / MAP_STEM, config)
    title = f"occupancy grid ({grid.resolution:g} m cells, {grid.scans} scans), smoothed MAP trajectory"
    png = save_png(grid, out / f"{MAP_STEM}.png", trajectory=trajectory, title=title)
    return pgm, yml, png
