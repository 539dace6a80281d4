"""What the ptm_ros nodes share: QoS profiles, ROS parameters declared from the config dataclasses,
message conversions, diagnostics and the process entry point.

Parameters
----------
Every leaf field of :class:`~ptm_ros.config.PtmConfig` becomes one read-only ROS parameter named by its
dotted path (``inference.particles``, ``model.odometry.a_xy``), typed after the field (bool, integer,
double, string, string array), with the description and the range of its declaration
(:func:`ptm_ros.settings.setting`; an exclusive bound is given to ROS as inclusive, the configuration's
own check then refuses the bound itself). A field whose
type admits None (``detector.kind``, ``model.appearance.nig_kappa``) is dynamically typed and unset by
default; the strings ``null``, ``~`` and ``""`` also mean None. The values are validated by building the
configuration with :func:`ptm_ros.configio.from_dict`, so a node rejects exactly what ``ptm-run`` rejects,
with the same message naming the field. Nested YAML sections in a ``--params-file`` are flattened by ROS
itself, so ``config/ptm.yaml`` serves the nodes unchanged.

Message conversions keep the offline pipeline's numbers bit for bit: stamps are
``(sec·10⁹ + nanosec) / 10⁹`` correctly rounded and yaws are decoded with
:func:`ptm_ros.io.bag.quaternion_to_yaw`, exactly as :func:`ptm_ros.io.bag.read_run` does.

Bad input (issue #9). A header stamp with ``sec < 0`` or ``nanosec >= 10⁹`` is no ROS time
(:func:`ptm_ros.io.validation.valid_stamp`). :class:`~ptm_ros.nodes.stream_guard.StreamGuard` keeps one
sensor stream honest: exact duplicates are dropped; a stamp jump (or an odometry teleport) is held until
``confirm`` consistent messages confirm it and dropped as an outlier if the stream returns to its old
timeline; a stream's first messages are confirmed the same way, so no lone bad message can set or move
a stream's timeline. Every callback of
the nodes is wrapped by :func:`guarded`: an unexpected exception is logged once per type with its
traceback, counted as ``internal_errors`` and swallowed, so no message can stop a node.
:func:`run_node` turns an unreadable or malformed ``--params-file`` into the same exit code 2 as a bad
parameter value.
"""

from __future__ import annotations

import dataclasses
import faulthandler
import functools
import itertools
import math
import signal
import sys
import traceback
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose
from numpy.typing import NDArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from ptm_ros.config import ROS_ONLY_PARAMETERS, PtmConfig
from ptm_ros.configio import from_dict, yaml_problem
from ptm_ros.errors import BagError, ConfigError
from ptm_ros.io.bag import (
    NS_PER_S,
    decode_image,
    ns_to_stamp,
    quaternion_to_yaw,
    stamp_to_ns,
    yaw_to_quaternion,
)
from ptm_ros.io.validation import odometry_xy_yaw
from ptm_ros.settings import admitted, default_of, settings_fields, spec_of, unwrap_optional

if typing.TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.publisher import Publisher

# ------------------------------------------------------------------------------------- end of input


# ----------------------------------------------------------------------------------------------- QoS

#: Values of the ``sensor_qos`` parameter.
SENSOR_QOS = ("reliable", "sensor_data")

