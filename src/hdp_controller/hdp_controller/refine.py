"""Kinematic refinement: pull the joint trajectory onto the pose trajectory.

The joint diffuser's trajectory is always feasible for the arm but only
approximately where the pose diffuser (whose goal is exactly the NBP) says
the end effector should be. Refinement closes that gap with damped
Gauss-Newton steps on || poses - FK(joints) || through differentiable
kinematics (the Jacobian's damped pseudo-inverse, from pytorch-kinematics),
every waypoint at once. Beyond the paper and its official code:

- the start waypoint is held (it is where the arm is) and every step is
  clamped inside the joint limits;
- a joint held at its limit is taken out of the step, so the other six
  make up for it instead of the error staying;
- both sampled trajectories are smoothed first (ends held): the diffusers'
  samples wobble from waypoint to waypoint, and a timed path slows at every
  turn, so an unsmoothed one executes several times slower;
- the Panda hand's two fingers are alike, so a grasp turned half a turn about
  the approach axis is the same grasp. When the joint diffuser ends nearer
  that turned goal, the rotation targets turn to it, spread along the
  trajectory, instead of winding the wrist back through half a turn.
- a waypoint left stuck against a joint limit is refined again from its
  refined predecessor (``_restart_stuck``).

Why not Adam on the pose loss (this module's first version)? Adam scales
every joint's step alike, so the arm also moves where the loss does not care
(the null space) and winds the wrist the short way round into its limit: on
validation seed reach_target 901 it stopped 11 cm and 26 deg short with
joint 7 at its limit, where these steps reach the turned goal exactly.
"""

from __future__ import annotations

import functools

import torch

from hdp_motion import panda
from hdp_motion.kinematics import (continuous_quats, fk_pose, forward_kinematics, matrix_to_quat, panda_chain,
                                   pose_error, quat_to_matrix)
from hdp_motion.panda import ROBOT_BASE

_LIMIT_MARGIN = 1e-3      # rad inside the limits
# A joint trajectory that moves a joint further than this between two of its 64
# waypoints is not one motion of one arm configuration.
MAX_JOINT_STEP = 0.5      # rad
# A refined waypoint further than this from its target is stuck.
STUCK_TRANSLATION = 0.005  # m
STUCK_ROTATION = 0.05      # rad
_RESTART_STEPS = 10        # from a predecessor millimetres away, a few steps converge
_TRACK_STEPS = 10          # track(): the same, for every waypoint
_TRACK_CENTRING = 0.05     # track(): gain of the null-space step towards mid-range (open_box 925/929)
# Passes of a [1, 2, 1] / 4 filter over the sampled trajectories before refinement.
SMOOTHING_PASSES = 4


def _half_turn(dtype: torch.dtype) -> torch.Tensor:
    """Rz(pi): the hand turned half a turn about its approach (z) axis."""
    return torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=dtype))


def refine(joints: torch.Tensor, poses: torch.Tensor, steps: int = 50, max_step: float = 0.1,
           damping: float = 1e-2, smoothing: int = SMOOTHING_PASSES,
           limits: panda.JointLimits = panda.ROBOT_LIMITS['panda']) -> torch.Tensor:
    """joints (B, T, 7) rad, poses (B, T, 7) xyz + quat xyzw -> refined joints (B, T, 7).

    Both are first smoothed by ``smoothing`` filter passes; then ``steps``
    Gauss-Newton steps, each at most ``max_step`` rad per joint: a far-off
    waypoint would otherwise jump to another arm configuration that the
    executed motion then sweeps through. Every waypoint after the start stays inside ``limits``
    (the robot's, panda.limits_for).
    """
    lower = torch.tensor(limits.lower, dtype=joints.dtype) + _LIMIT_MARGIN
    upper = torch.tensor(limits.upper, dtype=joints.dtype) - _LIMIT_MARGIN
    joints = smooth(continuous_start(joints.detach()), smoothing)
    poses = smooth_poses(poses.detach(), smoothing)
    start, sampled = joints[:, :1], joints[:, 1:].clamp(lower, upper)
    rotation = hand_symmetric_targets(quat_to_matrix(poses[:, 1:, 3:]), forward_kinematics(sampled)[1])
    targets = (poses[:, 1:, :3], rotation)
    solve = functools.partial(_gauss_newton, steps=steps, max_step=max_step, damping=damping, limits=(lower, upper))
    q = solve(sampled.reshape(-1, 7), _flat(targets)).reshape(sampled.shape)
    return _restart_stuck(torch.cat([start, q], dim=1), targets, solve)


