"""Ground-truth trajectories: the CARMEN ``*-gt-*.txt`` files and the simulator's ``ground_truth.json``.

Both load into a :class:`GroundTruthTrajectory` (stamps in seconds, poses ``(x, y, yaw)``), which
:func:`interpolate_pose` evaluates at arbitrary stamps.

CARMEN ground truth (see ``datasets/README.md``), one row per scan of the matching raw log, same order::

    intel, aces:  scan raw_scan_index logger_timestamp x_corr y_corr theta_corr x_raw y_raw theta_raw
    mit-csail:    corr_scan raw_scan_index ipc_timestamp logger_timestamp x_corr … theta_raw

The layout is taken from the ``# …`` header line naming the columns, else from the column count (9 or
10). The stamp is ``logger_timestamp``, the stamp the converted bags carry.

Simulator ground truth (schema ``ptm_ros.ground_truth/1``)::

    {"schema": "ptm_ros.ground_truth/1", "frame_id": "map",
     "poses": {"stamp": [...], "x": [...], "y": [...], "yaw": [...]},
     "raw_poses": {"x": [...], "y": [...], "yaw": [...]},
     "places": [{"id": 0, "x": 1.0, "y": 2.0, "kind": "junction"}],
     "passages": [{"stamp": 12.5, "place": 0}]}

``raw_poses`` (optional) is the raw odometry at the same stamps, when the ground truth came with one: a
CARMEN run's, kept by ``ptm-run --detector ground-truth`` in the file it writes (``ptm-eval`` checks the
landmarks' odometry against it).

Is it this run's ground truth? (issue #25). :func:`within_span`, :func:`odometry_fit_at`,
:func:`coverage_problem` and :func:`odometry_fit_problem` are the rule ``ptm-eval`` applies to a PTM's
landmarks (most of them outside the ground truth's time span, or their odometry not moving as the ground
truth does: :func:`ptm_ros.scoring.evaluation.odometry_fit`); :func:`run_ground_truth_problem` applies the
same rule, with the same thresholds, to a bag's whole odometry before any landmark is known (``ptm-run``,
right after reading the bag), at points :data:`RUN_FIT_SPACING_M` of travel apart. Each returns the one-line
problem (None: none); the tools add how to override it (``--force``).

:func:`with_placed_landmarks` adds landmarks fixed along the path and their visits (the
``ground-truth`` detector's) to a trajectory that has none (:mod:`ptm_ros.perception.detectors`);
:func:`save_sim_gt` writes any ground truth in the simulator's schema (what ``ptm-run --detector
ground-truth`` leaves beside its ``ptm.json``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import DataError
from ptm_ros.model.geometry import FloatArray, interpolate_poses
from ptm_ros.perception.detectors import (
    PlacedLandmarksConfig,
    landmark_passages,
    place_landmarks,
    resample_path,
)
from ptm_ros.scoring.evaluation import OdometryFit, odometry_fit, path_samples

SIM_SCHEMA = "ptm_ros.ground_truth/1"
SIM_FILENAME = "ground_truth.json"
#: How far (s) a stamp may lie outside a ground truth's time span and still be given its end pose.
MAX_EXTRAPOLATION_S = 0.5
#: Metres of odometry travel between the points at which ``ptm-run`` judges a ground truth
#: (:func:`run_ground_truth_problem`).
RUN_FIT_SPACING_M = 1.0
_POSE_COLUMNS = "x_corr y_corr theta_corr x_raw y_raw theta_raw"
_CARMEN_COLUMNS = {
    9: f"scan raw_scan_index logger_timestamp {_POSE_COLUMNS}",
    10: f"corr_scan raw_scan_index ipc_timestamp logger_timestamp {_POSE_COLUMNS}",
}
_REQUIRED = ("logger_timestamp", "x_corr", "y_corr", "theta_corr", "x_raw", "y_raw", "theta_raw")


@dataclass(frozen=True)
class Place:
    """A ground-truth place of the simulated world."""

    id: int | str
    x: float
    y: float
    kind: str


@dataclass(frozen=True)
class Passage:
    """The robot passes ``place`` at ``stamp`` (s)."""

    stamp: float
    place: int | str


@dataclass(frozen=True)
class GroundTruthTrajectory:
    """``stamps (T,)`` s and ``poses_corrected (T, 3)`` (the true poses, in ``frame_id``);
    ``poses_raw (T, 3)`` is the raw odometry of the same instants when the file has it (CARMEN)."""

    stamps: FloatArray
    poses_corrected: FloatArray
    poses_raw: FloatArray | None = None
    frame_id: str = "map"
    places: tuple[Place, ...] = ()
    passages: tuple[Passage, ...] = ()
    raw_scan_index: NDArray[np.int64] | None = None


def _header_names(lines: Sequence[str]) -> list[str] | None:
    for text in lines:
        if text.lstrip().startswith("#"):
            names = text.lstrip()[1:].split()
            if "logger_timestamp" in names and "x_corr" in names:
                return names
    return None


def load_carmen_gt(path: str | Path) -> GroundTruthTrajectory:
    """Read a CARMEN ``*-gt-*.txt`` file (rows in file order, stamps = ``logger_timestamp``)."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeError) as err:
        msg = f"cannot read ground truth {p}: {err}"
        raise DataError(msg) from err
    rows: list[list[float]] = []
    width = None
    for lineno, text in enumerate(lines, start=1):
        tokens = text.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if width is None:
            width = len(tokens)
        if len(tokens) != width:
            msg = f"{p}:{lineno}: expected {width} columns like the first row, got {len(tokens)}"
            raise DataError(msg)
        try:
            rows.append([float(t) for t in tokens])
        except ValueError as err:
            msg = f"{p}:{lineno}: non-numeric value: {err}"
            raise DataError(msg) from err
    if not rows:
        msg = f"ground truth {p} has no data rows"
        raise DataError(msg)
    names = _header_names(lines)
    if names is None or len(names) != width:
        if width not in _CARMEN_COLUMNS:
            msg = f"{p}: cannot tell the column layout: no header naming the columns and {width} columns"
            raise DataError(msg)
        names = _CARMEN_COLUMNS[width].split()
    missing = [c for c in _REQUIRED if c not in names]
    if missing:
        msg = f"{p}: the column header lacks {', '.join(missing)}"
        raise DataError(msg)
    data = np.array(rows, dtype=float)
    col = {name: data[:, i] for i, name in enumerate(names)}
    stamps = col["logger_timestamp"].copy()
    corrected = np.stack([col["x_corr"], col["y_corr"], col["theta_corr"]], axis=1)
    raw = np.stack([col["x_raw"], col["y_raw"], col["theta_raw"]], axis=1)
    if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(corrected)) and np.all(np.isfinite(raw))):
        msg = f"{p}: non-finite stamp or pose"
        raise DataError(msg)
    index = col.get("raw_scan_index")
    return GroundTruthTrajectory(
        stamps=stamps,
        poses_corrected=corrected,
        poses_raw=raw,
        frame_id="map",
        raw_scan_index=None if index is None else index.astype(np.int64),
    )


