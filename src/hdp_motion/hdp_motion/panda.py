"""Franka Panda facts every package shares: where it stands, joint names, limits, the gripper.

Limits are the real robot's (Franka datasheet), which are slightly tighter
than pybullet_data's URDF; everything clamps to these.
"""

from typing import NamedTuple

import numpy as np

# The arm's link 0 in the world frame, facing +x: it stands on the table top.
ROBOT_BASE = (0.0, 0.0, 0.75)       # m
# The end effector of every pose (next-best poses, IK, kinematics): 0.105 m beyond the hand flange.
EE_LINK = 'panda_grasptarget'

ARM_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
FINGER_JOINTS = ('panda_finger_joint1', 'panda_finger_joint2')
# The same in pybullet_data's franka_panda/panda.urdf, as PyBullet numbers them: joint indices of
# panda_joint1..7 and of the two fingers, link index of EE_LINK. The simulator and the planners share them.
ARM_JOINT_IDS = tuple(range(7))
FINGER_JOINT_IDS = (9, 10)
EE_LINK_ID = 11

# rad
LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
# rad/s
VELOCITY_LIMITS = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
# rad/s^2
ACCELERATION_LIMITS = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])

# A comfortable home pose, inside every limit.
HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])

FINGER_MAX = 0.04           # m per finger: gripper opening = 2 x finger position
GRIPPER_OPEN_WIDTH = 0.08   # m
OPEN_MARGIN = 0.005         # m below the open width that still reads as open


def reads_open(width: float) -> bool:
    """The gripper's state from its fingers' width (m): open when (nearly) fully open. A grasped
    object is narrower than the open width, so fingers closed on a handle read as closed."""
    return width >= GRIPPER_OPEN_WIDTH - OPEN_MARGIN


class JointLimits(NamedTuple):
    """Position (rad) and velocity (rad/s) limits of the seven arm joints, each (7,)."""
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray


# Per robot type, from franka_description (robots/fer and robots/fr3/joint_limits.yaml): the
# Panda (FER) and the FR3 share kinematics but not limits (the FR3's joint 6 cannot go below
# 0.5445 rad, its joint 1 stops at +-2.7437, its joints are faster). Models and the simulator
# are the Panda's; what goes to a robot is checked, refined and timed against its own limits.
ROBOT_LIMITS = {
    'panda': JointLimits(LOWER, UPPER, VELOCITY_LIMITS),
    'fr3': JointLimits(np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
                       np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
                       np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])),
}


def limits_for(robot_type: str) -> JointLimits:
    """The joint limits of 'panda' or 'fr3'; ValueError naming the known types otherwise."""
    if robot_type not in ROBOT_LIMITS:
        raise ValueError(f'unknown robot type {robot_type!r}; robot types: {", ".join(ROBOT_LIMITS)}')
    return ROBOT_LIMITS[robot_type]


def joint_names(prefix: str = 'panda') -> tuple[str, ...]:
    """Arm joint names for a robot prefix ('panda', or 'fr3' for the FR3)."""
    return tuple(name.replace('panda', prefix, 1) for name in ARM_JOINTS)


def finger_joint_names(prefix: str = 'panda') -> tuple[str, ...]:
    """Finger joint names for a robot prefix ('panda', or 'fr3' for the FR3)."""
    return tuple(name.replace('panda', prefix, 1) for name in FINGER_JOINTS)


def within_limits(q, tol: float = 1e-6, limits: JointLimits = ROBOT_LIMITS['panda']) -> bool:
    q = np.asarray(q, dtype=float)
    return bool(np.all(q >= limits.lower - tol) and np.all(q <= limits.upper + tol))