def track(start: torch.Tensor, poses: torch.Tensor, steps: int = _TRACK_STEPS, max_step: float = 0.1,
          damping: float = 1e-2, limits: panda.JointLimits = panda.ROBOT_LIMITS['panda']) -> torch.Tensor:
    """start (B, 7) rad, poses (B, T, 7) -> joints (B, T, 7) from ``start``: the (smoothed) pose
    trajectory followed waypoint by waypoint, each solved from its solved predecessor, so the
    whole path stays in the start's arm configuration. T - 1 solves one after another, where
    ``refine`` solves every waypoint at once from the joint sample's configuration. Least-motion
    steps alone let a long path drift in the null space into a joint limit, so each step also
    moves the joints towards the middle of their ranges in the Jacobian's null space, where the
    pose does not change (``_TRACK_CENTRING``): on open_box validation seeds 925 and 929 the
    lid's lift then ends 1.1 and 2.3 cm from its NBP where it stalled 25 and 23 cm short.
    """
    lower = torch.tensor(limits.lower, dtype=start.dtype) + _LIMIT_MARGIN
    upper = torch.tensor(limits.upper, dtype=start.dtype) - _LIMIT_MARGIN
    poses = smooth_poses(poses.detach(), SMOOTHING_PASSES)
    held = start.detach()[:, None].expand(-1, poses.shape[1] - 1, 7)
    rotation = hand_symmetric_targets(quat_to_matrix(poses[:, 1:, 3:]), forward_kinematics(held)[1])
    joints = [start.detach()]
    for t in range(poses.shape[1] - 1):
        joints.append(_gauss_newton(joints[-1], (poses[:, t + 1, :3], rotation[:, t]), steps, max_step, damping,
                                    (lower, upper), centring=_TRACK_CENTRING))
    return torch.stack(joints, 1)


def pull_to_goal(joints: torch.Tensor, goal_pose: torch.Tensor, steps: int = 10, max_step: float = 0.1,
                 damping: float = 1e-2, limits: panda.JointLimits = panda.ROBOT_LIMITS['panda']) -> torch.Tensor:
    """joints (B, T, 7), goal_pose (B, 7) -> joints whose last waypoint is solved onto the goal
    (or the same grasp turned half a turn, whichever is nearer) by ``steps`` Gauss-Newton steps
    from where it was, the correction spread along the trajectory as a ramp from zero at the
    start: the end moves, the shape stays. The joint diffuser's goal guidance (RKDiffuser.sample)."""
    lower = torch.tensor(limits.lower, dtype=joints.dtype) + _LIMIT_MARGIN
    upper = torch.tensor(limits.upper, dtype=joints.dtype) - _LIMIT_MARGIN
    last = joints[:, -1].clamp(lower, upper)
    goal = goal_pose.to(joints.dtype)
    rotation = hand_symmetric_targets(quat_to_matrix(goal[:, None, 3:]), forward_kinematics(last[:, None])[1])[:, 0]
    solved = _gauss_newton(last, (goal[:, :3], rotation), steps, max_step, damping, (lower, upper))
    ramp = torch.linspace(0.0, 1.0, joints.shape[1], dtype=joints.dtype)[None, :, None]
    return joints + ramp * (solved - joints[:, -1])[:, None]


def _gauss_newton(q, targets, steps: int, max_step: float, damping: float, limits,
                  centring: float = 0.0) -> torch.Tensor:
    """q (N, 7) -> after ``steps`` bounded steps towards targets ((N, 3) m, (N, 3, 3)); see
    _gauss_newton_step for ``centring``."""
    for _ in range(steps):
        step = _gauss_newton_step(q, targets, damping, limits, centring)
        q = (q + step * (max_step / step.abs().amax(1, keepdim=True).clamp(min=max_step))).clamp(*limits)
    return q


