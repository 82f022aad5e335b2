"""What every HDP node adds to rclpy: ros (init with the Fast DDS profile, Node, Status, run) and liveness."""
