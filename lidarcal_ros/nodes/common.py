"""What the three nodes share: flight-configuration parameters, QoS, diagnostics, main loop.

Flight-configuration parameters
-------------------------------
:class:`FlightParameters` declares every parameter of :data:`lidarcal_ros.core.config.SCHEMA` on
a node (dotted names as in the schema, e.g. ``calibration.solve_for``) with a
``ParameterDescriptor`` (description, ``FloatingPointRange`` / ``IntegerRange``, read-only), plus
node-specific ones. A value set at run time is checked by :func:`~lidarcal_ros.core.config.coerce`
and :func:`~lidarcal_ros.core.config.cross_check` (the checks ``lidarcal calibrate --config``
applies) and refused with the reason in ``SetParametersResult.reason``; an accepted change
updates :attr:`FlightParameters.config` and calls the node's listeners.

The calibrator and the corrector follow the flight-configuration node
(``lidarcal_flight_config``): they listen to ``/parameter_events`` from it and, once its
parameter services are up, fetch its current values; every accepted change there is applied to
their own parameters through the same validation.
"""

from __future__ import annotations

import logging
import math
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterEvent,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_parameter_events,
)

from lidarcal_ros.core.allocator import NODE_TRIM_THRESHOLD_BYTES, tune_allocator
from lidarcal_ros.core.config import SCHEMA, FlightConfig, ParameterSpec, coerce, cross_check
from lidarcal_ros.errors import ConfigError, LidarcalError
from lidarcal_ros.io.ros_messages import StatusSpec

logger = logging.getLogger(__name__)

FLIGHT_CONFIG_NODE = "lidarcal_flight_config"
CALIBRATOR_NODE = "lidarcal_calibrator"
CORRECTOR_NODE = "lidarcal_corrector"

ESTIMATE_TOPIC = "/lidar/calibration/estimate"
YAML_TOPIC = "/lidar/calibration/yaml"
DIAGNOSTICS_TOPIC = "/diagnostics"

_KIND_TYPES = {
    "float": ParameterType.PARAMETER_DOUBLE,
    "int": ParameterType.PARAMETER_INTEGER,
    "str": ParameterType.PARAMETER_STRING,
    "bool": ParameterType.PARAMETER_BOOL,
    "str_list": ParameterType.PARAMETER_STRING_ARRAY,
}


