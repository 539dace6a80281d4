"""The PTM result and its JSON form (schema ``ptm_ros.ptm/1``, see CONTRACT.md and README; its JSON
Schema is ``ptm_ros/schema/ptm.schema.json``, loaded by :func:`ptm_schema`).

A probabilistic topological map is the list of the most probable topologies of the landmark visits with
their posterior masses (thesis Ch. 0.3). This module holds the result type shared by every inference
method (exact, MCMC, RBPF), the nodes and the evaluation, and its strict JSON round trip.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ptm_ros.errors import DataError
from ptm_ros.model.partitions import Labels, canonical, is_canonical

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from ptm_ros.model.visits import Visit

SCHEMA = "ptm_ros.ptm/1"
#: The JSON Schema (draft 2020-12) of ptm.json, package data under ``ptm_ros/`` (:func:`ptm_schema`).
SCHEMA_FILE = ("schema", "ptm.schema.json")
#: ``Ptm.inference`` key of the particle filter's PTM after each visit (:func:`timeline_list`).
TIMELINE_KEY = "timeline"
#: ``Ptm.extra`` key (top level of ptm.json) of the greedy baseline's answer (:func:`greedy_dict`).
GREEDY_KEY = "greedy"


@dataclass(frozen=True)
class Landmark:
    """A landmark visit as written to ptm.json: order, header stamp (s), the input odometry pose
    (x, y, yaw), and the pose the inference used when scan matching corrected the odometry
    (``corrected_pose``, JSON key of the same name; the frame of the topologies' place positions)."""

    index: int
    stamp: float
    pose: tuple[float, float, float]
    corrected_pose: tuple[float, float, float] | None = None

    @property
    def map_pose(self) -> tuple[float, float, float]:
        """The pose in the frame of the place positions: ``corrected_pose`` if any, else ``pose``."""
        return self.pose if self.corrected_pose is None else self.corrected_pose

    @classmethod
    def from_visit(cls, visit: Visit) -> Landmark:
        """The landmark of a visit: its input odometry pose, and its corrected pose when it differs."""
        x, y, yaw = visit.input_pose
        corrected = None
        if visit.odom_pose is not None:
            cx, cy, cyaw = visit.pose
            corrected = (float(cx), float(cy), float(cyaw))
        return cls(int(visit.index), float(visit.stamp), (float(x), float(y), float(yaw)), corrected)


@dataclass(frozen=True)
class Topology:
    """One topology of the PTM: canonical labels, posterior mass and optional per-place positions."""

    labels: Labels
    probability: float
    log_posterior: float | None = None
    positions: tuple[tuple[float, float], ...] | None = None  # (M, 2) place positions in frame_id


@dataclass(frozen=True)
class Ptm:
    """A probabilistic topological map (most probable topology first)."""

    landmarks: tuple[Landmark, ...]
    topologies: tuple[Topology, ...]
    frame_id: str = "odom"
    inference: Mapping[str, Any] = field(default_factory=dict)
    timing: Mapping[str, Any] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def map_topology(self) -> Topology:
        """The most probable topology."""
        if not self.topologies:
            msg = "the PTM holds no topology"
            raise DataError(msg)
        return self.topologies[0]


def make_ptm(
    landmarks: Sequence[Landmark],
    weighted: Mapping[Labels, float] | Sequence[tuple[Labels, float]],
    *,
    top: int | None = None,
    positions: Mapping[Labels, Sequence[Sequence[float]] | NDArray[np.floating[Any]]] | None = None,
    log_posteriors: Mapping[Labels, float] | None = None,
    **kwargs: Any,
) -> Ptm:
    """Build a :class:`Ptm` from topology masses (merging duplicates, sorting most probable first).

    ``weighted`` may list one topology several times (e.g. particles); masses are summed per canonical
    topology (a sum that rounds above 1 is 1). ``top`` keeps only the most probable ones (the masses then
    sum to less than 1).
    """
    items = weighted.items() if isinstance(weighted, Mapping) else weighted
    mass: dict[Labels, float] = {}
    for labels, p in items:
        key = canonical(labels)
        mass[key] = min(mass.get(key, 0.0) + float(p), 1.0)
    ranked = sorted(mass.items(), key=lambda kv: (-kv[1], kv[0]))
    if top is not None:
        ranked = ranked[:top]
    topologies = tuple(
        Topology(
            labels=lab,
            probability=p,
            log_posterior=None if log_posteriors is None else log_posteriors.get(lab),
            positions=None
            if positions is None or lab not in positions
            else tuple((float(x), float(y)) for x, y in positions[lab]),
        )
        for lab, p in ranked
    )
    return Ptm(landmarks=tuple(landmarks), topologies=topologies, **kwargs)


def to_json_dict(ptm: Ptm) -> dict[str, Any]:
    """The ptm.json document of a PTM."""
    tops = []
    for t in ptm.topologies:
        d: dict[str, Any] = {"labels": list(t.labels), "probability": t.probability}
        if t.log_posterior is not None:
            d["log_posterior"] = t.log_posterior
        if t.positions is not None:
            d["positions"] = [list(p) for p in t.positions]
        tops.append(d)
    doc: dict[str, Any] = {
        "schema": SCHEMA,
        "frame_id": ptm.frame_id,
        "landmarks": [_landmark_dict(lm) for lm in ptm.landmarks],
        "topologies": tops,
        "inference": dict(ptm.inference),
        "timing": dict(ptm.timing),
    }
    doc.update(ptm.extra)
    return doc


def _landmark_dict(lm: Landmark) -> dict[str, Any]:
    d: dict[str, Any] = {"index": lm.index, "stamp": lm.stamp, "pose": list(lm.pose)}
    if lm.corrected_pose is not None:
        d["corrected_pose"] = list(lm.corrected_pose)
    return d


def _pose(values: Any, what: str) -> tuple[float, float, float]:
    pose = tuple(float(v) for v in values)
    if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
        raise _fail(f"{what} must be 3 finite numbers (x, y, yaw), got {list(pose)}")
    return pose


def _landmark(d: Mapping[str, Any]) -> Landmark:
    corrected = d.get("corrected_pose")
    where = f"landmark {d.get('index')}"
    stamp = float(d["stamp"])
    if not math.isfinite(stamp):
        raise _fail(f"{where}: stamp {stamp} must be finite")
    return Landmark(
        int(d["index"]),
        stamp,
        _pose(d["pose"], f"{where}: pose"),
        None if corrected is None else _pose(corrected, f"{where}: corrected_pose"),
    )


def _fail(msg: str) -> DataError:
    return DataError(f"invalid ptm.json: {msg}")


def from_json_dict(doc: Mapping[str, Any]) -> Ptm:
    """Parse and validate a ptm.json document (raises :class:`DataError` with the offending field)."""
    if doc.get("schema") != SCHEMA:
        raise _fail(f"schema is {doc.get('schema')!r}, expected {SCHEMA!r}")
    try:
        landmarks = tuple(_landmark(d) for d in doc["landmarks"])
        n = len(landmarks)
        topologies = []
        for k, d in enumerate(doc["topologies"]):
            labels = tuple(int(v) for v in d["labels"])
            if len(labels) != n or not is_canonical(labels):
                raise _fail(f"topology {k}: labels {labels} are not a canonical sequence of {n} visits")
            p = float(d["probability"])
            if not (0.0 <= p <= 1.0 + 1e-9) or math.isnan(p):
                raise _fail(f"topology {k}: probability {p} outside [0, 1]")
            pos = d.get("positions")
            if pos is not None and (
                len(pos) != max(labels, default=-1) + 1
                or not all(len(xy) == 2 and all(math.isfinite(float(c)) for c in xy) for xy in pos)
            ):
                raise _fail(f"topology {k}: positions must be finite, one (x, y) per place")
            topologies.append(
                Topology(
                    labels=labels,
                    probability=p,
                    log_posterior=None if d.get("log_posterior") is None else float(d["log_posterior"]),
                    positions=None if pos is None else tuple((float(a), float(b)) for a, b in pos),
                )
            )
    except (KeyError, TypeError, ValueError) as err:
        raise _fail(f"{type(err).__name__}: {err}") from err
    if any(lm.index != i for i, lm in enumerate(landmarks)):
        raise _fail("landmark indices must be 0..N-1 in order")
    if sum(t.probability for t in topologies) > 1.0 + 1e-6:
        raise _fail("topology probabilities sum to more than 1")
    known = {"schema", "frame_id", "landmarks", "topologies", "inference", "timing"}
    return Ptm(
        landmarks=landmarks,
        topologies=tuple(topologies),
        frame_id=str(doc.get("frame_id", "odom")),
        inference=dict(doc.get("inference", {})),
        timing=dict(doc.get("timing", {})),
        extra={k: v for k, v in doc.items() if k not in known},
    )


@dataclass(frozen=True)
class TimelineStep:
    """The PTM after one visit: ``visits`` visits so far and the most probable ``topologies`` of them
    (canonical labels, one per visit so far) with their probabilities, most probable first."""

    visits: int
    topologies: tuple[tuple[Labels, float], ...]


def timeline_list(steps: Sequence[TimelineStep]) -> list[dict[str, Any]]:
    """The JSON form of a timeline: ``[{"visits": n, "topologies": [{"labels", "probability"}, …]}, …]``."""
    return [
        {
            "visits": st.visits,
            "topologies": [{"labels": list(lab), "probability": p} for lab, p in st.topologies],
        }
        for st in steps
    ]


def ptm_timeline(ptm: Ptm) -> tuple[TimelineStep, ...]:
    """The timeline in ``ptm.inference`` (:data:`TIMELINE_KEY`), checked; empty when there is none.

    Raises:
        DataError: a malformed timeline (steps not for 1, 2, … visits, labels not canonical sequences of
            that many visits, probabilities outside [0, 1]).
    """
    raw = ptm.inference.get(TIMELINE_KEY)
    if raw is None:
        return ()
    steps = []
    try:
        for k, d in enumerate(raw):
            n = int(d["visits"])
            if n != k + 1:
                raise _fail(f"timeline step {k} is for {n} visits, expected {k + 1}")
            tops = []
            for t in d["topologies"]:
                labels = tuple(int(v) for v in t["labels"])
                p = float(t["probability"])
                if len(labels) != n or not is_canonical(labels):
                    raise _fail(f"timeline step {k}: labels {labels} are not a canonical sequence of {n}")
                if not 0.0 <= p <= 1.0 + 1e-9:
                    raise _fail(f"timeline step {k}: probability {p} outside [0, 1]")
                tops.append((labels, p))
            steps.append(TimelineStep(n, tuple(tops)))
    except (KeyError, TypeError, ValueError) as err:
        raise _fail(f"timeline: {type(err).__name__}: {err}") from err
    return tuple(steps)


def greedy_dict(labels: Labels, gate_probability: float) -> dict[str, Any]:
    """The JSON form of the greedy baseline's answer: its canonical ``labels``, number of ``places`` and
    the ``gate_probability`` of its association gate (:class:`ptm_ros.scoring.baselines.GreedyConfig`)."""
    lab = canonical(labels)
    return {"labels": list(lab), "places": max(lab, default=-1) + 1, "gate_probability": gate_probability}


def ptm_greedy(ptm: Ptm) -> Labels | None:
    """The greedy baseline's labels in ``ptm.extra`` (:data:`GREEDY_KEY`), checked; None without them.

    Raises:
        DataError: labels that are not a canonical sequence of the PTM's visits.
    """
    raw = ptm.extra.get(GREEDY_KEY)
    if raw is None:
        return None
    try:
        labels = tuple(int(v) for v in raw["labels"])
    except (KeyError, TypeError, ValueError) as err:
        raise _fail(f"greedy: {type(err).__name__}: {err}") from err
    if len(labels) != len(ptm.landmarks) or not is_canonical(labels):
        raise _fail(f"greedy: labels {labels} are not a canonical sequence of {len(ptm.landmarks)} visits")
    return labels


def save_ptm(ptm: Ptm, path: str | Path) -> Path:
    """Write ``ptm`` as JSON to ``path`` (parent directories created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_json_dict(ptm), indent=1) + "\n")
    return path


def ptm_schema() -> dict[str, Any]:
    """The JSON Schema of ptm.json (``ptm_ros/schema/ptm.schema.json``, installed with the package)."""
    folder, name = SCHEMA_FILE
    return json.loads((files("ptm_ros") / folder / name).read_text(encoding="utf-8"))


def load_ptm(path: str | Path) -> Ptm:
    """Read and validate a ptm.json file."""
    path = Path(path)
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        msg = f"cannot read {path}: {err}"
        raise DataError(msg) from err
    return from_json_dict(doc)