def _finite_list(obj: Any, where: str) -> FloatArray:
    if not isinstance(obj, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in obj
    ):
        msg = f"{where} must be a list of numbers"
        raise DataError(msg)
    values = np.array(obj, dtype=float)
    if not np.all(np.isfinite(values)):
        msg = f"{where} holds non-finite numbers"
        raise DataError(msg)
    return values


def _number(obj: Mapping[str, Any], key: str, where: str) -> float:
    v = obj.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        msg = f"{where}.{key} must be a finite number, got {v!r}"
        raise DataError(msg)
    return float(v)


def _place_id(v: Any, where: str) -> int | str:
    if isinstance(v, bool) or not isinstance(v, int | str):
        msg = f"{where} must be an integer or a string, got {v!r}"
        raise DataError(msg)
    return v


def _records(doc: Mapping[str, Any], key: str, p: Path) -> list[Mapping[str, Any]]:
    items = doc.get(key, [])
    if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
        msg = f"{p}: {key!r} must be a list of objects"
        raise DataError(msg)
    return items


def load_sim_gt(path: str | Path) -> GroundTruthTrajectory:
    """Read the simulator's ``ground_truth.json`` (schema ``ptm_ros.ground_truth/1``)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeError) as err:
        msg = f"cannot read ground truth {p}: {err}"
        raise DataError(msg) from err
    except json.JSONDecodeError as err:
        msg = f"{p} is not valid JSON: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict) or doc.get("schema") != SIM_SCHEMA:
        got = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        msg = f"{p}: expected schema {SIM_SCHEMA!r}, got {got!r}"
        raise DataError(msg)
    frame_id = doc.get("frame_id")
    if not isinstance(frame_id, str) or not frame_id:
        msg = f"{p}: 'frame_id' must be a non-empty string"
        raise DataError(msg)
    poses = doc.get("poses")
    if not isinstance(poses, dict):
        msg = f"{p}: 'poses' must be an object with lists 'stamp', 'x', 'y', 'yaw'"
        raise DataError(msg)
    cols = {k: _finite_list(poses.get(k), f"{p}: poses.{k}") for k in ("stamp", "x", "y", "yaw")}
    lengths = {k: v.size for k, v in cols.items()}
    if len(set(lengths.values())) != 1 or lengths["stamp"] == 0:
        msg = f"{p}: poses lists must be non-empty and of equal length, got {lengths}"
        raise DataError(msg)
    places = tuple(
        Place(
            id=_place_id(d.get("id"), f"{p}: places[{i}].id"),
            x=_number(d, "x", f"places[{i}]"),
            y=_number(d, "y", f"places[{i}]"),
            kind=str(d.get("kind", "")),
        )
        for i, d in enumerate(_records(doc, "places", p))
    )
    ids = {pl.id for pl in places}
    if len(ids) != len(places):
        msg = f"{p}: place ids are not unique"
        raise DataError(msg)
    passages = tuple(
        Passage(
            stamp=_number(d, "stamp", f"passages[{i}]"),
            place=_place_id(d.get("place"), f"{p}: passages[{i}].place"),
        )
        for i, d in enumerate(_records(doc, "passages", p))
    )
    unknown = sorted({str(ps.place) for ps in passages if ps.place not in ids})
    if unknown:
        msg = f"{p}: passages refer to unknown places {', '.join(unknown)}"
        raise DataError(msg)
    raw = None
    if doc.get("raw_poses") is not None:
        raw_doc = doc["raw_poses"]
        if not isinstance(raw_doc, dict):
            msg = f"{p}: 'raw_poses' must be an object with lists 'x', 'y', 'yaw'"
            raise DataError(msg)
        raw_cols = [_finite_list(raw_doc.get(k), f"{p}: raw_poses.{k}") for k in ("x", "y", "yaw")]
        if any(c.size != lengths["stamp"] for c in raw_cols):
            msg = f"{p}: raw_poses lists must be as long as the poses' ({lengths['stamp']})"
            raise DataError(msg)
        raw = np.stack(raw_cols, axis=1)
    return GroundTruthTrajectory(
        stamps=cols["stamp"],
        poses_corrected=np.stack([cols["x"], cols["y"], cols["yaw"]], axis=1),
        poses_raw=raw,
        frame_id=frame_id,
        places=places,
        passages=passages,
    )


def load_ground_truth(path: str | Path) -> GroundTruthTrajectory:
    """Dispatch on the file type: ``.txt`` → :func:`load_carmen_gt`, ``.json`` → :func:`load_sim_gt`;
    a directory (a simulated bag) → its ``ground_truth.json``."""
    p = Path(path)
    if p.is_dir():
        p = p / SIM_FILENAME
    if not p.is_file():
        msg = f"ground truth {p} does not exist"
        raise DataError(msg)
    suffix = p.suffix.lower()
    if suffix == ".txt":
        return load_carmen_gt(p)
    if suffix == ".json":
        return load_sim_gt(p)
    msg = f"ground truth {p}: unknown file type {suffix!r} (expected .txt CARMEN or .json simulator)"
    raise DataError(msg)


def with_placed_landmarks(
    truth: GroundTruthTrajectory, config: PlacedLandmarksConfig | None = None
) -> GroundTruthTrajectory:
    """``truth`` with the places and passages of the ``ground-truth`` detector
    (:mod:`ptm_ros.perception.detectors`): unchanged when it has passages already (a simulated run: its
    world's places), else landmarks placed along the corrected trajectory every ``config.spacing`` m (places
    ``0 … K−1`` of kind ``"placed"``)
    and their visits."""
    if truth.passages:
        return truth
    cfg = config or PlacedLandmarksConfig()
    stamps, xy = resample_path(truth.stamps, truth.poses_corrected[:, :2], cfg.step)
    marks = place_landmarks(xy, cfg.spacing)
    visits = landmark_passages(stamps, xy, marks, cfg.capture_radius, cfg.leave_radius)
    return replace(
        truth,
        places=tuple(Place(k, float(x), float(y), "placed") for k, (x, y) in enumerate(marks)),
        passages=tuple(Passage(stamp, j) for stamp, j in visits),
    )


def sim_gt_document(truth: GroundTruthTrajectory) -> dict[str, Any]:
    """``truth`` as a ``ptm_ros.ground_truth/1`` document (corrected poses, the raw ones when it has them,
    places, passages): what :func:`load_sim_gt` reads (the simulator adds its own keys)."""
    t = truth.poses_corrected
    raw = {}
    if truth.poses_raw is not None:
        r = truth.poses_raw
        raw = {"raw_poses": {"x": r[:, 0].tolist(), "y": r[:, 1].tolist(), "yaw": r[:, 2].tolist()}}
    return {
        "schema": SIM_SCHEMA,
        "frame_id": truth.frame_id,
        "poses": {
            "stamp": truth.stamps.tolist(),
            "x": t[:, 0].tolist(),
            "y": t[:, 1].tolist(),
            "yaw": t[:, 2].tolist(),
        },
        **raw,
        "places": [{"id": pl.id, "x": pl.x, "y": pl.y, "kind": pl.kind} for pl in truth.places],
        "passages": [{"stamp": ps.stamp, "place": ps.place} for ps in truth.passages],
    }


def save_sim_gt(truth: GroundTruthTrajectory, path: str | Path) -> Path:
    """Write :func:`sim_gt_document` of ``truth`` to ``path``; returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(sim_gt_document(truth)), encoding="utf-8")
    return p


