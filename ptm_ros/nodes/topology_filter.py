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
:meth:`~ptm_ros.inference.rbpf.TopologyFilter.state_dict`) and its place in the detector's stream (session id,
next visit index, end marker, counters, sessions that ended) — is written atomically to ``state_file``
(:func:`ptm_ros.inference.persistence.save_filter_state`, with the configuration as meta data) every
``autosave_every`` visits, at the detector's end marker, on ``~/save_state`` and at a clean shutdown.
With ``resume: true``, a starting node continues from ``state_file`` when it exists, and publishes the
restored ensemble. The visits since the last save come back from the detector: ``landmark_visits`` is
reliable, keep-all and transient local, so a new subscription receives the detector's whole history (a
keep-all Fast DDS writer keeps its latest 5000 messages: measured), in order; the restored ones are
skipped (``redelivered``), the rest mapped, and the ensemble is exactly that of a filter never
interrupted. This needs the detector that made the saved visits to be still running (a restarted
detector starts a new session, hence a new map). A ``ptm-run`` state file (the same filter session,
without a place in a detector stream) is resumed too: the first detector session that delivers one of
its visits (same index, stamp and pose: a replay of the same bag) is adopted and its visits up to the
saved ones are skipped. A file that cannot be used — truncated, corrupt,
foreign, or made with another configuration or ``refit_max_visits`` — is logged as an error, moved to
``<state_file>.rejected``, and the node starts afresh (the detector's history rebuilds the map; the
diagnostics say WARN: ``persistence.resume_rejected``). A failed save is logged and counted
(``persistence.save_failures``, WARN); the previous file stays intact.

