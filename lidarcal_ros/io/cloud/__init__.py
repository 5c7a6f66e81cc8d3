"""PointCloud2 and the other ROS messages as numpy and CDR bytes, without rclpy."""