def interpolate_pose(
    traj: GroundTruthTrajectory,
    stamps: ArrayLike,
    *,
    which: Literal["corrected", "raw"] = "corrected",
    tolerance: float = 1e-6,
) -> FloatArray:
    """Poses ``(T, 3)`` at ``stamps``: linear in x, y and along the shorter arc in yaw between the two
    neighbouring knots (knots sorted by stamp). A stamp equal to a knot gives that knot's pose exactly;
    interpolated yaws are wrapped to ``[−π, π)``. Stamps more than ``tolerance`` s outside the knots'
    range, or repeated knot stamps, raise :class:`DataError`; stamps within it get the end pose.
    """
    if which not in ("corrected", "raw"):
        msg = f"which must be 'corrected' or 'raw', got {which!r}"
        raise DataError(msg)
    poses = traj.poses_corrected if which == "corrected" else traj.poses_raw
    if poses is None:
        msg = f"ground truth has no {which!r} poses"
        raise DataError(msg)
    q = np.asarray(stamps, dtype=float)
    shape = q.shape
    q = q.reshape(-1)
    if not np.all(np.isfinite(q)):
        msg = "query stamps must be finite"
        raise DataError(msg)
    order = np.argsort(traj.stamps, kind="stable")
    t = traj.stamps[order]
    P = poses[order]
    if t.size > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        msg = f"ground-truth stamp {float(t[i])!r} s repeats; cannot interpolate"
        raise DataError(msg)
    outside = (q < t[0] - tolerance) | (q > t[-1] + tolerance)
    if np.any(outside):
        bad = q[outside]
        msg = (
            f"{bad.size} stamp(s) outside the ground truth's range [{float(t[0])!r}, {float(t[-1])!r}] s "
            f"(tolerance {tolerance} s), first {float(bad[0])!r}"
        )
        raise DataError(msg)
    out = interpolate_poses(t, P, q)
    return out.reshape((*shape, 3))


