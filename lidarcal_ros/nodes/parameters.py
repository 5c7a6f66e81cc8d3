"""The parameters of a node: the flight configuration and the node's own, as ROS 2 parameters.

:class:`FlightParameters` declares them with descriptors, checks a value set at run time as
``lidarcal calibrate --config`` does, and follows ``lidarcal_flight_config``'s accepted changes
(docs/nodes.md, "Parameters").
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

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
from rclpy.qos import qos_profile_parameter_events

from lidarcal_ros.core.config import (
    FLIGHT_CONFIG_NODE,
    SCHEMA,
    FlightConfig,
    ParameterSpec,
    check_value,
    coerce,
    cross_check,
)
from lidarcal_ros.errors import ConfigError, LidarcalError

__all__ = ["FlightParameters", "Listener", "descriptor_for", "parameter_value"]

_KIND_TYPES = {
    "float": ParameterType.PARAMETER_DOUBLE,
    "int": ParameterType.PARAMETER_INTEGER,
    "str": ParameterType.PARAMETER_STRING,
    "bool": ParameterType.PARAMETER_BOOL,
    "str_list": ParameterType.PARAMETER_STRING_ARRAY,
}


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


Listener = Callable[[FlightConfig, set[str]], None]


class FlightParameters:
    """The flight configuration of a node as ROS 2 parameters (docs/nodes.md, "Parameters").

    Parameters
    ----------
    node : rclpy Node
    extra : dict of name to ParameterSpec
        The node's own parameters (:data:`lidarcal_ros.core.config.NODE_PARAMETERS`).
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
        extra: Mapping[str, ParameterSpec] | None = None,
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
        for name, spec in self.extra.items():
            value = spec.default
            if name in overrides:
                value = self._checked_override(name, overrides, self._check_extra)
            self.extra_values[name] = value
        declared = [(name, _ros_value(spec, values[name]), descriptor_for(name, spec))
                    for name, spec in SCHEMA.items()]
        declared += [(name, self.extra_values[name], descriptor_for(name, spec))
                     for name, spec in self.extra.items()]
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
        spec = SCHEMA.get(name) or self.extra[name]
        # Keep the override in the declared type (an integer written for a float).
        overrides[name] = Parameter(name, value=_ros_value(spec, value))
        return value

    def _check_extra(self, name: str, value: Any) -> Any:
        return check_value(name, self.extra[name], value)

    def has_control(self) -> bool:
        """Whether control points are available: a control points file configured, or the node's
        ``has_control`` says so."""
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
                extra[p.name] = self._check_extra(p.name, value)
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

