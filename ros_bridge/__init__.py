"""The ROS 2 bridge: the only package that imports rclpy."""
