"""``topology_filter``: the Rao-Blackwellized particle filter over topologies as a ROS 2 node.

Subscribes ``landmark_visits`` (std_msgs/String, visit JSON ``ptm_ros.visit/1``, reliable, keep all,
transient local) and after every visit publishes

* ``ptm_graph`` (std_msgs/String, reliable + transient local): the ensemble as a JSON document — the
  ptm.json content (schema ``ptm_ros.ptm/1``, see CONTRACT.md) plus ``graph_schema``
  (``ptm_ros.ptm_graph/1``), ``edges`` and ``stream`` (see :func:`graph_document`);
* ``ptm_markers`` (visualization_msgs/MarkerArray): DELETEALL, then for each of the
  ``marker_topologies`` most probable topologies a namespace ``topology_<rank>`` with the visits coloured
  by place, the places, the edges between consecutively visited places and a label, all with alpha
  growing with the topology's probability and lifted by ``rank × 1 m`` in z so the hypotheses stack;
* ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, every second): visits, particles, ESS, update time,
  replays, dropped and invalid messages.

Services (std_srvs/Trigger): ``~/save_ptm`` writes ``<out_dir>/ptm.json`` (the graph document) and
``config.yaml``; ``~/reset`` forgets every visit (the next visit starts a new map); ``~/save_state``
writes the filter's state to ``state_file`` (below).

Bad input (issue #9): every problem is logged once (a warning; later ones at debug level) and counted in
``/diagnostics`` and the graph document's ``diagnostics``; none stops the node or changes the map:

* ``invalid``: not JSON (also nested too deep or numbers beyond float range), an unknown schema, a
  malformed visit (negative index, non-finite or negative stamp, non-numeric / non-finite / wrongly
  shaped signature, words or patch, a signature or word histogram of another length than the map's) or
  end marker (a negative count, or fewer visits than already received): dropped.
* ``duplicates``: a visit of the current session already received (also visit 0 again): dropped.
* ``gaps``: visits that never arrived (the next one is used); a jump of more than
  :data:`MAX_VISIT_GAP` visits is implausible and the visit is dropped instead (``implausible``).
* ``out_of_order``: a visit older (stamp) than the map's latest: dropped.
* ``rejected``: a visit the models cannot use (the session is unchanged).
* ``foreign``: a visit or end marker of another detector session that does not start it (index > 0),
  and any visit of a session that already ended (one the map left for a newer session).
* ``resets``: the detector started a new session (``session`` id changed, visit 0; or, for visits
  without a session id, a different visit 0): the map is started afresh, as after ``~/reset``. An end
  marker of a new session without a visit (a restarted detector that found nothing more) ends the input
  with the map as it is.
* ``redelivered`` (no problem): a visit or end marker the filter restored from its state file, which the
  detector's history delivers again to a resumed filter: skipped.
* ``internal_errors``: a bug caught by the last-resort guard (:func:`ptm_ros.nodes.common.guarded`).

Every message is counted once in ``messages`` and once in ``accepted`` (visits given to the filter,
mapped or ``rejected``), ``ends`` (end markers taken) or one of the drop counters above.

Persistence (issues #8, #9). Parameters ``state_file`` (path, ``''`` = off), ``autosave_every`` (visits,
0 = off) and ``resume`` (bool, default false). The node's state — the filter session (visits with their
measurements, the registration cache, the particle filter's
:meth:`~ptm_ros.rbpf.TopologyFilter.state_dict`) and its place in the detector's stream (session id, next
visit index, end marker, counters, sessions that ended) — is written atomically to ``state_file``
(:func:`ptm_ros.persistence.save_filter_state`, with the configuration as meta data) every
``autosave_every`` visits, at the detector's end marker, on ``~/save_state`` and at a clean shutdown.
With ``resume: true``, a starting node continues from ``state_file`` when it exists, and publishes the
restored ensemble. The visits since the last save come back from the detector: ``landmark_visits`` is
reliable, keep-all and transient local, so a new subscription receives the detector's whole history (a
keep-all Fast DDS writer keeps its latest 5000 messages: measured), in order; the restored ones are
skipped (``redelivered``), the rest mapped, and the ensemble is exactly that of a filter never
interrupted. This needs the detector that made the saved visits to be still running (a restarted
detector starts a new session, hence a new map). A file that cannot be used — truncated, corrupt,
foreign, or made with another configuration or ``refit_max_visits`` — is logged as an error, moved to
``<state_file>.rejected``, and the node starts afresh (the detector's history rebuilds the map; the
diagnostics say WARN: ``persistence.resume_rejected``). A failed save is logged and counted
(``persistence.save_failures``, WARN); the previous file stays intact.

Streaming equals offline. The appearance model's priors are fitted to *all* visits of a run (empirical
Bayes, :func:`ptm_ros.appearance.fit_appearance_model`), which a stream only knows at its end. So
:class:`FilterSession` re-fits them after every visit and, when they change, replays the (deterministic,
seeded) filter over the visits so far; otherwise it updates the filter with the new visit. Laser
registrations are cached per pair, so a replay costs only filter updates. After every visit the
ensemble is therefore exactly what ``ptm-run`` computes on the visits so far — and at the end of a bag,
exactly its result. A replay costs N filter updates (measured: 1.7 s at N = 52 with 100 particles),
so beyond ``refit_max_visits`` visits (default 100; 0 = never, as ``ptm-bringup`` sets for exactness)
the priors are frozen as fitted then and the filter only moves forward: a live robot's filter keeps up
on long runs, at the price of priors fitted to the first visits rather than to all.
"""

