"""The fixed topics of the node suite (docs/interface.md), their QoS, the diagnostics message."""

from __future__ import annotations

from collections.abc import Iterable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from lidarcal_ros.io.cloud.messages import StatusSpec

__all__ = ["DIAGNOSTICS_TOPIC", "ESTIMATE_TOPIC", "YAML_TOPIC", "diagnostic_array",
           "latched_qos", "stream_qos"]

ESTIMATE_TOPIC = "/lidar/calibration/estimate"
YAML_TOPIC = "/lidar/calibration/yaml"
DIAGNOSTICS_TOPIC = "/diagnostics"


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

