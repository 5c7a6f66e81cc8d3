"""``lidarcal_corrector``: applies the latest estimate and the radiometric model to each cloud.

    ros2 run lidarcal_ros lidarcal_corrector --ros-args --params-file config/flight_config.yaml

The work is :class:`~lidarcal_ros.pipeline.correction.live.LiveCorrector`'s; this process only
takes clouds off DDS into shared memory and publishes. Topics and behaviour: docs/nodes.md,
"``lidarcal_corrector``"; how it is built: docs/correction.md, "The live corrector".
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray

from lidarcal_ros.core.config import CORRECTOR_NODE, NODE_PARAMETERS, node_options
from lidarcal_ros.core.params import format_value
from lidarcal_ros.io.cloud.messages import StatusSpec, parse_estimate, warm_up_cloud_codec
from lidarcal_ros.nodes.parameters import FlightParameters
from lidarcal_ros.nodes.process import run_main
from lidarcal_ros.nodes.serialized_publisher import SerializedPublisher
from lidarcal_ros.nodes.serialized_subscription import SerializedSubscription
from lidarcal_ros.nodes.topics import (
    DIAGNOSTICS_TOPIC,
    ESTIMATE_TOPIC,
    diagnostic_array,
    latched_qos,
    stream_qos,
)
from lidarcal_ros.nodes.trajectory_input import TrajectoryInput
from lidarcal_ros.pipeline.correction.live import CorrectorOptions, LiveCorrector
from lidarcal_ros.pipeline.correction.process import InboundRegion

__all__ = ["CORRECTOR_PARAMETERS", "CorrectorNode"]

CORRECTOR_PARAMETERS = NODE_PARAMETERS[CORRECTOR_NODE]


class CorrectorNode(Node):
    """Corrects point-cloud chunks with the latest estimate (docs/nodes.md)."""

    def __init__(self, *, context: Any = None, node_name: str = CORRECTOR_NODE,
                 **kwargs: Any) -> None:
        super().__init__(node_name, context=context, **kwargs)
        self.params = FlightParameters(self, extra=CORRECTOR_PARAMETERS)
        cfg = self.params.config
        self._segment_checked = False
        self.publisher = self.create_publisher(PointCloud2, cfg["topics.corrected"],
                                               stream_qos(self.params["queue_depth"]))
        # Corrected clouds go to rcl from the correction's shared memory, not through a
        # bytes copy (:mod:`~lidarcal_ros.nodes.serialized_publisher`).
        self._corrected_out = SerializedPublisher(self.publisher)
        self.diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        #: The correction (ROS-free): clouds in, corrected clouds out to the publisher.
        self.correction = LiveCorrector(cfg, self._options(), publish=self.publish_corrected,
                                        calibration=self.params["calibration"])
        warm_up_cloud_codec()

        points_group = MutuallyExclusiveCallbackGroup()
        other_group = MutuallyExclusiveCallbackGroup()
        # Clouds are taken from DDS straight into the correction's shared memory
        # (:mod:`~lidarcal_ros.nodes.serialized_subscription`).
        self.points_input = SerializedSubscription(
            self, PointCloud2, cfg["topics.points"],
            stream_qos(self.params["queue_depth"], best_effort=self.params["best_effort"]),
            allocate=self.correction.receive_buffer, callback=self._on_points,
            discard=_give_back, callback_group=points_group)
        self.trajectory_input = TrajectoryInput(
            self, cfg["topics.trajectory"], self.params["trajectory_type"],
            self.correction.add_pose, callback_group=other_group)
        self.create_subscription(Float64MultiArray, ESTIMATE_TOPIC, self._on_estimate,
                                 latched_qos(), callback_group=other_group)
        self.params.on_change(lambda config, _changed: self.correction.set_config(config))
        self.params.on_extra_change(lambda _name, _value: self.correction.set_options(
            self._options()))
        self.create_timer(1.0, self._publish_diagnostics, callback_group=other_group)
        self.get_logger().info(f"correcting {cfg['topics.points']} -> "
                               f"{cfg['topics.corrected']} (biases from "
                               f"{self.correction.estimate_source})")

    def _options(self) -> CorrectorOptions:
        return node_options(CorrectorOptions, CORRECTOR_NODE, self.params.extra_values)

    # -- input callbacks (convert and hand over only) ------------------------------------
    def _on_points(self, raw: bytes | memoryview, region: InboundRegion | None) -> None:
        size = memoryview(raw).nbytes
        if not self._segment_checked and size > 256 * 1024:
            self._warn_small_segment(size)
        self.correction.add_cloud(raw, region)

    def _on_estimate(self, msg: Float64MultiArray) -> None:
        try:
            est = parse_estimate(msg.data, [d.label for d in msg.layout.dim])
        except ValueError as exc:
            self.get_logger().error(f"{ESTIMATE_TOPIC}: {exc}; ignored")
            return
        if not np.isfinite(est.delta).all():
            self.get_logger().error(f"{ESTIMATE_TOPIC}: non-finite values; ignored")
            return
        self.correction.set_estimate(est.delta, ESTIMATE_TOPIC)
        self.get_logger().info("new estimate: " + ", ".join(
            f"{n} {format_value(n, v)}" for n, v in est.values.items()))

    def _warn_small_segment(self, size: int) -> None:
        """Say once when clouds outgrow the DDS profile's shared-memory segment: they then
        travel as UDP fragments, and the trajectory queues behind them (seconds late)."""
        from lidarcal_ros.ros.environment import shared_memory_segment_bytes

        self._segment_checked = True
        segment = shared_memory_segment_bytes()
        if segment is not None and size > segment // 2:
            self.get_logger().warning(
                f"clouds of {size / 2**20:.1f} MiB but the DDS profile's shared-memory "
                f"segment is {segment / 2**20:.1f} MiB: they go as UDP fragments and delay the "
                "trajectory; use the project's config/loopback.xml (128 MiB)")

    # -- outputs ----------------------------------------------------------------------------
    def publish_corrected(self, cdr: bytes | memoryview) -> None:
        """Publish a corrected chunk (its CDR bytes, read during the call only; from the
        correction's reader thread)."""
        self._corrected_out.publish(cdr)

    def status(self) -> StatusSpec:
        """The diagnostics ``lidarcal: corrector``."""
        return self.correction.status()

    def _publish_diagnostics(self) -> None:
        self.diagnostics.publish(diagnostic_array(self, [self.status()]))

    def close(self) -> None:
        """Stop the correction; held chunks are corrected and published first."""
        self.correction.close()


def _give_back(region: InboundRegion | None) -> None:
    """Memory taken for a cloud that never came (see SerializedSubscription)."""
    if region is not None:
        region.release()


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``lidarcal_corrector``."""
    # The node's callbacks are light (the numerics run in the correction's own process):
    # one executor thread, no hand-over of each callback to a pool.
    return run_main([CorrectorNode], args, threads=1)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
