"""Landmark visits: what a detector hands to the topology inference (thesis Ch. 1.2, 3.10).

A :class:`Visit` is one passage of the robot through a landmark ("special place"). The topology
inference only ever sees a sequence of visits; the sensors behind them are abstracted into the
measurements each model needs:

* odometry: the odometry pose of the visit (wheel odometry, corrected by scan matching when the run has
  scans: :mod:`ptm_ros.perception.laser_odometry`) plus the distance and absolute rotation travelled since
  the previous visit (for the odometry noise model, :mod:`ptm_ros.model.odometry`);
* appearance: a Fourier signature (:mod:`ptm_ros.model.appearance`) and/or a bag-of-words histogram;
* laser: a local map patch, points in the visit's own frame (:mod:`ptm_ros.perception.laser`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, SupportsFloat, cast

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import ModelError

#: Largest |x|, |y| of a pose (m; UTM northings stay below 1e7) …
MAX_COORDINATE = 1e7
#: … and largest travel (m) or rotation (rad) between two visits: finite values far beyond these are no
#: odometry, and they overflow the models' covariances (a travel of 1e308 m made the filter's 2×2 Cholesky
#: factor NaN).
MAX_TRAVEL = 1e6


@dataclass(frozen=True)
class Visit:
    """One landmark visit.

    Attributes:
        index: position in the visit sequence (0-based).
        stamp: time of the visit (s), from the message header stamps.
        pose: odometry pose ``(x, y, yaw)`` of the visit in the odometry frame (laser-corrected if enabled).
        travel: odometry path length since the previous visit (m); 0 for the first visit.
        rotation: accumulated absolute heading change since the previous visit (rad); 0 for the first.
        signature: Fourier signature of the panorama at the visit, shape ``(K,)``, or None.
        words: bag-of-words counts of the panorama, shape ``(V,)`` integers, or None.
        patch: local laser map around the visit, shape ``(P, 2)`` points in the visit's frame, or None.
        odom_pose: the input odometry pose at the visit when ``pose`` was corrected by scan matching
            (ptm.json reports it as the landmark pose); None when ``pose`` is the input odometry.
        signature_spread: ``(K,)`` half the squared difference, per component, between ``signature`` and
            the signature of a panorama taken about one place's width away: one sample of the
            within-place appearance variance (:func:`ptm_ros.model.appearance.fit_appearance_model`), or None.
    """

    index: int
    stamp: float
    pose: tuple[float, float, float]
    travel: float = 0.0
    rotation: float = 0.0
    signature: NDArray[np.float64] | None = field(default=None, compare=False, repr=False)
    words: NDArray[np.int64] | None = field(default=None, compare=False, repr=False)
    patch: NDArray[np.float64] | None = field(default=None, compare=False, repr=False)
    odom_pose: tuple[float, float, float] | None = field(default=None, compare=False, repr=False)
    signature_spread: NDArray[np.float64] | None = field(default=None, compare=False, repr=False)

    @property
    def input_pose(self) -> tuple[float, float, float]:
        """The input (wheel) odometry pose of the visit: ``odom_pose`` if set, else ``pose``."""
        return self.pose if self.odom_pose is None else self.odom_pose

    def __post_init__(self) -> None:
        if not np.all(np.isfinite(self.pose)) or len(self.pose) != 3:
            msg = f"visit {self.index}: pose must be 3 finite numbers, got {self.pose}"
            raise ModelError(msg)
        if max(abs(self.pose[0]), abs(self.pose[1])) > MAX_COORDINATE:
            msg = f"visit {self.index}: pose {self.pose} lies beyond ±{MAX_COORDINATE:g} m"
            raise ModelError(msg)
        if self.odom_pose is not None and (
            len(self.odom_pose) != 3 or not np.all(np.isfinite(self.odom_pose))
        ):
            msg = f"visit {self.index}: odom_pose must be 3 finite numbers, got {self.odom_pose}"
            raise ModelError(msg)
        if not (np.isfinite(self.travel) and 0.0 <= self.travel <= MAX_TRAVEL):
            msg = f"visit {self.index}: travel must be in [0, {MAX_TRAVEL:g}] m, got {self.travel}"
            raise ModelError(msg)
        if not (np.isfinite(self.rotation) and 0.0 <= self.rotation <= MAX_TRAVEL):
            msg = f"visit {self.index}: rotation must be in [0, {MAX_TRAVEL:g}] rad, got {self.rotation}"
            raise ModelError(msg)
        if self.signature_spread is not None:
            # a visit without its signature keeps the spread, unused (a missing measurement)
            spread = np.asarray(self.signature_spread)
            shape_ok = spread.ndim == 1 and (
                self.signature is None or spread.shape == np.shape(self.signature)
            )
            if not (shape_ok and np.all(np.isfinite(spread) & (spread >= 0.0))):
                msg = (
                    f"visit {self.index}: signature_spread must be finite, >= 0 and shaped like the "
                    f"signature, got shape {spread.shape}"
                )
                raise ModelError(msg)


def pose_field(values: Iterable[SupportsFloat]) -> tuple[float, float, float]:
    """``values`` as a tuple of Python floats, for a pose read from untyped data (JSON, a saved state).
    Typed as the pose it must be but not checked here: :class:`Visit` rejects any other length itself,
    with its own message."""
    return cast("tuple[float, float, float]", tuple(float(x) for x in values))


def poses_array(visits: Sequence[Visit]) -> NDArray[np.float64]:
    """The odometry poses of a visit sequence as an ``(N, 3)`` array."""
    return np.array([v.pose for v in visits], dtype=float).reshape(-1, 3)


#: Writes one array of a visit (never None) in a codec's form: a numpy copy, base64 JSON, …
ArrayEncoder = Callable[[NDArray[Any]], object]


class ArrayDecoder(Protocol):
    """Reads one array of a visit (never None) back from a codec's form. ``dtype`` is the field's own
    (float64, int64 for ``words``): a decoder may cast to it or keep the dtype it stored."""

    def __call__(self, value: Any, dtype: type[np.generic], /) -> NDArray[Any]: ...


def visit_fields(visit: Visit, encode: ArrayEncoder) -> dict[str, Any]:
    """The fields of a visit as plain values, in their fixed order (the key order of every visit codec):
    poses as lists, arrays through ``encode``, None kept None."""

    def array(a: NDArray[Any] | None) -> object:
        return None if a is None else encode(a)

    return {
        "index": visit.index,
        "stamp": visit.stamp,
        "pose": list(visit.pose),
        "odom_pose": None if visit.odom_pose is None else list(visit.odom_pose),
        "travel": visit.travel,
        "rotation": visit.rotation,
        "signature": array(visit.signature),
        "words": array(visit.words),
        "patch": array(visit.patch),
        "signature_spread": array(visit.signature_spread),
    }


def visit_from_fields(d: Mapping[str, Any], decode: ArrayDecoder, *, arrays_optional: bool = False) -> Visit:
    """Inverse of :func:`visit_fields`, reading the fields in the same order. ``odom_pose`` and
    ``signature_spread`` may be absent (saved before they existed); the other arrays only with
    ``arrays_optional``.

    Raises:
        KeyError, TypeError, ValueError: a missing or malformed field (and whatever ``decode`` raises);
        ModelError: values no :class:`Visit` can hold.
    """

    def array(name: str, dtype: type[np.generic], *, added_later: bool = False) -> NDArray[Any] | None:
        value = d.get(name) if arrays_optional or added_later else d[name]
        return None if value is None else decode(value, dtype)

    odom_pose = d.get("odom_pose")
    return Visit(
        index=int(d["index"]),
        stamp=float(d["stamp"]),
        pose=pose_field(d["pose"]),
        odom_pose=None if odom_pose is None else pose_field(odom_pose),
        travel=float(d["travel"]),
        rotation=float(d["rotation"]),
        signature=array("signature", np.float64),
        words=array("words", np.int64),
        patch=array("patch", np.float64),
        signature_spread=array("signature_spread", np.float64, added_later=True),
    )
