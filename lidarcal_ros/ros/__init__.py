"""ROS 2 process support that must come before rclpy starts (this package never imports rclpy).

:mod:`lidarcal_ros.ros.environment` confines DDS to this machine. It sits below the two front
ends that talk to ROS, :mod:`lidarcal_ros.nodes` (which applies it on import) and the ROS
commands of :mod:`lidarcal_ros.cli`, and serves launch files, tests and benches alike, without
side effects on import.
"""

# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---
from lidarcal_ros.exports import lazy_exports

_EXPORTS = {
    "environment": (
        "AUTO_DOMAIN_IDS", "DEFAULT_RMW", "FASTDDS_DEFAULT_SEGMENT_BYTES", "FASTDDS_RMWS",
        "MAX_DOMAIN_ID", "PACKAGE", "PACKAGE_DIR", "PROFILE_ENV", "PROFILE_NAME",
        "claim_domain_id", "configure_ros_environment", "domain_lock_dir",
        "loopback_profile_path", "pid_domain_id", "shared_memory_segment_bytes",
    ),
}
__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
# --- end of exports ---
