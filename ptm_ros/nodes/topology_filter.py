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
``config.yaml``; ``~/reset`` forgets every visit (the next visit starts a new map).

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
import time
from collections.abc import Sequence
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
from ptm_ros.errors import ConfigError, DataError, PtmError
from ptm_ros.geometry import RelativePose
from ptm_ros.landmarks import VISIT_SCHEMA, visit_from_json
from ptm_ros.nodes.common import (
    END_SCHEMA,
    LATCHED_QOS,
    STREAM_QOS,
    OnceLogger,
    check_parameter_names,
    declare_config,
    declare_node_parameter,
    publish_diagnostics,
    run_node,
    time_msg,
)
from ptm_ros.posterior import PosteriorModel
from ptm_ros.ptm import Ptm, Topology, to_json_dict
from ptm_ros.rbpf import FilterState, RbpfConfig, TopologyFilter
from ptm_ros.tools.pipeline import Inference, build_ptm, make_registrar, rbpf_inference
from ptm_ros.visits import Visit

NODE_NAME = "topology_filter"
GRAPH_SCHEMA = "ptm_ros.ptm_graph/1"
MARKER_Z_STEP = 1.0  # m between stacked hypotheses


# ------------------------------------------------------------------------------------- filter session


def same_model(a: Any, b: Any) -> bool:
    """Whether two fitted appearance models (or None) are identical, array by array."""
    if a is None or b is None:
        return a is b
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(
            same_model(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(a, b))
    return bool(a == b)


class FilterSession:
    """The RBPF over a stream of visits; after every visit, exactly ``ptm-run``'s RBPF on the visits so far.

    Args:
        config: the configuration (``inference.method`` must be ``rbpf``).
        refit_max_visits: re-fit the appearance priors (and replay when they change) up to this many
            visits; later the priors stay as fitted then. 0: always (exactly ``ptm-run``).

    Raises:
        ConfigError: another inference method, or ``refit_max_visits < 0``.
    """

    def __init__(self, config: PtmConfig, *, refit_max_visits: int = 100) -> None:
        if config.inference.method != "rbpf":
            msg = (
                f"{NODE_NAME} computes the PTM online with the RBPF (inference.method: rbpf), got "
                f"{config.inference.method!r}; use ptm-run for '{config.inference.method}'"
            )
            raise ConfigError(msg)
        if refit_max_visits < 0:
            msg = f"refit_max_visits must be >= 0, got {refit_max_visits}"
            raise ConfigError(msg)
        self.config = config
        self.refit_max_visits = refit_max_visits
        self.registrations: dict[str, Any] = {}
        self._visits: list[Visit] = []
        self._pairs: dict[tuple[int, int], RelativePose | None] = {}
        self._filter: TopologyFilter | None = None
        self.replays = 0
        self.wall_s = 0.0
        inner = make_registrar(self._visits, config, self.registrations) if config.model.use_laser else None
        self._registrar = None if inner is None else self._cached(inner)

    def _cached(self, inner: Any) -> Any:
        def registrar(i: int, j: int) -> RelativePose | None:
            key = (i, j)
            if key not in self._pairs:
                self._pairs[key] = inner(i, j)
            return self._pairs[key]

        return registrar

    @property
    def visits(self) -> tuple[Visit, ...]:
        """The visits processed so far."""
        return tuple(self._visits)

    @property
    def filter(self) -> TopologyFilter | None:
        """The particle filter (None before the first visit)."""
        return self._filter

    def add(self, visit: Visit) -> FilterState:
        """Process the next visit (``visit.index`` must equal the number of visits so far).

        Raises:
            DataError: a visit out of order.
            ModelError: a visit the models cannot use; the session is unchanged.
        """
        start = time.perf_counter()
        n = len(self._visits)
        if visit.index != n:
            msg = f"expected visit {n}, got visit {visit.index}"
            raise DataError(msg)
        self._visits.append(visit)
        try:
            state = self._advance(visit)
        except BaseException:
            self._visits.pop()
            for key in [k for k in self._pairs if k[1] == n]:
                del self._pairs[key]
            raise
        self.wall_s += time.perf_counter() - start
        return state

    def _advance(self, visit: Visit) -> FilterState:
        inf = self.config.inference
        # the same model object ptm-run builds: its prior and its (re-)fitted appearance priors
        model = PosteriorModel(self._visits, self.config.model, seed=inf.seed)
        old = self._filter
        if old is not None:
            frozen = 0 < self.refit_max_visits < len(self._visits)
            if same_model(model.appearance, old.appearance) or (
                frozen and (model.appearance is None) == (old.appearance is None)
            ):
                return old.update(visit)
        new = TopologyFilter(
            RbpfConfig(particles=inf.particles, resample=inf.resample),
            model.prior,
            self.config.model.odometry,
            appearance=model.appearance,
            registrar=self._registrar,
            seed=inf.seed,
        )
        state = None
        for v in self._visits:
            state = new.update(v)
        assert state is not None
        self._filter = new
        self.replays += int(old is not None)
        return state

    def reset(self) -> None:
        """Forget every visit."""
        self._visits.clear()
        self._pairs.clear()
        self._filter = None
        self.replays = 0
        self.wall_s = 0.0
        self.registrations.clear()

    def inference(self) -> Inference:
        """The current ensemble as ``ptm-run``'s RBPF result (the ``inference.top`` most probable)."""
        flt = self._filter
        if flt is None:
            msg = "no visit has been processed yet"
            raise DataError(msg)
        return rbpf_inference(flt, self.config, replays=self.replays)

    def to_ptm(self, *, frame_id: str = "odom", **extra: Any) -> Ptm:
        """The current PTM (as :func:`ptm_ros.tools.pipeline.build_ptm` writes it)."""
        return build_ptm(
            self._visits, self.inference(), self.config, frame_id=frame_id, wall_s=self.wall_s, **extra
        )


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


def parse_visit_message(text: str) -> Visit | int:
    """A ``landmark_visits`` message: the :class:`Visit`, or the visit count of an end marker.

    Raises:
        DataError: malformed JSON, an unknown schema or a malformed visit.
    """
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        msg = f"visit message is not JSON: {err}"
        raise DataError(msg) from err
    if isinstance(doc, dict) and doc.get("schema") == END_SCHEMA:
        count = doc.get("visits")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            msg = f"end-of-visits marker with a bad count {count!r}"
            raise DataError(msg)
        return count
    if not isinstance(doc, dict) or doc.get("schema") != VISIT_SCHEMA:
        schema = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        msg = f"visit message schema must be {VISIT_SCHEMA!r} or {END_SCHEMA!r}, got {schema!r}"
        raise DataError(msg)
    return visit_from_json(text)


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
    xy = np.array([lm.pose[:2] for lm in ptm.landmarks], dtype=float).reshape(-1, 2)
    labels = np.asarray(t.labels)
    return np.array([xy[labels == k].mean(axis=0) for k in range(m)])


def ensemble_markers(ptm: Ptm, count: int, stamp: float) -> MarkerArray:
    """DELETEALL, then the ``count`` most probable topologies (see the module docstring)."""
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    clear.header.frame_id = ptm.frame_id
    out.markers.append(clear)
    xy = np.array([lm.pose[:2] for lm in ptm.landmarks], dtype=float).reshape(-1, 2)
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
        self.frame_id = declare_node_parameter(self, "frame_id", "odom", "odometry frame of the visits")
        self.session = FilterSession(self.config, refit_max_visits=refit)
        self.counters = {"messages": 0, "invalid": 0, "rejected": 0, "duplicates": 0, "gaps": 0, "resets": 0}
        self._next_index: int | None = None  # the detector's index of the next visit (None: any)
        self._end_count: int | None = None  # visits the detector announced at its end
        self._last: FilterState | None = None
        self._log_once = OnceLogger(self.get_logger())
        self._graph_pub = self.create_publisher(String, "ptm_graph", LATCHED_QOS)
        self._marker_pub = self.create_publisher(MarkerArray, "ptm_markers", LATCHED_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(String, "landmark_visits", self._on_visit, STREAM_QOS)
        self.create_service(Trigger, "~/save_ptm", self._on_save)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_timer(1.0, self._publish_diagnostics, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f"RBPF with {self.config.inference.particles} particles, seed {self.config.inference.seed}"
        )

    # -------------------------------------------------------------------------------- visits

    @property
    def complete(self) -> bool:
        """Whether the detector reported its end and every visit it announced has been consumed."""
        if self._end_count is None:
            return False
        return (self._next_index or 0) >= self._end_count

    def _on_visit(self, msg: String) -> None:
        self.counters["messages"] += 1
        try:
            item = parse_visit_message(msg.data)
        except DataError as err:
            self.counters["invalid"] += 1
            self._log_once("invalid-visit", f"dropped a malformed landmark_visits message: {err}")
            return
        if isinstance(item, int):
            self._end_count = item
            self.get_logger().info(f"end of visits reported ({item}); {len(self.session.visits)} in the map")
            self._publish()
            return
        self._add(item)

    def _add(self, visit: Visit) -> None:
        """Consume the detector's visit ``visit.index`` (re-indexed from the last reset on)."""
        expected = visit.index if self._next_index is None else self._next_index
        if visit.index < expected:
            if visit.index != 0:
                self.counters["duplicates"] += 1
                self._log_once("duplicate", f"dropped visit {visit.index}: already processed")
                return
            self.get_logger().warning("visit 0 arrived again: the detector restarted; starting a new map")
            self._reset()
        elif visit.index > expected:
            self.counters["gaps"] += 1
            self._log_once(
                "gap", f"visits {expected}..{visit.index - 1} never arrived; continuing without them"
            )
        self._next_index = visit.index + 1
        n = len(self.session.visits)
        if visit.index != n:
            visit = dataclasses.replace(visit, index=n)
        replays, wall = self.session.replays, self.session.wall_s
        try:
            self._last = state = self.session.add(visit)
        except PtmError as err:
            self.counters["rejected"] += 1
            self._log_once("rejected", f"the filter rejected visit {visit.index}: {err}")
            if self.complete:
                self._publish()
            return
        how = "replayed" if self.session.replays > replays else "updated"
        self.get_logger().info(
            f"visit {visit.index}: {state.n_topologies} topologies, ESS {state.ess:.1f}, "
            f"{how} in {(self.session.wall_s - wall) * 1e3:.0f} ms"
        )
        self._publish()

    def current_ptm(self) -> Ptm:
        """The ensemble now (an empty PTM before the first visit)."""
        if self.session.filter is None:
            return Ptm(
                landmarks=(), topologies=(), frame_id=self.frame_id, extra={"diagnostics": self.diagnostics()}
            )
        return self.session.to_ptm(frame_id=self.frame_id, diagnostics=self.diagnostics())

    def _publish(self) -> None:
        if self.session.filter is None and not self.complete:
            return  # nothing to tell yet (a complete empty stream is published: it ends the run)
        ptm = self.current_ptm()
        doc = graph_document(ptm, complete=self.complete)
        self._graph_pub.publish(String(data=json.dumps(doc)))
        stamp = ptm.landmarks[-1].stamp if ptm.landmarks else 0.0
        self._marker_pub.publish(ensemble_markers(ptm, self.marker_topologies, stamp))

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
        }

    def _publish_diagnostics(self) -> None:
        values = self.diagnostics()
        bad = values["invalid"] + values["rejected"] + values["gaps"]
        publish_diagnostics(
            self,
            self._diag_pub,
            "RBPF",
            hardware_id=NODE_NAME,
            message=f"{values['visits']} visits, {values['particles']} topologies, ESS {values['ess']:.1f}",
            values=values,
            warn=bad > 0,
        )

    # ------------------------------------------------------------------------------ services

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
        self._last = None
        self.counters["resets"] += 1

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        n = len(self.session.visits)
        self._reset()
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
