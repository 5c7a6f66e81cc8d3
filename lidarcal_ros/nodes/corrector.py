"""``lidarcal_corrector``: applies the latest estimate and the radiometric model to each chunk.

    ros2 run lidarcal_ros lidarcal_corrector --ros-args --params-file config/flight_config.yaml

Subscribes (raw CDR) to the points (``topics.points``; each cloud taken from DDS straight
into the correction's shared memory, :mod:`~lidarcal_ros.nodes.serialized_subscription`) and
the trajectory (``topics.trajectory``), and to the calibrator's estimate
(``/lidar/calibration/estimate``, transient-local); publishes each chunk corrected on
``topics.corrected`` with every input field, ``x, y, z`` corrected (docs/method.md eq. [13])
and the FLOAT32 ``reflectance``, ``range``, ``incidence``, ``scan_angle`` plus UINT8
``correction_flags`` (:mod:`lidarcal_ros.core.flags`). Header stamp and frame are the input's. The
``reflectance`` is the Lambertian reflectance (0-1) when ``radiometry.calibration_constant``
is set, else relative (intensity normalised to ``radiometry.reference_range_m``; intensity
units: :mod:`lidarcal_ros.core.radiometry`); a ``radiometry.reference_target`` needs the
whole mission, so the node does not use it (``lidarcal report`` and ``lidarcal correct`` derive
the constant from it).

A new estimate is used from the next chunk on, without a restart; so are accepted changes of
the flight configuration (atmosphere, radiometry, time field...). Until an estimate arrives the
corrector uses the file named by its ``calibration`` parameter, else the configuration's
``calibration.fixed.*`` values.

Every input point comes out exactly once, in the order received. A chunk is corrected once
the trajectory covers it (a sample past its last point time) or after
``max_trajectory_wait_s``. The normals come from one grid per strip that every chunk's points
join (:class:`~lidarcal_ros.core.normals.strip_normals.StripNormals`): by default (``lookahead``
false) a chunk is corrected at once, its points seeing the earlier chunks as neighbours; with
``lookahead`` true it waits until the next chunks cover the grid rows beyond it (about three
rows, a few chunks), which gives exactly the normals of ``lidarcal correct`` at that cost in
latency. Held chunks are corrected without look-ahead once no chunk came for
``flush_timeout_s``. A malformed chunk (bad layout, missing field, wrong frame) is logged and
skipped; the node keeps running.

The work is :class:`~lidarcal_ros.pipeline.correction.live.LiveCorrector`'s (waiting for the
trajectory, the backlog bound, the time-out, the diagnostics); the numerics run in a child
process (``separate_process``, :mod:`~lidarcal_ros.pipeline.correction.process`): this
process only takes messages off DDS and publishes, so that its callbacks (hundreds of
trajectory samples a second) never wait for the interpreter lock of the numerics. The clouds
go there and back through shared memory (``shared_memory_mib``; pipes where a host has none:
diagnostics key ``transport``): each is taken from DDS into the inbound ring, and published
from the outbound ring where it was corrected
(:mod:`~lidarcal_ros.nodes.serialized_publisher`), so the node copies none.

Node-specific parameters: ``calibration`` (YAML path), ``queue_depth``, ``best_effort``,
``trajectory_type`` (``auto`` or a type), ``trajectory_buffer_s``, ``max_trajectory_wait_s``,
``flush_timeout_s``, ``lookahead``, ``workers``, ``batch_points``, ``separate_process``,
``shared_memory_mib``.
Diagnostics (``lidarcal: corrector``) report clouds and points in and out, skipped chunks,
points not covered by the trajectory and the latency.
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
    """Corrects point-cloud chunks with the latest estimate (module docstring)."""

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
