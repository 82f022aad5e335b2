"""Kinematic refinement: pull the joint trajectory onto the pose trajectory.

The joint diffuser's trajectory is always feasible for the arm but only
approximately where the pose diffuser (whose goal is exactly the NBP) says
the end effector should be. Gradient steps on || poses - FK(joints) ||
through differentiable kinematics close that gap, with the two fixes the
official code lacks: the start waypoint is held (it is where the arm is)
and every step is projected back inside the joint limits. The last
waypoint, the NBP itself, is weighted up so the segment ends on it. A few
damped Gauss-Newton steps (the Jacobian's pseudo-inverse, also through
pytorch-kinematics) then settle every waypoint to sub-millimetre.
"""

from __future__ import annotations

import torch

from hdp_msgs_py import panda

from .kinematics import ROBOT_BASE, fk_pose, forward_kinematics, panda_chain, pose_error, quat_to_matrix

_LIMIT_MARGIN = 1e-3      # rad inside the limits
_PER_CM = 100.0
_MAX_NEWTON_STEP = 0.1    # rad per joint and Gauss-Newton step
# A joint trajectory that moves a joint further than this between two of its 64
# waypoints is not one motion of one arm configuration.
MAX_JOINT_STEP = 0.5      # rad
# ||R_a - R_b||_F^2 ~= 2 angle^2 for small angles; in degrees^2 after this scale.
_PER_RAD_SQUARED = (180 / torch.pi) ** 2


def refine(joints: torch.Tensor, poses: torch.Tensor, steps: int = 100, lr: float = 0.05,
           goal_weight: float = 10.0, newton_steps: int = 20) -> torch.Tensor:
    """joints (B, T, 7) rad, poses (B, T, 7) xyz + quat xyzw -> refined joints (B, T, 7).

    Adam on the per-waypoint squared translation error in cm plus the
    squared rotation-matrix distance scaled so 1 deg weighs about 1 cm; the
    step size decays (cosine) so the last steps settle to sub-mm. Waypoint 0
    is fixed and the limits are enforced after each step.
    """
    lower = torch.tensor(panda.LOWER, dtype=joints.dtype) + _LIMIT_MARGIN
    upper = torch.tensor(panda.UPPER, dtype=joints.dtype) - _LIMIT_MARGIN
    joints = continuous_start(joints.detach())
    start = joints[:, :1]
    free = joints[:, 1:].detach().clamp(lower, upper).requires_grad_(True)
    target_xyz, target_rot = poses[:, 1:, :3], quat_to_matrix(poses[:, 1:, 3:])
    weights = torch.ones(free.shape[1], dtype=joints.dtype)
    weights[-1] = goal_weight
    optimizer = torch.optim.Adam([free], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps, eta_min=lr * 0.02)
    with torch.enable_grad():
        for _ in range(steps):
            position, rotation = forward_kinematics(free)
            per_waypoint = ((position - target_xyz) * _PER_CM).square().sum(-1) + \
                _PER_RAD_SQUARED / 2 * (rotation - target_rot).square().sum((-2, -1))
            loss = (per_waypoint * weights).sum(-1).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()
            with torch.no_grad():
                free.clamp_(lower, upper)
    free = free.detach()
    for _ in range(newton_steps):
        free = _damped_least_squares_step(free, poses[:, 1:], lower, upper)
    return torch.cat([start, free], dim=1)


def _damped_least_squares_step(q, poses, lower, upper, damping: float = 1e-2):
    """One Gauss-Newton step per waypoint, q (B, T, 7) -> (B, T, 7): the Jacobian's damped
    pseudo-inverse applied to the 6-D pose error, then clamped into the limits. After the
    gradient phase the errors are small, and a few of these take them to sub-millimetre."""
    flat = q.reshape(-1, 7)
    jacobian, eef = panda_chain(q.dtype, str(q.device)).jacobian(flat, ret_eef_pose=True)   # (N, 6, 7), (N, 4, 4)
    position = eef[:, :3, 3] + torch.tensor(ROBOT_BASE, dtype=q.dtype)
    rotation = eef[:, :3, :3]
    target = poses.reshape(-1, 7)
    error_rotation = quat_to_matrix(target[:, 3:]) @ rotation.transpose(1, 2)
    # The rotation vector of the small error rotation (sin(angle) * axis; exact direction).
    skew = (error_rotation - error_rotation.transpose(1, 2)) / 2
    error = torch.cat([target[:, :3] - position, torch.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], 1)], 1)
    jjt = jacobian @ jacobian.transpose(1, 2) + damping ** 2 * torch.eye(6, dtype=q.dtype)
    step = (jacobian.transpose(1, 2) @ torch.linalg.solve(jjt, error[:, :, None]))[:, :, 0]
    # A far-off waypoint would otherwise jump to another arm configuration (a wrist
    # turned by 2 pi, an elbow flipped) that the executed motion then sweeps through.
    step = step * (_MAX_NEWTON_STEP / step.abs().amax(1, keepdim=True).clamp(min=_MAX_NEWTON_STEP))
    return (flat + step).clamp(lower, upper).reshape(q.shape)


def continuous_start(joints: torch.Tensor, max_step: float = MAX_JOINT_STEP) -> torch.Tensor:
    """joints (B, T, 7) -> the same, or for a trajectory that leaves its start waypoint by more
    than ``max_step`` rad in one step (it lies in another arm configuration than the arm is in),
    the start repeated: refinement then grows the motion out of where the arm is."""
    jump = torch.diff(joints, dim=1).abs().amax((1, 2))
    return torch.where((jump > max_step)[:, None, None], joints[:, :1].expand_as(joints), joints)


def goal_error(joints: torch.Tensor, goal_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) translation (m) and rotation (rad) errors of the last waypoint's FK against (B, 7) goals."""
    return pose_error(fk_pose(joints[:, -1]), goal_pose)