def _restart_stuck(path: torch.Tensor, targets, solve) -> torch.Tensor:
    """path (B, T, 7) from the start; targets ((B, T - 1, 3), (B, T - 1, 3, 3)) for path[:, 1:].

    Each waypoint is refined on its own, so one can end stuck far from its target against a
    joint limit while its neighbours are on theirs (open_box validation seed 911: every
    waypoint on the lid's arc but the last, 23 cm off with joints 5 and 6 at their limits).
    Such a waypoint, in path order, is refined again from its refined predecessor,
    millimetres away along the path; the result is kept if it ends nearer its target.

    A waypoint that reaches its target in another arm configuration than its predecessor's
    (a jump the motion sweeps through) is left as it is: continuing the first configuration
    instead ran later open_door segments into joint limits (on 10 validation seeds, 902-928,
    1 episode succeeded that way and 7 without).
    """
    path = path.clone()
    batch, length = targets[0].shape[:2]
    miss = _miss(path[:, 1:].reshape(-1, 7), _flat(targets)).reshape(batch, length)
    for b, t in (miss > 1).nonzero().tolist():
        target = (targets[0][b, t:t + 1], targets[1][b, t:t + 1])
        again = solve(path[b, t:t + 1], target, steps=_RESTART_STEPS)
        if _miss(again, target)[0] < miss[b, t]:
            path[b, t + 1] = again[0]
    return path


def _miss(q: torch.Tensor, targets) -> torch.Tensor:
    """(N,) the pose error in units of STUCK_TRANSLATION and STUCK_ROTATION, the larger."""
    error = _pose_error(q, targets)[0]
    return torch.maximum(error[:, :3].norm(dim=1) / STUCK_TRANSLATION, error[:, 3:].norm(dim=1) / STUCK_ROTATION)


def _flat(targets):
    """((B, T, 3), (B, T, 3, 3)) -> ((B T, 3), (B T, 3, 3))."""
    return targets[0].reshape(-1, 3), targets[1].reshape(-1, 3, 3)


def smooth(path: torch.Tensor, passes: int) -> torch.Tensor:
    """(B, T, D) -> the same after ``passes`` of a [1, 2, 1] / 4 filter along T, the ends held
    (where the arm is and the goal). Four passes average over about three waypoints each side."""
    for _ in range(passes):
        path = torch.cat([path[:, :1], 0.25 * path[:, :-2] + 0.5 * path[:, 1:-1] + 0.25 * path[:, 2:],
                          path[:, -1:]], dim=1)
    return path


def smooth_poses(poses: torch.Tensor, passes: int) -> torch.Tensor:
    """(B, T, 7) xyz + quat xyzw -> smoothed the same way, each quaternion first put on its
    predecessor's side (q and -q are one rotation) and renormalised after."""
    smoothed = smooth(torch.cat([poses[..., :3], continuous_quats(poses[..., 3:])], -1), passes)
    return torch.cat([smoothed[..., :3], torch.nn.functional.normalize(smoothed[..., 3:], dim=-1)], -1)


def _gauss_newton_step(q, targets, damping: float, limits, centring: float = 0.0) -> torch.Tensor:
    """q (N, 7), targets ((N, 3) m, (N, 3, 3)) -> the step (N, 7): the Jacobian's damped
    pseudo-inverse applied to the 6-D pose error (the least joint motion that removes it), plus,
    with ``centring`` > 0, that gain times a step towards the middle of the joint ranges projected
    into the Jacobian's null space (the redundant seventh joint's freedom, which leaves the pose).

    A joint at a limit that the step would push beyond is taken out of the Jacobian and the
    step solved again, so the other six joints make up for it; clamping alone would leave the
    error where it is (a door's arc followed into joint 6's limit then tears the grasp).
    """
    error, jacobian = _pose_error(q, targets)
    step = _damped_least_squares(jacobian, error, damping)
    blocked = ((q <= limits[0]) & (step < 0)) | ((q >= limits[1]) & (step > 0))
    if blocked.any():
        step = _damped_least_squares(jacobian * (~blocked).to(q.dtype)[:, None, :], error, damping)
    if centring:
        middle, half_range = (limits[0] + limits[1]) / 2, (limits[1] - limits[0]) / 2
        towards_middle = (middle - q) / half_range ** 2
        moves_hand = _damped_least_squares(jacobian, (jacobian @ towards_middle[:, :, None])[:, :, 0], damping)
        step = step + centring * (towards_middle - moves_hand)
    return step