from __future__ import annotations

import colorsys
import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import ColorRGBA, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from ptm_ros.config import PtmConfig, save_config
from ptm_ros.configio import to_dict
from ptm_ros.doubts import doubt_lines, find_doubts
from ptm_ros.errors import ConfigError, DataError, PtmError
from ptm_ros.figures import ess_fraction
from ptm_ros.nodes.common import (
    LATCHED_QOS,
    STREAM_QOS,
    OnceLogger,
    Publishes,
    advertise,
    check_parameter_names,
    declare_config,
    declare_node_parameter,
    guarded,
    publish_diagnostics,
    run_node,
    time_msg,
)
from ptm_ros.nodes.messages import parse_visit_envelope
from ptm_ros.persistence import (
    differences,
    load_filter_state,
    save_filter_state,
)
from ptm_ros.ptm import Ptm, Topology, to_json_dict
from ptm_ros.rbpf import FilterState
from ptm_ros.session import FilterSession
from ptm_ros.visits import Visit, pose_field

NODE_NAME = "topology_filter"
GRAPH_SCHEMA = "ptm_ros.ptm_graph/1"
FRAME_ID = "odom"  # default of the frame_id parameter: the frame of the visits, the graph and the markers
#: What the node publishes (topic: message type, QoS), the table its publishers are made from.
PUBLISHES: Publishes = {
    "ptm_graph": (String, LATCHED_QOS),
    "ptm_markers": (MarkerArray, LATCHED_QOS),
    "/diagnostics": (DiagnosticArray, 10),
}
#: Schema tag of the node's state file content (its ``session`` is a :class:`FilterSession` state).
NODE_STATE_SCHEMA = "ptm_ros.topology_filter_state/1"
MARKER_Z_STEP = 1.0  # m between stacked hypotheses
MAX_VISIT_GAP = 1000  # visits: a larger jump of the detector's index is a corrupt message
COUNTERS = (
    "messages",
    "accepted",
    "ends",
    "invalid",
    "rejected",
    "duplicates",
    "gaps",
    "implausible",
    "out_of_order",
    "foreign",
    "resets",
    "redelivered",
    "internal_errors",
)
#: Counters that are no problem (the others turn /diagnostics to WARN).
BENIGN = ("messages", "accepted", "ends", "resets", "redelivered")
MAX_RETIRED = 64  # finished detector sessions remembered (their late visits never start a new map)


