"""ROS 2 nodes, thin rclpy wrappers around :mod:`lidarcal_ros.pipeline`.

Importing this package confines ROS 2 / DDS to this machine before any node module imports
rclpy; an environment already configured (a test's domain id, a launch file's) is kept.
"""

from lidarcal_ros.ros.environment import configure_ros_environment

configure_ros_environment()