#: Landmark visits: nothing may be lost and a late subscriber (a restarted filter) gets every visit.
STREAM_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: Maps, the ensemble and end-of-input markers: the latest message, kept for late subscribers.
LATCHED_QOS = QoSProfile(
    depth=1,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: Replayed sensor data: reliable and unbounded, so a slow subscriber throttles the player instead of
#: losing messages (compatible with both ``sensor_qos`` settings of the subscribers).
REPLAY_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: The detector's stream for the map (``landmark_odom``, ``landmark_scans``: a few messages per metre of
#: travel): reliable and unbounded, nothing lost; a late subscriber starts from what follows.
MAP_STREAM_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: Display topics (landmark poses): reliable, a deep queue.
DISPLAY_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


#: A node module's table of what it publishes: topic -> (message type, QoS or history depth).
Publishes = Mapping[str, tuple[type, QoSProfile | int]]


def advertise(node: Node, publishes: Publishes, topic: str) -> Publisher:
    """The publisher of ``topic`` with the message type and QoS of the node module's table ``publishes``:
    the node creates its publishers from the table that tools read without starting DDS (the RViz
    configuration's test, ``test/test_rviz.py``), so the two cannot disagree."""
    msg_type, qos = publishes[topic]
    return node.create_publisher(msg_type, topic, qos)


def sensor_qos(kind: str) -> QoSProfile:
    """QoS of the sensor subscriptions: ``reliable`` (keep all; replay without loss, the default) or
    ``sensor_data`` (best effort, shallow: a live robot, where a late scan is worth less than a new one).

    Raises:
        ConfigError: an unknown kind.
    """
    if kind == "reliable":
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    if kind == "sensor_data":
        return qos_profile_sensor_data
    msg = f"sensor_qos must be one of {SENSOR_QOS}, got {kind!r}"
    raise ConfigError(msg)


# ---------------------------------------------------------------------------------------- parameters

_NONE_STRINGS = ("", "null", "~", "None")
_SCALAR_TYPES: dict[Any, int] = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
}
_ARRAY_TYPES: dict[Any, int] = {
    bool: ParameterType.PARAMETER_BOOL_ARRAY,
    int: ParameterType.PARAMETER_INTEGER_ARRAY,
    float: ParameterType.PARAMETER_DOUBLE_ARRAY,
    str: ParameterType.PARAMETER_STRING_ARRAY,
}
_TYPE_NAMES = {
    ParameterType.PARAMETER_NOT_SET: "any",
    ParameterType.PARAMETER_BOOL: "bool",
    ParameterType.PARAMETER_INTEGER: "integer",
    ParameterType.PARAMETER_DOUBLE: "double",
    ParameterType.PARAMETER_STRING: "string",
    ParameterType.PARAMETER_BOOL_ARRAY: "bool array",
    ParameterType.PARAMETER_INTEGER_ARRAY: "integer array",
    ParameterType.PARAMETER_DOUBLE_ARRAY: "double array",
    ParameterType.PARAMETER_STRING_ARRAY: "string array",
}


@dataclass(frozen=True)
class ConfigParameter:
    """One leaf of the configuration as a ROS parameter.

    Attributes:
        name: dotted path (``inference.particles``).
        type: a ``rcl_interfaces/ParameterType`` constant; ``PARAMETER_NOT_SET`` when ``optional``.
        default: the dataclass default (None for an unset optional).
        optional: the field admits None (declared dynamically typed).
        description: the field's declared description (:func:`~ptm_ros.settings.setting`), its choices and
            its type.
        range: ``(low, high)``, inclusive, from the field's declared bounds (±inf where open), if any.
        admits: what the field admits, in words (``an integer >= 1``), for the error of a value out of
            the range.
    """

    name: str
    type: int
    default: Any
    optional: bool
    description: str
    range: tuple[float, float] | None = None
    admits: str = ""


def _ros_type(hint: Any) -> int:
    if hint in _SCALAR_TYPES:
        return _SCALAR_TYPES[hint]
    if typing.get_origin(hint) in (tuple, list):
        inner = [a for a in typing.get_args(hint) if a is not Ellipsis]
        if len(set(inner)) == 1 and inner[0] in _ARRAY_TYPES:
            return _ARRAY_TYPES[inner[0]]
    return ParameterType.PARAMETER_NOT_SET


def config_parameters(root: type = PtmConfig, prefix: str = "") -> tuple[ConfigParameter, ...]:
    """Every leaf field of the configuration dataclass ``root`` as a :class:`ConfigParameter`, described and
    bounded by its :func:`~ptm_ros.settings.setting` declaration."""
    out: list[ConfigParameter] = []
    for f, full_hint in settings_fields(root):
        name = f"{prefix}{f.name}"
        hint, optional = unwrap_optional(full_hint)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            out.extend(config_parameters(hint, f"{name}."))
            continue
        default = default_of(f)
        ros_type = ParameterType.PARAMETER_NOT_SET if optional else _ros_type(hint)
        if isinstance(default, tuple):
            default = list(default)
        spec = spec_of(f)
        text = spec.doc if spec is not None else ""
        if spec is not None and spec.choices is not None:
            text = f"{text}; one of {', '.join(map(str, spec.choices))}"
        type_name = getattr(hint, "__name__", str(hint))
        description = (
            f"{text} ({root.__name__}.{f.name}: {type_name}{' or None' if optional else ''})".strip()
        )
        out.append(
            ConfigParameter(
                name=name,
                type=ros_type,
                default=default,
                optional=optional,
                description=description,
                range=None if spec is None else spec.range(),
                admits="" if spec is None else admitted(hint, spec),
            )
        )
    return tuple(out)