# ----------------------------------------------------------------------------------- graph document


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
    """The ``ptm_graph`` message: ptm.json (:func:`ptm_ros.ptm.to_json_dict`) plus

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


# -------------------------------------------------------------------------------------------- markers


def place_colour(place: int, alpha: float) -> ColorRGBA:
    """A distinct colour per place (golden-ratio hues)."""
    r, g, b = colorsys.hsv_to_rgb((place * 0.618033988749895) % 1.0, 0.85, 0.95)
    return ColorRGBA(r=r, g=g, b=b, a=float(alpha))


def topology_alpha(probability: float) -> float:
    """Marker alpha of a topology: 0.15 at probability 0, 1 at probability 1."""
    return 0.15 + 0.85 * min(max(probability, 0.0), 1.0)


def place_points(ptm: Ptm, rank: int) -> np.ndarray:
    """``(M, 2)`` positions of the places of topology ``rank``: its estimated positions, else the mean
    odometry position of each place's visits."""
    t = ptm.topologies[rank]
    m = max(t.labels) + 1
    if t.positions is not None and len(t.positions) == m:
        return np.asarray(t.positions, dtype=float).reshape(m, 2)
    xy = np.array([lm.map_pose[:2] for lm in ptm.landmarks], dtype=float).reshape(-1, 2)
    labels = np.asarray(t.labels)
    return np.array([xy[labels == k].mean(axis=0) for k in range(m)])


def ensemble_markers(ptm: Ptm, count: int, stamp: float) -> MarkerArray:
    """DELETEALL, then the ``count`` most probable topologies (see the module docstring)."""
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    clear.header.frame_id = ptm.frame_id
    out.markers.append(clear)
    xy = np.array([lm.map_pose[:2] for lm in ptm.landmarks], dtype=float).reshape(-1, 2)
    for rank, t in enumerate(ptm.topologies[:count]):
        alpha = topology_alpha(t.probability)
        z = rank * MARKER_Z_STEP
        places = place_points(ptm, rank)
        ns = f"topology_{rank}"

        def marker(kind: int, mid: int, scale: float, ns: str = ns) -> Marker:
            mk = Marker()
            mk.header.frame_id = ptm.frame_id
            mk.header.stamp = time_msg(stamp)
            mk.ns, mk.id, mk.type, mk.action = ns, mid, kind, Marker.ADD
            mk.pose.orientation.w = 1.0
            mk.scale.x = mk.scale.y = mk.scale.z = scale
            return mk

        visits = marker(Marker.SPHERE_LIST, 0, 0.25)
        visits.points = [Point(x=float(x), y=float(y), z=z) for x, y in xy]
        visits.colors = [place_colour(k, alpha) for k in t.labels]
        visits.color = place_colour(0, alpha)
        nodes = marker(Marker.SPHERE_LIST, 1, 0.6)
        nodes.points = [Point(x=float(x), y=float(y), z=z) for x, y in places]
        nodes.colors = [place_colour(k, alpha) for k in range(len(places))]
        nodes.color = place_colour(0, alpha)
        edges = marker(Marker.LINE_LIST, 2, 0.08)
        pairs = sorted(
            {(min(a, b), max(a, b)) for a, b in zip(t.labels[:-1], t.labels[1:], strict=True) if a != b}
        )
        for a, b in pairs:
            edges.points += [Point(x=float(places[a, 0]), y=float(places[a, 1]), z=z)]
            edges.points += [Point(x=float(places[b, 0]), y=float(places[b, 1]), z=z)]
        edges.color = ColorRGBA(r=0.8, g=0.8, b=0.8, a=alpha)
        label = marker(Marker.TEXT_VIEW_FACING, 3, 0.5)
        label.pose.position.x, label.pose.position.y = float(places[0, 0]), float(places[0, 1])
        label.pose.position.z = z + 0.8
        label.text = f"#{rank + 1} p={t.probability:.3f} places={len(places)}"
        label.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=alpha)
        out.markers += [visits, nodes, edges, label]
    return out


