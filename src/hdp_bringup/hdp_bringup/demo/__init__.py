"""`hdp demo`: the whole graph on one task, watched from outside, with its figures.

One concern per module:
    cli         the command: arguments, ROS_DOMAIN_ID, starting and stopping the nodes, outputs
    watcher     the demo's node and the episode it drives (instruction -> the planner's outcome)
    episode_log what one episode looked like from outside: segments, frames, joint states
    cpu         CPU seconds per node process tree, from /proc
    figures     stage-time and CPU statistics over episodes, and their table
    media       the episode's GIF and trajectory plot
Nothing here is part of the control loop: the demo only publishes the instruction (and resets)
and listens.
"""