# ---------------------------------------------------------------------------- QoS
def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable, transient-local: late joiners get the last ``depth`` messages."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def stream_qos(depth: int = 100, *, best_effort: bool = False) -> QoSProfile:
    """Volatile keep-last stream (reliable unless ``best_effort``)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(int(depth), 1),
                      reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                   else ReliabilityPolicy.RELIABLE),
                      durability=DurabilityPolicy.VOLATILE)


# ---------------------------------------------------------------------------- parameters
def descriptor_for(name: str, spec: ParameterSpec) -> ParameterDescriptor:
    """The ParameterDescriptor of a schema entry."""
    desc = ParameterDescriptor(name=name, type=_KIND_TYPES[spec.kind],
                               description=spec.description, read_only=spec.read_only)
    notes = []
    if spec.choices:
        notes.append("one of " + ", ".join(spec.choices))
    if spec.kind == "float" and (spec.minimum is not None or spec.maximum is not None):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(spec.minimum if spec.minimum is not None else -sys.float_info.max),
            to_value=float(spec.maximum if spec.maximum is not None else sys.float_info.max),
            step=0.0)]
    elif spec.kind == "int" and (spec.minimum is not None or spec.maximum is not None):
        desc.integer_range = [IntegerRange(
            from_value=int(spec.minimum if spec.minimum is not None else -(2**63)),
            to_value=int(spec.maximum if spec.maximum is not None else 2**63 - 1), step=0)]
    if notes:
        desc.additional_constraints = "; ".join(notes)
    return desc


def _ros_value(spec: ParameterSpec, value: Any) -> Any:
    if spec.kind == "str_list":
        return [str(v) for v in value]
    if spec.kind == "float":
        return float(value)
    return value


def parameter_value(param: Any) -> Any:
    """Python value of an ``rcl_interfaces/Parameter`` message or rclpy ``Parameter``."""
    if isinstance(param, Parameter):
        value = param.value
    else:
        value = Parameter.from_parameter_msg(param).value
    if isinstance(value, (list, tuple)) or type(value).__name__ == "array":
        return list(value)
    return value


class NodeParameter:
    """A node-specific parameter (not part of the flight configuration)."""

    def __init__(self, default: Any, description: str, *, minimum: float | None = None,
                 maximum: float | None = None, read_only: bool = False) -> None:
        kind = {bool: "bool", int: "int", float: "float", str: "str"}[type(default)]
        self.spec = ParameterSpec(default, kind, description, minimum, maximum,
                                  read_only=read_only)

    def check(self, name: str, value: Any) -> Any:
        spec = self.spec
        if spec.kind == "float" and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if spec.kind == "float" and not (isinstance(value, float) and math.isfinite(value)):
            raise ConfigError(f"{name}: expected a finite number, got {value!r}")
        if spec.kind == "int" and (isinstance(value, bool) or not isinstance(value, int)):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        if spec.kind == "str" and not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        if spec.kind == "bool" and not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        if spec.minimum is not None and value < spec.minimum:
            raise ConfigError(f"{name}: {value} is below the minimum {spec.minimum}")
        if spec.maximum is not None and value > spec.maximum:
            raise ConfigError(f"{name}: {value} is above the maximum {spec.maximum}")
        return value


Listener = Callable[[FlightConfig, set[str]], None]


class FlightParameters:
    """The flight configuration of a node as ROS 2 parameters (module docstring).

    Parameters
    ----------
    node : rclpy Node
    extra : dict of name to NodeParameter
        Node-specific parameters.
    follow : bool
        Follow the flight-configuration node (calibrator, corrector); False for that node.
    has_control : callable, optional
        Whether control points are available now (for the cross-check "dZ without control").

    Raises
    ------
    ConfigError
        A value given at start-up (``--params-file``, ``-p``) is refused: one line naming it.
    """

    def __init__(
        self,
        node: Node,
        *,
        extra: Mapping[str, NodeParameter] | None = None,
        follow: bool = True,
        has_control: Callable[[], bool] | None = None,
    ) -> None:
        self.node = node
        self.extra = dict(extra or {})
        self._has_control = has_control or (lambda: False)
        self._listeners: list[Listener] = []
        self._extra_listeners: list[Callable[[str, Any], None]] = []
        self._lock = threading.RLock()
        self.refused: list[str] = []  # reasons of refused changes (newest last)
        values: dict[str, Any] = {}
        overrides = getattr(node, "_parameter_overrides", {})
        for name, spec in SCHEMA.items():
            value = spec.default
            if name in overrides:
                value = self._checked_override(name, overrides, coerce)
            values[name] = value
        self.config = FlightConfig(values)
        self.extra_values: dict[str, Any] = {}
        for name, par in self.extra.items():
            value = par.spec.default
            if name in overrides:
                value = self._checked_override(name, overrides, par.check)
            self.extra_values[name] = value
        declared = [(name, _ros_value(spec, values[name]), descriptor_for(name, spec))
                    for name, spec in SCHEMA.items()]
        declared += [(name, self.extra_values[name], descriptor_for(name, par.spec))
                     for name, par in self.extra.items()]
        node.declare_parameters("", declared)
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)
        reason = cross_check(self.config.values, has_control=self.has_control())
        if reason:
            node.get_logger().warning(f"flight configuration at start-up: {reason}")
        self._source: str | None = None
        self._client: Any = None
        self._sync_timer: Any = None
        if follow:
            self._follow()

    # -- values ----------------------------------------------------------------------
    def _checked_override(self, name: str, overrides: dict[str, Any],
                          check: Callable[[str, Any], Any]) -> Any:
        raw = parameter_value(overrides[name])
        try:
            value = check(name, raw)
        except ConfigError as exc:
            raise ConfigError(f"{self.node.get_name()}: parameter {exc}") from None
        spec = SCHEMA.get(name) or self.extra[name].spec
        # Keep the override in the declared type (an integer written for a float).
        overrides[name] = Parameter(name, value=_ros_value(spec, value))
        return value

    def has_control(self) -> bool:
        return bool(self.config["calibration.control_points_file"]) or bool(self._has_control())

    def __getitem__(self, name: str) -> Any:
        if name in self.extra_values:
            return self.extra_values[name]
        return self.config[name]

    def on_change(self, listener: Listener) -> None:
        """Call ``listener(config, changed_names)`` after each accepted flight-config change."""
        self._listeners.append(listener)

    def on_extra_change(self, listener: Callable[[str, Any], None]) -> None:
        """Call ``listener(name, value)`` after each accepted node-specific change."""
        self._extra_listeners.append(listener)

    # -- validation ------------------------------------------------------------------
    def check(self, params: Sequence[Parameter]) -> tuple[dict[str, Any], dict[str, Any]]:
        """Validate a set of changes; returns (flight-config values, extra values).

        Raises
        ------
        ConfigError
            The reason the set is refused.
        """
        values = dict(self.config.values)
        extra: dict[str, Any] = {}
        for p in params:
            value = parameter_value(p)
            if p.name in SCHEMA:
                values[p.name] = coerce(p.name, value)
            elif p.name in self.extra:
                extra[p.name] = self.extra[p.name].check(p.name, value)
            elif p.name == "use_sim_time":
                continue
            else:
                raise ConfigError(f"unknown parameter '{p.name}'")
        reason = cross_check(values, has_control=bool(values["calibration.control_points_file"])
                             or bool(self._has_control()))
        if reason:
            raise ConfigError(reason)
        return values, extra

    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        try:
            self.check(params)
        except LidarcalError as exc:
            reason = str(exc)
            self.refused.append(reason)
            del self.refused[:-20]
            self.node.get_logger().warning(f"parameter change refused: {reason}")
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _apply(self, params: list[Parameter]) -> None:
        with self._lock:
            values, extra = self.check(params)
            changed = {n for n, v in values.items() if self.config.values.get(n) != v}
            config = FlightConfig(values)
        if changed:
            self.node.get_logger().info("flight configuration changed: " + ", ".join(
                f"{n}={values[n]}" for n in sorted(changed)))
            for listener in self._listeners:
                try:
                    listener(config, changed)
                except Exception as exc:  # a listener must not break parameter setting
                    self.node.get_logger().error(f"applying {sorted(changed)} failed: {exc}")
        # The new flight configuration shows only once the listeners have applied it: whoever
        # sees it (another thread, a test waiting for the node to follow) may rely on its
        # effect. Node-specific values show before their listeners run: those read them back.
        with self._lock:
            self.config = config
            self.extra_values.update(extra)
        for name, value in extra.items():
            for extra_listener in self._extra_listeners:
                extra_listener(name, value)

    # -- following the flight-configuration node ---------------------------------------
    def _follow(self) -> None:
        node = self.node
        ns = node.get_namespace().rstrip("/")
        self._source = f"{ns}/{FLIGHT_CONFIG_NODE}"
        node.create_subscription(ParameterEvent, "/parameter_events", self._on_event,
                                 qos_profile_parameter_events)
        from rclpy.parameter_client import AsyncParameterClient

        self._client = AsyncParameterClient(node, self._source)
        self._sync_timer = node.create_timer(0.5, self._try_sync)

    def _try_sync(self) -> None:
        if self._client is None or not self._client.services_are_ready():
            return
        assert self._sync_timer is not None
        self._sync_timer.cancel()
        names = [n for n, s in SCHEMA.items() if not s.read_only]
        future = self._client.get_parameters(names)
        future.add_done_callback(lambda f: self._on_fetched(names, f))

    def _on_fetched(self, names: list[str], future: Any) -> None:
        try:
            response = future.result()
        except Exception as exc:  # the remote node went away
            self.node.get_logger().warning(f"cannot fetch {self._source} parameters: {exc}")
            return
        if response is None:
            return
        params = []
        for name, pv in zip(names, response.values):
            if pv.type == ParameterType.PARAMETER_NOT_SET:
                continue
            params.append(Parameter(name, value=Parameter.from_parameter_msg(
                _named(name, pv)).value))
        self.follow(params, source=f"{self._source} (start-up)")

    def _on_event(self, event: ParameterEvent) -> None:
        if event.node != self._source:
            return
        params = [Parameter.from_parameter_msg(p)
                  for p in (*event.new_parameters, *event.changed_parameters)
                  if p.name in SCHEMA and not SCHEMA[p.name].read_only]
        self.follow(params, source=self._source or "")

    def follow(self, params: Iterable[Parameter], *, source: str) -> bool:
        """Apply values accepted elsewhere (the flight-configuration node) to this node."""
        todo = []
        for p in params:
            try:
                value = coerce(p.name, parameter_value(p))
            except ConfigError:
                continue
            if self.config.values.get(p.name) != value:
                todo.append(Parameter(p.name, value=_ros_value(SCHEMA[p.name], value)))
        if not todo:
            return True
        result = self.node.set_parameters_atomically(todo)
        if not result.successful:
            self.node.get_logger().warning(
                f"not following {source}: {', '.join(p.name for p in todo)} refused here: "
                f"{result.reason}")
            return False
        return True


def _named(name: str, value: Any) -> Any:
    from rcl_interfaces.msg import Parameter as ParameterMsg

    return ParameterMsg(name=name, value=value)


# ---------------------------------------------------------------------------- diagnostics
def diagnostic_array(node: Node, statuses: Iterable[StatusSpec]) -> DiagnosticArray:
    """A DiagnosticArray stamped now, hardware id = the node's name."""
    msg = DiagnosticArray()
    msg.header.stamp = node.get_clock().now().to_msg()
    for s in statuses:
        msg.status.append(DiagnosticStatus(
            level=bytes([int(s.level)]), name=s.name, message=s.message,
            hardware_id=node.get_name(),
            values=[KeyValue(key=str(k), value=str(v)) for k, v in s.values.items()]))
    return msg