def newest_doubt(ptm: Ptm | None) -> str | None:
    """A log line when the map is unsure where its newest visit is (:mod:`ptm_ros.doubts`), else None."""
    if ptm is None or not ptm.topologies:
        return None
    doubts = find_doubts(ptm)
    last = len(ptm.landmarks) - 1
    if not doubts.visits or doubts.visits[-1].visit != last:
        return None
    return doubt_lines(replace(doubts, visits=doubts.visits[-1:]))[-1]


def visit_line(index: int, state: FilterState, map_mass: float, *, how: str, ms: float) -> str:
    """The log line after a visit: the effective sample size ``1/Σw²`` as a share of the particles it is
    computed over (each particle a distinct topology, so it is near 1 whenever one topology holds nearly
    all the mass: the line says how much), and the update's time.

    ``visit_line(7, state, 0.806, how="updated", ms=56.3)`` →
    ``"visit 7: ESS 1.46/100 particles (each a distinct topology; the most probable holds 0.806),
    updated in 56 ms"``.
    """
    return (
        f"visit {index}: ESS {ess_fraction(state.ess, state.n_topologies)} particles (each a distinct "
        f"topology; the most probable holds {map_mass:.3f}), {how} in {ms:.0f} ms"
    )


# ----------------------------------------------------------------------------------------------- node


