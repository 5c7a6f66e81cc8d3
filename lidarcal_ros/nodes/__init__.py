"""ROS 2 nodes: thin rclpy wrappers around :mod:`lidarcal_ros.pipeline`.

Importing this package confines ROS 2 / DDS to this machine
(:func:`lidarcal_ros.ros.environment.configure_ros_environment`) before any node module imports
rclpy: ``ros2 run lidarcal_ros <node>`` and ``lidarcal run`` start rclpy only through these
modules. An environment already configured (a test's domain id, a launch file's settings) is
kept.
"""

from lidarcal_ros.ros.environment import configure_ros_environment

configure_ros_environment()
