"""Pure numeric core of lidarcal_ros: numpy and scipy only, never rclpy."""
