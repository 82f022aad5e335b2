"""The next-best pose as RViz and Foxglove draw it: a TF frame and an arrow along the hand's
approach, green for a gripper that opens there, red for one that closes."""

from __future__ import annotations

import numpy as np

from hdp_motion import panda
from hdp_motion.rotations import quat_to_matrix
from hdp_msgs_py.msg import ColorRGBA, Marker, Point, Transform, TransformStamped, Vector3

NBP_FRAME_ID = 'hdp_next_best_pose'
ARROW_LENGTH = 0.10                 # m, ending where the fingertips go
_OPEN, _CLOSE = ColorRGBA(r=0.1, g=0.8, b=0.2, a=0.9), ColorRGBA(r=0.9, g=0.15, b=0.1, a=0.9)


def nbp_transform(nbp) -> TransformStamped:
    """geometry_msgs/PoseStamped (in 'world') -> world -> hdp_next_best_pose, same stamp."""
    p, q = nbp.pose.position, nbp.pose.orientation
    return TransformStamped(header=nbp.header, child_frame_id=NBP_FRAME_ID, transform=Transform(
        translation=Vector3(x=p.x, y=p.y, z=p.z), rotation=q))


def nbp_marker(nbp, gripper_open: bool) -> Marker:
    """An arrow from ARROW_LENGTH behind the pose, along the hand's z (approach), to the pose."""
    p, q = nbp.pose.position, nbp.pose.orientation
    tip = np.array([p.x, p.y, p.z])
    tail = tip - ARROW_LENGTH * quat_to_matrix([q.x, q.y, q.z, q.w])[:, 2]
    return Marker(header=nbp.header, ns='hdp', id=0, type=Marker.ARROW, action=Marker.ADD,
                  points=[Point(x=float(x), y=float(y), z=float(z)) for x, y, z in (tail, tip)],
                  scale=Vector3(x=0.01, y=0.02, z=0.03), color=_OPEN if gripper_open else _CLOSE,
                  frame_locked=False)


def opens(gripper_goal) -> bool:
    """The planner's gripper goal (sensor_msgs/JointState, width in m) -> whether it opens."""
    return gripper_goal.position[0] >= panda.GRIPPER_OPEN_WIDTH / 2