# --------------------------------------------------------------------------------------------------
# Is it this run's ground truth? (module docstring)


def within_span(
    truth: GroundTruthTrajectory, stamps: ArrayLike, max_extrapolation: float = MAX_EXTRAPOLATION_S
) -> NDArray[np.bool_]:
    """Which ``stamps`` lie within the ground truth's time span, ``max_extrapolation`` s either side
    included (those have a true pose: :func:`interpolate_pose` with that tolerance)."""
    q = np.asarray(stamps, dtype=float).reshape(-1)
    t0, t1 = float(np.min(truth.stamps)), float(np.max(truth.stamps))
    return (q >= t0 - max_extrapolation) & (q <= t1 + max_extrapolation)


def odometry_fit_at(
    truth: GroundTruthTrajectory,
    stamps: ArrayLike,
    odom_xy: ArrayLike,
    *,
    max_extrapolation: float = MAX_EXTRAPOLATION_S,
) -> OdometryFit:
    """How well odometry positions ``odom_xy (n, 2)`` at ``stamps (n,)`` (in order) fit the ground truth at
    the same stamps (:func:`ptm_ros.scoring.evaluation.odometry_fit`): against its raw odometry when it has
    one (CARMEN: the same odometry), else its true poses; stamps outside :func:`within_span` are left out."""
    q = np.asarray(stamps, dtype=float).reshape(-1)
    odom = np.asarray(odom_xy, dtype=float).reshape(-1, 2)
    inside = within_span(truth, q, max_extrapolation)
    which: Literal["corrected", "raw"] = "raw" if truth.poses_raw is not None else "corrected"
    ref = interpolate_pose(truth, q[inside], which=which, tolerance=max_extrapolation)
    return odometry_fit(odom[inside], ref[:, :2])