class TopologyFilterNode(Node):
    """The ``topology_filter`` node (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        check_parameter_names(self)
        self.config: PtmConfig = declare_config(self)
        self.out_dir = declare_node_parameter(
            self, "out_dir", "out/topology_filter", "directory ~/save_ptm writes ptm.json to", read_only=False
        )
        self.marker_topologies = declare_node_parameter(
            self, "marker_topologies", 5, "most probable topologies drawn on ptm_markers", minimum=0
        )
        refit = declare_node_parameter(
            self,
            "refit_max_visits",
            100,
            "re-fit the appearance priors and replay the filter up to this many visits; 0 = always "
            "(the ensemble then equals ptm-run's exactly, at O(N) updates per visit)",
            minimum=0,
        )
        self.frame_id = declare_node_parameter(self, "frame_id", FRAME_ID, "odometry frame of the visits")
        state_file = declare_node_parameter(
            self,
            "state_file",
            "",
            "file of the filter's saved state (~/save_state, autosave, resume); '' = off",
        )
        self.state_file = Path(state_file) if state_file else None
        self.autosave_every = declare_node_parameter(
            self,
            "autosave_every",
            0,
            "save the state to state_file every this many visits; 0 = off",
            minimum=0,
        )
        resume = declare_node_parameter(
            self, "resume", False, "on start, continue from state_file if it exists (else start afresh)"
        )
        self.refit_max_visits = refit
        self.session = FilterSession(self.config, refit_max_visits=refit)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._next_index: int | None = None  # the detector's index of the next visit (None: any)
        self._end_count: int | None = None  # visits the detector announced at its end
        self._stream: str | None = None  # the detector session of the map's visits
        self._first: tuple[float, tuple[float, float, float]] | None = None  # (stamp, pose) of its visit 0
        self._last_stamp = -math.inf  # stamp of the latest visit in the map
        self._last: FilterState | None = None
        self._retired: dict[str, int] = {}  # finished detector sessions -> visits they had
        self._resumed: dict[str | None, int] = {}  # detector sessions -> visits restored from state_file
        self._unsaved = 0  # visits taken since the state was last saved
        self._dirty = False  # anything changed since then (visits, end markers, resets)
        self.persistence = {"resumed_visits": 0, "resume_rejected": 0, "saves": 0, "save_failures": 0}
        self._log_once = OnceLogger(self.get_logger())
        self._graph_pub = advertise(self, PUBLISHES, "ptm_graph")
        self._marker_pub = advertise(self, PUBLISHES, "ptm_markers")
        self._diag_pub = advertise(self, PUBLISHES, "/diagnostics")
        self.create_subscription(String, "landmark_visits", self._on_visit, STREAM_QOS)
        self.create_service(Trigger, "~/save_ptm", self._on_save)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/save_state", self._on_save_state)
        self.create_timer(1.0, self._publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f"RBPF with {self.config.inference.particles} particles, seed {self.config.inference.seed}"
        )
        if resume and self.state_file is not None:
            self._resume(self.state_file)

    # -------------------------------------------------------------------------------- visits

    @property
    def complete(self) -> bool:
        """Whether the detector reported its end and every visit it announced has been consumed."""
        if self._end_count is None:
            return False
        return (self._next_index or 0) >= self._end_count

    def _drop(self, counter: str, message: str) -> None:
        self.counters[counter] += 1
        self._log_once(counter, message)

    @guarded
    def _on_visit(self, msg: String) -> None:
        self.counters["messages"] += 1
        try:
            item, session = parse_visit_envelope(msg.data)
        except DataError as err:
            self._drop("invalid", f"dropped a malformed landmark_visits message: {err}")
            return
        if isinstance(item, int):
            self._on_end(item, session)
            return
        self._add(item, session)

    def _on_end(self, count: int, session: str | None) -> None:
        if session != self._stream and session in self._resumed:
            self.counters["redelivered"] += 1  # the end of a session restored from state_file
            return
        if self._next_index is not None and session != self._stream:
            if count != 0 or session in self._retired:
                self._drop("foreign", f"ignored the end marker of detector session {session!r}")
                return
            self.get_logger().warning(
                f"detector session {session!r} ended without a visit: the map of {self._stream!r} is final"
            )
            count = self._next_index  # a restarted detector found nothing more: the input is over
        if count < (self._next_index or 0):
            self._drop(
                "invalid", f"ignored an end marker of {count} visits: {self._next_index} already arrived"
            )
            return
        self._end_count = count
        self.counters["ends"] += 1
        self.get_logger().info(f"end of visits reported ({count}); {len(self.session.visits)} in the map")
        self._dirty = True
        if self.autosave_every > 0:
            self._autosave()
        self._publish()

    def _shapes_differ(self, visit: Visit) -> bool:
        """Whether the visit's signature or word histogram differs in length from the map's."""
        for name in ("signature", "words"):
            new = getattr(visit, name)
            old = next((a for v in self.session.visits if (a := getattr(v, name)) is not None), None)
            if new is not None and old is not None and new.shape != old.shape:
                return True
        return False

    def _add(self, visit: Visit, session: str | None = None) -> None:
        """Consume the detector's visit ``visit.index`` of detector session ``session`` (re-indexed from
        the last reset on; see the module docstring for what is dropped)."""
        key = (visit.stamp, visit.pose)
        if self._redelivered(session, visit.index, key):
            self.counters["redelivered"] += 1
            if self.counters["redelivered"] == 1:
                self.get_logger().info("the detector redelivers visits restored from the state file: skipped")
            return
        if self._next_index is not None and session != self._stream:
            if visit.index != 0 or session in self._retired:
                self._drop("foreign", f"dropped visit {visit.index} of another detector session {session!r}")
                return
            self.get_logger().warning(f"detector session {session!r} started: starting a new map")
            self._retire()
            self._reset()
        elif self._next_index is not None and visit.index < self._next_index:
            if visit.index != 0 or session is not None or key == self._first:
                self._drop("duplicates", f"dropped visit {visit.index}: already processed")
                return
            self.get_logger().warning(
                "a different visit 0 arrived: the detector restarted; starting a new map"
            )
            self._reset()
        elif self._next_index is not None and visit.index > self._next_index + MAX_VISIT_GAP:
            self._drop("implausible", f"dropped visit {visit.index}: {self._next_index} was expected")
            return
        if visit.stamp < self._last_stamp:
            self._drop("out_of_order", f"dropped visit {visit.index}: older than the map's latest visit")
            return
        if self._shapes_differ(visit):
            self._drop("invalid", f"dropped visit {visit.index}: measurements shaped unlike the map's")
            return
        expected = visit.index if self._next_index is None else self._next_index
        if visit.index > expected:
            self._drop("gaps", f"visits {expected}..{visit.index - 1} never arrived; continuing without them")
        if self._next_index is None:
            self._stream = session
            self._first = key if visit.index == 0 else None
        self._next_index = visit.index + 1
        self.counters["accepted"] += 1
        n = len(self.session.visits)
        if visit.index != n:
            visit = dataclasses.replace(visit, index=n)
        replays, wall = self.session.replays, self.session.wall_s
        self._unsaved += 1
        self._dirty = True
        try:
            self._last = state = self.session.add(visit)
        except PtmError as err:
            self._drop("rejected", f"the filter rejected visit {visit.index}: {err}")
            self._maybe_autosave()
            if self.complete:
                self._publish()
            return
        self._last_stamp = visit.stamp
        how = "replayed" if self.session.replays > replays else "updated"
        flt = self.session.filter
        map_mass = max(flt.ptm_weights().values(), default=0.0) if flt is not None else 0.0
        ms = (self.session.wall_s - wall) * 1e3
        self.get_logger().info(visit_line(visit.index, state, map_mass, how=how, ms=ms))
        self._maybe_autosave()
        ptm = self._publish()
        doubt = newest_doubt(ptm)
        if doubt:
            self.get_logger().info(doubt)

    def _redelivered(self, session: str | None, index: int, key: tuple[Any, ...]) -> bool:
        """Whether a visit was restored from the state file (the detector's history delivers it again to
        a resumed filter). Without session ids, a visit 0 unlike the map's is a restart, not a repeat."""
        limit = self._resumed.get(session)
        if limit is None or index >= limit:
            return False
        return not (session is None and index == 0 and key != self._first)

    def _retire(self) -> None:
        """Remember the current detector session as finished (its late visits never start a map)."""
        if self._stream is None:
            return
        self._retired[self._stream] = self._next_index or 0
        while len(self._retired) > MAX_RETIRED:
            del self._retired[next(iter(self._retired))]

    def current_ptm(self) -> Ptm:
        """The ensemble now (an empty PTM before the first visit)."""
        if self.session.filter is None:
            return Ptm(
                landmarks=(), topologies=(), frame_id=self.frame_id, extra={"diagnostics": self.diagnostics()}
            )
        return self.session.to_ptm(frame_id=self.frame_id, diagnostics=self.diagnostics())

    def _publish(self) -> Ptm | None:
        if self.session.filter is None and not self.complete:
            return None  # nothing to tell yet (a complete empty stream is published: it ends the run)
        ptm = self.current_ptm()
        doc = graph_document(ptm, complete=self.complete)
        self._graph_pub.publish(String(data=json.dumps(doc)))
        stamp = ptm.landmarks[-1].stamp if ptm.landmarks else 0.0
        self._marker_pub.publish(ensemble_markers(ptm, self.marker_topologies, stamp))
        return ptm

    # --------------------------------------------------------------------------- persistence

    def state_meta(self) -> dict[str, Any]:
        """What the state file records about how its state was made (checked on resume)."""
        return {
            "node": NODE_NAME,
            "config": to_dict(self.config),
            "refit_max_visits": self.refit_max_visits,
            "frame_id": self.frame_id,
        }

    def state_dict(self) -> dict[str, Any]:
        """The node's state: the filter session and the position in the detector's visit stream."""
        return {
            "schema": NODE_STATE_SCHEMA,
            "session": self.session.state_dict(),
            "next_index": self._next_index,
            "end_count": self._end_count,
            "stream": self._stream,
            "first": None if self._first is None else [self._first[0], list(self._first[1])],
            "last_stamp": self._last_stamp,
            "last": None if self._last is None else dataclasses.astuple(self._last),
            "counters": dict(self.counters),
            "retired": [[k, n] for k, n in self._retired.items()],
        }

    def save_state(self) -> Path:
        """Write :meth:`state_dict` to ``state_file`` (atomically).

        Raises:
            DataError: no ``state_file``, or it cannot be written (the previous file is then unchanged).
        """
        if self.state_file is None:
            msg = "parameter state_file is not set"
            raise DataError(msg)
        self.state_file.parent.mkdir(parents=True, exist_ok=True)
        path = save_filter_state(self.state_file, self.state_dict(), meta=self.state_meta())
        self._unsaved, self._dirty = 0, False
        self.persistence["saves"] += 1
        return path

    def _maybe_autosave(self) -> None:
        if self.autosave_every > 0 and self._unsaved >= self.autosave_every:
            self._autosave()

    def _autosave(self) -> None:
        if self.state_file is None:
            return
        try:
            self.save_state()
        except (OSError, DataError) as err:
            self.persistence["save_failures"] += 1
            self._log_once("save-failure", f"cannot save the state to {self.state_file}: {err}")
            return
        self.get_logger().debug(f"saved the state ({len(self.session.visits)} visits) to {self.state_file}")

    def _resume(self, path: Path) -> None:
        """Continue from the state file (if it exists). A file that cannot be used (corrupt, foreign, made
        with another configuration) is moved aside to ``<file>.rejected`` and the filter starts afresh:
        the detector's transient-local history then rebuilds the map."""
        if not path.exists():
            self.get_logger().info(f"resume: no state file {path} yet; starting afresh")
            return
        try:
            state, meta = load_filter_state(path)
            self._check_meta(meta)
            self._load_state(state)
        except (DataError, ConfigError) as err:
            self._reset_all()
            self.persistence["resume_rejected"] += 1
            aside = path.with_name(path.name + ".rejected")
            try:
                path.replace(aside)
            except OSError as move_err:
                aside = Path(f"(not moved: {move_err})")
            self.get_logger().error(
                f"cannot resume from {path}: {err}; starting afresh (file kept as {aside})"
            )
            return
        n = len(self.session.visits)
        self.persistence["resumed_visits"] = n
        self.get_logger().info(
            f"resumed from {path}: {n} visits of detector session {self._stream!r}, "
            f"next detector visit {self._next_index}"
        )
        self._publish()

    def _check_meta(self, meta: dict[str, Any]) -> None:
        mine = self.state_meta()
        if meta.get("node") != NODE_NAME:
            msg = f"the state was saved by {meta.get('node')!r}, not {NODE_NAME}"
            raise DataError(msg)
        for key in ("config", "refit_max_visits"):
            if meta.get(key) != mine[key]:
                diff = differences(meta.get(key), mine[key]) if isinstance(mine[key], dict) else [key]
                msg = f"the state was made with another {key} ({', '.join(diff[:5])} differ)"
                raise ConfigError(msg)

    def _load_state(self, state: dict[str, Any]) -> None:
        if state.get("schema") != NODE_STATE_SCHEMA:
            msg = f"not a {NODE_NAME} state (schema {state.get('schema')!r})"
            raise DataError(msg)
        try:
            self.session.load_state(state["session"])
            self._next_index = None if state["next_index"] is None else int(state["next_index"])
            self._end_count = None if state["end_count"] is None else int(state["end_count"])
            self._stream = state["stream"]
            first = state["first"]
            self._first = None if first is None else (float(first[0]), pose_field(first[1]))
            self._last_stamp = float(state["last_stamp"])
            self._last = None if state["last"] is None else FilterState(*state["last"])
            unknown = set(state["counters"]) - set(COUNTERS)
            if unknown:
                msg = f"unknown counters {sorted(unknown)}"
                raise DataError(msg)
            self.counters.update({k: int(v) for k, v in state["counters"].items()})
            self._retired = {str(k): int(n) for k, n in state["retired"]}
        except (KeyError, TypeError, ValueError, IndexError) as err:
            msg = f"malformed {NODE_NAME} state: {type(err).__name__}: {err}"
            raise DataError(msg) from err
        self._resumed = dict(self._retired.items())
        self._resumed[self._stream] = self._next_index or 0
        self._unsaved, self._dirty = 0, False

    def _reset_all(self) -> None:
        self.session.reset()
        self._next_index = self._end_count = self._stream = self._first = self._last = None
        self._last_stamp = -math.inf
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._retired, self._resumed = {}, {}

    @guarded
    def _on_save_state(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            path = self.save_state()
        except (OSError, DataError) as err:
            response.success, response.message = False, f"cannot save the state: {err}"
            return response
        response.success = True
        response.message = json.dumps({"path": str(path), "visits": len(self.session.visits)})
        return response

    def destroy_node(self) -> None:
        """Save the state (if ``state_file`` is set and changed since the last save), then destroy."""
        if getattr(self, "state_file", None) is not None and getattr(self, "_dirty", False):
            self._autosave()
        super().destroy_node()

    # --------------------------------------------------------------------------- diagnostics

    def diagnostics(self) -> dict[str, Any]:
        """Counters reported on /diagnostics and in the graph document."""
        last = self._last
        return {
            "visits": len(self.session.visits),
            "particles": 0 if self.session.filter is None else self.session.filter.n_topologies,
            "ess": 0.0 if last is None else last.ess,
            "update_ms": 0.0 if last is None else last.update_s * 1e3,
            "replays": self.session.replays,
            "registrations": dict(self.session.registrations),
            **self.counters,
            "persistence": dict(self.persistence),
        }

    @guarded
    def _publish_diagnostics(self) -> None:
        values = self.diagnostics()
        bad = sum(values[k] for k in COUNTERS if k not in BENIGN)
        bad += self.persistence["resume_rejected"] + self.persistence["save_failures"]
        publish_diagnostics(
            self,
            self._diag_pub,
            "RBPF",
            hardware_id=NODE_NAME,
            message=(
                f"{values['visits']} visits, {values['particles']} topologies, "
                f"ESS {ess_fraction(values['ess'], values['particles'])}"
            ),
            values=values,
            warn=bad > 0,
        )

    # ------------------------------------------------------------------------------ services

    @guarded
    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.session.filter is None:
            response.success, response.message = False, "no visit received yet: nothing to save"
            return response
        out = Path(self.get_parameter("out_dir").value)
        try:
            ptm = self.session.to_ptm(frame_id=self.frame_id, diagnostics=self.diagnostics())
            out.mkdir(parents=True, exist_ok=True)
            path = out / "ptm.json"
            path.write_text(json.dumps(graph_document(ptm, complete=self.complete), indent=1) + "\n")
            save_config(self.config, out / "config.yaml")
        except (OSError, PtmError) as err:
            response.success, response.message = False, f"cannot write {out}/ptm.json: {err}"
            return response
        response.success = True
        response.message = json.dumps(
            {"path": str(path), "visits": len(ptm.landmarks), "topologies": len(ptm.topologies)}
        )
        return response

    def _reset(self) -> None:
        self.session.reset()
        self._next_index = None
        self._end_count = None
        self._stream = None
        self._first = None
        self._last_stamp = -math.inf
        self._last = None
        self.counters["resets"] += 1
        self._dirty = True

    @guarded
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        n = len(self.session.visits)
        self._reset()
        self._resumed = {}  # a new map from the next visit on, whatever it is
        self._marker_pub.publish(
            ensemble_markers(Ptm(landmarks=(), topologies=(), frame_id=self.frame_id), 0, 0.0)
        )
        response.success, response.message = True, f"forgot {n} visits"
        return response


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``topology_filter``."""
    return run_node(TopologyFilterNode, args, NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
