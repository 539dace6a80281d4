"""A 2-D robot simulator: noisy wheel odometry, a laser scanner and a panoramic camera in a textured world.

The robot (an ATRV-like skid-steer base, thesis Ch. 5) drives through the place visits of a
:class:`~ptm_ros.io.worlds.World` route at constant speed along the corridor centrelines: straight lines
joined by circular arcs of radius ``turn_radius`` at turns up to 135 degrees, and turns on the spot
(at ``rotation_speed``) where the route turns back (dead ends). It starts half-way along the corridor
that leads to the first visit and stops half-way along the corridor after the last one, so every visit
is a passage: the true position comes closest to the place, within ``passage_radius``.

Odometry (at ``odom_rate``) integrates the true body-frame increments ``u_k = x_{k-1} ⊖ x_k`` (distance
``δ_k``, rotation ``φ_k``) corrupted as

.. math::
    δ'_k = (1 + s)\\, (δ_k + σ_t \\sqrt{δ_k}\\, ξ_k), \\qquad
    φ'_k = φ_k + \\sqrt{σ_r^2 δ_k + σ_φ^2 |φ_k|}\\, ζ_k + b_k δ_k, \\qquad
    b_k = b_{k-1} + σ_w \\sqrt{δ_k}\\, η_k, \\quad b_0 \\sim N(\\bar b, σ_{b}^2),

with independent standard normals ξ, ζ, η. Variances grow linearly with the motion, so the error
statistics do not depend on the odometry rate; ``b`` is a heading drift per metre (a wheel-radius
mismatch that wanders slowly), the "realistic drift in heading" of a real base. Two systematic errors
are off by default: a scale error ``s`` of the distances (a wrong wheel radius) and a mean heading drift
``b̄`` (rad/m, one wheel smaller than the other). The odometry frame
starts at the origin; ``odometry_frame_offset`` = the true start pose maps it into the world frame.

Laser scans (sensor at the robot centre, beams counter-clockwise from ``angle_min``) and panoramas are
ray cast against the wall segments, vectorised over poses x rays x walls. A panorama is a cylindrical
360-degree image: column ``j`` looks along world azimuth ``yaw + 2πj/W`` (column 0 = robot heading,
increasing counter-clockwise), rows span heights ``h_c ± d tan(vfov/2)`` at distance ``d`` (row 0 at the
top). A pixel shows the wall texture at the hit's position along the wall and its height, ceiling above
the wall and floor below. Textures are procedural and seeded per texture id (panels, doors, posters,
rails, stripes); ``texture_aliasing`` mixes each wall's shared texture with a wall-unique one
(1 = walls with the same texture id are identical, 0 = every wall differs). Turning the robot by a whole
number of columns rolls the panorama exactly, so row-mean Fourier magnitudes (thesis Ch. 2.5) are
rotation invariant.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import BagError, ConfigError
from ptm_ros.io.groundtruth import SIM_FILENAME, GroundTruthTrajectory, Passage, Place, sim_gt_document
from ptm_ros.io.worlds import World
from ptm_ros.model.geometry import FloatArray, between, wrap_angle
from ptm_ros.perception.detectors import landmark_passages

#: Turns sharper than this (rad) are made on the spot instead of along an arc.
MAX_ARC_TURN = 0.75 * math.pi
#: Largest number of (ray, wall) pairs evaluated at once by the ray caster.
_RAY_CHUNK = 1 << 21


def _positive(owner: str, **values: float) -> None:
    for name, v in values.items():
        if not (math.isfinite(v) and v > 0.0):
            msg = f"{owner}.{name} must be finite and > 0, got {v}"
            raise ConfigError(msg)


def _non_negative(owner: str, **values: float) -> None:
    for name, v in values.items():
        if not (math.isfinite(v) and v >= 0.0):
            msg = f"{owner}.{name} must be finite and >= 0, got {v}"
            raise ConfigError(msg)


@dataclass(frozen=True)
class OdometryNoiseConfig:
    """Odometry error model (see the module docstring); all standard deviations.

    ``trans`` m/√m along the track; ``rot`` rad/√m heading noise from translation; ``turn`` rad/√rad
    heading noise from rotation; ``bias_init`` rad/m initial heading drift; ``bias_walk`` rad/m/√m
    random walk of the drift. Systematic errors (0 by default, which leaves the noise bit-identical to a
    model without them): ``scale`` the relative error of every distance (0.02 = odometry reads 2 % long),
    ``bias_mean`` rad/m the mean of the initial heading drift.
    """

    trans: float = 0.03
    rot: float = 0.005
    turn: float = 0.02
    bias_init: float = 5e-4
    bias_walk: float = 1e-4
    scale: float = 0.0
    bias_mean: float = 0.0

    def __post_init__(self) -> None:
        _non_negative(
            "OdometryNoiseConfig",
            trans=self.trans,
            rot=self.rot,
            turn=self.turn,
            bias_init=self.bias_init,
            bias_walk=self.bias_walk,
        )
        if not (math.isfinite(self.scale) and self.scale > -1.0):
            msg = f"OdometryNoiseConfig.scale must be finite and > -1, got {self.scale}"
            raise ConfigError(msg)
        if not math.isfinite(self.bias_mean):
            msg = f"OdometryNoiseConfig.bias_mean must be finite, got {self.bias_mean}"
            raise ConfigError(msg)


@dataclass(frozen=True)
class LaserConfig:
    """A planar laser scanner at the robot centre: ``beams`` over ``fov`` (rad) at ``rate`` Hz.

    With ``fov`` < 2π the beams span ``[-fov/2, fov/2]`` inclusive (181 beams over π = 1 degree apart);
    with ``fov`` = 2π they start at -π and the last beam stops one increment short of the first.
    Returns beyond ``range_max`` are +inf (REP 117); ``noise`` is the range standard deviation (m).
    ``stamp_delay`` (s, >= 0): each scan is stamped this long after it was taken, as by a driver that
    stamps scans on read-out (what ``laser_odometry.time_offset`` and ``ptm-calibrate`` undo).
    """

    rate: float = 10.0
    beams: int = 181
    fov: float = math.pi
    range_min: float = 0.05
    range_max: float = 20.0
    noise: float = 0.01
    stamp_delay: float = 0.0

    def __post_init__(self) -> None:
        _positive("LaserConfig", rate=self.rate, fov=self.fov, range_max=self.range_max)
        _non_negative("LaserConfig", range_min=self.range_min, noise=self.noise, stamp_delay=self.stamp_delay)
        if self.beams < 2:
            msg = f"LaserConfig.beams must be >= 2, got {self.beams}"
            raise ConfigError(msg)
        if self.fov > 2.0 * math.pi + 1e-12:
            msg = f"LaserConfig.fov must be <= 2π, got {self.fov}"
            raise ConfigError(msg)
        if self.range_min >= self.range_max:
            msg = f"LaserConfig.range_min ({self.range_min}) must be < range_max ({self.range_max})"
            raise ConfigError(msg)

    @property
    def full_circle(self) -> bool:
        """True when the beams cover 360 degrees."""
        return self.fov > 2.0 * math.pi - 1e-9

    @property
    def angle_min(self) -> float:
        """Angle of the first beam (rad, sensor frame, counter-clockwise from the heading)."""
        return -math.pi if self.full_circle else -self.fov / 2.0

    @property
    def angle_increment(self) -> float:
        """Angle between consecutive beams (rad)."""
        return self.fov / self.beams if self.full_circle else self.fov / (self.beams - 1)

    @property
    def angles(self) -> FloatArray:
        """Beam angles ``(B,)`` in the sensor frame (rad)."""
        return self.angle_min + self.angle_increment * np.arange(self.beams, dtype=float)


@dataclass(frozen=True)
class CameraConfig:
    """The panoramic camera: one ``height`` x ``width`` image every ``spacing`` m of travel.

    ``vfov`` (rad) is the vertical field of view of the cylindrical projection; ``camera_height`` and
    ``wall_height`` in m; ``noise`` the pixel noise standard deviation (grey levels); ``encoding``
    ``mono8`` or ``rgb8``; ``texture_aliasing`` in [0, 1] (see the module docstring); ``texture_seed``
    fixes the look of the textures (independent of the run's seed).
    """

    enabled: bool = True
    spacing: float = 1.0
    height: int = 64
    width: int = 512
    encoding: str = "mono8"
    vfov: float = math.radians(90.0)
    camera_height: float = 1.0
    wall_height: float = 2.5
    noise: float = 2.0
    texture_aliasing: float = 0.9
    texture_seed: int = 0

    def __post_init__(self) -> None:
        _positive(
            "CameraConfig",
            spacing=self.spacing,
            camera_height=self.camera_height,
            wall_height=self.wall_height,
        )
        _non_negative("CameraConfig", noise=self.noise)
        if self.height < 64 or self.width < 512:
            msg = f"CameraConfig: panoramas must be at least 64 x 512, got {self.height} x {self.width}"
            raise ConfigError(msg)
        if self.encoding not in ("mono8", "rgb8"):
            msg = f"CameraConfig.encoding must be 'mono8' or 'rgb8', got {self.encoding!r}"
            raise ConfigError(msg)
        if not 0.0 < self.vfov < math.pi:
            msg = f"CameraConfig.vfov must be in (0, π), got {self.vfov}"
            raise ConfigError(msg)
        if not 0.0 <= self.texture_aliasing <= 1.0:
            msg = f"CameraConfig.texture_aliasing must be in [0, 1], got {self.texture_aliasing}"
            raise ConfigError(msg)
        if self.camera_height >= self.wall_height:
            msg = f"CameraConfig.camera_height ({self.camera_height}) must be below wall_height"
            raise ConfigError(msg)


@dataclass(frozen=True)
class SimConfig:
    """Root configuration of a simulated run (motion, odometry noise, laser, camera)."""

    odom_rate: float = 20.0
    speed: float = 0.5
    rotation_speed: float = 0.5
    turn_radius: float = 1.0
    passage_radius: float = 1.0
    start_stamp: float = 1000.0
    odometry: OdometryNoiseConfig = field(default_factory=OdometryNoiseConfig)
    laser: LaserConfig = field(default_factory=LaserConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)

    def __post_init__(self) -> None:
        _positive(
            "SimConfig",
            odom_rate=self.odom_rate,
            speed=self.speed,
            rotation_speed=self.rotation_speed,
            turn_radius=self.turn_radius,
            passage_radius=self.passage_radius,
        )
        _non_negative("SimConfig", start_stamp=self.start_stamp)
        if self.laser.rate > self.odom_rate:
            msg = f"SimConfig: laser rate {self.laser.rate} Hz exceeds the odometry rate {self.odom_rate} Hz"
            raise ConfigError(msg)

    def to_dict(self) -> dict[str, Any]:
        """The configuration as plain JSON-able values."""
        return asdict(self)


# --------------------------------------------------------------------------------------------------
# Trajectory


_LINE, _ARC, _SPIN = 0, 1, 2


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A piecewise path: lines, arcs and turns on the spot, traversed at constant speeds.

    Primitive ``k`` starts at time ``t0[k]`` (s from the start) in pose ``start[k]`` and lasts
    ``duration[k]``; ``turn[k]`` is its signed heading change (0 for lines) and ``radius[k]`` the arc
    radius (0 otherwise).
    """

    kind: NDArray[np.int64]
    start: FloatArray
    t0: FloatArray
    duration: FloatArray
    turn: FloatArray
    radius: FloatArray
    speed: float
    rotation_speed: float

    @property
    def total_time(self) -> float:
        """Duration of the whole path (s)."""
        return float(self.t0[-1] + self.duration[-1])

    def pose_at(self, t: FloatArray) -> FloatArray:
        """True poses ``(T, 3)`` at times ``t`` (s from the start, clipped to the path)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        k = np.clip(np.searchsorted(self.t0, t, side="right") - 1, 0, len(self.t0) - 1)
        tau = np.clip(t - self.t0[k], 0.0, self.duration[k])
        x0, y0, h0 = self.start[k, 0], self.start[k, 1], self.start[k, 2]
        sign = np.sign(self.turn[k])
        s = self.speed * tau
        out = np.empty((len(t), 3))
        line = self.kind[k] == _LINE
        out[line] = np.stack([x0 + s * np.cos(h0), y0 + s * np.sin(h0), h0], axis=-1)[line]
        arc = self.kind[k] == _ARC
        if np.any(arc):
            r = np.where(arc, self.radius[k], 1.0)
            h = h0 + sign * s / r
            cx = x0 - sign * r * np.sin(h0)
            cy = y0 + sign * r * np.cos(h0)
            out[arc] = np.stack([cx + sign * r * np.sin(h), cy - sign * r * np.cos(h), h], axis=-1)[arc]
        spin = self.kind[k] == _SPIN
        out[spin] = np.stack([x0, y0, h0 + sign * self.rotation_speed * tau], axis=-1)[spin]
        out[:, 2] = wrap_angle(out[:, 2])
        return out


def plan_trajectory(world: World, config: SimConfig, visits: int | None = None) -> Trajectory:
    """The path through the first ``visits`` place visits of the cyclic route, from half-way along the
    corridor before the first visit to half-way along the corridor after the last one."""
    route = world.route
    names = world.visits(visits)
    before = world.place(route[-1])
    after = world.place(route[len(names) % len(route)])
    pts = np.array([(world.place(v).x, world.place(v).y) for v in names])
    start = 0.5 * (pts[0] + np.array([before.x, before.y]))
    end = 0.5 * (pts[-1] + np.array([after.x, after.y]))
    way = np.vstack([start, pts, end])

    prims: list[tuple[int, float, float, float, float, float, float]] = []  # kind,x,y,h,length,turn,r

    def line(p: FloatArray, q: FloatArray) -> None:
        length = float(np.hypot(*(q - p)))
        if length > 1e-12:
            prims.append((_LINE, p[0], p[1], math.atan2(q[1] - p[1], q[0] - p[0]), length, 0.0, 0.0))

    cur = way[0]
    for i in range(1, len(way) - 1):
        d_in, d_out = way[i] - way[i - 1], way[i + 1] - way[i]
        l_in, l_out = float(np.hypot(*d_in)), float(np.hypot(*d_out))
        h_in, h_out = math.atan2(d_in[1], d_in[0]), math.atan2(d_out[1], d_out[0])
        turn = float(wrap_angle(h_out - h_in))
        if abs(turn) < 1e-9:
            continue
        if abs(turn) <= MAX_ARC_TURN:
            half = math.tan(abs(turn) / 2.0)
            r = min(config.turn_radius, 0.5 * min(l_in, l_out) / half)
            a = way[i] - r * half * d_in / l_in
            line(cur, a)
            prims.append((_ARC, a[0], a[1], h_in, r * abs(turn), turn, r))
            cur = way[i] + r * half * d_out / l_out
        else:
            line(cur, way[i])
            prims.append((_SPIN, way[i][0], way[i][1], h_in, 0.0, turn, 0.0))
            cur = way[i]
    line(cur, way[-1])

    arr = np.array(prims, dtype=float)
    kind = arr[:, 0].astype(np.int64)
    duration = np.where(kind == _SPIN, np.abs(arr[:, 5]) / config.rotation_speed, arr[:, 4] / config.speed)
    t0 = np.concatenate([[0.0], np.cumsum(duration)[:-1]])
    return Trajectory(
        kind=kind,
        start=arr[:, 1:4].copy(),
        t0=t0,
        duration=duration,
        turn=arr[:, 5].copy(),
        radius=arr[:, 6].copy(),
        speed=config.speed,
        rotation_speed=config.rotation_speed,
    )


# --------------------------------------------------------------------------------------------------
# Odometry


def odometry_from_truth(
    true_poses: FloatArray, noise: OdometryNoiseConfig, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """Noisy odometry along a true trajectory ``(K, 3)`` (model in the module docstring).

    Returns the odometry poses ``(K, 3)``, starting at the origin, and the noisy body-frame increments
    ``(K-1, 3)`` ``(dx, dy, dyaw)`` from pose ``k-1`` to pose ``k``.
    """
    true_poses = np.asarray(true_poses, dtype=float)
    if true_poses.ndim != 2 or true_poses.shape[1] != 3 or len(true_poses) < 1:
        msg = f"true_poses must have shape (K, 3) with K >= 1, got {true_poses.shape}"
        raise ConfigError(msg)
    inc = between(true_poses[:-1], true_poses[1:])
    dist = np.hypot(inc[:, 0], inc[:, 1])
    rot = np.abs(inc[:, 2])
    n = len(inc)
    xi, zeta, eta = rng.standard_normal((3, n))
    b0 = noise.bias_mean + noise.bias_init * rng.standard_normal()
    bias = b0 + np.cumsum(noise.bias_walk * np.sqrt(dist) * eta)
    scale = (1.0 + noise.scale) * (
        1.0 + np.divide(noise.trans * np.sqrt(dist) * xi, dist, out=np.zeros(n), where=dist > 0.0)
    )
    dyaw = inc[:, 2] + np.sqrt(noise.rot**2 * dist + noise.turn**2 * rot) * zeta + bias * dist
    noisy = np.stack([inc[:, 0] * scale, inc[:, 1] * scale, dyaw], axis=-1)
    theta = np.concatenate([[0.0], np.cumsum(dyaw)])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    x = np.concatenate([[0.0], np.cumsum(c * noisy[:, 0] - s * noisy[:, 1])])
    y = np.concatenate([[0.0], np.cumsum(s * noisy[:, 0] + c * noisy[:, 1])])
    return np.stack([x, y, wrap_angle(theta)], axis=-1), noisy


# --------------------------------------------------------------------------------------------------
# Ray casting


@dataclass(frozen=True, eq=False)
class RayHits:
    """First wall hits of rays: ``range`` (m, +inf when none), ``wall`` index (-1 when none) and ``along``,
    the hit's distance from the wall's start (m). All of shape ``(N, B)``."""

    range: FloatArray
    wall: NDArray[np.int64]
    along: FloatArray


def cast_rays(segments: FloatArray, origins: FloatArray, angles: FloatArray) -> RayHits:
    """Cast rays from ``origins`` ``(N, 2)`` at world ``angles`` ``(N, B)`` against ``segments`` ``(S, 4)``.

    Solves ``p + t d = a + s (b - a)`` for every ray and wall with 2-D cross products,
    ``t = (w × e) / (d × e)``, ``s = (w × d) / (d × e)``, ``w = a - p``, ``e = b - a``; keeps ``t > 0`` and
    ``0 <= s <= 1`` and the smallest ``t``.
    """
    segments = np.asarray(segments, dtype=float).reshape(-1, 4)
    origins = np.asarray(origins, dtype=float).reshape(-1, 2)
    angles = np.asarray(angles, dtype=float)
    if angles.ndim == 1:
        angles = np.broadcast_to(angles, (len(origins), len(angles)))
    n, b = angles.shape
    out_range = np.full((n, b), np.inf)
    out_wall = np.full((n, b), -1, dtype=np.int64)
    out_along = np.zeros((n, b))
    if len(segments) == 0 or n == 0:
        return RayHits(out_range, out_wall, out_along)
    a = segments[:, :2]
    e = segments[:, 2:] - a
    lengths = np.hypot(e[:, 0], e[:, 1])
    chunk = max(1, _RAY_CHUNK // (b * len(segments)))
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        dx, dy = np.cos(angles[lo:hi])[..., None], np.sin(angles[lo:hi])[..., None]  # (n, B, 1)
        w = a[None, :, :] - origins[lo:hi, None, :]  # (n, S, 2)
        wx, wy = w[:, None, :, 0], w[:, None, :, 1]  # (n, 1, S)
        denom = dx * e[:, 1] - dy * e[:, 0]  # (n, B, S)
        parallel = np.abs(denom) < 1e-12
        safe = np.where(parallel, 1.0, denom)
        t = (wx * e[:, 1] - wy * e[:, 0]) / safe
        s = (wx * dy - wy * dx) / safe
        valid = ~parallel & (t > 1e-9) & (s >= -1e-9) & (s <= 1.0 + 1e-9)
        t = np.where(valid, t, np.inf)
        k = np.argmin(t, axis=-1)  # (n, B)
        best = np.take_along_axis(t, k[..., None], axis=-1)[..., 0]
        hit = np.isfinite(best)
        out_range[lo:hi] = best
        out_wall[lo:hi] = np.where(hit, k, -1)
        s_best = np.take_along_axis(s, k[..., None], axis=-1)[..., 0]
        out_along[lo:hi] = np.where(hit, np.clip(s_best, 0.0, 1.0) * lengths[k], 0.0)
    return RayHits(out_range, out_wall, out_along)


def simulate_scans(
    segments: FloatArray, poses: FloatArray, laser: LaserConfig, rng: np.random.Generator | None = None
) -> NDArray[np.float32]:
    """Laser ranges ``(N, B)`` (float32) from true ``poses`` ``(N, 3)`` among wall ``segments`` ``(S, 4)``;
    +inf beyond ``range_max``.

    Gaussian range noise of ``laser.noise`` is added when ``rng`` is given; ranges are clipped at
    ``range_min``.
    """
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    hits = cast_rays(segments, poses[:, :2], poses[:, 2:3] + laser.angles[None, :])
    r = hits.range
    if rng is not None and laser.noise > 0.0:
        r = r + laser.noise * rng.standard_normal(r.shape)
    r = np.where(np.isfinite(hits.range) & (r <= laser.range_max), np.maximum(r, laser.range_min), np.inf)
    return r.astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Panoramas

#: Texture tiles: resolution (m per texel) and period along the wall (m).
_TEXEL = 0.05
_PERIOD = 4.0
_CEILING, _FLOOR = 215.0, 70.0


def _texture_tile(rng: np.random.Generator, wall_height: float) -> tuple[FloatArray, FloatArray]:
    """A procedural wall texture ``(Hz, Hu)`` (grey levels, period ``_PERIOD`` along the wall) and tint."""
    hz, hu = math.ceil(wall_height / _TEXEL), round(_PERIOD / _TEXEL)
    z = (np.arange(hz) + 0.5) * _TEXEL
    u = (np.arange(hu) + 0.5) * _TEXEL
    tile = np.full((hz, hu), rng.uniform(90.0, 170.0))
    # Periodic stripes along the wall.
    for _ in range(2):
        cycles = rng.integers(1, 9)
        tile += rng.uniform(8.0, 25.0) * np.sin(
            2.0 * np.pi * cycles * u / _PERIOD + rng.uniform(0, 2 * np.pi)
        )
    # Panels and doors: full or door-height vertical bands with a darker frame.
    for _ in range(rng.integers(1, 4)):
        u0, width = rng.uniform(0.0, _PERIOD - 1.3), rng.uniform(0.4, 1.2)
        top = wall_height if rng.random() < 0.5 else 2.1
        inside = ((u >= u0) & (u < u0 + width))[None, :] & (z < top)[:, None]
        frame = ((np.abs(u - u0) < 0.06) | (np.abs(u - u0 - width) < 0.06))[None, :] & (z < top)[:, None]
        tile[inside] += rng.uniform(-60.0, 60.0)
        tile[frame] = rng.uniform(20.0, 60.0)
    # Posters: blocky random patterns at eye height (corners and blobs for SIFT).
    for _ in range(rng.integers(1, 4)):
        u0, width = rng.uniform(0.0, _PERIOD - 1.0), rng.uniform(0.4, 1.0)
        z0, height = rng.uniform(0.9, 1.3), rng.uniform(0.4, 0.8)
        iu = np.flatnonzero((u >= u0) & (u < u0 + width))
        iz = np.flatnonzero((z >= z0) & (z < min(z0 + height, wall_height)))
        blocks = rng.uniform(0.0, 255.0, (len(iz) // 2 + 1, len(iu) // 2 + 1))
        tile[np.ix_(iz, iu)] = np.kron(blocks, np.ones((2, 2)))[: len(iz), : len(iu)]
    # Skirting board and a rail.
    tile[z < 0.15] -= 45.0
    rail = rng.uniform(0.8, 1.1)
    tile[(z >= rail) & (z < rail + 0.08)] += rng.uniform(-50.0, 50.0)
    tile += rng.normal(0.0, 6.0, tile.shape)
    return np.clip(tile, 0.0, 255.0), rng.uniform(0.55, 1.0, 3)


@dataclass(frozen=True, eq=False)
class PanoramaRenderer:
    """Renders panoramas of a world; one texture tile ``(S, Hz, Hu)`` and tint ``(S, 3)`` per wall."""

    world: World
    camera: CameraConfig
    tiles: FloatArray
    tints: FloatArray

    @classmethod
    def build(cls, world: World, camera: CameraConfig) -> PanoramaRenderer:
        """Make the wall textures: shared per texture id, mixed with a wall-unique one by the aliasing."""
        shared: dict[int, tuple[FloatArray, FloatArray]] = {}
        tiles, tints = [], []
        alpha = camera.texture_aliasing
        for k, tex in enumerate(world.wall_textures.tolist()):
            if tex not in shared:
                shared[tex] = _texture_tile(
                    np.random.default_rng([camera.texture_seed, 0, tex]), camera.wall_height
                )
            tile, tint = shared[tex]
            if alpha < 1.0:
                own_tile, own_tint = _texture_tile(
                    np.random.default_rng([camera.texture_seed, 1, k]), camera.wall_height
                )
                tile = alpha * tile + (1.0 - alpha) * own_tile
                tint = alpha * tint + (1.0 - alpha) * own_tint
            tiles.append(tile)
            tints.append(tint)
        hz, hu = math.ceil(camera.wall_height / _TEXEL), round(_PERIOD / _TEXEL)
        return cls(
            world=world,
            camera=camera,
            tiles=np.array(tiles).reshape(-1, hz, hu),
            tints=np.array(tints).reshape(-1, 3),
        )

    def render(self, poses: FloatArray, rng: np.random.Generator | None = None) -> NDArray[np.uint8]:
        """Panoramas ``(N, H, W)`` (mono8) or ``(N, H, W, 3)`` (rgb8) at ``poses`` ``(N, 3)``.

        Pixel noise of ``camera.noise`` grey levels is added when ``rng`` is given.
        """
        cam = self.camera
        poses = np.asarray(poses, dtype=float).reshape(-1, 3)
        h, w = cam.height, cam.width
        azimuth = poses[:, 2:3] + 2.0 * np.pi * np.arange(w)[None, :] / w
        hits = cast_rays(self.world.segments, poses[:, :2], azimuth)
        # Cylindrical projection: row i looks at slope y_i (rise over horizontal distance).
        slope = (h / 2.0 - np.arange(h) - 0.5) * (2.0 * math.tan(cam.vfov / 2.0) / h)
        d = hits.range[:, None, :]  # (N, 1, W)
        z = cam.camera_height + d * slope[None, :, None]  # (N, H, W) height on the wall
        wall = np.maximum(hits.wall, 0)[:, None, :]
        on_wall = np.isfinite(d) & (z >= 0.0) & (z < cam.wall_height)
        hz, hu = self.tiles.shape[1:]
        iz = np.clip(np.where(on_wall, z, 0.0) / _TEXEL, 0, hz - 1).astype(np.int64)
        iu = np.clip((np.mod(hits.along, _PERIOD) / _TEXEL).astype(np.int64), 0, hu - 1)[:, None, :]
        shade = 0.45 + 0.55 * np.exp(-np.where(np.isfinite(d), d, 1e3) / 12.0)
        grey = self.tiles[wall, iz, iu] * shade
        above = slope[None, :, None] > 0.0
        background = np.where(above, _CEILING, _FLOOR)
        if cam.encoding == "mono8":
            img = np.where(on_wall, grey, background)
        else:
            tint = self.tints[wall]  # (N, 1, W, 3)
            bg = background[..., None] * np.array([1.0, 0.97, 0.9])
            img = np.where(on_wall[..., None], grey[..., None] * tint, bg)
        if rng is not None and cam.noise > 0.0:
            img = img + cam.noise * rng.standard_normal(img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------------
# The run


@dataclass(frozen=True, eq=False)
class SimRun:
    """A simulated run, all in memory. Stamps in s; poses ``(x, y, yaw)``.

    ``true_poses`` / ``odom_poses`` / ``odom_twist`` ``(vx, wz)`` at ``odom_stamps`` ``(K,)``;
    ``scan_ranges`` ``(M, B)`` float32 at ``scan_stamps``; ``images`` ``(P, H, W[, 3])`` uint8 at
    ``image_stamps`` (P = 0 without camera); ``route`` the planned place visits and ``passages`` the
    detected ones; ``odometry_frame_offset`` the world pose of the odometry frame's origin.
    """

    world: World
    config: SimConfig
    seed: int | None
    route: tuple[str, ...]
    odom_stamps: FloatArray
    true_poses: FloatArray
    odom_poses: FloatArray
    odom_twist: FloatArray
    scan_stamps: FloatArray
    scan_ranges: NDArray[np.float32]
    image_stamps: FloatArray
    image_poses: FloatArray
    images: NDArray[np.uint8]
    passages: tuple[Passage, ...]
    odometry_frame_offset: tuple[float, float, float]

    @property
    def duration(self) -> float:
        """Length of the run (s)."""
        return float(self.odom_stamps[-1] - self.odom_stamps[0])

    @property
    def path_length(self) -> float:
        """True distance travelled (m)."""
        return float(np.sum(np.hypot(*np.diff(self.true_poses[:, :2], axis=0).T)))

    def events(self, *, scans: bool = True, images: bool = True) -> list[tuple[float, int, int]]:
        """``(stamp, kind, index)`` of every odometry sample (kind 0) and, as asked, scan (1) and panorama
        (2), in time order."""
        streams = [(0, self.odom_stamps)]
        if scans:
            streams.append((1, self.scan_stamps))
        if images:
            streams.append((2, self.image_stamps))
        return sorted((s, kind, i) for kind, stamps in streams for i, s in enumerate(stamps.tolist()))

    def odometry_error(self) -> FloatArray:
        """Odometry minus truth ``(K, 3)`` (x, y, wrapped yaw) in the odometry frame."""
        truth = between(np.asarray(self.odometry_frame_offset), self.true_poses)
        err = self.odom_poses - truth
        err[:, 2] = wrap_angle(err[:, 2])
        return err

    def ground_truth(self) -> dict[str, Any]:
        """The ``ptm_ros.ground_truth/1`` document: true poses in the world frame ``map`` at the odometry
        stamps, the odometry published at them (``raw_poses``, as a CARMEN ground truth carries its raw
        odometry: the check that a ground truth is the run's own compares the bag's odometry with it, so a
        robot however noisy passes it), every place of the world, the passages, and
        ``odometry_frame_offset``, the world pose of the odometry frame's origin (``true ≈ offset ⊕ odom``);
        plus the planned ``route`` and the ``config`` used."""
        truth = GroundTruthTrajectory(
            self.odom_stamps,
            self.true_poses,
            poses_raw=self.odom_poses,
            frame_id="map",
            places=tuple(Place(p.id, p.x, p.y, p.kind) for p in self.world.places),
            passages=self.passages,
        )
        return {
            **sim_gt_document(truth),
            "world": self.world.name,
            "seed": self.seed,
            "odometry_frame_offset": list(self.odometry_frame_offset),
            "route": list(self.route),
            "config": self.config.to_dict(),
        }


def detect_passages(
    stamps: FloatArray, poses: FloatArray, world: World, radius: float
) -> tuple[Passage, ...]:
    """Every time the position comes within ``radius`` of a place: the stamp of the closest approach.

    One passage per contiguous stretch within ``radius`` (a turn on the spot is one passage), sorted in
    time (:func:`ptm_ros.perception.detectors.landmark_passages`).
    """
    found = landmark_passages(stamps, poses[:, :2], world.place_xy, radius)
    return tuple(Passage(stamp, world.places[j].id) for stamp, j in found)


def _rng_seed(rng: np.random.Generator) -> int | None:
    seq = getattr(rng.bit_generator, "seed_seq", None)
    entropy = getattr(seq, "entropy", None)
    if isinstance(entropy, int) and not getattr(seq, "spawn_key", ()):
        return entropy
    return None


def simulate(
    world: World, config: SimConfig, rng: np.random.Generator, *, visits: int | None = None
) -> SimRun:
    """Drive the first ``visits`` place visits of ``world``'s route (default ``world.default_visits``).

    Deterministic given the state of ``rng``; ``SimRun.seed`` records the integer seed when ``rng``
    came from ``np.random.default_rng(seed)``.
    """
    route = world.visits(visits)
    traj = plan_trajectory(world, config, visits)
    dt = 1.0 / config.odom_rate
    k = np.arange(math.floor(traj.total_time / dt + 1e-9) + 1, dtype=float)
    t = k * dt
    true = traj.pose_at(t)
    odom, inc = odometry_from_truth(true, config.odometry, rng)
    twist = np.zeros((len(t), 2))
    twist[1:] = inc[:, [0, 2]] / dt

    laser = config.laser
    t_scan = np.arange(math.floor(traj.total_time * laser.rate + 1e-9) + 1, dtype=float) / laser.rate
    ranges = simulate_scans(world.segments, traj.pose_at(t_scan), laser, rng)

    cam = config.camera
    if cam.enabled:
        travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(true[:, :2], axis=0).T))])
        marks = np.arange(math.floor(travelled[-1] / cam.spacing + 1e-9) + 1) * cam.spacing
        idx = np.unique(np.minimum(np.searchsorted(travelled, marks - 1e-9), len(t) - 1))
        image_poses = true[idx]
        images = PanoramaRenderer.build(world, cam).render(image_poses, rng)
        t_img = t[idx]
    else:
        shape = (0, cam.height, cam.width) if cam.encoding == "mono8" else (0, cam.height, cam.width, 3)
        images, image_poses, t_img = np.zeros(shape, np.uint8), np.zeros((0, 3)), np.zeros(0)

    def stamps(times: FloatArray) -> FloatArray:
        # Whole nanoseconds, so that the stamps survive a bag round trip bit for bit.
        return np.rint((config.start_stamp + times) * 1e9) / 1e9

    return SimRun(
        world=world,
        config=config,
        seed=_rng_seed(rng),
        route=route,
        odom_stamps=stamps(t),
        true_poses=true,
        odom_poses=odom,
        odom_twist=twist,
        scan_stamps=stamps(t_scan + laser.stamp_delay),
        scan_ranges=ranges,
        image_stamps=stamps(t_img),
        image_poses=image_poses,
        images=images,
        passages=detect_passages(stamps(t), true, world, config.passage_radius),
        odometry_frame_offset=(float(true[0, 0]), float(true[0, 1]), float(true[0, 2])),
    )


def write_run(run: SimRun, out_bag: str | Path, storage: Literal["mcap", "sqlite3"] = "mcap") -> Path:
    """Write ``/odom``, ``/scan`` and ``/panorama`` (in time order) to a new rosbag2 ``out_bag`` through
    :class:`ptm_ros.io.bag.BagWriter`, then ``out_bag/ground_truth.json``. Returns the bag directory."""
    import json

    from ptm_ros.io.bag import BagWriter

    out = Path(out_bag)
    if out.exists():
        msg = f"{out} already exists; choose a new bag path"
        raise BagError(msg)
    laser = run.config.laser
    with BagWriter(out, storage=storage) as bag:
        for stamp, kind, i in run.events():
            if kind == 0:
                bag.write_odometry(stamp, run.odom_poses[i], twist=tuple(run.odom_twist[i]))
            elif kind == 1:
                bag.write_scan(
                    stamp,
                    run.scan_ranges[i],
                    angle_min=laser.angle_min,
                    angle_increment=laser.angle_increment,
                    range_min=laser.range_min,
                    range_max=laser.range_max,
                )
            else:
                bag.write_image(stamp, run.images[i])
    with (out / SIM_FILENAME).open("w", encoding="utf-8") as fh:
        json.dump(run.ground_truth(), fh)
    return out