_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1  # an open integer range in a ROS IntegerRange


def _descriptor(p: ConfigParameter) -> ParameterDescriptor:
    d = ParameterDescriptor(
        name=p.name,
        type=p.type,
        description=p.description,
        read_only=True,
        dynamic_typing=p.type == ParameterType.PARAMETER_NOT_SET,
    )
    if p.range is not None:
        lo, hi = p.range
        if p.type == ParameterType.PARAMETER_INTEGER:
            low = _INT64_MIN if lo == -math.inf else math.ceil(lo)
            high = _INT64_MAX if hi == math.inf else math.floor(hi)
            d.integer_range = [IntegerRange(from_value=low, to_value=high, step=0)]
        elif p.type == ParameterType.PARAMETER_DOUBLE:
            d.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
    return d


def _nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, value in flat.items():
        *path, leaf = name.split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out


def config_from_parameters(values: Mapping[str, Any], root: type = PtmConfig) -> Any:
    """Build the configuration from flat parameter values (missing names take their defaults).

    An optional field given as ``None`` or one of ``"", "null", "~", "None"`` is None; arrays become
    tuples. Raises :class:`ConfigError` naming the field, exactly as ``ptm-run`` would.
    """
    specs = {p.name: p for p in config_parameters(root)}
    unknown = sorted(set(values) - set(specs))
    if unknown:
        msg = f"unknown parameter(s) {unknown}"
        raise ConfigError(msg)
    flat: dict[str, Any] = {}
    for name, raw in values.items():
        value = raw
        if specs[name].optional and (value is None or (isinstance(value, str) and value in _NONE_STRINGS)):
            value = None
        if value is None and not specs[name].optional:
            continue  # an unset parameter: its default
        flat[name] = list(value) if isinstance(value, (tuple, list)) else value
    return from_dict(root, _nest(flat))


def declare_config(node: Node, root: type = PtmConfig) -> Any:
    """Declare every configuration field of ``root`` on ``node`` and return the validated configuration.

    Raises:
        ConfigError: a value of the wrong type, out of range, or rejected by the dataclass (the message
            names the parameter).
    """
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    values: dict[str, Any] = {}
    for p in config_parameters(root):
        try:
            param = node.declare_parameter(p.name, p.default, _descriptor(p))
        except InvalidParameterTypeException as err:
            expected = _TYPE_NAMES.get(p.type, str(p.type))
            hint = " (write a double with a decimal point, e.g. 3.0)" if expected == "double" else ""
            msg = f"parameter {p.name}: expected {expected}{hint}; {err}"
            raise ConfigError(msg) from err
        except InvalidParameterValueException as err:
            rule = f" must be {p.admits}" if p.admits else ""
            msg = f"parameter {p.name}{rule}: {err}"
            raise ConfigError(msg) from err
        values[p.name] = param.value
    return config_from_parameters(values, root)


#: The detector's input-validation parameters (:class:`GuardConfig`, ``silence_s``).
GUARD_PARAMETERS = frozenset({"stamp_jump_s", "jump_confirm", "max_speed", "silence_s"})

#: The topology filter's persistence parameters (``state_file``, ``autosave_every``, ``resume``).
PERSISTENCE_PARAMETERS = frozenset({"state_file", "autosave_every", "resume"})

#: Every node-specific parameter of the suite (not configuration). One ``/**`` parameter file serves all
#: nodes, so each node accepts the others' parameters too; any other name is a typo and is rejected.
NODE_PARAMETERS = ROS_ONLY_PARAMETERS | GUARD_PARAMETERS | PERSISTENCE_PARAMETERS


def check_parameter_names(node: Node, root: type = PtmConfig) -> None:
    """Reject parameter overrides (``--params-file``, ``-p``) that no ptm_ros node knows.

    ROS itself ignores undeclared overrides, so a misspelt parameter would pass silently; this makes the
    nodes as strict as ``ptm-run``. (Reads rclpy's ``_parameter_overrides``; skipped if it is absent.)

    Raises:
        ConfigError: naming the unknown parameters.
    """
    overrides = getattr(node, "_parameter_overrides", None)
    if not isinstance(overrides, Mapping):
        return
    known = NODE_PARAMETERS | {p.name for p in config_parameters(root)}
    unknown = sorted(n for n in overrides if n not in known and not n.startswith("qos_overrides."))
    if unknown:
        msg = f"unknown parameter(s) {unknown} (see config/ptm.yaml and the node's documentation)"
        raise ConfigError(msg)


