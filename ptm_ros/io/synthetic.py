"""Synthetic visit runs: a route over fixed places with odometry drawn from the model's own noise.

For tests and benchmarks that need visits with a known truth but no sensors: the robot stands at each place
of ``route`` facing the next one; the odometry of each step is the true relative pose plus N(0, Σ_k), Σ_k
the covariance of :class:`~ptm_ros.model.odometry.OdometryConfig` for that step's travel and rotation (times
``noise``). Visits may carry signatures: a per-place appearance plus N(0, ``sig_noise``²) per component.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from ptm_ros.model.geometry import FloatArray, NoMatch, Registrar, RelativePose, between, compose
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.visits import Visit, pose_field

#: Heading at the last visit: towards the previous place (``back``) or straight on, away from it (``ahead``).
EndHeading = Literal["back", "ahead"]


def true_poses(route: Sequence[int], places: ArrayLike, end_heading: EndHeading = "back") -> FloatArray:
    """``(N, 3)`` true poses of the visits of ``route`` (place indices into ``places``, ``(P, 2)``): each at
    its place, facing the next place of the route."""
    pts = np.asarray(places, dtype=float)
    out = []
    for i, p in enumerate(route):
        if i + 1 < len(route):
            nxt = pts[route[i + 1]]
        else:
            nxt = pts[route[i - 1]] if end_heading == "back" else 2 * pts[p] - pts[route[i - 1]]
        out.append(np.array([*pts[p], math.atan2(*(nxt - pts[p])[::-1])]))
    return np.array(out)


def odometry_visits(
    true: FloatArray,
    odometry: OdometryConfig,
    rng: np.random.Generator,
    *,
    noise: float = 1.0,
    appearance: FloatArray | None = None,
    sig_noise: float = 0.1,
    nonnegative: bool = False,
    yaw_bias: float = 0.0,
    patches: Sequence[FloatArray | None] | None = None,
) -> list[Visit]:
    """Visits at the true poses ``true`` (``(N, 3)``) with odometry from ``odometry``'s noise model.

    Draws from ``rng``, per visit: the odometry noise (after the first visit), then the signature noise
    when ``appearance`` (``(N, K)``, the true appearance at each visit) is given. ``nonnegative`` takes the
    signatures' absolute values; ``yaw_bias`` (rad/m) adds a systematic heading drift to the odometry;
    ``patches`` are the visits' laser patches.
    """
    visits, u = [], true[0].copy()
    for i in range(len(true)):
        travel = rotation = 0.0
        if i > 0:
            rel = between(true[i - 1], true[i])
            travel, rotation = float(np.hypot(rel[0], rel[1])), abs(float(rel[2]))
            var_xy = odometry.a_xy * travel + odometry.b_xy
            var_th = odometry.a_th * rotation + odometry.c_th * travel + odometry.b_th
            error = noise * rng.normal(0.0, np.sqrt([var_xy, var_xy, var_th]))
            if yaw_bias:
                error = error + np.array([0.0, 0.0, yaw_bias * travel])
            u = compose(u, rel + error)
        sig = None
        if appearance is not None:
            sig = appearance[i] + rng.normal(0.0, sig_noise, appearance.shape[1])
            if nonnegative:
                sig = np.abs(sig)
        patch = None if patches is None else patches[i]
        visits.append(
            Visit(i, float(i), pose_field(u), travel=travel, rotation=rotation, signature=sig, patch=patch)
        )
    return visits


def visits_at(poses: ArrayLike) -> list[Visit]:
    """Visits at the odometry poses ``poses`` (``(N, 3)``), travel and rotation from the straight steps
    between them."""
    u = np.asarray(poses, dtype=float)
    out = [Visit(0, 0.0, pose_field(u[0]))]
    for k in range(1, len(u)):
        o = between(u[k - 1], u[k])
        travel, rotation = float(np.hypot(o[0], o[1])), abs(float(o[2]))
        out.append(Visit(k, float(k), pose_field(u[k]), travel=travel, rotation=rotation))
    return out


def simulate_route(
    route: Sequence[int],
    places: ArrayLike,
    odometry: OdometryConfig,
    seed: int = 0,
    *,
    signatures: bool = False,
    sig_noise: float = 0.1,
) -> tuple[list[Visit], FloatArray]:
    """The visits of ``route`` (:func:`true_poses`, :func:`odometry_visits` from ``default_rng(seed)``) and
    their true poses. With ``signatures``, signatures of 4 components around a random appearance per place
    (uniform in [1, 3)); the appearance is drawn first, with or without ``signatures``, so a seed gives the
    same odometry either way."""
    rng = np.random.default_rng(seed)
    appearance = rng.uniform(1.0, 3.0, size=(np.shape(places)[0], 4))
    true = true_poses(route, places)
    at_visits = appearance[np.asarray(route)] if signatures else None
    return odometry_visits(true, odometry, rng, appearance=at_visits, sig_noise=sig_noise), true


def grid_route(
    n: int, side: int = 4, spacing: float = 8.0, seed: int = 0
) -> tuple[list[tuple[float, float]], list[int]]:
    """A random walk of ``n`` visits over a side×side grid of places ``spacing`` m apart, without immediate
    U-turns, from place 0: (the places' positions, the route)."""
    rng = np.random.default_rng(seed)
    steps = ((1, 0), (-1, 0), (0, 1), (0, -1))
    cur, prev, route = 0, -1, [0]
    for _ in range(n - 1):
        x, y = cur % side, cur // side
        nb = [(x + dx) + (y + dy) * side for dx, dy in steps if 0 <= x + dx < side and 0 <= y + dy < side]
        if prev in nb:
            nb.remove(prev)
        prev, cur = cur, int(rng.choice(nb))
        route.append(cur)
    return [(spacing * (i % side), spacing * (i // side)) for i in range(side * side)], route


def truth_registrar(
    true: FloatArray,
    route: Sequence[int],
    sd: tuple[float, float, float] = (0.05, 0.05, 0.01),
    seed: int = 0,
    *,
    fitness: bool = False,
) -> Registrar:
    """Laser measurements between visits of the same true place (the true relative pose plus N(0, sd²),
    seeded per pair), None for other pairs. With ``fitness``, matches carry a fitness evidence of 2.5 and
    other pairs are :class:`~ptm_ros.model.geometry.NoMatch` outcomes with a negative one (varying by
    pair)."""

    def registrar(i: int, j: int) -> RelativePose | NoMatch | None:
        if route[i] != route[j]:
            return NoMatch(i, j, -1.0 - 0.3 * ((i + j) % 3)) if fitness else None
        rng = np.random.default_rng([seed, i, j])
        mean = between(true[i], true[j]) + rng.normal(0.0, sd)
        return RelativePose(i, j, mean, np.diag(np.square(sd)), 2.5 if fitness else 0.0)

    return registrar
