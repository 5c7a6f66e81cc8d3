"""When the suite of ``lidarcal run`` is up (graph queries); its state on ``/lidarcal/suite``.

What "up" means: docs/nodes.md, "The helper nodes of the CLI".
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node
from std_msgs.msg import String

from lidarcal_ros.core.config import CALIBRATOR_NODE, CORRECTOR_NODE, FLIGHT_CONFIG_NODE
from lidarcal_ros.nodes.topics import latched_qos

__all__ = ["RUN_NODE", "SUITE_NODES", "SUITE_TOPIC", "SuiteMonitor", "SuiteNode",
           "node_is_up", "read_suite_state"]

SUITE_TOPIC = "/lidarcal/suite"
RUN_NODE = "lidarcal_run"
_PARAMETER_EVENTS = "/parameter_events"  # (every node following parameters subscribes to it)


@dataclass(frozen=True)
class SuiteNode:
    """What a suite node makes before it is up: its input subscriptions (besides
    ``/parameter_events``) and its private services (``~/name``)."""

    inputs: int
    services: tuple[str, ...] = ()


#: The nodes of ``lidarcal run`` (their constructors: points, trajectory and control points
#: for the calibrator, then ~/solve, ~/reset, ~/save; points, trajectory and the estimate for
#: the corrector; control points for the flight configuration).
SUITE_NODES: dict[str, SuiteNode] = {
    FLIGHT_CONFIG_NODE: SuiteNode(1),
    CALIBRATOR_NODE: SuiteNode(3, ("solve", "reset", "save")),
    CORRECTOR_NODE: SuiteNode(3),
}


def node_is_up(graph: Node, name: str, spec: SuiteNode) -> bool:
    """Whether ``graph`` (any node: its view of the ROS graph) shows node ``name`` with the
    subscriptions and services of ``spec``."""
    namespace = next((ns for n, ns in graph.get_node_names_and_namespaces() if n == name), None)
    if namespace is None:
        return False
    try:
        inputs = [t for t, _ in graph.get_subscriber_names_and_types_by_node(name, namespace)
                  if t != _PARAMETER_EVENTS]
        services = {s for s, _ in graph.get_service_names_and_types_by_node(name, namespace)}
    except Exception:  # (rclpy's NodeNameNonExistentError: it went away meanwhile)
        return False
    prefix = f"{namespace.rstrip('/')}/{name}/"
    return len(inputs) >= spec.inputs and all(prefix + s in services for s in spec.services)


def read_suite_state(text: str) -> dict[str, Any]:
    """The state a :class:`SuiteMonitor` published (``state``: ``starting`` or ``up``;
    ``nodes``, ``up``: node names; ``seconds`` since ``lidarcal run`` started); ``{}`` for
    text that is not one."""
    try:
        state = json.loads(text)
    except ValueError:
        return {}
    return state if isinstance(state, dict) and "state" in state else {}


class SuiteMonitor(Node):
    """Watches the graph until every node of ``names`` is up (docs/nodes.md).

    Parameters
    ----------
    names : node names, keys of :data:`SUITE_NODES`
    started : ``time.monotonic()`` when ``lidarcal run`` started (the line's seconds)
    announce : called once with the line, e.g. ``lidarcal run: suite up (lidarcal_calibrator,
        lidarcal_corrector, lidarcal_flight_config) in 3.2 s``
    """

    def __init__(self, names: Sequence[str], *, started: float,
                 announce: Callable[[str], None], context: Any = None) -> None:
        super().__init__(RUN_NODE, context=context)
        self.names = sorted(names)
        self.started = started
        self.announce = announce
        #: Seconds from ``started`` until the suite was up (None: not yet).
        self.up_after_s: float | None = None
        self._up: list[str] = []
        self.publisher = self.create_publisher(String, SUITE_TOPIC, latched_qos())
        self._publish("starting")
        self._timer = self.create_timer(0.1, self._look)

    def _publish(self, state: str) -> None:
        self.publisher.publish(String(data=json.dumps({
            "state": state, "nodes": self.names, "up": self._up,
            "seconds": round(time.monotonic() - self.started, 3)})))

    def _look(self) -> None:
        self.check()

    def check(self) -> bool:
        """Look at the graph once; returns whether the suite is up."""
        if self.up_after_s is not None:
            return True
        up = [n for n in self.names if node_is_up(self, n, SUITE_NODES[n])]
        if up != self._up:
            self._up = up
            if len(up) < len(self.names):
                self._publish("starting")
        if len(up) < len(self.names):
            return False
        self.up_after_s = time.monotonic() - self.started
        self._timer.cancel()
        self._publish("up")
        self.announce(f"lidarcal run: suite up ({', '.join(self.names)}) in "
                      f"{self.up_after_s:.1f} s")
        return True
