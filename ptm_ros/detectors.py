"""Landmark detectors: when does the robot visit a landmark? (thesis Ch. 4.5 equidistant landmarks).

Detectors are streaming objects fed with odometry (and, for the surprise detectors of Ch. 4.6–4.8, with
scans or images); each ``on_*`` call returns True when a landmark visit happens at that message. The
same objects run offline (``ptm-run``) and inside the detector node.

:class:`OdometryTracker` accumulates the odometry path length and absolute rotation between visits,
which the odometry noise model needs (:class:`ptm_ros.visits.Visit` ``travel`` / ``rotation``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptm_ros.errors import ConfigError, DataError
from ptm_ros.geometry import wrap_angle


@dataclass(frozen=True)
class EquidistantConfig:
    """Equidistant landmarks (Ch. 4.5): every ``spacing`` metres of travel and/or every ``period`` s.

    A value of 0 disables that criterion; at least one must be enabled. ``first_at_start`` emits a visit
    at the first odometry message.
    """

    spacing: float = 3.0
    period: float = 0.0
    first_at_start: bool = True

    def __post_init__(self) -> None:
        for name in ("spacing", "period"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                msg = f"equidistant {name} must be finite and >= 0, got {v}"
                raise ConfigError(msg)
        if self.spacing == 0.0 and self.period == 0.0:
            msg = "equidistant detector needs spacing > 0 or period > 0"
            raise ConfigError(msg)


class OdometryTracker:
    """Path length and absolute heading change since the last reset; rejects stamps going backwards."""

    def __init__(self) -> None:
        self.last_stamp: float | None = None
        self.last_pose: np.ndarray | None = None
        self.travel = 0.0
        self.rotation = 0.0

    def update(self, stamp: float, pose: np.ndarray) -> None:
        """Add one odometry sample (raises DataError on a non-finite pose or a stamp going back)."""
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)) or not math.isfinite(stamp):
            msg = f"odometry sample at {stamp} is not a finite (x, y, yaw) pose: {pose}"
            raise DataError(msg)
        if self.last_stamp is not None and stamp < self.last_stamp:
            msg = f"odometry stamp went backwards: {stamp:.9f} after {self.last_stamp:.9f}"
            raise DataError(msg)
        if self.last_pose is not None:
            self.travel += float(math.hypot(*(pose[:2] - self.last_pose[:2])))
            self.rotation += abs(float(wrap_angle(pose[2] - self.last_pose[2])))
        self.last_stamp, self.last_pose = float(stamp), pose

    def reset(self) -> tuple[float, float]:
        """Return (travel, rotation) since the last reset and start counting afresh."""
        out = (self.travel, self.rotation)
        self.travel = self.rotation = 0.0
        return out


class EquidistantDetector:
    """Fires every ``spacing`` metres of odometry travel and/or every ``period`` seconds (Ch. 4.5)."""

    def __init__(self, config: EquidistantConfig | None = None) -> None:
        self.config = config or EquidistantConfig()
        self._tracker = OdometryTracker()
        self._last_visit_stamp: float | None = None

    def on_odometry(self, stamp: float, pose: np.ndarray) -> bool:
        """Feed one odometry sample; True when a landmark visit is declared at this sample."""
        self._tracker.update(stamp, pose)
        cfg = self.config
        if self._last_visit_stamp is None:
            fire = cfg.first_at_start
            if not fire:
                self._last_visit_stamp = stamp
        else:
            by_distance = cfg.spacing > 0.0 and self._tracker.travel >= cfg.spacing
            by_time = cfg.period > 0.0 and stamp - self._last_visit_stamp >= cfg.period
            fire = by_distance or by_time
        if fire:
            self._last_visit_stamp = stamp
            self._tracker.reset()
        return fire
