"""ROS 2 nodes: thin rclpy wrappers around :mod:`lidarcal_ros.pipeline`.

Importing this package confines ROS 2 / DDS to this machine
(:func:`lidarcal_ros.ros.environment.configure_ros_environment`) before any node module imports
rclpy: ``ros2 run lidarcal_ros <node>`` and ``lidarcal run`` start rclpy only through these
modules. An environment already configured (a test's domain id, a launch file's settings) is
kept.
"""

from lidarcal_ros.ros.environment import configure_ros_environment

configure_ros_environment()

# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---
from lidarcal_ros.exports import lazy_exports  # noqa: E402

_EXPORTS = {
    "CALIBRATOR_PARAMETERS": "calibrator",
    "CalibratorNode": "calibrator",
    "CORRECTOR_PARAMETERS": "corrector",
    "CorrectorNode": "corrector",
    "FlightConfigNode": "flight_config",
    "FlightParameters": "parameters",
    "Listener": "parameters",
    "descriptor_for": "parameters",
    "parameter_value": "parameters",
    "PLAYER_NODE": "player",
    "PlayerNode": "player",
    "message_class": "player",
    "topic_qos": "player",
    "Shutdown": "process",
    "run_main": "process",
    "spin_nodes": "process",
    "start_ros": "process",
    "DEFAULT_TOPICS": "recorder",
    "RECORDER_NODE": "recorder",
    "RecorderNode": "recorder",
    "DIAGNOSTICS_TOPIC": "topics",
    "ESTIMATE_TOPIC": "topics",
    "YAML_TOPIC": "topics",
    "diagnostic_array": "topics",
    "latched_qos": "topics",
    "stream_qos": "topics",
    "TrajectoryInput": "trajectory_input",
    "trajectory_message_classes": "trajectory_input",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = [
    "CALIBRATOR_PARAMETERS",
    "CORRECTOR_PARAMETERS",
    "DEFAULT_TOPICS",
    "DIAGNOSTICS_TOPIC",
    "ESTIMATE_TOPIC",
    "PLAYER_NODE",
    "RECORDER_NODE",
    "YAML_TOPIC",
    "CalibratorNode",
    "CorrectorNode",
    "FlightConfigNode",
    "FlightParameters",
    "Listener",
    "PlayerNode",
    "RecorderNode",
    "Shutdown",
    "TrajectoryInput",
    "descriptor_for",
    "diagnostic_array",
    "latched_qos",
    "message_class",
    "parameter_value",
    "run_main",
    "spin_nodes",
    "start_ros",
    "stream_qos",
    "topic_qos",
    "trajectory_message_classes",
]
# --- end of exports ---
