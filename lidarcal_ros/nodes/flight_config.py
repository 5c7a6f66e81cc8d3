"""``lidarcal_flight_config``: the flight configuration as a ROS 2 parameter service.

    ros2 run lidarcal_ros lidarcal_flight_config --ros-args --params-file config/flight_config.yaml

Its checks and who follows it: docs/nodes.md, "``lidarcal_flight_config``".
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from lidarcal_ros.core.config import FLIGHT_CONFIG_NODE
from lidarcal_ros.nodes.parameters import FlightParameters
from lidarcal_ros.nodes.process import run_main
from lidarcal_ros.nodes.topics import latched_qos

__all__ = ["FlightConfigNode"]


class FlightConfigNode(Node):
    """Parameter server of the flight configuration."""

    def __init__(self, *, context: Any = None, node_name: str = FLIGHT_CONFIG_NODE,
                 **kwargs: Any) -> None:
        super().__init__(node_name, context=context, **kwargs)
        self._control_seen = False
        self.params = FlightParameters(self, follow=False,
                                       has_control=lambda: self._control_seen)
        self.create_subscription(PointCloud2, self.params["topics.control_points"],
                                 self._on_control, latched_qos(), raw=True)
        self.get_logger().info("serving the flight configuration "
                               f"({len(self.params.config.values)} parameters)")

    def _on_control(self, raw: bytes) -> None:
        self._control_seen = True

    def close(self) -> None:
        """Nothing to release (parameters die with the node)."""


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``lidarcal_flight_config``."""
    return run_main([FlightConfigNode], args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
