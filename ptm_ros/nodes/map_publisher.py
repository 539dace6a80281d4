"""``map_publisher``: the most probable topology as a path, and the ensemble written to ptm.json on request.

Subscribes ``ptm_graph`` (std_msgs/String, the topology filter's JSON document, reliable + transient
local), validates each document (:func:`ptm_ros.model.ptm.from_json_dict`) and keeps the latest. Publishes
``ptm_path`` (nav_msgs/Path, reliable + transient local) of the MAP topology: **one pose per visit, in
visit order**, at the estimated position of the place the MAP topology assigns the visit to (the
odometry position of the visit when the document carries no place positions), with the visit's odometry
heading and header stamp; so revisits of a place coincide and the path draws the topological map.

The metric map (issue #8, :mod:`ptm_ros.maps.mapping`). The node also subscribes the detector's
``landmark_visits`` (the visits, with their laser patches), ``landmark_odom`` (the odometry the visits are
measured in, every ``mapping.pose_xy`` / ``pose_yaw`` of motion) and ``landmark_scans`` (the keyframe
scans, every ``mapping.keyframe_xy`` / ``keyframe_yaw``) and keeps an :class:`ptm_ros.maps.mapping.OnlineMap`
of them. Whenever the MAP topology or the keyframes changed — at most every ``mapping.period``
seconds, and never for more than a fifth of the time — it smooths, in a background thread while the
callbacks keep taking samples, the odometry for the MAP topology
(its same-place constraints and the laser registrations of its places, refined by scan matches between
the keyframes of revisited passages when ``refinement.enabled``: the function ``ptm-run`` uses) and
publishes

* ``map`` (nav_msgs/OccupancyGrid, reliable + transient local; ``occupancy.*`` parameters): the scans
  drawn along the smoothed trajectory, in the frame of the ensemble (the odometry's), with the values
  map_server publishes for the saved map in ``occupancy.mode`` (trinary: 100 / 0 / -1; scale: also
  1..99, :func:`ptm_ros.maps.occupancy.to_ros_data`);
* ``ptm_trajectory`` (nav_msgs/Path, reliable + transient local): the smoothed trajectory the scans were
  drawn along, one pose per odometry sample the map was drawn from (``ptm-bringup`` reads it for the
  trajectory errors and the route graph).

Service ``~/save_map`` (std_srvs/Trigger) draws the map from everything received and writes
``<out_dir>/map.pgm`` (``map_scale.png`` in scale mode) + ``map.yaml`` (nav2 map_server format: ``ros2 run
nav2_map_server map_server --ros-args -p yaml_filename:=map.yaml`` loads it) and ``map.png``; its response
message is JSON ``{"yaml", "image", "png", "width", "height", "resolution", "scans", "trajectory", "maps",
"map_ms", "complete", "input"}`` (``trajectory``: the poses of the map's ``ptm_trajectory``; maps drawn so
far, the time the latest took; ``input``: the map's counters; ``complete``: the ensemble is complete and
every keyframe scan the detector's end marker counts was received, so the map covers the whole input). A
map needs the visits of the ensemble (matched by stamp) and their session's odometry; until both are there
it waits. A new detector session (visit 0 of another session id; odometry going back in time or jumping)
starts the map afresh.

Service ``~/save_ptm`` (std_srvs/Trigger) writes the latest document to ``<out_dir>/ptm.json`` (it
refuses, ``success: false``, while it has no document or one without visits, as ``ptm-run`` does); its
response message is JSON ``{"path", "visits", "topologies", "complete"}`` (``complete``: the filter had
every visit of a finished input), which ``ptm-bringup`` uses to know the run is fully mapped.
``/diagnostics`` every second: documents received, invalid ones, visits of the latest, and the map's
counters (odometry samples and scans received and kept, maps drawn and the time of the latest, resets).

Bad input (issue #9): a document that is not JSON (also nested too deep, or numbers beyond float range),
not a valid ptm.json, or has non-finite stamps, poses or place positions, positions of the wrong shape
or a ``stream`` section that is not a mapping with a boolean ``complete`` is dropped (``invalid``); a
repetition of the latest document is dropped (``duplicates``); the previous document stays in force.
A visit message that cannot be parsed, or a visit out of sequence (``visits_ignored``), an odometry
sample with a bad stamp or non-finite pose (``odometry_invalid``) and a scan with a bad stamp or
malformed fields (``scans_invalid``) are skipped; a map the smoothing cannot draw (``map_errors``) leaves
the previous map in place. Each is logged once and counted; a bug reached by some input is caught by the
callback's last-resort guard (``internal_errors``).
"""

