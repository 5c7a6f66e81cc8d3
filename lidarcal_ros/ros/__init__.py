"""ROS 2 process support that must come before rclpy starts (this package never imports rclpy).

:mod:`lidarcal_ros.ros.environment` confines DDS to this machine. It sits below the two front
ends that talk to ROS, :mod:`lidarcal_ros.nodes` (which applies it on import) and the ROS
commands of :mod:`lidarcal_ros.cli`, and serves launch files, tests and benches alike, without
side effects on import.
"""

__all__: list[str] = []