def declare_node_parameter(
    node: Node,
    name: str,
    default: Any,
    description: str,
    *,
    choices: Sequence[str] | None = None,
    minimum: float | None = None,
    read_only: bool = True,
) -> Any:
    """Declare one node-specific parameter (not part of the configuration) and return its value.

    Raises:
        ConfigError: a value of the wrong type, not among ``choices`` or below ``minimum``.
    """
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    ptype = _SCALAR_TYPES[type(default)]
    desc = ParameterDescriptor(name=name, type=ptype, description=description, read_only=read_only)
    if choices is not None:
        desc.additional_constraints = f"one of {', '.join(choices)}"
    if minimum is not None and ptype == ParameterType.PARAMETER_INTEGER:
        desc.integer_range = [IntegerRange(from_value=int(minimum), to_value=2**62, step=0)]
    elif minimum is not None and ptype == ParameterType.PARAMETER_DOUBLE:
        desc.floating_point_range = [FloatingPointRange(from_value=float(minimum), to_value=1e300, step=0.0)]
    try:
        value = node.declare_parameter(name, default, desc).value
    except (InvalidParameterTypeException, InvalidParameterValueException) as err:
        msg = f"parameter {name}: {err}"
        raise ConfigError(msg) from err
    if choices is not None and value not in choices:
        msg = f"parameter {name} must be one of {tuple(choices)}, got {value!r}"
        raise ConfigError(msg)
    return value


# ---------------------------------------------------------------------------------------- conversions


def header_stamp(header: Any) -> float:
    """A message header's stamp in seconds, exactly as :func:`ptm_ros.io.bag.read_run` computes it."""
    return ns_to_stamp(int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec))


