"""HDP data: recorded episodes (rosbag2), keyframes, the tasks' instructions and the workspace."""
