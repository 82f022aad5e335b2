"""Kinematic refinement: pull the joint trajectory onto the pose trajectory.

The joint diffuser's trajectory is always feasible for the arm but only
approximately where the pose diffuser (whose goal is exactly the NBP) says
the end effector should be. Gradient steps on || poses - FK(joints) ||
through differentiable kinematics close that gap, with the two fixes the
official code lacks: the start waypoint is held (it is where the arm is)
and every step is projected back inside the joint limits. The last
waypoint, the NBP itself, is weighted up so the segment ends on it.
"""

from __future__ import annotations

import torch

from hdp_msgs_py import panda

from .kinematics import forward_kinematics, pose_error, quat_to_matrix, fk_pose

_LIMIT_MARGIN = 1e-3      # rad inside the limits
_PER_CM = 100.0
# ||R_a - R_b||_F^2 ~= 2 angle^2 for small angles; in degrees^2 after this scale.
_PER_RAD_SQUARED = (180 / torch.pi) ** 2


def refine(joints: torch.Tensor, poses: torch.Tensor, steps: int = 100, lr: float = 0.01,
           goal_weight: float = 10.0) -> torch.Tensor:
    """joints (B, T, 7) rad, poses (B, T, 7) xyz + quat xyzw -> refined joints (B, T, 7).

    Adam on the per-waypoint squared translation error in cm plus the
    squared rotation-matrix distance scaled so 1 deg weighs about 1 cm; the
    step size decays (cosine) so the last steps settle to sub-mm. Waypoint 0
    is fixed and the limits are enforced after each step.
    """
    lower = torch.tensor(panda.LOWER, dtype=joints.dtype) + _LIMIT_MARGIN
    upper = torch.tensor(panda.UPPER, dtype=joints.dtype) - _LIMIT_MARGIN
    start = joints[:, :1].detach()
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
    return torch.cat([start, free.detach()], dim=1)


def goal_error(joints: torch.Tensor, goal_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) translation (m) and rotation (rad) errors of the last waypoint's FK against (B, 7) goals."""
    return pose_error(fk_pose(joints[:, -1]), goal_pose)
