"""ROS 2 nodes: thin rclpy wrappers around :mod:`lidarcal_ros.pipeline`."""