Streaming equals offline. The appearance model's priors are fitted to *all* visits of a run (empirical
Bayes, :func:`ptm_ros.model.appearance.fit_appearance_model`), which a stream only knows at its end. So
:class:`FilterSession` re-fits them after every visit and, when they change, replays the (deterministic,
seeded) filter over the visits so far; otherwise it updates the filter with the new visit. Laser
registrations are cached per pair, so a replay costs only filter updates. After every visit the
ensemble is therefore exactly what ``ptm-run`` computes on the visits so far — and at the end of a bag,
exactly its result. A replay costs N filter updates, so beyond ``refit_max_visits`` visits (default
100; 0 = never, as ``ptm-bringup`` sets for exactness)
the priors are frozen as fitted then and the filter only moves forward: a live robot's filter keeps up
on long runs, at the price of priors fitted to the first visits rather than to all.
"""

from __future__ import annotations

import colorsys
import json
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
from ptm_ros.errors import DataError, PtmError
from ptm_ros.model.ptm import Ptm
from ptm_ros.nodes.common import (
    LATCHED_QOS,
    STREAM_QOS,
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
from ptm_ros.nodes.filter_inbox import NODE_NAME, FilterInbox, Reaction
from ptm_ros.nodes.logs import OnceLogger
from ptm_ros.nodes.messages import graph_document
from ptm_ros.reporting.doubts import doubt_lines, find_doubts
from ptm_ros.reporting.figures import ess_fraction

FRAME_ID = "odom"  # default of the frame_id parameter: the frame of the visits, the graph and the markers
#: What the node publishes (topic: message type, QoS), the table its publishers are made from.
PUBLISHES: Publishes = {
    "ptm_graph": (String, LATCHED_QOS),
    "ptm_markers": (MarkerArray, LATCHED_QOS),
    "/diagnostics": (DiagnosticArray, 10),
}
MARKER_Z_STEP = 1.0  # m between stacked hypotheses


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
    """A log line when the map is unsure where its newest visit is (:mod:`ptm_ros.reporting.doubts`), else
    None."""
    if ptm is None or not ptm.topologies:
        return None
    doubts = find_doubts(ptm)
    last = len(ptm.landmarks) - 1
    if not doubts.visits or doubts.visits[-1].visit != last:
        return None
    return doubt_lines(replace(doubts, visits=doubts.visits[-1:]))[-1]


# ----------------------------------------------------------------------------------------------- node


class TopologyFilterNode(Node):
    """The ``topology_filter`` node (see the module docstring): topics, services, parameters and timers
    around a :class:`~ptm_ros.nodes.filter_inbox.FilterInbox`, which does the work."""

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
        autosave_every = declare_node_parameter(
            self,
            "autosave_every",
            0,
            "save the state to state_file every this many visits; 0 = off",
            minimum=0,
        )
        resume = declare_node_parameter(
            self, "resume", False, "on start, continue from state_file if it exists (else start afresh)"
        )
        self.inbox = FilterInbox(
            self.config,
            self.get_logger(),
            refit_max_visits=refit,
            frame_id=self.frame_id,
            state_file=Path(state_file) if state_file else None,
            autosave_every=autosave_every,
        )
        self._log_once = OnceLogger(self.get_logger())
        self._graph_pub = advertise(self, PUBLISHES, "ptm_graph")
        self._marker_pub = advertise(self, PUBLISHES, "ptm_markers")
        self._diag_pub = advertise(self, PUBLISHES, "/diagnostics")
        self.create_subscription(String, "landmark_visits", self._on_visit, STREAM_QOS)
        self.create_service(Trigger, "~/save_ptm", self._on_save)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/save_state", self._on_save_state)
        self.create_timer(1.0, self._publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME))
        inf = self.config.inference
        self.get_logger().info(
            f"RBPF with {inf.particles} particles (up to {inf.particles_cap} where the "
            f"posterior is spread), seed {inf.seed}"
        )
        if resume and self.inbox.state_file is not None:
            self._react(self.inbox.resume(self.inbox.state_file))

    @property
    def counters(self) -> dict[str, int]:
        """The inbox's message counters (the guard of :func:`ptm_ros.nodes.common.guarded` adds to them)."""
        return self.inbox.counters

    @guarded
    def _on_visit(self, msg: String) -> None:
        self._react(self.inbox.receive(msg.data))

    def _react(self, reaction: Reaction) -> None:
        if reaction is Reaction.NONE:
            return
        ptm = self._publish()
        doubt = newest_doubt(ptm) if reaction is Reaction.NEW_VISIT else None
        if doubt:
            self.get_logger().info(doubt)

    def _publish(self) -> Ptm | None:
        inbox = self.inbox
        if inbox.session.filter is None and not inbox.complete:
            return None  # nothing to tell yet (a complete empty stream is published: it ends the run)
        ptm = inbox.current_ptm()
        doc = graph_document(ptm, complete=inbox.complete)
        self._graph_pub.publish(String(data=json.dumps(doc)))
        stamp = ptm.landmarks[-1].stamp if ptm.landmarks else 0.0
        self._marker_pub.publish(ensemble_markers(ptm, self.marker_topologies, stamp))
        return ptm

    def destroy_node(self) -> None:
        """Save the state (if ``state_file`` is set and changed since the last save), then destroy."""
        inbox = getattr(self, "inbox", None)
        if inbox is not None and inbox.dirty:
            inbox.autosave()
        super().destroy_node()

    @guarded
    def _publish_diagnostics(self) -> None:
        values = self.inbox.diagnostics()
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
            warn=self.inbox.problems() > 0,
        )

    # ------------------------------------------------------------------------------ services

    @guarded
    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        inbox = self.inbox
        if inbox.session.filter is None:
            response.success, response.message = False, "no visit received yet: nothing to save"
            return response
        out = Path(self.get_parameter("out_dir").value)
        try:
            ptm = inbox.current_ptm()
            out.mkdir(parents=True, exist_ok=True)
            path = out / "ptm.json"
            path.write_text(json.dumps(graph_document(ptm, complete=inbox.complete), indent=1) + "\n")
            save_config(self.config, out / "config.yaml")
        except (OSError, PtmError) as err:
            response.success, response.message = False, f"cannot write {out}/ptm.json: {err}"
            return response
        response.success = True
        response.message = json.dumps(
            {"path": str(path), "visits": len(ptm.landmarks), "topologies": len(ptm.topologies)}
        )
        return response

    @guarded
    def _on_save_state(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            path = self.inbox.save_state()
        except (OSError, DataError) as err:
            response.success, response.message = False, f"cannot save the state: {err}"
            return response
        response.success = True
        response.message = json.dumps({"path": str(path), "visits": len(self.inbox.session.visits)})
        return response

    @guarded
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        n = self.inbox.forget()
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
