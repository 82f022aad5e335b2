"""What robot_state_publisher gives a real arm, from the simulated one: /robot_description
and the TF of every link, so RViz and Foxglove can draw the robot.

As robot_state_publisher does: fixed joints (and `world -> panda_link0`, the arm's mounting)
are static transforms, movable joints go out on /tf with every joint state, each as
parent link -> child link.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import pybullet
import pybullet_data

from hdp_motion.panda import ROBOT_BASE
from hdp_motion.rotations import quat_to_matrix
from hdp_msgs_py.conversions import matrix_to_transform
from hdp_msgs_py.msg import Header, TransformStamped

WORLD_FRAME = 'world'
BASE_LINK = 'panda_link0'
URDF = pathlib.Path(pybullet_data.getDataPath()) / 'franka_panda' / 'panda.urdf'


def robot_description() -> str:
    """The simulated Panda's URDF, its meshes as file:// URIs a local RViz or Foxglove loads."""
    return URDF.read_text().replace('package://meshes/', (URDF.parent / 'meshes').as_uri() + '/')


@dataclasses.dataclass(frozen=True)
class _Joint:
    index: int            # pybullet joint (= child link) index
    parent_index: int     # pybullet link index of the parent link, -1 for the base
    parent: str
    child: str
    fixed: bool


class LinkTransforms:
    """Parent -> child transforms of the robot's links, read from PyBullet's link frames."""

    def __init__(self, client: int, robot: int):
        self._client, self.robot = client, robot
        infos = [pybullet.getJointInfo(robot, j, physicsClientId=client)
                 for j in range(pybullet.getNumJoints(robot, physicsClientId=client))]
        names = {-1: BASE_LINK} | {info[0]: info[12].decode() for info in infos}
        self.joints = [_Joint(info[0], info[16], names[info[16]], names[info[0]], info[2] == pybullet.JOINT_FIXED)
                       for info in infos]

    def _world_pose(self, link: int) -> np.ndarray:
        """4x4 pose of a link's URDF frame in the world."""
        pose = np.eye(4)
        if link == -1:        # the base link's frame: where the arm is mounted, unrotated
            pose[:3, 3] = ROBOT_BASE
            return pose
        state = pybullet.getLinkState(self.robot, link, computeForwardKinematics=True,
                                      physicsClientId=self._client)
        pose[:3, :3], pose[:3, 3] = quat_to_matrix(state[5]), state[4]
        return pose

    def _stamped(self, parent: str, child: str, matrix: np.ndarray, stamp) -> TransformStamped:
        return TransformStamped(header=Header(stamp=stamp, frame_id=parent), child_frame_id=child,
                                transform=matrix_to_transform(matrix))

    def _joint_transforms(self, fixed: bool, stamp) -> list[TransformStamped]:
        joints = [j for j in self.joints if j.fixed == fixed]
        # Each link's pose read once: a parent (the hand) serves several children (both fingers).
        poses = {link: self._world_pose(link) for j in joints for link in (j.parent_index, j.index)}
        return [self._stamped(j.parent, j.child, np.linalg.inv(poses[j.parent_index]) @ poses[j.index], stamp)
                for j in joints]

    def static(self, stamp) -> list[TransformStamped]:
        """`world -> panda_link0` and every fixed joint (for /tf_static)."""
        return [self._stamped(WORLD_FRAME, BASE_LINK, self._world_pose(-1), stamp),
                *self._joint_transforms(True, stamp)]

    def moving(self, stamp) -> list[TransformStamped]:
        """Every movable joint, now (for /tf)."""
        return self._joint_transforms(False, stamp)
