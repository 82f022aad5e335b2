"""Joint waypoints -> a JointTrajectory the arm can execute.

What controller_node publishes and what the controller benchmark times: the
arm's current joints first, then the policy's waypoints, timed with a
trapezoidal profile inside the Panda's velocity limits (and a gentle
acceleration), and checked against the joint position limits so that no
trajectory outside them is ever handed to a controller.
"""

from __future__ import annotations

import numpy as np

from hdp_motion import panda
from hdp_motion.timing import path_velocities, time_parameterize
from hdp_msgs_py.conversions import build_joint_trajectory

# Fraction of the velocity limits a generated trajectory may use.
VELOCITY_SCALE = 0.5
_LIMIT_TOLERANCE = 1e-6     # rad
# An arm pressed against a limit (a hinge pushing the wrist) reads up to this far past it; a plan
# that starts where the arm is starts there (Table 1, open_door 1007: joint 7 read 0.0023 rad past).
PRESSED_TOLERANCE = 0.01    # rad


class TrajectoryError(ValueError):
    pass


def timed_waypoints(q_current, joints, velocity_scale: float = VELOCITY_SCALE,
                    limits: panda.JointLimits = panda.ROBOT_LIMITS['panda']) -> tuple[np.ndarray, np.ndarray]:
    """(positions (K + 1, 7) from q_current, times_from_start (K + 1,) s), within ``limits``
    (the robot's: panda.limits_for).

    Raises TrajectoryError for non-finite or out-of-limit waypoints. A waypoint may be as far past
    a limit as the arm already reads itself (up to PRESSED_TOLERANCE): it is where the arm is.
    """
    path = np.vstack([np.asarray(q_current, dtype=float), np.asarray(joints, dtype=float)])
    if path.ndim != 2 or path.shape[1] != 7 or not np.all(np.isfinite(path)):
        raise TrajectoryError(f'joint waypoints must be finite (K, 7), got shape {path.shape}')
    pressed = np.clip(np.maximum(limits.lower - path[0], path[0] - limits.upper), 0.0, PRESSED_TOLERANCE)
    excess = np.maximum(limits.lower - path[1:], path[1:] - limits.upper) - pressed
    if excess.max() > _LIMIT_TOLERANCE:
        joint = int(np.argmax(excess.max(axis=0)))
        raise TrajectoryError(f'a waypoint is {excess.max() + pressed[joint]:.4f} rad outside the joint position '
                              f'limits (joint {joint + 1}: [{limits.lower[joint]:.4f}, {limits.upper[joint]:.4f}])')
    # Onto the limits exactly: a controller refuses a point beyond them, point 0 included (the
    # soak saw panda_joint5 at 2.8973 + 1e-7 refused).
    path = np.clip(path, limits.lower, limits.upper)
    return path, time_parameterize(path, velocity_scale=velocity_scale, velocity_limits=limits.velocity)


def joint_trajectory(q_current, joints, joint_names=panda.ARM_JOINTS, velocity_scale: float = VELOCITY_SCALE,
                     stamp=None, limits: panda.JointLimits = panda.ROBOT_LIMITS['panda']):
    """trajectory_msgs/JointTrajectory through ``joints`` (K, 7) from ``q_current`` (7,)."""
    positions, times = timed_waypoints(q_current, joints, velocity_scale, limits)
    velocities = path_velocities(positions, times, velocity_scale, limits.velocity)
    return build_joint_trajectory(joint_names, positions, times, velocities, stamp=stamp)
