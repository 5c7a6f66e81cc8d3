"""``lidarcal_calibrator``: live calibration from the strips as they are flown.

    ros2 run lidarcal_ros lidarcal_calibrator --ros-args --params-file config/flight_config.yaml

The node decodes, hands over to a
:class:`~lidarcal_ros.pipeline.calibration.service.CalibrationService` and publishes. Its
topics, services, statuses and how it works: docs/nodes.md, "``lidarcal_calibrator``".
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import Trigger

from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.config import CALIBRATOR_NODE, NODE_PARAMETERS, SCHEMA
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.mission import ControlPoints
from lidarcal_ros.errors import ConfigError, LidarcalError
from lidarcal_ros.io.bag.format import stamp_seconds
from lidarcal_ros.io.cloud.columns import extract_columns, extract_xyz
from lidarcal_ros.io.cloud.messages import (
    ESTIMATE_COLUMN_LABEL,
    ESTIMATE_ROWS,
    WARN,
    calibration_yaml,
    estimate_matrix,
    estimate_row_label,
    parse_cloud,
    qa_summary,
    warm_up_cloud_codec,
    worst_level,
)
from lidarcal_ros.io.cloud.sensor_time import SensorCloudDecoder
from lidarcal_ros.nodes.parameters import FlightParameters
from lidarcal_ros.nodes.process import run_main
from lidarcal_ros.nodes.topics import (
    DIAGNOSTICS_TOPIC,
    ESTIMATE_TOPIC,
    YAML_TOPIC,
    diagnostic_array,
    latched_qos,
    stream_qos,
)
from lidarcal_ros.nodes.trajectory_input import TrajectoryInput
from lidarcal_ros.pipeline.calibration.service import CalibrationService, CalibratorOptions

__all__ = ["CALIBRATOR_PARAMETERS", "CalibratorNode"]

CALIBRATOR_PARAMETERS = NODE_PARAMETERS[CALIBRATOR_NODE]
#: Static transforms a late joiner takes from each publisher of ``/tf_static``.
TF_STATIC_DEPTH = 100


class CalibratorNode(Node):
    """Live calibration node (docs/nodes.md)."""

    def __init__(self, *, context: Any = None, node_name: str = CALIBRATOR_NODE,
                 **kwargs: Any) -> None:
        super().__init__(node_name, context=context, **kwargs)
        self._control_from_topic = False
        self.params = FlightParameters(self, extra=CALIBRATOR_PARAMETERS,
                                       has_control=lambda: self._control_from_topic)
        cfg = self.params.config
        self.calibration = CalibrationService(cfg, self._options(),
                                              on_result=self._publish_result)
        warm_up_cloud_codec()
        self._decoder = SensorCloudDecoder(
            field=cfg["time_field"] if cfg["time_field"] != SCHEMA["time_field"].default
            else None, convention=cfg["sensor_frame.time_convention"])
        self._offered: tuple[str, str, Mounting] | None = None

        self.estimate_pub = self.create_publisher(Float64MultiArray, ESTIMATE_TOPIC,
                                                  latched_qos())
        self.yaml_pub = self.create_publisher(String, YAML_TOPIC, latched_qos())
        # the calibrated mounting as a plain TransformStamped: live without tf2_msgs too
        self.extrinsic_pub = self.create_publisher(TransformStamped, cfg["topics.extrinsic"],
                                                   latched_qos())
        self.diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        input_group = MutuallyExclusiveCallbackGroup()
        service_group = ReentrantCallbackGroup()
        self.create_subscription(PointCloud2, cfg["topics.points"], self._on_points,
                                 stream_qos(self.params["queue_depth"]), raw=True,
                                 callback_group=input_group)
        self.trajectory_input = TrajectoryInput(self, cfg["topics.trajectory"],
                                                self.params["trajectory_type"],
                                                self.calibration.add_pose,
                                                callback_group=input_group,
                                                on_child_frame=self.calibration.set_base_frame)
        self.create_subscription(PointCloud2, cfg["topics.control_points"], self._on_control,
                                 latched_qos(), raw=True, callback_group=input_group)
        # the nominal mounting as robot_state_publisher offers it; the calibrated one back
        self.tf_pub: Any = None
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:  # (the interfaces installed from wheels have no tf2_msgs)
            self.get_logger().warning(
                f"tf2_msgs is not installed: {cfg['topics.tf_static']} is neither read nor "
                "offered; clouds in the sensor's frame take their mounting from "
                f"sensor_frame.mounting, the calibrated one is on {cfg['topics.extrinsic']}")
        else:
            self.create_subscription(TFMessage, cfg["topics.tf_static"], self._on_tf_static,
                                     latched_qos(TF_STATIC_DEPTH), callback_group=input_group)
            self.tf_pub = self.create_publisher(TFMessage, cfg["topics.tf_static"],
                                                latched_qos())
        for name, request in (("~/solve", self.calibration.solve),
                              ("~/reset", self.calibration.reset),
                              ("~/save", self.calibration.save)):
            self.create_service(Trigger, name, _trigger(request), callback_group=service_group)
        self.create_timer(1.0, self._publish_diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.params.on_change(self.calibration.set_config)
        self.params.on_extra_change(lambda _name, _value: self.calibration.set_options(
            self._options()))
        self.calibration.start()

    def _options(self) -> CalibratorOptions:
        return CalibratorOptions.from_parameters(self.params.extra_values)

    # -- input callbacks (decode and hand over only) -------------------------------------
    def _on_points(self, raw: bytes) -> None:
        source = self.params["topics.points"]
        try:
            cloud = parse_cloud(raw, source=source)
            names = cloud.points.dtype.names or ()
            if cloud.frame_id != self.params["frame_id"] and "strip_id" not in names and \
                    "point_source_id" not in names:
                self._on_sensor_cloud(cloud, source)
                return
            cols = extract_columns(cloud.points, time_field=self.params["time_field"],
                                   source=source,
                                   coordinate_tolerance_m=self.params["sensor.range_noise_m"])
            if cols.strip_id is None:
                raise LidarcalError(f"{source}: cloud lacks field 'strip_id' (or "
                                    "'point_source_id')")
        except LidarcalError as exc:
            self.calibration.cloud_skipped(str(exc))
            self.get_logger().error(f"malformed cloud skipped: {exc}", throttle_duration_sec=2.0)
            return
        self.calibration.add_cloud(cols, cloud.frame_id)

    def _on_sensor_cloud(self, cloud: Any, source: str) -> None:
        """A driver's cloud in the sensor's frame (docs/method.md section 12), decoded as a
        bag's is (:class:`SensorCloudDecoder`)."""
        first = self._decoder.reading is None
        xyz, t, _intensity = self._decoder.decode(
            cloud.points, stamp_seconds(cloud.msg.header.stamp), source=source)
        if first and self._decoder.reading is not None:
            self.get_logger().warning(f"{source}: {self._decoder.reading.describe()}")
        self.calibration.add_sensor_cloud(xyz, t, cloud.frame_id)

    def _on_tf_static(self, msg: Any) -> None:
        """Static transforms: the nominal mounting's chain (our own offer left out)."""
        transforms: dict[str, tuple[str, Mounting]] = {}
        for tf in msg.transforms:
            if self._offered is not None and tf.child_frame_id == self._offered[1]:
                continue
            tr, q = tf.transform.translation, tf.transform.rotation
            try:
                transforms[str(tf.child_frame_id)] = (str(tf.header.frame_id),
                                                      Mounting.from_quaternion(
                                                          [tr.x, tr.y, tr.z],
                                                          [q.x, q.y, q.z, q.w]))
            except ConfigError as exc:
                self.get_logger().error(f"{self.params['topics.tf_static']}: "
                                        f"{tf.header.frame_id} -> {tf.child_frame_id} "
                                        f"ignored: {exc}")
        if transforms:
            self.calibration.add_transforms(transforms, self.params["topics.tf_static"])

    def _on_control(self, raw: bytes) -> None:
        source = self.params["topics.control_points"]
        try:
            cloud = parse_cloud(raw, source=source)
            xyz = extract_xyz(cloud.points, source=source,
                              coordinate_tolerance_m=self.params["sensor.range_noise_m"])
        except LidarcalError as exc:
            self.get_logger().error(f"control points ignored: {exc}")
            return
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if not len(xyz):
            self.get_logger().warning(f"{source}: no finite control point; ignored")
            return
        self._control_from_topic = True
        if self.params["calibration.control_points_file"]:
            self.get_logger().info(f"{source}: control points ignored, "
                                   "calibration.control_points_file takes precedence")
            return
        self.calibration.set_control(ControlPoints([f"C{i + 1}" for i in range(len(xyz))],
                                                   xyz), source)

    # -- outputs --------------------------------------------------------------------------
    def _publish_result(self, result: CalibrationResult) -> None:
        """Publish an estimate (in the service's worker thread): matrix, YAML, diagnostics,
        and its QA summary on the console (for the crew running ``lidarcal run``)."""
        msg = Float64MultiArray()
        n_rows, n_cols = len(ESTIMATE_ROWS), 8
        msg.layout.dim = [
            MultiArrayDimension(label=estimate_row_label(result.converged), size=n_rows,
                                stride=n_rows * n_cols),
            MultiArrayDimension(label=ESTIMATE_COLUMN_LABEL, size=n_cols, stride=n_cols)]
        msg.data = estimate_matrix(result).ravel().tolist()
        self.estimate_pub.publish(msg)
        # (the block as ~/save writes it: with the timing bias)
        extrinsic = self.calibration.timed_extrinsic()
        self.yaml_pub.publish(String(data=calibration_yaml(result, extrinsic=extrinsic)))
        self._offer_mounting()
        self._publish_diagnostics()
        statuses = self.calibration.estimate_statuses()
        summary = qa_summary(statuses)
        # (rclpy refuses one call site logging at two severities: two calls.)
        if worst_level(s for s in statuses if s.name.startswith("lidarcal: strips ")) >= WARN:
            self.get_logger().warning(summary)
        else:
            self.get_logger().info(summary)

    def _offer_mounting(self) -> None:
        """The calibrated mounting of clouds in the sensor's frame, ``base_link ->
        sensor_frame.calibrated_frame`` (default ``<sensor>_calibrated``, beside the nominal,
        which stays robot_state_publisher's): on ``topics.extrinsic`` and, where tf2_msgs is
        installed, on ``/tf_static``. Translation in m, rotation as a unit quaternion."""
        cal, feed = self.calibration.mounting, self.calibration.sensor
        if cal is None or feed.frame_id is None:
            return
        child = self.params["sensor_frame.calibrated_frame"] or f"{feed.frame_id}_calibrated"
        self._offered = (feed.base_frame, child, cal.mounting)
        tf = TransformStamped()
        tf.header.stamp = self.get_clock().now().to_msg()
        tf.header.frame_id = feed.base_frame
        tf.child_frame_id = child
        t, q = cal.mounting.translation, cal.mounting.quaternion
        tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = \
            (float(v) for v in t)
        (tf.transform.rotation.x, tf.transform.rotation.y, tf.transform.rotation.z,
         tf.transform.rotation.w) = (float(v) for v in q)
        self.extrinsic_pub.publish(tf)
        if self.tf_pub is not None:
            from tf2_msgs.msg import TFMessage

            self.tf_pub.publish(TFMessage(transforms=[tf]))

    def _publish_diagnostics(self) -> None:
        self.diagnostics.publish(diagnostic_array(self, self.calibration.statuses()))

    def close(self) -> None:
        """Stop the calibration: it converges (for a while) and writes a last checkpoint."""
        self.calibration.close()


def _trigger(request: Callable[[], str]) -> Callable[[Any, Any], Any]:
    """A ``std_srvs/Trigger`` callback answering with what ``request`` returns, or with the
    reason it failed."""

    def serve(_request: Any, response: Any) -> Any:
        try:
            response.message = request()
            response.success = True
        except Exception as exc:
            response.success = False
            response.message = str(exc) if isinstance(exc, LidarcalError) else \
                f"{type(exc).__name__}: {exc}"
        return response

    return serve


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``lidarcal_calibrator``."""
    return run_main([CalibratorNode], args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
