"""What a process must set before rclpy starts (DDS confined to this machine); never rclpy."""
