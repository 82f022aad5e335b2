"""What a low-level policy observes, taken from the simulator: a rendered front camera's points
and a PandaWorld's arm state, made into a request as controller_node makes it from messages."""

from __future__ import annotations

import numpy as np

from hdp_controller.inputs import ArmState
from hdp_controller.low_level import SegmentRequest
from hdp_controller.observation import CAMERA_SIZE, N_POINTS, workspace_points
from hdp_controller.segment_planning import segment_request as planning_request
from hdp_data.depth_filters import DepthFilter
from hdp_motion import panda
from hdp_msgs_py import conversions
from hdp_sim_bridge.cameras import CameraRig, default_cameras


def front_camera(width: int = CAMERA_SIZE[0], height: int = CAMERA_SIZE[1]):
    """The sim's "front" D415 at ``width`` x ``height``."""
    return default_cameras(width, height)['front']


def front_points(world_or_client, camera, n_points: int = N_POINTS,
                 rng: np.random.Generator | None = None, rig: CameraRig | None = None,
                 frame: int = 0, depth_filter: DepthFilter | None = None) -> np.ndarray:
    """Render ``camera`` in a PandaWorld (or its BulletClient) -> (n_points, 3) float32 world points.

    rig: a CameraRig holding ``camera``: the render is its frame number ``frame`` (sensor model,
    calibration error), unprojected through the camera's nominal intrinsics and pose as a
    subscriber does. None: the ideal render. depth_filter: the camera's post-processing chain,
    which the depth goes through first (as controller_node's filtered depth); None: none."""
    client = getattr(world_or_client, 'client', world_or_client)
    _, depth_mm = rig.render(client, camera.name, frame) if rig is not None else camera.render(client)
    if depth_filter is not None:
        depth_mm = depth_filter.apply(depth_mm, camera.intrinsics.fx, frame)
    points = conversions.depth_to_points(depth_mm * 0.001, camera.intrinsics, camera.camera_to_world)
    return workspace_points(points, n_points, rng)


def segment_request(world, goal_pose, goal_gripper_open: bool, points) -> SegmentRequest:
    """A SegmentRequest from a PandaWorld's current state towards ``goal_pose`` (7,) xyz + quat xyzw,
    made as controller_node makes it from /joint_states (segment_planning.segment_request: the
    gripper's state read from the fingers, the start pose by FK)."""
    state = ArmState(world.joint_positions(), world.joint_velocities(), world.gripper_width())
    return planning_request(state, panda.reads_open(state.gripper_width), goal_pose, goal_gripper_open,
                            np.asarray(points, dtype=np.float32))