def _pose_error(q, targets) -> tuple[torch.Tensor, torch.Tensor]:
    """q (N, 7), targets ((N, 3) m, (N, 3, 3)) -> the error (N, 6): translation (m) and rotation
    vector (rad) from FK to the target, world frame; and the Jacobian (N, 6, 7)."""
    jacobian, eef = panda_chain(q.dtype, str(q.device)).jacobian(q, ret_eef_pose=True)   # (N, 6, 7), (N, 4, 4)
    position = eef[:, :3, 3] + torch.tensor(ROBOT_BASE, dtype=q.dtype)
    rotation = rotation_vector(targets[1] @ eef[:, :3, :3].transpose(1, 2))
    return torch.cat([targets[0] - position, rotation], 1), jacobian


def _damped_least_squares(jacobian, error, damping: float) -> torch.Tensor:
    """J^T (J J^T + damping^2 I)^-1 e for (N, 6, 7) J and (N, 6) e -> (N, 7)."""
    jjt = jacobian @ jacobian.transpose(1, 2) + damping ** 2 * torch.eye(6, dtype=jacobian.dtype)
    return (jacobian.transpose(1, 2) @ torch.linalg.solve(jjt, error[:, :, None]))[:, :, 0]


def rotation_vector(rotation: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) -> (N, 3) axis * angle (rad); the factor angle / sin(angle) is capped at 3,
    so a half-turn error (no defined axis) still steps, if slowly."""
    skew = (rotation - rotation.transpose(1, 2)) / 2
    axis_sin = torch.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], 1)
    angle = torch.acos(((rotation.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1.0, 1.0))
    return axis_sin * (angle / torch.sin(angle).clamp(min=1e-6)).clamp(max=3.0)[:, None]


def hand_symmetric_targets(targets: torch.Tensor, reached: torch.Tensor) -> torch.Tensor:
    """targets, reached (B, T, 3, 3) -> targets, or where the last reached rotation is nearer the
    goal turned half a turn about the approach axis, targets turned progressively to that goal:
    targets[t] Rz(+-pi t / (T - 1)), the sign whichever stays nearer the reached rotations."""
    goal, end = targets[:, -1], reached[:, -1]
    turned = (end * (goal @ _half_turn(goal.dtype))).sum((-2, -1)) > (end * goal).sum((-2, -1))   # trace(A^T B)
    angle = torch.pi * torch.linspace(1 / targets.shape[1], 1.0, targets.shape[1], dtype=targets.dtype)
    options = [targets @ _z_rotation(sign * angle) for sign in (1.0, -1.0)]
    closeness = [(reached * option).sum((-3, -2, -1)) for option in options]
    ramp = torch.where((closeness[0] >= closeness[1])[:, None, None, None], options[0], options[1])
    return torch.where(turned[:, None, None, None], ramp, targets)


def _z_rotation(angle: torch.Tensor) -> torch.Tensor:
    """(T,) rad -> (T, 3, 3) rotations about z."""
    cos, sin, zero, one = angle.cos(), angle.sin(), torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([cos, -sin, zero, sin, cos, zero, zero, zero, one], -1).reshape(-1, 3, 3)


def continuous_start(joints: torch.Tensor, max_step: float = MAX_JOINT_STEP) -> torch.Tensor:
    """joints (B, T, 7) -> the same, or for a trajectory that leaves its start waypoint by more
    than ``max_step`` rad in one step (it lies in another arm configuration than the arm is in),
    the start repeated: refinement then grows the motion out of where the arm is."""
    jump = torch.diff(joints, dim=1).abs().amax((1, 2))
    return torch.where((jump > max_step)[:, None, None], joints[:, :1].expand_as(joints), joints)


def goal_error(joints: torch.Tensor, goal_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) translation (m) and rotation (rad) errors of the last waypoint's FK against (B, 7) goals,
    the rotation against the goal or the same grasp turned half a turn, whichever is nearer."""
    reached = fk_pose(joints[:, -1])
    goal = goal_pose.to(reached.dtype)
    turned = torch.cat([goal[:, :3], matrix_to_quat(quat_to_matrix(goal[:, 3:]) @ _half_turn(goal.dtype))], 1)
    translation, angle = pose_error(reached, goal)
    return translation, torch.minimum(angle, pose_error(reached, turned)[1])
