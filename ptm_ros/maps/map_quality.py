"""How well an occupancy map matches a reference map of the same scans drawn at the true poses.

A map can score well on the trajectory (ATE) and still be unusable for navigation: rays that clear
space outside the building, walls erased by passing beams. This module compares the product's map with
a *reference*: the same scans placed at the ground-truth poses (with only the beams that returned, so
the reference clears nothing a return does not vouch for), the product's map carried into the
reference frame by the rigid 2-D motion ``x ↦ R_θ x + t`` of the ATE alignment
(:func:`ptm_ros.scoring.evaluation.rigid_alignment` of the map's trajectory onto the ground truth).

Both maps are given as map_server trinary classes (:data:`~ptm_ros.maps.occupancy.OCCUPIED`,
:data:`~ptm_ros.maps.occupancy.FREE`, :data:`~ptm_ros.maps.occupancy.UNKNOWN`, row 0 = lowest y), the
reference also with its set of *seen* cells (any beam passed or ended there, whatever its class). Distances
are between cell centres: a map cell centre is carried into the other grid and takes the distance
(Euclidean distance transform, metres) stored at the cell holding it. With ``F`` the map's free cells,
``W`` its occupied cells, ``S`` the reference's seen cells and ``W*`` its walls:

.. math::
    \\text{leak} = \\frac{|\\{c \\in F : d(c, S) > r_\\text{leak}\\}|}{|F|}, \\qquad
    \\text{precision} = \\frac{|\\{c \\in W : d(c, W^*) \\le r_\\text{wall}\\}|}{|W|}, \\qquad
    \\text{recall} = \\frac{|\\{c \\in W^* : d(c, W) \\le r_\\text{wall}\\}|}{|W^*|}

and the free-area ratio ``|F| a / |F*| a*`` (``a``, ``a*`` the cell areas, ``F*`` the reference's free
cells), with ``r_leak = 0.3`` m and ``r_wall = 0.2`` m by default. An empty denominator gives NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import distance_transform_edt

from ptm_ros.errors import DataError
from ptm_ros.maps.occupancy import FREE, OCCUPIED
from ptm_ros.model.geometry import FloatArray

LEAK_RADIUS = 0.3  # m: a free cell farther than this from every seen reference cell is a leak
WALL_RADIUS = 0.2  # m: an occupied cell this close to a wall of the other map matches it


@dataclass(frozen=True)
class ClassGrid:
    """Trinary classes ``classes (H, W)`` (row 0 = lowest y) with the world pose ``origin (x, y, yaw=0)``
    of cell (0, 0)'s lower-left corner and the cell size ``resolution`` (m); ``seen (H, W)`` marks the
    cells any beam reached (None: the cells whose class is not unknown)."""

    classes: NDArray[np.int8]
    origin: tuple[float, float, float]
    resolution: float
    seen: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        c = np.asarray(self.classes)
        if c.ndim != 2:
            msg = f"classes must be (H, W), got shape {c.shape}"
            raise DataError(msg)
        if self.seen is not None and np.shape(self.seen) != c.shape:
            msg = f"seen has shape {np.shape(self.seen)}, classes {c.shape}"
            raise DataError(msg)
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            msg = f"resolution must be a positive finite number, got {self.resolution}"
            raise DataError(msg)
        if self.origin[2] != 0.0:
            msg = f"only grids with yaw 0 are supported, got origin yaw {self.origin[2]}"
            raise DataError(msg)

    def seen_cells(self) -> NDArray[np.bool_]:
        return np.asarray(self.seen, dtype=bool) if self.seen is not None else np.asarray(self.classes) != -1

    def centres(self, mask: NDArray[np.bool_]) -> FloatArray:
        """World ``(n, 2)`` centres of the cells of ``mask``."""
        rows, cols = np.nonzero(mask)
        return np.column_stack(
            [
                self.origin[0] + (cols + 0.5) * self.resolution,
                self.origin[1] + (rows + 0.5) * self.resolution,
            ]
        )

    def distance_at(self, mask: NDArray[np.bool_], points: FloatArray, reach: float) -> FloatArray:
        """Distance (m) from each world point's cell to the nearest cell centre of ``mask``; points off the
        grid by more than ``reach`` and grids without a cell in ``mask`` read ``inf``."""
        out = np.full(len(points), np.inf)
        if not np.any(mask) or len(points) == 0:
            return out
        pad = math.ceil(reach / self.resolution) + 1
        dist = distance_transform_edt(~np.pad(mask, pad), sampling=self.resolution)
        ij = np.floor((points - np.asarray(self.origin[:2])) / self.resolution).astype(np.int64) + pad
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < dist.shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < dist.shape[0])
        out[inside] = dist[ij[inside, 1], ij[inside, 0]]
        return out


@dataclass(frozen=True)
class MapQuality:
    """The figures of the module docstring; counts are cells, areas m²."""

    leak: float
    wall_precision: float
    wall_recall: float
    free_area_ratio: float
    free_area_m2: float
    reference_free_area_m2: float
    free_cells: int
    leaked_cells: int
    wall_cells: int
    reference_wall_cells: int

    def as_dict(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}


def _share(count: int, total: int) -> float:
    return count / total if total else math.nan


def _motion(theta: float, t: ArrayLike | Sequence[float]) -> tuple[FloatArray, FloatArray]:
    """Rotation matrix and shift of ``x ↦ R_theta x + t``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]]), np.asarray(t, dtype=float).reshape(2)