# ---------------------------------------------------------------------------- main
class Shutdown:
    """SIGINT / SIGTERM turn into a flag the spin loop polls (clean exit, no traceback)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._previous: dict[int, Any] = {}

    def install(self) -> Shutdown:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, _frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    @property
    def requested(self) -> bool:
        return self.event.is_set()


def spin_nodes(
    nodes: Sequence[Node], context: Any, shutdown: Shutdown, *, threads: int = 4
) -> None:
    """Spin ``nodes`` until ``shutdown`` is requested: on a multi-threaded executor, or a
    single-threaded one with ``threads=1`` (each callback runs in the spinning thread: no
    hand-over to a pool thread, which costs interpreter-lock switches)."""
    from rclpy.executors import (
        ExternalShutdownException,
        MultiThreadedExecutor,
        SingleThreadedExecutor,
    )

    executor: Any = (SingleThreadedExecutor(context=context) if threads == 1 else
                     MultiThreadedExecutor(num_threads=threads, context=context))
    for n in nodes:
        executor.add_node(n)
    log = nodes[0].get_logger() if nodes else None
    try:
        while not shutdown.requested and context.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception as exc:  # a callback failed: report it, keep the nodes running
                if log is not None:
                    log.error(f"callback failed: {type(exc).__name__}: {exc}",
                              throttle_duration_sec=5.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # Let callbacks in flight finish before the executor destroys its guard condition
        # (rclpy's MultiThreadedExecutor.shutdown does not wait for them).
        import time

        deadline = time.monotonic() + 5.0
        while any(not f.done() for f in getattr(executor, "_futures", ())) and \
                time.monotonic() < deadline:
            time.sleep(0.01)
        executor.shutdown(timeout_sec=2.0)


def start_ros(argv: list[str]) -> tuple[Any, Shutdown]:
    """Initialise a ROS context with lidarcal's own SIGINT/SIGTERM handling (``Shutdown``).

    The allocator is tuned first (:func:`lidarcal_ros.core.allocator.tune_allocator`): every
    cloud taken from or handed to DDS is a buffer of several MB, and with glibc's defaults
    each one is mapped and faulted in afresh, which costs a raw subscription about four times
    the CPU of the copy itself.
    """
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    tune_allocator(single_arena=False, trim_threshold_bytes=NODE_TRIM_THRESHOLD_BYTES)
    shutdown = Shutdown().install()
    context = Context()
    rclpy.init(args=argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
    return context, shutdown


def run_main(
    factories: Sequence[Callable[..., Node]],
    args: Sequence[str] | None = None,
    *,
    threads: int = 4,
) -> int:
    """Start nodes in this process (``--ros-args`` in ``args``), spin, stop cleanly on SIGINT
    or SIGTERM; returns the exit status (0, or 1 with a one-line reason on bad start-up
    configuration)."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    context, shutdown = start_ros(list(sys.argv if args is None else args))
    nodes: list[Node] = []
    status = 0
    try:
        for factory in factories:
            nodes.append(factory(context=context))
        spin_nodes(nodes, context, shutdown, threads=threads)
    except LidarcalError as exc:
        print(f"lidarcal: error: {exc}", file=sys.stderr)
        status = 1
    except KeyboardInterrupt:
        pass
    finally:
        for n in reversed(nodes):
            close = getattr(n, "close", None)
            try:
                if close is not None:
                    close()
                n.destroy_node()
            except Exception as exc:  # shutting down: report, continue
                print(f"lidarcal: error stopping {n.get_name()}: {exc}", file=sys.stderr)
        context.try_shutdown()
        shutdown.restore()
    return status


