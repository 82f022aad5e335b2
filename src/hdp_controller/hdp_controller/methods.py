"""controller_node's low-level methods by name: the one list that policy.load_policy, controller_node,
`hdp launch`, `hdp demo` and `hdp eval low-level` accept. Imports nothing, so a command line can check a
method without loading torch."""

METHODS = ('rkd', 'planner', 'planner_rrt', 'pose_ik', 'joint')
LEARNED = ('rkd', 'pose_ik', 'joint')        # they read the checkpoint and the camera's points
