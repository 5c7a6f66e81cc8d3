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
from lidarcal_ros.exports import lazy_exports  # noqa: E402 (after the DDS set-up)

_EXPORTS = {
    "calibrator": ("CALIBRATOR_PARAMETERS", "CalibratorNode"),
    "corrector": ("CORRECTOR_PARAMETERS", "CorrectorNode"),
    "flight_config": ("FlightConfigNode",),
    "parameters": ("FlightParameters", "Listener", "descriptor_for", "parameter_value"),
    "player": ("PLAYER_NODE", "PlayerNode", "SUITE_INPUTS", "message_class", "topic_qos"),
    "process": ("Shutdown", "run_main", "spin_nodes", "start_ros"),
    "rcl_functions": (
        "ALLOCATE", "DEALLOCATE", "RCL_RET_OK", "REALLOCATE", "SerializedMessage",
        "ZERO_ALLOCATE", "c_function", "take_rcl_error",
    ),
    "recorder": ("DEFAULT_TOPICS", "RECORDER_NODE", "RecorderNode"),
    "serialized_publisher": ("SerializedPublisher", "rcl_serialized_publish"),
    "serialized_subscription": ("SerializedSubscription", "rcl_serialized_take"),
    "suite": (
        "RUN_NODE", "SUITE_NODES", "SUITE_TOPIC", "SuiteMonitor", "SuiteNode", "node_is_up",
        "read_suite_state",
    ),
    "topics": (
        "DIAGNOSTICS_TOPIC", "ESTIMATE_TOPIC", "YAML_TOPIC", "diagnostic_array", "latched_qos",
        "stream_qos",
    ),
    "trajectory_input": ("TrajectoryInput", "trajectory_message_classes"),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
# --- end of exports ---
