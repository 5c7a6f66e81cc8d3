"""Numerics of lidarcal_ros: numpy, scipy and numba only; no files, no rclpy."""