from __future__ import annotations

import array
import json
import queue
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid as GridMsg
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import LaserScan
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ptm_ros.config import PtmConfig
from ptm_ros.errors import PtmError
from ptm_ros.maps.mapping import MapInputs, MapResult, draw_map
from ptm_ros.maps.occupancy import OccupancyConfig, OccupancyGrid, save_map_files, to_ros_data
from ptm_ros.model.geometry import Registrar
from ptm_ros.model.ptm import Ptm
from ptm_ros.nodes.common import (
    LATCHED_QOS,
    MAP_STREAM_QOS,
    STREAM_QOS,
    Publishes,
    advertise,
    check_parameter_names,
    declare_config,
    declare_node_parameter,
    diagnostic_status,
    guarded,
    pose_msg,
    run_node,
    time_msg,
)
from ptm_ros.nodes.logs import OnceLogger
from ptm_ros.nodes.map_inbox import MapInbox

NODE_NAME = "map_publisher"
CLOSE_WAIT_S = 3.0  # s the node waits for a drawing in progress when it is destroyed
BUILD_SHARE = 4.0  # a map that took d seconds to draw waits 4 d before the next: at most 1/5 of a core
#: What the node publishes (topic: message type, QoS), the table its publishers are made from.
PUBLISHES: Publishes = {
    "ptm_path": (PathMsg, LATCHED_QOS),
    "map": (GridMsg, LATCHED_QOS),
    "ptm_trajectory": (PathMsg, LATCHED_QOS),
    "/diagnostics": (DiagnosticArray, 10),
}


def grid_msg(grid: OccupancyGrid, frame_id: str, stamp: float, config: OccupancyConfig) -> GridMsg:
    """The ``nav_msgs/OccupancyGrid`` of a grid as map_server would publish its saved ``map.yaml``
    (:func:`ptm_ros.maps.occupancy.to_ros_data`: ``config``'s mode and thresholds)."""
    msg = GridMsg()
    msg.header.frame_id = frame_id
    msg.header.stamp = time_msg(stamp)
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(grid.resolution)
    msg.info.width, msg.info.height = grid.width, grid.height
    msg.info.origin = pose_msg(grid.origin[0], grid.origin[1], grid.origin[2])
    msg.data = array.array("b", to_ros_data(grid, config).tobytes())
    return msg


def trajectory_msg(result: MapResult, frame_id: str) -> PathMsg:
    """The smoothed trajectory of a map (a pose per odometry sample) as a ``nav_msgs/Path``."""
    path = PathMsg()
    path.header.frame_id = frame_id
    for t, (x, y, yaw) in zip(result.stamps, result.trajectory, strict=True):
        ps = PoseStamped()
        ps.header.frame_id = frame_id
        ps.header.stamp = time_msg(float(t))
        ps.pose = pose_msg(float(x), float(y), float(yaw))
        path.poses.append(ps)
    if path.poses:
        path.header.stamp = path.poses[-1].header.stamp
    return path


def map_path(ptm: Ptm) -> PathMsg:
    """The ``nav_msgs/Path`` of the MAP topology (see the module docstring); empty without topologies."""
    path = PathMsg()
    path.header.frame_id = ptm.frame_id
    if not ptm.topologies or not ptm.landmarks:
        return path
    top = ptm.topologies[0]
    places = None
    if top.positions is not None and len(top.positions) == max(top.labels) + 1:
        places = np.asarray(top.positions, dtype=float)
    for lm, label in zip(ptm.landmarks, top.labels, strict=True):
        x, y = places[label] if places is not None else lm.map_pose[:2]
        ps = PoseStamped()
        ps.header.frame_id = ptm.frame_id
        ps.header.stamp = time_msg(lm.stamp)
        ps.pose = pose_msg(float(x), float(y), lm.map_pose[2])
        path.poses.append(ps)
    path.header.stamp = time_msg(ptm.landmarks[-1].stamp)
    return path


