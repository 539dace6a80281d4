"""SE(2) pose algebra shared by the odometry, laser and simulation code.

A pose is ``(x, y, yaw)`` with yaw in radians. All functions accept a single pose of shape ``(3,)`` or
a stack of poses of shape ``(..., 3)`` and broadcast.

.. math::
    a \\oplus b = (a_x + \\cos a_\\theta b_x - \\sin a_\\theta b_y,\\;
                   a_y + \\sin a_\\theta b_x + \\cos a_\\theta b_y,\\; a_\\theta + b_\\theta)

    a \\ominus b = a^{-1} \\oplus b \\quad\\text{(the pose of b seen from a)}
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(theta: ArrayLike) -> FloatArray:
    """Wrap angles to ``[-pi, pi)``."""
    t = np.asarray(theta, dtype=float)
    return (t + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a ⊕ b``: the pose ``b`` (expressed in frame ``a``) expressed in the frame ``a`` is expressed in."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: ArrayLike) -> FloatArray:
    """``a^{-1}`` such that ``a ⊕ a^{-1} = 0``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a ⊖ b = a^{-1} ⊕ b``: the pose of ``b`` in the frame of ``a`` (relative odometry from a to b)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def moved(a: ArrayLike, b: ArrayLike, xy: float, yaw: float) -> bool:
    """Whether pose ``b`` lies ``xy`` or more from pose ``a`` or is turned ``yaw`` or more from it (the
    keyframe and motion-gate test of the laser modules and the map)."""
    d = between(a, b)
    return bool(math.hypot(d[0], d[1]) >= xy or abs(d[2]) >= yaw)


def transform_points(pose: ArrayLike, points: ArrayLike) -> FloatArray:
    """Map 2-D points ``(P, 2)`` from the frame of ``pose`` into the frame ``pose`` is expressed in."""
    p = np.asarray(pose, dtype=float)
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    c, s = np.cos(p[2]), np.sin(p[2])
    rot = np.array([[c, -s], [s, c]])
    return pts @ rot.T + p[:2]


def path_length(poses: ArrayLike) -> float:
    """Length of the polyline through the ``(x, y)`` of a pose sequence ``(T, 3)``."""
    p = np.asarray(poses, dtype=float)
    if len(p) < 2:
        return 0.0
    return float(np.sum(np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))))


@dataclass(frozen=True)
class RelativePose:
    """A Gaussian measurement of ``between(x_i, x_j)``, the pose of visit j in the frame of visit i.

    Produced by laser patch registration (:mod:`ptm_ros.perception.laser`) and consumed by the metric
    likelihood (:mod:`ptm_ros.model.odometry`). ``mean`` is ``(dx, dy, dyaw)``; ``cov`` is a symmetric
    positive-definite ``(3, 3)`` covariance in the same order.
    """

    i: int
    j: int
    mean: FloatArray
    cov: FloatArray
    log_bayes: float = 0.0  # evidence of the match's fitness for "one place" (see NoMatch)


@dataclass(frozen=True)
class NoMatch:
    """Patches of visits ``i < j`` that were registered and did not match (no relative pose).

    ``log_bayes`` = log p(fitness | one place) − log p(fitness | different places) of the best alignment
    found (:func:`ptm_ros.perception.laser.fitness_log_bayes`): usually negative, evidence against the same
    place.
    """

    i: int
    j: int
    log_bayes: float


#: Laser outcome for visits ``i < j``: a :class:`RelativePose` measurement of ``between(x_i, x_j)``, a
#: :class:`NoMatch`, or None when nothing could be registered ("no information"). Callers cache per pair.
Registrar = Callable[[int, int], "RelativePose | NoMatch | None"]


def interpolate_poses(stamps: ArrayLike, poses: ArrayLike, query: ArrayLike) -> FloatArray:
    """Poses at the ``query`` times: linear in x, y and along the shortest arc in yaw.

    ``stamps`` ``(T,)`` must be non-decreasing; a query equal to a knot returns that knot's pose exactly
    (yaw unwrapped as given); queries outside ``[stamps[0], stamps[-1]]`` take the end pose (callers
    decide how far outside is acceptable). Interpolated yaws are wrapped to ``[-pi, pi)``.
    """
    t = np.asarray(stamps, dtype=float).reshape(-1)
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    q = np.atleast_1d(np.asarray(query, dtype=float)).reshape(-1)
    if len(t) == 0 or len(t) != len(p):
        msg = f"need matching non-empty stamps and poses, got {len(t)} and {len(p)}"
        raise ValueError(msg)
    if len(t) == 1:
        return np.repeat(p, len(q), axis=0)
    q = np.clip(q, t[0], t[-1])
    hi = np.clip(np.searchsorted(t, q, side="right"), 1, len(t) - 1)
    lo = hi - 1
    span = t[hi] - t[lo]
    frac = np.divide(q - t[lo], span, out=np.zeros_like(q), where=span > 0)
    xy = p[lo, :2] + frac[:, None] * (p[hi, :2] - p[lo, :2])
    yaw = wrap_angle(p[lo, 2] + frac * wrap_angle(p[hi, 2] - p[lo, 2]))
    out = np.column_stack([xy, yaw])
    k = np.searchsorted(t, q, side="left")
    exact = t[np.minimum(k, len(t) - 1)] == q
    out[exact] = p[k[exact]]
    return out