def time_msg(stamp: float) -> Time:
    """``builtin_interfaces/Time`` of a stamp in seconds (the inverse of :func:`header_stamp`; stamps
    that no ROS time can hold become zero)."""
    try:
        ns = stamp_to_ns(stamp)
    except BagError:
        ns = 0
    return Time(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def odometry_sample(msg: Any) -> tuple[float, tuple[float, float, float]]:
    """``(stamp, (x, y, yaw))`` of a ``nav_msgs/Odometry`` (non-finite values passed through)."""
    return header_stamp(msg.header), odometry_xy_yaw(msg)


def scan_fields(msg: Any) -> tuple[float, NDArray[np.float32], float, float, float, float]:
    """``(stamp, ranges, angle_min, angle_increment, range_min, range_max)`` of a LaserScan."""
    return (
        header_stamp(msg.header),
        np.asarray(msg.ranges, dtype=np.float32),
        float(msg.angle_min),
        float(msg.angle_increment),
        float(msg.range_min),
        float(msg.range_max),
    )


def image_array(msg: Any) -> NDArray[Any] | None:
    """The pixels of a ``sensor_msgs/Image`` as ``(H, W)`` or ``(H, W, C)``; None for an unsupported
    encoding (decoded exactly as :func:`ptm_ros.io.bag.read_run` does).

    Raises:
        BagError: the data is shorter than ``height × step``.
    """
    return decode_image(msg)


def pose_msg(x: float, y: float, yaw: float, z: float = 0.0) -> Pose:
    """A ``geometry_msgs/Pose`` of a planar pose (yaw encoded so that ``read_run`` decodes it exactly)."""
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = float(x), float(y), float(z)
    if math.isfinite(yaw):
        qx, qy, qz, qw = yaw_to_quaternion(yaw)
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = qx, qy, qz, qw
    return pose


def path_arrays(msg: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(stamps (K,), poses (K, 3))`` of a ``nav_msgs/Path`` (the inverse of :func:`pose_msg` and
    :func:`time_msg` per pose; the poses' own header stamps)."""
    stamps = np.array([header_stamp(ps.header) for ps in msg.poses], dtype=float)
    poses = np.array(
        [
            (ps.pose.position.x, ps.pose.position.y, quaternion_to_yaw(*_xyzw(ps.pose.orientation)))
            for ps in msg.poses
        ],
        dtype=float,
    ).reshape(-1, 3)
    return stamps, poses


def _xyzw(q: Any) -> tuple[float, float, float, float]:
    return float(q.x), float(q.y), float(q.z), float(q.w)


def key_values(values: Mapping[str, Any], prefix: str = "") -> list[KeyValue]:
    """Flatten a (nested) mapping of counters into ``diagnostic_msgs/KeyValue`` (dotted keys)."""
    out: list[KeyValue] = []
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.extend(key_values(value, f"{name}."))
        elif isinstance(value, float):
            out.append(KeyValue(key=name, value=f"{value:.6g}"))
        else:
            out.append(KeyValue(key=name, value=str(value)))
    return out


def diagnostic_status(
    name: str, hardware_id: str, message: str, values: Mapping[str, Any], *, warn: bool
) -> DiagnosticStatus:
    """One ``diagnostic_msgs/DiagnosticStatus`` (level OK or WARN)."""
    return DiagnosticStatus(
        level=DiagnosticStatus.WARN if warn else DiagnosticStatus.OK,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=key_values(values),
    )


def publish_diagnostics(
    node: Any,
    publisher: Any,
    title: str,
    *,
    hardware_id: str,
    message: str,
    values: Mapping[str, Any],
    warn: bool,
) -> None:
    """Publish one ``diagnostic_msgs/DiagnosticArray`` with a single status named ``<node>: <title>``."""
    msg = DiagnosticArray()
    msg.header.stamp = node.get_clock().now().to_msg()
    msg.status = [diagnostic_status(f"{node.get_name()}: {title}", hardware_id, message, values, warn=warn)]
    publisher.publish(msg)


# ------------------------------------------------------------------------------------------ bad input


def guarded(method: Callable[..., Any]) -> Callable[..., Any]:
    """Last-resort guard of a node callback (subscription, timer or service).

    An exception escaping ``method`` is counted in ``self.counters["internal_errors"]``, logged once per
    exception type with its traceback (``self._log_once``) and swallowed, so that no message stops the
    node; a service callback then answers ``success: false``. Known bad input is handled inside the
    callbacks; this only catches bugs.
    """

    @functools.wraps(method)
    def wrapper(self: Any, *args: Any) -> Any:
        try:
            return method(self, *args)
        except Exception as err:  # the guard of last resort
            self.counters["internal_errors"] = self.counters.get("internal_errors", 0) + 1
            kind = f"internal-{type(err).__name__}"
            self._log_once(
                kind,
                f"internal error in {method.__name__}: {type(err).__name__}: {err}\n{traceback.format_exc()}",
            )
            response = args[-1] if args and hasattr(args[-1], "success") else None
            if response is not None:
                response.success = False
                response.message = f"internal error: {type(err).__name__}: {err}"
            return response

    return wrapper


# ------------------------------------------------------------------------------------------- process


def _check_parameter_tree(node: Any, file: str, path: tuple[str, ...] = ()) -> None:
    where = f"parameter file {file}, at {'.'.join(path) or 'the top level'}"
    if not isinstance(node, Mapping) or not node:
        msg = f"{where}: expected a mapping of node names to 'ros__parameters:' sections"
        raise ConfigError(msg)
    for key, value in node.items():
        if key == "ros__parameters":
            if not isinstance(value, Mapping):
                msg = f"{where}: 'ros__parameters' must be a mapping, got {type(value).__name__}"
                raise ConfigError(msg)
        else:
            _check_parameter_tree(value, file, (*path, str(key)))


def check_params_files(args: Sequence[str]) -> None:
    """Validate every ``--params-file FILE`` of a command line before rclpy reads it.

    rcl accepts a parameter file that is not a mapping of ``node: ros__parameters: {...}`` sections (for
    instance a bare string) and ignores it silently; this rejects it, and an unreadable or unparsable
    file, with a message naming the file.

    Raises:
        ConfigError: the file is missing, not YAML, or not a ROS 2 parameter file.
    """
    import yaml

    for flag, value in itertools.pairwise(args):
        if flag != "--params-file":
            continue
        try:
            doc = yaml.safe_load(Path(value).read_text())
        except (OSError, UnicodeDecodeError) as err:
            msg = f"cannot read parameter file {value}: {err}"
            raise ConfigError(msg) from err
        except yaml.YAMLError as err:
            msg = f"malformed YAML in {value}, {yaml_problem(err)}"
            raise ConfigError(msg) from err
        _check_parameter_tree(doc, value)


#: s a node may take to stop (destroy itself, shut rclpy down, exit) before it prints every thread's
#: stack to stderr: a stop that hangs (ptm-bringup then escalates to SIGTERM and SIGKILL) says where.
STOP_REPORT_S = 4.0
#: s the spin waits for work before it looks at the stop request again: the longest a stop waits (a
#: Python signal handler runs only when the main thread is back in Python, not inside rcl's wait).
STOP_POLL_S = 0.1
#: The signals that stop a node (each one: a request, answered between two callbacks).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """SIGINT / SIGTERM as a request that :func:`run_node`'s main thread answers between two callbacks.

    rclpy's own signal handling raises ``KeyboardInterrupt`` wherever the main thread happens to be (in
    the middle of a callback writing ptm.json, while the node is being built, in its teardown) and, from a
    thread of its own, shuts the context down at the same time: the node's teardown then races that
    shutdown (``Context.try_shutdown`` checks ``ok()`` and then shuts down: ``RCLError: failed to
    shutdown``), and a node still being built fails with ``RCLError: ... context is not valid``: exit code
    1 for a plain Ctrl-C. A :class:`StopRequest` installed as the Python handler instead only records the
    signal; nothing is interrupted and only the main thread ever shuts the context down.
    """

    def __init__(self) -> None:
        self.signals: list[int] = []

    @property
    def requested(self) -> bool:
        """Whether a stop signal has arrived."""
        return bool(self.signals)

    def __call__(self, signum: int, frame: Any) -> None:
        self.signals.append(signum)

    def install(self) -> dict[int, Any]:
        """Make this the handler of :data:`STOP_SIGNALS` and unblock them; returns the handlers it replaces.

        A process started with the signals blocked (``ptm-bringup`` starts its nodes so) holds a signal
        sent while Python imported the node's modules, and it arrives here, as a stop request, instead of
        as a ``KeyboardInterrupt`` in the middle of an import."""
        previous: dict[int, Any] = {sig: signal.signal(sig, self) for sig in STOP_SIGNALS}
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
        return previous


def spin_until_stopped(node: Node, stop: StopRequest) -> None:
    """Spin ``node`` in this thread until ``stop`` is requested or its context is shut down, then destroy
    it (see :func:`run_node`)."""
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=node.context)
    try:
        executor.add_node(node)
        while not stop.requested and executor.context.ok():
            executor.spin_once(timeout_sec=STOP_POLL_S)
    except ExternalShutdownException:
        pass
    except Exception as err:
        if executor.context.ok():
            raise
        node.get_logger().warning(f"stopped while shutting down: {type(err).__name__}: {err}")
    finally:
        # armed until the process exits (not cancelled): a hang in the node's teardown, in rclpy's shutdown
        # or in the interpreter's exit prints the stacks instead of dying silently
        faulthandler.dump_traceback_later(STOP_REPORT_S, exit=False, file=sys.__stderr__ or sys.stderr)
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown(timeout_sec=0.0)


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, name: str = "ptm_ros") -> int:
    """Initialise rclpy, build the node, spin until stopped; return the process exit code.

    A :class:`ConfigError` while building the node (a bad parameter) or a bad ``--params-file``
    (:func:`check_params_files`, or rcl refusing the arguments) is logged as fatal and gives exit code 2.
    SIGINT / SIGTERM, from the moment this function starts (while rclpy initialises, while the node is
    built, during a callback or the teardown; before it, while the modules were imported, when the process
    started with them blocked), are a :class:`StopRequest`: the callback running completes,
    the spin ends before the next one (within :data:`STOP_POLL_S`), the node is destroyed and rclpy shut
    down by this thread alone, exit code 0 (rclpy's own signal handlers are not installed). A context shut
    down by someone else (``rclpy.shutdown()`` in process) also ends the spin cleanly, and so does an error
    the spin raises once the context is shut down; with the context alive such an error is a bug and
    propagates (exit code 1). A stop that takes more than :data:`STOP_REPORT_S` prints every thread's stack
    to stderr (this is a process's entry point: call it last).
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    argv = list(args) if args is not None else sys.argv
    stop = StopRequest()
    previous = stop.install()
    try:
        try:
            check_params_files(argv)
            rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
        except (ConfigError, RuntimeError) as err:  # rclpy's RCLError is a RuntimeError
            rclpy.logging.get_logger(name).fatal(f"invalid arguments: {err}")
            return 2
        try:
            try:
                node = factory()
            except ConfigError as err:
                rclpy.logging.get_logger(name).fatal(f"invalid parameters: {err}")
                return 2
            spin_until_stopped(node, stop)
            return 0
        finally:
            rclpy.try_shutdown()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