class MapPublisherNode(Node):
    """The ``map_publisher`` node (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        check_parameter_names(self)
        self.out_dir = declare_node_parameter(
            self, "out_dir", "out/map_publisher", "where ~/save_ptm and ~/save_map write", read_only=False
        )
        self.config: PtmConfig = declare_config(self)
        self.inbox = MapInbox(self.config, self.get_logger())
        self.map: MapResult | None = None
        self.map_ms = 0.0
        self._next_build = 0.0  # time.monotonic() before which no map is drawn
        self._closing = False
        self._idle = threading.Event()  # no map being drawn in the background
        self._idle.set()
        self._jobs: queue.Queue[tuple[Any, ...] | None] = queue.Queue()
        self._lock = threading.Lock()  # counters and the latest map, shared with the drawing thread
        self._log_once = OnceLogger(self.get_logger())
        self._path_pub = advertise(self, PUBLISHES, "ptm_path")
        self._map_pub = advertise(self, PUBLISHES, "map")
        self._trajectory_pub = advertise(self, PUBLISHES, "ptm_trajectory")
        self._diag_pub = advertise(self, PUBLISHES, "/diagnostics")
        self.create_subscription(String, "ptm_graph", self._on_graph, LATCHED_QOS)
        self.create_subscription(String, "landmark_visits", self._on_visit, STREAM_QOS)
        self.create_subscription(Odometry, "landmark_odom", self._on_odom, MAP_STREAM_QOS)
        self.create_subscription(LaserScan, "landmark_scans", self._on_scan, MAP_STREAM_QOS)
        self.create_service(Trigger, "~/save_ptm", self._on_save)
        self.create_service(Trigger, "~/save_map", self._on_save_map)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.create_timer(0.1, self._on_map_timer, clock=steady)
        self._worker = threading.Thread(target=self._work, name="map_publisher-draw", daemon=True)
        self._worker.start()

    @property
    def counters(self) -> dict[str, int]:
        """The inbox's counters (the guard of :func:`ptm_ros.nodes.common.guarded` adds to them)."""
        return self.inbox.counters

    @guarded
    def _on_graph(self, msg: String) -> None:
        ptm = self.inbox.graph(msg.data)
        if ptm is not None:
            self._path_pub.publish(map_path(ptm))

    # ------------------------------------------------------------------------------ metric map

    @guarded
    def _on_visit(self, msg: String) -> None:
        self.inbox.visit(msg.data)

    @guarded
    def _on_odom(self, msg: Odometry) -> None:
        self.inbox.odometry_message(msg)

    @guarded
    def _on_scan(self, msg: LaserScan) -> None:
        self.inbox.scan_message(msg)

    def _draw(
        self, snap: MapInputs, labels: tuple[int, ...], frame: str, registrar: Registrar
    ) -> MapResult | None:
        """Draw a map (any thread) and publish it; None (counted) when the smoothing cannot."""
        start = time.monotonic()
        try:
            cfg = self.config
            result = draw_map(
                snap, labels, cfg.model, cfg.occupancy, registrar, refinement=cfg.refinement, laser=cfg.laser
            )
        except PtmError as err:
            with self._lock:
                self.counters["map_errors"] += 1
            self._log_once("map-error", f"could not draw the map: {err}")
            return None
        finally:
            self.map_ms = 1e3 * (time.monotonic() - start)
            self._next_build = time.monotonic() + max(
                self.config.mapping.period, BUILD_SHARE * self.map_ms / 1e3
            )
        with self._lock:
            self.map = result
            self.counters["maps"] += 1
        if self._closing:
            return result
        if result.grid is not None:
            self._map_pub.publish(
                grid_msg(result.grid, frame, float(result.stamps[-1]), self.config.occupancy)
            )
        self._trajectory_pub.publish(trajectory_msg(result, frame))
        return result

    @guarded
    def _draw_in_background(self, *snap: Any) -> None:
        self._draw(*snap)

    def _work(self) -> None:
        """The drawing thread: one for the node's life (so its allocations stay in one malloc arena)."""
        while (job := self._jobs.get()) is not None:
            try:
                self._draw_in_background(*job)
            finally:
                self._idle.set()

    def _wait_for_drawing(self, timeout: float | None = None) -> None:
        self._idle.wait(timeout)

    def build_map(self) -> MapResult | None:
        """Draw and publish the map of the latest ensemble's MAP topology now, in this thread (after a
        drawing still running in the background); None when it cannot."""
        self._wait_for_drawing()
        snap = self.inbox.snapshot()
        return None if snap is None else self._draw(*snap)

    @guarded
    def _on_map_timer(self) -> None:
        """Hand the drawing thread a map to draw when due (callbacks keep taking samples meanwhile)."""
        if not self._idle.is_set() or self._closing:
            return
        if not self.inbox.dirty or time.monotonic() < self._next_build or self.inbox.map_inputs() is None:
            return
        self.inbox.dirty = False
        snap = self.inbox.snapshot()
        if snap is not None:
            self._idle.clear()
            self._jobs.put(snap)

    def destroy_node(self) -> None:
        """Wait (at most :data:`CLOSE_WAIT_S` in all) for a drawing still running and for the drawing thread
        to stop, destroy the node; a drawing that ends later publishes nothing."""
        self._closing = True
        deadline = time.monotonic() + CLOSE_WAIT_S  # one budget: ptm-bringup sends SIGTERM after 5 s
        self._wait_for_drawing(CLOSE_WAIT_S)
        self._jobs.put(None)
        self._worker.join(max(0.0, deadline - time.monotonic()))
        super().destroy_node()

    @guarded
    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        # draw now when the inputs changed since the last map, or while the drawing thread still draws
        # them (the timer took them: ``self.map`` is then older than what was received)
        drawing = not self._idle.is_set()
        fresh = self.build_map() if self.inbox.dirty or self.map is None or drawing else None
        if fresh is not None:
            self.inbox.dirty = False
        result = fresh or self.map  # the latest map when the current inputs cannot be drawn yet
        if result is None or result.grid is None:
            why = "no map yet: it needs the ensemble, its visits, their odometry and scans"
            response.success, response.message = False, why
            return response
        out = Path(self.get_parameter("out_dir").value)
        try:
            image, yml, png = save_map_files(
                result.grid, out, self.config.occupancy, trajectory=result.trajectory
            )
        except OSError as err:
            response.success, response.message = False, f"cannot write the map to {out}: {err}"
            return response
        grid = result.grid
        response.success = True
        response.message = json.dumps(
            {
                "yaml": str(yml),
                "image": str(image),
                "png": str(png),
                "width": grid.width,
                "height": grid.height,
                "resolution": grid.resolution,
                "scans": grid.scans,
                "trajectory": len(result.stamps),
                "maps": self.counters["maps"],
                "map_ms": round(self.map_ms, 1),
                "complete": self.inbox.complete and self.inbox.scans_complete,
                "input": {"scans_received": self.inbox.scans_received, **vars(self.inbox.online.counters)},
            }
        )
        self.get_logger().info(f"wrote {yml} ({grid.width} x {grid.height} cells, {grid.scans} scans)")
        return response

    @guarded
    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.inbox.doc is None or self.inbox.ptm is None:
            response.success, response.message = False, "no ensemble received yet: nothing to save"
            return response
        if not self.inbox.ptm.landmarks:
            response.success, response.message = (
                False,
                "the ensemble holds no landmark visit: nothing to save",
            )
            return response
        out = Path(self.get_parameter("out_dir").value)
        path = out / "ptm.json"
        try:
            out.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(self.inbox.doc, indent=1) + "\n")
        except OSError as err:
            response.success, response.message = False, f"cannot write {path}: {err}"
            return response
        response.success = True
        response.message = json.dumps(
            {
                "path": str(path),
                "visits": len(self.inbox.ptm.landmarks),
                "topologies": len(self.inbox.ptm.topologies),
                "complete": self.inbox.complete,
            }
        )
        self.get_logger().info(f"wrote {path} ({len(self.inbox.ptm.landmarks)} visits)")
        return response

    @guarded
    def _publish_diagnostics(self) -> None:
        values = {
            **self.counters,
            "visits": 0 if self.inbox.ptm is None else len(self.inbox.ptm.landmarks),
            "topologies": 0 if self.inbox.ptm is None else len(self.inbox.ptm.topologies),
            "complete": self.inbox.complete,
            "map_ms": round(self.map_ms, 1),
            **{f"map_{k}": v for k, v in vars(self.inbox.online.counters).items()},
        }
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [
            diagnostic_status(
                f"{self.get_name()}: ensemble",
                NODE_NAME,
                f"{values['visits']} visits, {values['topologies']} topologies",
                values,
                warn=any(self.counters[k] for k in ("invalid", "internal_errors", "map_errors")),
            )
        ]
        self._diag_pub.publish(msg)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``map_publisher``."""
    return run_node(MapPublisherNode, args, NODE_NAME)


if __name__ == "__main__":
    raise SystemExit(main())