def coverage_problem(outside: int, total: int, what: str) -> str | None:
    """The problem when more than half of ``total`` points (``what`` they are) lie ``outside`` the ground
    truth's time span: the ground truth of another run, or of part of this one; None otherwise."""
    if 2 * outside <= total:
        return None
    return (
        f"{outside} of {total} {what} lie outside the ground truth's time span: is it another run's, or "
        "on another clock?"
    )


def odometry_fit_problem(fit: OdometryFit, *, raw: bool, what: str) -> str | None:
    """The problem, with the figures, when the odometry (``what``: whose) does not fit the ground truth
    (:attr:`OdometryFit.fits`): another run's, its clock overlapping this one's; ``raw``: the fit was
    against the ground truth's raw odometry, else its true poses. None when it fits or cannot be judged."""
    if fit.fits or fit.statistic is None:
        return None
    legacy = (
        ""
        if raw
        else "; one of a real run written without its raw odometry by an older ptm-run: write it again"
    )
    return (
        f"{what} does not move as the ground truth's {'raw odometry does' if raw else 'poses do'}: relative "
        f"residual {fit.statistic:.2f} over {fit.window_m:g} m stretches ({fit.quantile:.0%} quantile of "
        f"{fit.windows}; a run's own ground truth stays below {fit.limit:g}): is it another run's?{legacy}"
    )


def run_ground_truth_problem(
    truth: GroundTruthTrajectory,
    stamps: ArrayLike,
    poses: ArrayLike,
    *,
    spacing: float = RUN_FIT_SPACING_M,
    max_extrapolation: float = MAX_EXTRAPOLATION_S,
) -> tuple[OdometryFit, str | None]:
    """Whether ``truth`` is the ground truth of the run whose odometry is ``poses (n, 3)`` at ``stamps
    (n,)`` (a bag's, in stamp order), judged before any landmark is known: ``ptm-eval``'s rule
    (:func:`coverage_problem`, then :func:`odometry_fit_problem`) at the odometry's points ``spacing`` m
    of travel apart (:func:`ptm_ros.scoring.evaluation.path_samples`) instead of the landmarks. Returns the
    fit and the problem (None: none)."""
    q = np.asarray(stamps, dtype=float).reshape(-1)
    xy = np.asarray(poses, dtype=float).reshape(len(q), -1)[:, :2]
    k = path_samples(xy, spacing)
    outside = int(np.count_nonzero(~within_span(truth, q[k], max_extrapolation)))
    fit = odometry_fit_at(truth, q[k], xy[k], max_extrapolation=max_extrapolation)
    what = f"points of the bag's odometry ({spacing:g} m of travel apart)"
    problem = coverage_problem(outside, len(k), what) or odometry_fit_problem(
        fit, raw=truth.poses_raw is not None, what="the bag's odometry"
    )
    return fit, problem