# ---------------------------------------------------------------------------- trajectory
def trajectory_message_classes() -> dict[str, Any]:
    """Message classes of the trajectory types the nodes accept, by ``pkg/msg/Type``."""
    from geometry_msgs.msg import PointStamped, PoseStamped, PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry

    return {
        "geometry_msgs/msg/PoseStamped": PoseStamped,
        "nav_msgs/msg/Odometry": Odometry,
        "geometry_msgs/msg/PoseWithCovarianceStamped": PoseWithCovarianceStamped,
        "geometry_msgs/msg/PointStamped": PointStamped,
    }


#: The ``trajectory_type`` parameter of the nodes that read the trajectory.
TRAJECTORY_TYPE_PARAMETER = NodeParameter(
    "auto", "Trajectory message type, or 'auto': PoseStamped until a publisher of another "
    "accepted type (Odometry, PoseWithCovarianceStamped, PointStamped) is seen, then that one. "
    "Give the type when a node of the same process publishes another type on the topic (one "
    "DDS participant holds a topic with one type only)", read_only=True)


class TrajectoryInput:
    """Subscribes to the trajectory topic, of a given type or the one its publishers use.

    Calls ``on_sample(t_seconds, (x, y, z), frame_id, orientation)`` for each sample (raw CDR
    decoded with rosbags; ``orientation`` its quaternion ``(x, y, z, w)``, NaN where the type
    has none: :func:`~lidarcal_ros.io.bag.trajectory_sample`). With
    ``msgtype`` ``auto`` the subscription is made at once for the contract's
    type (``geometry_msgs/msg/PoseStamped``), and the publishers on the topic are looked up
    every 0.5 s until one appears: if they use another accepted type, the subscription
    switches to it. Waiting for a publisher before subscribing at all would lose the first
    samples of every stream that starts after the node (up to a second of them, and at a
    replay's 10x rate the trajectory of a whole strip).
    """

    def __init__(self, node: Node, topic: str, msgtype: str,
                 on_sample: Callable[[float, tuple[float, float, float], str,
                                      tuple[float, ...]], None],
                 *, depth: int = 10000, callback_group: Any = None) -> None:
        self.node = node
        self.topic = topic
        self.on_sample = on_sample
        self.depth = depth
        self.group = callback_group
        self.msgtype: str | None = None
        self.subscription: Any = None
        self.errors = 0
        self._timer: Any = None
        from lidarcal_ros.io.bag import POSE_STAMPED, TRAJECTORY_TYPES, normalize_msgtype

        self._getters = TRAJECTORY_TYPES
        if msgtype and msgtype != "auto":
            self._subscribe(normalize_msgtype(msgtype))
            return
        self._subscribe(POSE_STAMPED, confirmed=False)
        self._timer = node.create_timer(0.5, self._discover, callback_group=callback_group)
        self._discover()

    def _discover(self) -> None:
        """Follow the type of the topic's publishers (``auto``), once they appear."""
        resolved = self.node.resolve_topic_name(self.topic)  # remappings applied
        types = sorted({info.topic_type
                        for info in self.node.get_publishers_info_by_topic(resolved)})
        if not types:
            return  # no publisher yet: keep the subscription of the contract's type
        if self.msgtype in types:
            self._subscribe(self.msgtype)  # confirmed: the subscription stays
            return
        accepted = [t for t in types if t in self._getters]
        if accepted:
            self._subscribe(accepted[0])
            return
        self.node.get_logger().error(
            f"{self.topic} has type(s) {', '.join(types)}; expected one of "
            f"{', '.join(self._getters)}", throttle_duration_sec=30.0)

    def _subscribe(self, msgtype: str, *, confirmed: bool = True) -> None:
        """Subscribe for ``msgtype`` (replacing a subscription of another type); once
        ``confirmed`` (a given type, or the publishers' own), stop looking."""
        classes = trajectory_message_classes()
        if msgtype not in classes:
            raise ConfigError(f"trajectory type {msgtype} is not one of {', '.join(classes)}")
        if confirmed and self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if msgtype == self.msgtype:
            if confirmed:
                self.node.get_logger().info(f"trajectory: {self.topic} ({msgtype})")
            return
        if self.subscription is not None:
            self.node.destroy_subscription(self.subscription)
        self.msgtype = msgtype
        # Each subscription decodes its own type (a message of the one replaced may still be
        # in a callback when the type changes).
        self.subscription = self.node.create_subscription(
            classes[msgtype], self.topic, lambda raw: self._on_raw(raw, msgtype),
            stream_qos(self.depth), raw=True, callback_group=self.group)
        if confirmed:
            self.node.get_logger().info(f"trajectory: {self.topic} ({msgtype})")

    def _on_raw(self, raw: bytes, msgtype: str) -> None:
        from lidarcal_ros.io.bag import trajectory_sample
        from lidarcal_ros.io.ros_messages import deserialize

        try:
            msg = deserialize(raw, msgtype)
            t, xyz, orientation = trajectory_sample(msgtype, msg)
        except Exception as exc:  # malformed message: log, skip, keep running
            self.errors += 1
            self.node.get_logger().error(f"{self.topic}: malformed {msgtype} skipped "
                                         f"({exc})", throttle_duration_sec=5.0)
            return
        self.on_sample(t, xyz, str(msg.header.frame_id), orientation)