def leaked_cells(
    product: ClassGrid,
    reference: ClassGrid,
    *,
    theta: float = 0.0,
    t: ArrayLike | Sequence[float] = (0.0, 0.0),
    leak_radius: float = LEAK_RADIUS,
) -> NDArray[np.bool_]:
    """``(H, W)`` mask of the product's free cells whose centre, carried into the reference frame by
    ``x ↦ R_theta x + t``, lies more than ``leak_radius`` from every cell the reference has seen (the
    leak's numerator, module docstring)."""
    if not leak_radius >= 0:
        msg = f"leak_radius must be >= 0, got {leak_radius}"
        raise DataError(msg)
    rot, shift = _motion(theta, t)
    free = np.asarray(product.classes) == FREE
    free_in_ref = product.centres(free) @ rot.T + shift
    far = reference.distance_at(reference.seen_cells(), free_in_ref, leak_radius) > leak_radius
    out = np.zeros(free.shape, dtype=bool)
    rows, cols = np.nonzero(free)
    out[rows[far], cols[far]] = True
    return out


def map_quality(
    product: ClassGrid,
    reference: ClassGrid,
    *,
    theta: float = 0.0,
    t: ArrayLike | Sequence[float] = (0.0, 0.0),
    leak_radius: float = LEAK_RADIUS,
    wall_radius: float = WALL_RADIUS,
) -> MapQuality:
    """Compare ``product`` (in its own frame) with ``reference``, the product carried into the reference
    frame by ``x ↦ R_theta x + t`` (module docstring)."""
    if not (leak_radius >= 0 and wall_radius >= 0):
        msg = f"radii must be >= 0, got leak_radius={leak_radius}, wall_radius={wall_radius}"
        raise DataError(msg)
    rot, shift = _motion(theta, t)
    pc = np.asarray(product.classes)
    rc = np.asarray(reference.classes)
    free, walls = pc == FREE, pc == OCCUPIED
    ref_free, ref_walls = rc == FREE, rc == OCCUPIED
    leaked = int(
        np.count_nonzero(leaked_cells(product, reference, theta=theta, t=t, leak_radius=leak_radius))
    )
    walls_in_ref = product.centres(walls) @ rot.T + shift
    precise = int(
        np.count_nonzero(reference.distance_at(ref_walls, walls_in_ref, wall_radius) <= wall_radius)
    )
    ref_in_product = (reference.centres(ref_walls) - shift) @ rot
    found = int(np.count_nonzero(product.distance_at(walls, ref_in_product, wall_radius) <= wall_radius))
    n_free, n_walls, n_ref_walls = int(free.sum()), int(walls.sum()), int(ref_walls.sum())
    area = n_free * product.resolution**2
    ref_area = int(ref_free.sum()) * reference.resolution**2
    return MapQuality(
        leak=_share(leaked, n_free),
        wall_precision=_share(precise, n_walls),
        wall_recall=_share(found, n_ref_walls),
        free_area_ratio=area / ref_area if ref_area > 0 else math.nan,
        free_area_m2=area,
        reference_free_area_m2=ref_area,
        free_cells=n_free,
        leaked_cells=leaked,
        wall_cells=n_walls,
        reference_wall_cells=n_ref_walls,
    )
