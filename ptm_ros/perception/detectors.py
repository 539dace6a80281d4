"""Landmark detectors: when does the robot visit a landmark? (thesis Ch. 4.5 equidistant landmarks).

Detectors are streaming objects fed with odometry (and, for the surprise detectors of Ch. 4.6–4.8, with
scans or images); each ``on_*`` call returns True when a landmark visit happens at that message. The
same objects run offline (``ptm-run``) and inside the detector node.

Landmarks fixed in the environment, as in the thesis' Intel experiment (Ch. 4.5, Fig. 57: "63 landmarks
were placed in the environment at a distance of 5 meters from each other"), need the true path:
:func:`place_landmarks` places landmarks along it, :func:`landmark_passages` finds when the robot passes
them, and :class:`ScheduledDetector` fires at those stamps. The visits are then right by construction,
like those of the perfect landmark detector that Ch. 1–3 assume, so what is left wrong is the
inference's (topology inference judged apart from landmark detection, Ch. 4.1). Only offline runs with
a ground truth can use it.

:class:`OdometryTracker` accumulates the odometry path length and absolute rotation between visits,
which the odometry noise model needs (:class:`ptm_ros.model.visits.Visit` ``travel`` / ``rotation``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ConfigError, DataError
from ptm_ros.model.geometry import wrap_angle
from ptm_ros.settings import Settings, setting


class Detector(Protocol):
    """What the visit extractor (:class:`ptm_ros.perception.landmarks.VisitExtractor`) asks of a landmark
    detector: each ``on_*`` call feeds one message and returns True when a landmark visit is declared; the
    visit then lies at ``last_landmark_stamp`` when set (a detector that localises its landmark at an earlier
    measurement, e.g. the surprise maximum), else at the message's stamp. ``flush`` ends the data (True:
    one more visit).

    A Protocol: any object with these members is a detector. The bodies here ignore every input, so a
    class that subclasses ``Detector`` explicitly (as the detectors of this package do) inherits them and
    overrides only the inputs it uses."""

    last_landmark_stamp: float | None = None

    def on_odometry(self, stamp: float, pose: NDArray[np.float64]) -> bool:
        """Odometry: no landmark here."""
        del stamp, pose
        return False

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
        """A laser scan: no landmark here."""
        del stamp, ranges, angle_min, angle_increment, range_min, range_max
        return False

    def on_image(self, stamp: float, image: ArrayLike) -> bool:
        """A panorama: no landmark here."""
        del stamp, image
        return False

    def flush(self) -> bool:
        """End of data: no landmark left."""
        return False


@dataclass(frozen=True)
class EquidistantConfig(Settings):
    """Equidistant landmarks (Ch. 4.5): every ``spacing`` metres of travel and/or every ``period`` s.

    A value of 0 disables that criterion; at least one must be enabled. ``first_at_start`` emits a visit
    at the first odometry message.
    """

    spacing: float = setting(
        3.0, ge=0, doc="odometry travel since the last visit that declares the next one [m] (0: off)."
    )
    period: float = setting(
        0.0, ge=0, doc="time since the last visit that declares the next one [s] (0: off)."
    )
    first_at_start: bool = setting(True, doc="declare a visit at the first odometry message.")

    def check(self) -> None:
        """At least one of the two criteria is enabled."""
        if self.spacing == 0.0 and self.period == 0.0:
            msg = "equidistant detector needs spacing > 0 or period > 0"
            raise ConfigError(msg)


@dataclass(frozen=True)
class PlacedLandmarksConfig(Settings):
    """Landmarks placed along a true path, and their visits (module docstring; lengths in m)."""

    spacing: float = setting(
        5.0,
        gt=0,
        doc=(
            "the first landmark is at the start of the path, each next one where the path first lies "
            "``spacing`` or more from every landmark placed so far (any two are ``spacing`` apart or more; "
            "every point of the path lies within ``spacing`` of one). The thesis' Intel run: 5 m."
        ),
    )
    capture_radius: float = setting(
        1.0,
        gt=0,
        doc=(
            "a visit happens when the path comes within this of a landmark; its stamp is that of the closest "
            "approach. At most ``spacing / 2``, so a visit belongs to one landmark, and keep it below "
            "ptm-eval's same-place radius (1.5 m) so that every visit is scored."
        ),
    )
    leave_radius: float = setting(
        2.0,
        gt=0,
        doc=(
            "after a visit the path must get farther than this from the landmark before the next visit to it "
            "counts (a path grazing the capture circle makes one visit, not several)."
        ),
    )
    step: float = setting(
        0.05,
        gt=0,
        doc=(
            "the path is resampled every ``step`` along its length first (ground truth comes as one pose per "
            "scan, which can be metres apart at speed)."
        ),
    )

    def check(self) -> None:
        """A visit belongs to one landmark, and a path leaves a landmark only beyond its capture circle."""
        if self.capture_radius > self.spacing / 2.0:
            msg = (
                f"placed landmarks: capture_radius {self.capture_radius} m exceeds spacing / 2 "
                f"({self.spacing / 2.0} m): a visit would not belong to one landmark"
            )
            raise ConfigError(msg)
        if self.leave_radius < self.capture_radius:
            msg = f"placed landmarks: leave_radius {self.leave_radius} m is below capture_radius"
            raise ConfigError(msg)


def resample_path(
    stamps: np.ndarray, xy: np.ndarray, step: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(stamps, xy)`` of a path ``(T,)``, ``(T, 2)`` resampled every ``step`` m of its length, from
    its start to its end point, the stamps interpolated along it (where the path stood still, a point
    takes the stamp at which it moved on)."""
    t = np.asarray(stamps, dtype=float)
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    if t.shape != (p.shape[0],) or t.size == 0 or not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        msg = f"a path needs finite stamps (T,) and positions (T, 2), got {t.shape} and {p.shape}"
        raise DataError(msg)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    if s[-1] == 0.0:
        return t[-1:], p[-1:]
    grid = np.concatenate([np.arange(0.0, s[-1], step), [s[-1]]])
    k = np.clip(np.searchsorted(s, grid, side="right") - 1, 0, t.size - 2)  # last sample at or before
    while np.any(z := s[k + 1] == s[k]):  # only at the very end: step back over a final standstill
        k[z] -= 1
    f = ((grid - s[k]) / (s[k + 1] - s[k]))[:, None]
    return t[k] + f[:, 0] * (t[k + 1] - t[k]), p[k] + f * (p[k + 1] - p[k])


