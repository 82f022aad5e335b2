"""What a low-level policy observes: front-camera points in the workspace and the arm state.

One path from depth to points for every consumer, so the evaluation (a
rendered camera), controller_node and the training dataset (ROS messages)
all crop and subsample the cloud the same way: depth (mm) -> world points ->
keep those in ``workspace.WORKSPACE`` above the table -> exactly
``n_points`` rows.
"""

from __future__ import annotations

import numpy as np

from hdp_msgs_py import conversions, workspace

from .low_level import SegmentRequest

N_POINTS = 1024
# The training episodes were recorded at this resolution (`hdp collect --width 128 --height 96`).
CAMERA_SIZE = (128, 96)      # width, height


def front_camera(width: int = CAMERA_SIZE[0], height: int = CAMERA_SIZE[1]):
    """The sim's "front" D415 at ``width`` x ``height``."""
    from hdp_sim_bridge.cameras import default_cameras
    return default_cameras(width, height)['front']


def workspace_points(points, n_points: int = N_POINTS, rng: np.random.Generator | None = None) -> np.ndarray:
    """(n_points, 3) float32: the (N, 3) world ``points`` inside the workspace, subsampled
    (or repeated) to a fixed size; an empty crop gives copies of the workspace centre."""
    points = np.asarray(points, dtype=np.float32)
    kept = points[workspace.in_workspace(points)]
    rng = rng if rng is not None else np.random.default_rng(0)
    return workspace.fixed_size(kept, n_points, rng).astype(np.float32)


def front_points(world_or_client, camera, n_points: int = N_POINTS,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """Render ``camera`` in a PandaWorld (or its BulletClient) -> (n_points, 3) float32 world points."""
    client = getattr(world_or_client, 'client', world_or_client)
    _, depth_mm = camera.render(client)
    points = conversions.depth_to_points(depth_mm * 0.001, camera.intrinsics, camera.camera_to_world)
    return workspace_points(points, n_points, rng)


def points_from_messages(depth_msg, info_msg, camera_to_world, n_points: int = N_POINTS,
                         rng: np.random.Generator | None = None) -> np.ndarray:
    """front_points from ROS messages: a 16UC1 (mm) or 32FC1 (m) depth Image, its CameraInfo,
    and the optical frame's pose in the world, as a (4, 4) matrix or a (stamped) Transform."""
    if not isinstance(camera_to_world, np.ndarray) and (
            hasattr(camera_to_world, 'transform') or hasattr(camera_to_world, 'translation')):
        camera_to_world = conversions.transform_to_matrix(camera_to_world)
    points = conversions.depth_image_to_points(depth_msg, info_msg, camera_to_world)
    return workspace_points(points, n_points, rng)


def segment_request(world, goal_pose, goal_gripper_open: bool, points) -> SegmentRequest:
    """A SegmentRequest from a PandaWorld's current state towards ``goal_pose`` (7,) xyz + quat xyzw."""
    xyz, quat = world.ee_pose()
    return SegmentRequest(
        q=world.joint_positions(), qd=world.joint_velocities(),
        gripper_width=world.gripper_width(),
        # The commanded state, not the measured width: fingers closed on a handle are not
        # fully shut, and the keyframe rule (and so the training data) uses the command.
        gripper_open=bool(world._gripper_open),
        start_pose=np.concatenate([xyz, quat]),
        goal_pose=np.asarray(goal_pose, dtype=float).reshape(7),
        points=np.asarray(points, dtype=np.float32),
        goal_gripper_open=bool(goal_gripper_open))
