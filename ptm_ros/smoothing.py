"""Smoothed trajectories for a topology (thesis Ch. 5, Fig. 50/52, 56–57).

Given a topology, :func:`ptm_ros.odometry.optimize_poses` gives the maximum-likelihood visit poses X*
under the odometry, the topology's same-place constraints and the laser registrations. The full
trajectory between two visits is then the odometry deformed to fit them: a sample at time t between
visits k and k+1 is carried forward from X*_k and backward from X*_{k+1} by the raw odometry increments,

.. math::
    a_t = X^*_k \\oplus (u_k \\ominus u_t), \\qquad b_t = X^*_{k+1} \\oplus (u_{k+1} \\ominus u_t),

and the two are blended by the fraction of odometry travel s ∈ [0, 1] from k to k+1 (positions linearly,
headings along the shortest arc). At the visits the result equals X* exactly; before the first and after
the last visit the odometry is carried rigidly. This spreads each inter-visit correction along the path in
proportion to distance travelled, as odometry error accumulates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ModelError
from ptm_ros.geometry import between, compose, wrap_angle


def smoothed_trajectory(
    odom_stamps: ArrayLike, odom_poses: ArrayLike, visit_stamps: ArrayLike, visit_poses: ArrayLike
) -> NDArray[np.float64]:
    """The odometry trajectory ``(T, 3)`` deformed to pass through the optimised visit poses.

    ``visit_stamps`` must be odometry stamps (visits sit on odometry samples) in increasing order;
    ``visit_poses`` ``(N, 3)`` are the optimised poses at those stamps.
    """
    t = np.asarray(odom_stamps, dtype=float).reshape(-1)
    u = np.asarray(odom_poses, dtype=float).reshape(-1, 3)
    vs = np.asarray(visit_stamps, dtype=float).reshape(-1)
    x = np.asarray(visit_poses, dtype=float).reshape(-1, 3)
    if len(t) != len(u) or len(vs) != len(x) or len(vs) == 0:
        msg = f"need matching stamps/poses: {len(t)}/{len(u)} odometry, {len(vs)}/{len(x)} visits"
        raise ModelError(msg)
    idx = np.searchsorted(t, vs)
    if np.any(idx >= len(t)) or np.any(t[np.minimum(idx, len(t) - 1)] != vs) or np.any(np.diff(idx) <= 0):
        msg = "visit stamps must be increasing odometry stamps"
        raise ModelError(msg)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(u[:, 0]), np.diff(u[:, 1])))])
    out = np.empty_like(u)
    # before the first and after the last visit: rigid transport of the odometry
    out[: idx[0]] = compose(x[0], between(u[idx[0]], u[: idx[0]]))
    out[idx[-1] :] = compose(x[-1], between(u[idx[-1]], u[idx[-1] :]))
    for k in range(len(idx) - 1):
        lo, hi = idx[k], idx[k + 1]
        seg = u[lo : hi + 1]
        a = compose(x[k], between(u[lo], seg))
        b = compose(x[k + 1], between(u[hi], seg))
        span = travel[hi] - travel[lo]
        s = (travel[lo : hi + 1] - travel[lo]) / span if span > 0 else np.linspace(0.0, 1.0, hi - lo + 1)
        xy = (1.0 - s)[:, None] * a[:, :2] + s[:, None] * b[:, :2]
        yaw = wrap_angle(a[:, 2] + s * wrap_angle(b[:, 2] - a[:, 2]))
        out[lo : hi + 1] = np.column_stack([xy, yaw])
    out[idx] = x  # exactly the optimised poses at the visits
    return out
