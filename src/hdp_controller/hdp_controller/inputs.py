"""What controller_node takes in, validated: NBPs, gripper goals, joint states, camera extrinsics,
and the front camera's depth, filtered when a depth filter is on.

Each reader returns plain values or raises with a reason a person can act on; a refused NBP
goes back to the planner as 'failed: <reason>' (SegmentRefused).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hdp_motion import panda
from hdp_data import workspace
from hdp_data.depth_filters import DepthFilter, FilterSettings
from hdp_msgs_py import conversions, topics


class SegmentRefused(ValueError):
    """Why a segment cannot run; goes back to the planner as 'failed: <reason>'.

    report: how it was planned (segment_planning.PlanReport) when planning refused it."""

    def __init__(self, reason: str, report=None):
        super().__init__(reason)
        self.report = report


class ArmState(NamedTuple):
    q: np.ndarray              # (7,) rad, arm joint order
    qd: np.ndarray             # (7,) rad/s
    gripper_width: float       # m between the fingers


def validate_nbp(msg) -> np.ndarray:
    """(7,) xyz (m) + unit quaternion xyzw of a PoseStamped NBP, or SegmentRefused saying why."""
    if msg.header.frame_id != topics.NBP_FRAME:
        raise SegmentRefused(f"frame_id {msg.header.frame_id!r} is not {topics.NBP_FRAME!r} "
                             '(the controller takes NBPs in the world frame only)')
    try:
        xyz, quat = conversions.pose_to_xyz_quat(msg)
    except ValueError as err:          # NaN/inf, zero or non-unit quaternion
        raise SegmentRefused(f'invalid pose: {err}') from None
    if not workspace.in_workspace(xyz[None])[0]:
        low, high = workspace.WORKSPACE
        raise SegmentRefused(
            f'position ({xyz[0]:.3f}, {xyz[1]:.3f}, {xyz[2]:.3f}) m is outside the workspace '
            f'x [{low[0]}, {high[0]}], y [{low[1]}, {high[1]}], '
            f'z [{low[2] + workspace.ABOVE_TABLE:.3f}, {high[2]}]')
    return np.concatenate([xyz, quat])


def gripper_goal(msg) -> bool:
    """Whether a gripper goal (JointState, name [GRIPPER_GOAL_JOINT], position [width m]) opens."""
    if list(msg.name) != [topics.GRIPPER_GOAL_JOINT] or len(msg.position) != 1:
        raise ValueError(f'a gripper goal names [{topics.GRIPPER_GOAL_JOINT!r}] with one position, '
                         f'got names {list(msg.name)} and {len(msg.position)} positions')
    width = float(msg.position[0])
    if not 0.0 <= width <= panda.GRIPPER_OPEN_WIDTH + 1e-6:      # also refuses NaN
        raise ValueError(f'gripper goal width must be within [0, {panda.GRIPPER_OPEN_WIDTH}] m, got {width}')
    return width >= panda.GRIPPER_OPEN_WIDTH / 2


def arm_state(msg, arm_joints, finger_joints) -> ArmState:
    """The arm (by name, any order) and gripper width of a sensor_msgs/JointState."""
    names = list(msg.name)
    missing = [n for n in (*arm_joints, *finger_joints) if n not in names]
    if missing:
        raise ValueError(f'joint state lacks {missing}')
    position = np.asarray(msg.position, dtype=float)
    velocity = np.asarray(msg.velocity, dtype=float)
    arm = [names.index(n) for n in arm_joints]
    qd = velocity[arm] if len(velocity) == len(names) else np.zeros(len(arm))
    return ArmState(position[arm], qd, float(sum(position[names.index(n)] for n in finger_joints)))


def world_transform(transforms: dict, frame: str):
    """The TransformStamped world -> ``frame`` among /tf_static's (child frame -> transform)."""
    transform = transforms.get(frame)
    if transform is None:
        raise SegmentRefused(f"no /tf_static transform to the camera frame {frame!r} yet")
    if transform.header.frame_id != topics.NBP_FRAME:
        raise SegmentRefused(f"/tf_static gives {frame!r} in {transform.header.frame_id!r}, "
                             f"not {topics.NBP_FRAME!r}")
    return transform


class FilteredDepth:
    """The front camera's depth images through a RealSense post-processing chain
    (hdp_data.depth_filters), for SegmentController.on_depth: feed it every camera_info and depth
    image as they come, and hand on what ``filtered`` returns."""

    def __init__(self, settings: FilterSettings):
        self.depth_filter = DepthFilter(settings)
        self.info = None

    def on_camera_info(self, msg) -> None:
        self.info = msg

    def filtered(self, msg):
        """The depth Image filtered (its header, 16UC1 mm), or None before the first camera_info:
        the chain needs the focal length. ValueError when the depth is not 16UC1."""
        if self.info is None:
            return None
        depth = self.depth_filter.apply(conversions.image_to_numpy(msg), float(self.info.k[0]),
                                        conversions.time_to_ns(msg.header.stamp))
        return conversions.numpy_to_image(depth, '16UC1', msg.header)
