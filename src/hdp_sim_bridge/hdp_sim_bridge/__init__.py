"""PyBullet stand-in for the Panda and two D415 cameras, and the graph launch files."""