def place_landmarks(xy: np.ndarray, spacing: float) -> NDArray[np.float64]:
    """``(K, 2)`` landmarks placed greedily along a densely sampled path ``(T, 2)``
    (:class:`PlacedLandmarksConfig` ``spacing``): the first point, then each first point of the path
    ``spacing`` or more from all landmarks placed so far."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    if p.shape[0] == 0:
        return np.zeros((0, 2))
    chosen = [0]
    nearest = np.hypot(*(p - p[0]).T)
    while True:
        # nearest only shrinks, so no point before the last landmark can qualify later: this is the
        # sequential greedy scan, one numpy pass per landmark
        far = np.flatnonzero(nearest >= spacing)
        if far.size == 0:
            return p[chosen]
        k = int(far[0])
        chosen.append(k)
        nearest = np.minimum(nearest, np.hypot(*(p - p[k]).T))


def landmark_passages(
    stamps: np.ndarray,
    xy: np.ndarray,
    landmarks: np.ndarray,
    capture_radius: float,
    leave_radius: float | None = None,
) -> list[tuple[float, int]]:
    """``(stamp, landmark index)`` of every visit, in time order: each stretch of the path ``(T,)``,
    ``(T, 2)`` that comes within ``capture_radius`` of a landmark, from there until it gets farther than
    ``leave_radius`` (default ``capture_radius``), is one visit at its closest approach."""
    t = np.asarray(stamps, dtype=float)
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    leave = capture_radius if leave_radius is None else leave_radius
    out: list[tuple[float, int]] = []
    for j, centre in enumerate(np.asarray(landmarks, dtype=float).reshape(-1, 2)):
        d = np.hypot(*(p - centre).T)
        # state: 1 inside (entered, not left yet), 0 outside; between the radii it carries on
        event = np.where(d <= capture_radius, 1, np.where(d > leave, 0, -1))
        known = np.maximum.accumulate(np.where(event >= 0, np.arange(d.size), -1))
        inside = np.concatenate([[False], (known >= 0) & (event[np.maximum(known, 0)] == 1), [False]])
        edges = np.flatnonzero(np.diff(inside.astype(np.int8)))
        for lo, hi in zip(edges[::2], edges[1::2], strict=True):
            out.append((float(t[lo + int(np.argmin(d[lo:hi]))]), j))
    return sorted(out)


class ScheduledDetector(Detector):
    """Fires at given stamps: the visits of landmarks fixed in the environment (:func:`landmark_passages`).

    :meth:`on_odometry` returns True at the first odometry sample at or after each scheduled stamp and
    sets :attr:`last_landmark_stamp` to it (the extractor then snaps the visit to the odometry sample
    nearest that stamp). Stamps that fall between the same two samples fire one per sample.
    """

    def __init__(self, stamps: Sequence[float] | np.ndarray) -> None:
        s = np.sort(np.asarray(stamps, dtype=float).reshape(-1))
        if not np.all(np.isfinite(s)):
            msg = "scheduled landmark stamps must be finite"
            raise DataError(msg)
        self.stamps = s
        self._next = 0
        self.last_landmark_stamp: float | None = None

    def on_odometry(self, stamp: float, pose: NDArray[np.float64]) -> bool:
        """Feed one odometry sample; True when a scheduled stamp has been reached."""
        del pose
        if self._next < self.stamps.size and stamp >= self.stamps[self._next]:
            self.last_landmark_stamp = float(self.stamps[self._next])
            self._next += 1
            return True
        return False


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


class EquidistantDetector(Detector):
    """Fires every ``spacing`` metres of odometry travel and/or every ``period`` seconds (Ch. 4.5)."""

    def __init__(self, config: EquidistantConfig | None = None) -> None:
        self.config = config or EquidistantConfig()
        self._tracker = OdometryTracker()
        self._last_visit_stamp: float | None = None

    def on_odometry(self, stamp: float, pose: NDArray[np.float64]) -> bool:
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
