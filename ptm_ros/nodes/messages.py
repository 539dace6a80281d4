"""The wire format the ptm_ros nodes exchange, checked: ``landmark_visits`` and ``ptm_graph`` messages.

The topology filter and the map publisher both read the detector's visit messages
(:func:`parse_visit_envelope`): one check, so a message one node accepts the other accepts too. The map
publisher reads the filter's ensemble documents (written by :func:`graph_document`, read by
:func:`parse_graph`). The sensor messages' checks, shared with the bag reader, are
:mod:`ptm_ros.io.validation`. Bad input never raises past these functions except as
:class:`~ptm_ros.errors.DataError`, which the nodes count as skips (issue #9).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ptm_ros.errors import DataError, PtmError
from ptm_ros.model.ptm import Ptm, Topology, from_json_dict, to_json_dict
from ptm_ros.model.visits import Visit
from ptm_ros.perception.landmarks import VISIT_SCHEMA, visit_from_json, visit_to_json

#: The detector's in-band end marker after its last visit on ``landmark_visits``:
#: ``{"schema": END_SCHEMA, "visits": N}``, the number of visits it published.
END_SCHEMA = "ptm_ros.visits_end/1"
#: The bag player's last message, on ``end_of_input`` (std_msgs/String, latched):
#: ``{"schema": END_OF_INPUT_SCHEMA, "counts": {"/odom": 1343, ...}}``, messages published per topic.
END_OF_INPUT_SCHEMA = "ptm_ros.end_of_input/1"
#: Tag of the topology filter's ``ptm_graph`` documents (:func:`graph_document`).
GRAPH_SCHEMA = "ptm_ros.ptm_graph/1"

#: What a JSON parser may raise on hostile text besides JSONDecodeError (a ValueError): numbers with
#: more than 4300 digits (ValueError), nesting deeper than the recursion limit, values beyond float range.
JSON_ERRORS = (ValueError, TypeError, KeyError, OverflowError, RecursionError)

_ARRAYS = {
    "signature": ("f", 1),
    "signature_spread": ("f", 1),
    "words": ("iu", 1),
    "patch": ("f", 2),
}  # dtype kinds, dimensions


def check_visit(visit: Visit) -> None:
    """What :class:`Visit` itself does not check: index >= 0, a finite stamp >= 0, and numeric, finite,
    non-empty measurements of the right shape: signature ``(K,)`` >= 0 (Fourier magnitudes), words
    ``(V,)`` integers >= 0, patch ``(P, 2)``.

    Raises:
        DataError: naming the offending field.
    """
    if visit.index < 0:
        msg = f"visit index {visit.index} < 0"
        raise DataError(msg)
    if not (math.isfinite(visit.stamp) and visit.stamp >= 0.0):
        msg = f"visit {visit.index}: stamp {visit.stamp} is not a finite time >= 0"
        raise DataError(msg)
    for name, (kinds, ndim) in _ARRAYS.items():
        arr = getattr(visit, name)
        if arr is None:
            continue
        if (
            arr.dtype.kind not in kinds
            or arr.ndim != ndim
            or arr.size == 0
            or (ndim == 2 and arr.shape[1] != 2)
        ):
            msg = f"visit {visit.index}: {name} of dtype {arr.dtype} and shape {arr.shape}"
            raise DataError(msg)
        with np.errstate(invalid="ignore"):
            bad = arr.dtype.kind == "f" and not np.all(np.isfinite(arr))
            bad = bad or (name != "patch" and bool(np.any(arr < 0)))  # magnitudes and counts are >= 0
        if bad:
            msg = f"visit {visit.index}: {name} has non-finite or negative values"
            raise DataError(msg)


def visit_message(visit: Visit, session: str) -> str:
    """The ``landmark_visits`` JSON of a visit: :func:`~ptm_ros.perception.landmarks.visit_to_json` plus its
    ``session`` id (what :func:`parse_visit_envelope` reads)."""
    doc = json.loads(visit_to_json(visit))
    doc["session"] = session
    return json.dumps(doc)


def parse_visit_envelope(text: str) -> tuple[Visit | int, str | None]:
    """A ``landmark_visits`` message: ``(visit or end-marker count, session id or None)``.

    Raises:
        DataError: malformed JSON, an unknown schema, a malformed visit (:func:`check_visit`) or marker.
    """
    try:
        doc = json.loads(text)
    except JSON_ERRORS as err:
        msg = f"visit message is not JSON: {type(err).__name__}: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict):
        msg = f"visit message schema must be {VISIT_SCHEMA!r} or {END_SCHEMA!r}, got {type(doc).__name__!r}"
        raise DataError(msg)
    session = doc.get("session")
    if session is not None and not isinstance(session, str):
        msg = f"visit message with a session id {session!r} that is not a string"
        raise DataError(msg)
    if doc.get("schema") == END_SCHEMA:
        count = doc.get("visits")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            msg = f"end-of-visits marker with a bad count {count!r}"
            raise DataError(msg)
        return count, session
    if doc.get("schema") != VISIT_SCHEMA:
        msg = f"visit message schema must be {VISIT_SCHEMA!r} or {END_SCHEMA!r}, got {doc.get('schema')!r}"
        raise DataError(msg)
    try:
        visit = visit_from_json(text)
    except (PtmError, *JSON_ERRORS) as err:
        msg = f"malformed visit message: {type(err).__name__}: {err}"
        raise DataError(msg) from err
    check_visit(visit)
    return visit, session


def parse_visit_message(text: str) -> Visit | int:
    """A ``landmark_visits`` message: the :class:`Visit`, or the visit count of an end marker.

    Raises:
        DataError: malformed JSON, an unknown schema or a malformed visit.
    """
    return parse_visit_envelope(text)[0]


# ------------------------------------------------------------------------------------- ptm_graph


def edge_probabilities(topologies: Sequence[Topology]) -> list[dict[str, Any]]:
    """``P(edge a–b)``: the summed mass of the listed topologies in which two consecutive visits are at
    places ``a`` and ``b`` (``a < b``, either direction; canonical labels). Sorted by ``(a, b)``."""
    mass: dict[tuple[int, int], float] = {}
    for t in topologies:
        pairs = {(min(a, b), max(a, b)) for a, b in zip(t.labels[:-1], t.labels[1:], strict=True) if a != b}
        for pair in pairs:
            mass[pair] = mass.get(pair, 0.0) + t.probability
    return [{"places": [a, b], "probability": min(p, 1.0)} for (a, b), p in sorted(mass.items())]


def graph_document(ptm: Ptm, *, complete: bool) -> dict[str, Any]:
    """The ``ptm_graph`` message: ptm.json (:func:`ptm_ros.model.ptm.to_json_dict`) plus

    * ``graph_schema``: ``"ptm_ros.ptm_graph/1"``;
    * ``edges``: ``[{"places": [a, b], "probability": p}]`` (:func:`edge_probabilities`; places are
      canonical labels, so place ``a`` is the ``a``-th distinct place in order of first visit);
    * ``stream``: ``{"visits": N, "complete": bool}`` — ``complete`` once the detector has reported the
      end of its input and every visit is in.
    """
    doc = to_json_dict(ptm)
    doc["graph_schema"] = GRAPH_SCHEMA
    doc["edges"] = edge_probabilities(ptm.topologies)
    doc["stream"] = {"visits": len(ptm.landmarks), "complete": bool(complete)}
    return doc


def check_graph(doc: dict[str, Any]) -> None:
    """What a ``ptm_graph`` document adds to ptm.json (which :func:`ptm_ros.model.ptm.from_json_dict`
    validates): its ``stream`` section.

    Raises:
        DataError: naming the offending item.
    """
    stream = doc.get("stream", {})
    if not isinstance(stream, dict) or not isinstance(stream.get("complete", False), bool):
        msg = f"stream must be a mapping with a boolean 'complete', got {stream!r:.80}"
        raise DataError(msg)


def parse_graph(text: str) -> tuple[dict[str, Any], Ptm]:
    """The JSON document of a ``ptm_graph`` message and its validated :class:`Ptm`.

    Raises:
        DataError: not JSON, or not a valid ptm.json document (:func:`check_graph`).
    """
    try:
        doc = json.loads(text)
    except (ValueError, OverflowError, RecursionError) as err:
        msg = f"ptm_graph message is not JSON: {type(err).__name__}: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict):
        msg = f"ptm_graph message must be a JSON object, got {type(doc).__name__}"
        raise DataError(msg)
    try:
        ptm = from_json_dict(doc)
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as err:  # beside DataError
        msg = f"invalid ptm.json document: {type(err).__name__}: {err}"
        raise DataError(msg) from err
    check_graph(doc)
    return doc, ptm
