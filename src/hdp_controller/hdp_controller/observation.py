"""What a low-level policy observes: front-camera points in the workspace.

One path from depth to points for every consumer, so controller_node and the
training dataset (ROS messages) and the evaluation (a rendered camera,
hdp_eval.observation) all crop and subsample the cloud the same way: depth
(mm) -> world points -> keep those in ``workspace.WORKSPACE`` above the table
-> exactly ``n_points`` rows.
"""

from __future__ import annotations

import numpy as np

from hdp_data import workspace
from hdp_msgs_py import conversions

N_POINTS = 1024
# The training episodes were recorded at this resolution (`hdp collect --width 128 --height 96`).
CAMERA_SIZE = (128, 96)      # width, height


def workspace_points(points, n_points: int = N_POINTS, rng: np.random.Generator | None = None) -> np.ndarray:
    """(n_points, 3) float32: the (N, 3) world ``points`` inside the workspace, subsampled
    (or repeated) to a fixed size; an empty crop gives copies of the workspace centre."""
    points = np.asarray(points, dtype=np.float32)
    kept = points[workspace.in_workspace(points)]
    rng = rng if rng is not None else np.random.default_rng(0)
    return workspace.fixed_size(kept, n_points, rng).astype(np.float32)


def points_from_messages(depth_msg, info_msg, camera_to_world, n_points: int = N_POINTS,
                         rng: np.random.Generator | None = None) -> np.ndarray:
    """front_points from ROS messages: a 16UC1 (mm) or 32FC1 (m) depth Image, its CameraInfo,
    and the optical frame's pose in the world, as a (4, 4) matrix or a (stamped) Transform."""
    if not isinstance(camera_to_world, np.ndarray) and (
            hasattr(camera_to_world, 'transform') or hasattr(camera_to_world, 'translation')):
        camera_to_world = conversions.transform_to_matrix(camera_to_world)
    points = conversions.depth_image_to_points(depth_msg, info_msg, camera_to_world)
    return workspace_points(points, n_points, rng)
