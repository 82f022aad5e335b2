"""The workspace both levels see: an axis-aligned box in the world frame over the table.

One place for the bounds: the sim builds its scenes inside them, the
high-level agent voxelises them, RK-Diffuser crops its point cloud and
normalises positions to them. On a real robot the world frame is the
Panda's base frame raised by the table height (see the launch files).
"""

import numpy as np

from hdp_motion.panda import ROBOT_BASE

TABLE_TOP_Z = ROBOT_BASE[2]              # m: the arm stands on the table top
# The table, a solid block from the floor up (x -0.2..0.9, y -0.6..0.6): what the simulator
# builds and what a planner without perception avoids.
TABLE_CENTER_XY = (0.35, 0.0)            # m
TABLE_HALF_EXTENTS = (0.55, 0.6, TABLE_TOP_Z / 2)
# [[x_min, y_min, z_min], [x_max, y_max, z_max]], m
WORKSPACE = np.array([[0.2, -0.4, TABLE_TOP_Z], [0.8, 0.4, TABLE_TOP_Z + 0.6]])
# Points closer than this to the table top are the table itself.
ABOVE_TABLE = 0.005                      # m


def in_workspace(points, bounds=WORKSPACE, above_table: float = ABOVE_TABLE) -> np.ndarray:
    """(N,) bool: which of the (N, 3+) points lie in ``bounds`` and above the table."""
    xyz = np.asarray(points)[:, :3]
    lower = np.array(bounds[0], dtype=float)
    lower[2] += above_table
    return np.all((xyz >= lower) & (xyz <= bounds[1]), axis=1)


def fixed_size(points, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, C) rows drawn from the (N, C) ``points``: without replacement when N >= n,
    else all of them plus repeats. An empty cloud becomes n copies of the workspace centre."""
    points = np.asarray(points)
    if len(points) == 0:
        centre = np.zeros(points.shape[1] if points.ndim == 2 else 3, dtype=np.float32)
        centre[:3] = WORKSPACE.mean(axis=0)
        return np.repeat(centre[None], n, axis=0)
    if len(points) >= n:
        return points[rng.choice(len(points), n, replace=False)]
    extra = rng.choice(len(points), n - len(points), replace=True)
    return np.concatenate([points, points[extra]])
