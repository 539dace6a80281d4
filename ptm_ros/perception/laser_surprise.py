r"""Laser surprise: landmarks where a per-scan statistic is surprising (thesis Ch. 4.8, Fig. 62).

:class:`LaserSurpriseDetector` models the place by a Gaussian over a per-scan statistic
(:func:`scan_statistic`, one of :data:`STATISTICS`) under the Normal–Inverse-Wishart prior of
:class:`LaserSurpriseConfig`, and declares a landmark where the Bayesian surprise of a scan rises above
the predicted-surprise band. The surprise, the forgetting (``memory`` per scan, ``memory_distance`` per
metre) and the band trigger are :mod:`ptm_ros.perception.surprise`'s (Ch. 4.6).

Laser statistic (Ch. 4.8): the thesis models a place by the area swept by the scan. :func:`scan_statistic`
offers that (``log-area``) and alternatives; the default ``sectors`` is the mean log range in three
narrow sectors: around the left (+90°) and right (-90°) directions and straight ahead. A side opening
(junction, door, corner) enters the lateral sectors within about a corridor half-width of the decision
point and the lateral range jumps from the wall distance to the depth of the opening, a step the
surprise catches. The area and the wide-sector statistics are dominated by the long forward view and
ramp up over metres as an opening comes into view, which the forgetting model absorbs. The statistics
are compared on the simulated worlds in ``bench/bench_surprise.py``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ptm_ros.errors import DataError, ModelError
from ptm_ros.model.geometry import FloatArray, wrap_angle
from ptm_ros.perception.surprise import (
    GaussianStats,
    Niw,
    _SurpriseDetector,
    _vector,
    gaussian_surprise_step,
)
from ptm_ros.settings import Settings, setting

__all__ = [
    "STATISTICS",
    "LaserSurpriseConfig",
    "LaserSurpriseDetector",
    "scan_statistic",
]


#: Laser statistics :func:`scan_statistic` computes (dimension in brackets):
#: ``log-area`` (1), ``mean-log-range`` (1), ``sides`` (2: left, right), ``sectors`` (3: left, front, right).
STATISTICS = {"log-area": 1, "mean-log-range": 1, "sides": 2, "sectors": 3}


def scan_statistic(
    ranges: ArrayLike,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    *,
    kind: str = "sectors",
    front_half_angle: float = 0.25,
    side_half_angle: float = 0.25,
) -> FloatArray:
    """Per-scan statistic of the local structure (thesis Ch. 4.8), shape ``(STATISTICS[kind],)``.

    Beams are valid when not NaN and ``>= range_min``; ``+inf`` and returns beyond ``range_max`` count
    as ``range_max`` (no obstacle within range: open space, REP 117); NaN and too-short returns are
    dropped. Beam ``k`` points at ``angle_min + k·angle_increment`` (sensor frame, counter-clockwise from
    the heading).

    * ``log-area``: log of the area swept by the scan (the thesis' statistic): the fan of triangles
      between consecutive valid beams, ``½ Σ r_k r_{k+1} sin(θ_{k+1} - θ_k)`` (m²).
    * ``mean-log-range``: mean of ``log r`` over the valid beams.
    * ``sides``: mean ``log r`` over the beams within ``side_half_angle`` of the left (+90°) and of the
      right (-90°) direction.
    * ``sectors``: ``sides`` plus the front sector ``|θ| <= front_half_angle``: (left, front, right).

    Raises:
        ModelError: unknown ``kind`` or malformed scan geometry.
        DataError: no valid beam in a sector the statistic needs.
    """
    if kind not in STATISTICS:
        msg = f"unknown scan statistic {kind!r}; known: {sorted(STATISTICS)}"
        raise ModelError(msg)
    r = np.asarray(ranges, dtype=float)
    if r.ndim != 1 or r.size < 2:
        msg = f"ranges must be 1-D with >= 2 beams, got shape {r.shape}"
        raise ModelError(msg)
    if not (math.isfinite(angle_min) and math.isfinite(angle_increment) and angle_increment > 0.0):
        msg = f"need finite angle_min and angle_increment > 0, got {angle_min}, {angle_increment}"
        raise ModelError(msg)
    if not (math.isfinite(range_min) and math.isfinite(range_max) and 0.0 <= range_min < range_max):
        msg = f"need 0 <= range_min < range_max (finite), got {range_min}, {range_max}"
        raise ModelError(msg)
    with np.errstate(invalid="ignore"):
        valid = ~np.isnan(r) & (r >= range_min) & (r > 0.0)
    r = np.minimum(np.where(valid, r, 1.0), range_max)
    if kind == "log-area":
        idx = np.flatnonzero(valid)
        if idx.size < 2:
            msg = "scan has fewer than 2 valid beams"
            raise DataError(msg)
        gaps = np.minimum(np.diff(idx) * angle_increment, math.pi)
        area = 0.5 * float(np.sum(r[idx[:-1]] * r[idx[1:]] * np.sin(gaps)))
        return np.array([math.log(max(area, 1e-12))])
    log_r = np.log(r)
    if kind == "mean-log-range":
        masks = [valid]
    else:
        theta = angle_min + angle_increment * np.arange(r.size)
        left = valid & (np.abs(wrap_angle(theta - 0.5 * math.pi)) <= side_half_angle)
        right = valid & (np.abs(wrap_angle(theta + 0.5 * math.pi)) <= side_half_angle)
        if kind == "sides":
            masks = [left, right]
        else:
            masks = [left, valid & (np.abs(wrap_angle(theta)) <= front_half_angle), right]
    out = np.empty(len(masks))
    for i, mask in enumerate(masks):
        if not mask.any():
            msg = f"scan has no valid beam in sector {i} of statistic {kind!r}"
            raise DataError(msg)
        out[i] = log_r[mask].mean()
    return out


@dataclass(frozen=True)
class LaserSurpriseConfig(Settings):
    """Laser surprise detector (thesis Ch. 4.8); defaults chosen on the simulated worlds (see the bench)."""

    statistic: str = setting(
        "sectors",
        choices=tuple(STATISTICS),
        doc="per-scan statistic, a key of :data:`STATISTICS` (see :func:`scan_statistic`).",
    )
    front_half_angle: float = setting(
        0.25, gt=0, lt=0.5 * math.pi, doc="half-width of the front sector (rad)."
    )
    side_half_angle: float = setting(
        0.25, gt=0, lt=0.5 * math.pi, doc="half-width of the left / right sectors around ±90° (rad)."
    )
    max_range: float = setting(
        30.0, gt=0, doc="beams longer than this (m) count as this (caps ``range_max`` of the scan)."
    )
    memory: float = setting(20.0, gt=0, doc="forgetting per scan, in scans (see the module docstring).")
    memory_distance: float = setting(
        0.5, gt=0, finite=False, doc="forgetting per metre of odometry travel, in m (``inf`` = none)."
    )
    prior_std: float = setting(
        0.03,
        gt=0,
        doc=(
            "within-place standard deviation of each statistic component the prior expects (statistic units: "
            "log m for the log statistics); a floor under the model's spread."
        ),
    )
    prior_strength: float = setting(
        2.0, gt=0, doc="weight of that expectation in scans (``ν_0 = d + 1 + prior_strength``)."
    )
    prior_kappa: float = setting(
        0.1, gt=0, doc="prior pseudo-count of the place mean (centred on the first scan)."
    )
    band_sigmas: float = setting(
        5.0,
        gt=0,
        doc=(
            "``k`` of the band ``mean + k·std`` of the predicted surprise. The predicted surprise is skewed "
            "(about ``a + b·χ²_d``), so a band of a few ``std`` is exceeded by the model's own draws more "
            "often than a Gaussian's (``bench/surprise.json``)."
        ),
    )
    samples: int = setting(
        1000, ge=2, doc="measurements drawn from the predictive for the predicted surprise."
    )
    warmup: int = setting(10, ge=1, doc="scans absorbed before a landmark may be declared.")
    min_travel: float = setting(
        2.0,
        ge=0,
        doc=(
            "least odometry travel (m) between two landmarks (applies once odometry is fed): a junction is "
            "two changes (the opening appears, then ends) but one place."
        ),
    )
    localize_distance: float = setting(
        1.5,
        ge=0,
        doc=(
            "the landmark is placed at the most open scan (largest mean log range to the left and right, the "
            "``sides`` statistic) within this odometry travel (m) of the surprise maximum, and declared once "
            "the robot has travelled that far past it; 0 = at the maximum. The maximum lies where the change "
            "*starts*, which depends on the direction of travel (entering a junction from either side: about "
            "one corridor width apart, 1.7 m in the simulated worlds); the most open point of a junction or "
            "doorway region does not."
        ),
    )
    seed: int = setting(0, ge=0, doc="seed of the detector's random generator when none is passed in.")

    def prior(self, first: FloatArray) -> Niw:
        """NIW prior centred on the first measurement with ``E[Σ] = prior_std² I``."""
        d = first.size
        dof = d + 1.0 + self.prior_strength
        return Niw(first, self.prior_kappa, dof, self.prior_strength * self.prior_std**2 * np.eye(d))


_OPEN_PLATEAU = 0.1  # log m: scans this close to the most open one count as equally open (a junction)


class LaserSurpriseDetector(_SurpriseDetector):
    """Declares landmarks where a laser scan statistic is surprising (thesis Ch. 4.8, Fig. 62).

    Feed odometry with :meth:`on_odometry` (optional; used for forgetting per metre and ``min_travel``)
    and scans with :meth:`on_scan`, which returns True when a landmark is declared. The landmark is the
    scan of the surprise maximum, usually the previous scan: :attr:`last_landmark_stamp`.
    """

    def __init__(
        self, config: LaserSurpriseConfig | None = None, rng: np.random.Generator | None = None
    ) -> None:
        self.config = config or LaserSurpriseConfig()
        super().__init__(self.config.band_sigmas, self.config.warmup, self.config.min_travel)
        self._rng = rng if rng is not None else np.random.default_rng(self.config.seed)
        self._prior: Niw | None = None
        self._stats = GaussianStats.empty(STATISTICS[self.config.statistic])
        self._recent: deque[tuple[float, float, float]] = deque()  # (stamp, travel, openness)
        self._pending: tuple[float, float] | None = None  # (stamp, travel) of a maximum being localised

    def on_scan(
        self,
        stamp: float,
        ranges: ArrayLike,
        *,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
    ) -> bool:
        """Feed one ``LaserScan`` (fields as in sensor_msgs, stamp in s); True when a landmark is declared.

        Raises:
            DataError: stamp going backwards, or no valid beam in a sector (:func:`scan_statistic`).
            ModelError: malformed scan geometry.
        """
        cfg = self.config
        z = scan_statistic(
            ranges,
            angle_min,
            angle_increment,
            range_min,
            min(range_max, cfg.max_range),
            kind=cfg.statistic,
            front_half_angle=cfg.front_half_angle,
            side_half_angle=cfg.side_half_angle,
        )
        openness = None
        if cfg.localize_distance > 0.0:
            sides = self._sides(z, ranges, angle_min, angle_increment, range_min, range_max)
            openness = float(np.mean(sides))
        return self.on_statistic(stamp, z, openness=openness)

    def _sides(  # noqa: PLR0917 - the LaserScan fields read best positionally
        self,
        z: FloatArray,
        ranges: ArrayLike,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
    ) -> FloatArray:
        """The ``sides`` statistic of a scan whose configured statistic is ``z``: taken from ``z`` when it
        contains it (``sectors`` = left, front, right with the same side sectors: the same numbers, bit
        for bit), else computed (:func:`scan_statistic`)."""
        cfg = self.config
        if cfg.statistic == "sides":
            return z
        if cfg.statistic == "sectors":
            return z[[0, 2]]
        return scan_statistic(
            ranges,
            angle_min,
            angle_increment,
            range_min,
            min(range_max, cfg.max_range),
            kind="sides",
            side_half_angle=cfg.side_half_angle,
        )

    def on_statistic(self, stamp: float, z: ArrayLike, *, openness: float | None = None) -> bool:
        """Feed one precomputed ``(d,)`` statistic (:meth:`on_scan` after :func:`scan_statistic`) and the
        scan's openness (mean ``sides`` statistic) for landmark localisation (None: declare at the
        surprise maximum)."""
        self._check_stamp(stamp)
        v = _vector(z, self._stats.total.size)
        if self._prior is None:
            self._prior = self.config.prior(v)
        before = self._stats.decay(self._forgetting(self.config.memory, self.config.memory_distance))
        step = gaussian_surprise_step(self._prior, before, v, self._rng, self.config.samples)
        self._stats = before.add(v)
        fired = self._observe(stamp, step)
        d = self.config.localize_distance
        if openness is None or d == 0.0 or not self._odometry_seen:
            if fired is not None:
                self._declare(fired)
            return fired is not None
        travel = self._odometry.travel
        self._recent.append((stamp, travel, float(openness)))
        declared = False
        if fired is not None:
            declared = self.flush()  # a new maximum while one is pending: settle the pending one
            at = next((t for st, t, _ in reversed(self._recent) if st <= fired), travel)
            self._pending = (fired, at)
        if self._pending is not None and travel >= self._pending[1] + d:
            declared = self.flush() or declared
        while self._recent and self._recent[0][1] < travel - 2.0 * d - self.config.min_travel:
            self._recent.popleft()
        return declared

    def flush(self) -> bool:
        """Declare the landmark being localised (at the middle scan of the most open stretch seen within
        ``localize_distance`` of its surprise maximum so far); True if there was one."""
        if self._pending is None:
            return False
        _, at = self._pending
        d = self.config.localize_distance
        window = [(st, o) for st, t, o in self._recent if abs(t - at) <= d]
        stamp = self._pending[0]
        if window:
            top = max(o for _, o in window)
            plateau = [st for st, o in window if o >= top - _OPEN_PLATEAU]
            stamp = plateau[len(plateau) // 2]  # the middle of the most open stretch
        self._pending = None
        self._declare(stamp)
        return True
