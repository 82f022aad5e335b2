"""What every HDP node adds to rclpy: ros (init with the Fast DDS profile, Node, Status, run), liveness
and shm (the shared memory of dead Fast DDS processes, removed)."""
