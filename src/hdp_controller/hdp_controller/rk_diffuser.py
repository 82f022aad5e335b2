"""RK-Diffuser: a pose diffuser and a joint diffuser sharing one set of conditions.

Conditions C = {start pose, goal pose (the NBP), low-dim state (joint
positions and velocities, gripper width and open state), front-camera
points, trajectory rank}. The pose diffuser generates the (T, 7) EE pose
trajectory with start and goal inpainted (as its deviation from the straight
line between them); the joint diffuser generates the (T, 7) joint
trajectory with the start joints inpainted (as the motion from them, see
JOINT_MOTION_SCALE); one encoder embeds the conditions for both (the paper
gives them the same C). Training distils
the pose diffuser's accuracy into the joint diffuser through differentiable
kinematics:  L = b1 L_pose + b2 L_joint + b3 L_joint->pose,  the last term
comparing FK(predicted joints) with the demonstrated pose trajectory in
translation AND rotation (the official code drops rotation).

Classifier-free guidance: during training the scene context (points and
rank) is replaced by learned null embeddings with probability
``cond_dropout``; sampling extrapolates from the null-context prediction
towards the conditioned one with weight ``guidance``. Start, goal and
state are never dropped: without them the trajectory is unconstrained.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import nn

from hdp_motion import panda
from hdp_motion.kinematics import forward_kinematics, quat_to_matrix
from hdp_data.workspace import WORKSPACE

from .diffusion import TrajectoryDiffusion
from .low_level import HORIZON
from .pointnet2 import PointNet2Encoder
from .refine import pull_to_goal
from .unet import TemporalUnet

_CENTRE = torch.tensor(WORKSPACE.mean(axis=0), dtype=torch.float32)
_HALF = torch.tensor((WORKSPACE[1] - WORKSPACE[0]) / 2, dtype=torch.float32)
_LOWER = torch.tensor(panda.LOWER, dtype=torch.float32)
_UPPER = torch.tensor(panda.UPPER, dtype=torch.float32)
_VELOCITY = torch.tensor(panda.VELOCITY_LIMITS, dtype=torch.float32)


ROTATION_INPUTS = ('quaternion', 'matrix')
GOAL_LOSSES = ('squared', 'distance')


@dataclasses.dataclass
class RKDConfig:
    unet_dim: int = 32
    dim_mults: tuple = (1, 2, 4)
    point_features: int = 128
    point_width: int = 32
    n_points: int = 1024
    diffusion_steps: int = 100
    cond_dropout: float = 0.1
    guidance: float = 1.2
    loss_weights: tuple = (1.0, 1.0, 1.0)      # b1 pose, b2 joint, b3 joint->pose
    # How the joint diffuser is told its goal (model card, "Why the joint diffuser
    # missed its goal"); the defaults rebuild the checkpoints released before them.
    rotation_input: str = 'quaternion'         # start/goal orientation for the encoder: quaternion | matrix
    joint_reference: bool = False              # the straight line start -> goal as the joint U-Net's per-waypoint input
    goal_loss_weight: float = 0.0              # b4: FK(the predicted last joint waypoint) against the goal pose
    goal_loss: str = 'squared'                 # b4's error: squared | distance (its square root: a pull that
                                               # does not fade as the goal comes within centimetres)
    smooth_loss_weight: float = 0.0            # b5: second differences of the predicted joint motion

    def __post_init__(self):
        if self.rotation_input not in ROTATION_INPUTS:
            raise ValueError(f'rotation_input {self.rotation_input!r}: choose from {", ".join(ROTATION_INPUTS)}')
        if self.goal_loss not in GOAL_LOSSES:
            raise ValueError(f'goal_loss {self.goal_loss!r}: choose from {", ".join(GOAL_LOSSES)}')

    @classmethod
    def from_dict(cls, values: dict) -> RKDConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f'unknown RK-Diffuser config keys {sorted(unknown)}; known: {sorted(known)}')
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        return cls(**values)


# --- normalisation: everything the networks see is about [-1, 1] ------------------------

def normalize_positions(xyz: torch.Tensor) -> torch.Tensor:
    return (xyz - _CENTRE.to(xyz)) / _HALF.to(xyz)


def unnormalize_positions(xyz: torch.Tensor) -> torch.Tensor:
    return xyz * _HALF.to(xyz) + _CENTRE.to(xyz)


def normalize_poses(pose: torch.Tensor) -> torch.Tensor:
    return torch.cat([normalize_positions(pose[..., :3]), pose[..., 3:]], dim=-1)


def pose_features(pose: torch.Tensor) -> torch.Tensor:
    """(..., 7) poses -> (..., 9): normalised position and the rotation matrix's first two
    columns, a continuous encoding without the quaternion's double cover (Zhou et al. 2019)."""
    columns = quat_to_matrix(pose[..., 3:])[..., :2]
    return torch.cat([normalize_positions(pose[..., :3]), columns.flatten(-2)], dim=-1)


# The pose diffuser works on the deviation from the straight line start -> goal
# (both known: they are inpainted), in units of these scales. Straight moves
# (approaches, drawer pulls) are then the zero trajectory, and the network's
# capacity goes to the curves (hinge arcs, detours around obstacles).
_DEVIATION_SCALE = torch.tensor([0.1, 0.1, 0.1, 0.2, 0.2, 0.2, 0.2])     # m, m, m, quaternion units


def _straight_line(start: torch.Tensor, goal: torch.Tensor, horizon: int) -> torch.Tensor:
    """(B, 7) start and goal -> (B, horizon, 7) linear interpolation (quaternions not renormalised)."""
    s = torch.linspace(0, 1, horizon, dtype=start.dtype, device=start.device)[None, :, None]
    return start[:, None] + s * (goal - start)[:, None]


def pose_deviation(poses: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """(B, T, 7) poses -> their scaled deviation from the straight line; zero at both ends."""
    return (poses - _straight_line(start, goal, poses.shape[1])) / _DEVIATION_SCALE.to(poses)


def poses_from_deviation(deviation: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    poses = deviation * _DEVIATION_SCALE.to(deviation) + _straight_line(start, goal, deviation.shape[1])
    return torch.cat([poses[..., :3], nn.functional.normalize(poses[..., 3:], dim=-1)], dim=-1)


def normalize_joints(q: torch.Tensor) -> torch.Tensor:
    return 2 * (q - _LOWER.to(q)) / (_UPPER - _LOWER).to(q) - 1


# The joint diffuser works on the motion from the start joints, in units of
# this scale, rather than on absolute angles normalised over each joint's range
# (this module's first version). The start is then zero by construction and the
# network's residual error is a fraction of a segment's motion, not of a joint's
# 5.8 rad range: with absolute angles the CPU-trained diffuser's waypoints
# jittered by 0.3 rad (mean second difference; the demonstrations' is 0.0006)
# and half its trajectories left the inpainted start with a jump over 0.5 rad
# (validation seeds 900-909, DDIM-5), so refinement had to discard them.
JOINT_MOTION_SCALE = 0.5      # rad; segments move a joint by 0.2-0.6 rad (std)


def joint_motion(joints: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """(B, T, 7) joints, (B, 7) start joints -> (B, T, 7) scaled motion from the start."""
    return (joints - start[:, None]) / JOINT_MOTION_SCALE


def joints_from_motion(motion: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    return motion * JOINT_MOTION_SCALE + start[:, None]


def mlp(c_in: int, c_out: int) -> nn.Sequential:
    """The paper's condition MLP: two hidden layers of 128 and 512, GELU."""
    return nn.Sequential(nn.Linear(c_in, 128), nn.GELU(), nn.Linear(128, 512), nn.GELU(), nn.Linear(512, c_out))


class ConditionEncoder(nn.Module):
    """Batch of conditions -> (B, out_dim) vector; ``drop`` (B,) bool nulls the scene context."""

    def __init__(self, config: RKDConfig):
        super().__init__()
        self.encode_pose = pose_features if config.rotation_input == 'matrix' else normalize_poses
        pose_dim = 9 if config.rotation_input == 'matrix' else 7
        # start pose, goal pose, q, qd, gripper (width, open)
        self.state = mlp(2 * pose_dim + 7 + 7 + 2, 128)
        self.rank = mlp(1, 32)
        self.points = PointNet2Encoder(config.point_features, config.point_width)
        self.null_rank = nn.Parameter(torch.zeros(32))
        self.null_points = nn.Parameter(torch.zeros(config.point_features))
        self.out_dim = 128 + 32 + config.point_features

    def forward(self, batch: dict, drop: torch.Tensor) -> torch.Tensor:
        state = torch.cat([self.encode_pose(batch['start_pose']), self.encode_pose(batch['goal_pose']),
                           normalize_joints(batch['q']), batch['qd'] / _VELOCITY.to(batch['qd']),
                           batch['gripper'] * torch.tensor([1 / panda.GRIPPER_OPEN_WIDTH, 1.0]).to(batch['q'])],
                          dim=-1)
        rank = torch.where(drop[:, None], self.null_rank, self.rank(batch['rank']))
        points = torch.where(drop[:, None], self.null_points, self.points(normalize_positions(batch['points'])))
        return torch.cat([self.state(state), rank, points], dim=-1)


def straight_line_reference(start_pose: torch.Tensor, goal_pose: torch.Tensor) -> torch.Tensor:
    """(B, 7) start and goal -> (B, HORIZON, 9) pose_features of the straight line between them:
    at every waypoint the joint U-Net reads where the hand would be on a straight move,
    at the last one the goal itself."""
    return pose_features(_straight_line(start_pose, goal_pose, HORIZON))


def fk_pose_error(q: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Squared pose error (...,) of FK(q (..., 7)) against poses (..., 7): normalised
    translation plus the squared Frobenius distance of the rotation matrices."""
    position, rotation = forward_kinematics(q)
    translation = ((normalize_positions(position) - normalize_positions(poses[..., :3])) ** 2).sum(-1)
    return translation + ((rotation - quat_to_matrix(poses[..., 3:])) ** 2).sum((-2, -1))


def fk_pose_loss(q: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    return fk_pose_error(q, poses).mean()


def goal_loss(q_last: torch.Tensor, goal: torch.Tensor, kind: str = 'squared') -> torch.Tensor:
    """FK(q_last (B, 7)) against goal (B, 7): the mean squared error, or ('distance') the mean
    of its square root, whose gradient keeps its size as the error shrinks to centimetres."""
    error = fk_pose_error(q_last, goal)
    return error.mean() if kind == 'squared' else (error + 1e-8).sqrt().mean()


def smoothness_loss(motion_hat: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """MSE of the second differences (B, T - 2, 7) of predicted against demonstrated motion:
    zero for a perfect prediction, so it adds no bias, but it weighs waypoint-to-waypoint
    wiggle, which the plain MSE spreads over 64 waypoints, as much as the whole shape."""
    return nn.functional.mse_loss(torch.diff(motion_hat, n=2, dim=1), torch.diff(motion, n=2, dim=1))


class RKDiffuser(nn.Module):
    """One condition encoder feeding two x0-predicting diffusers over (HORIZON, 7)."""

    def __init__(self, config: RKDConfig):
        super().__init__()
        self.config = config
        self.encoder = ConditionEncoder(config)
        self.pose = self._diffuser(config)
        self.joint = self._diffuser(config, local_dim=9 if config.joint_reference else 0)

    def _diffuser(self, config: RKDConfig, local_dim: int = 0) -> TrajectoryDiffusion:
        net = TemporalUnet(7, self.encoder.out_dim, config.unet_dim, config.dim_mults, local_dim)
        return TrajectoryDiffusion(net, HORIZON, 7, config.diffusion_steps)

    def _joint_reference(self, batch: dict) -> torch.Tensor | None:
        if not self.config.joint_reference:
            return None
        return straight_line_reference(batch['start_pose'], batch['goal_pose'])

    def draw(self, batch_size: int, generator: torch.Generator | None = None) -> dict:
        """Every random number one ``loss`` uses for ``batch_size`` samples (on the CPU):
        drop (B,) the scene context nulled; pose_t, joint_t (B,) diffusion steps;
        pose_noise, joint_noise (B, HORIZON, 7)."""
        steps, shape = self.config.diffusion_steps, (batch_size, HORIZON, 7)
        return {'drop': torch.rand(batch_size, generator=generator) < self.config.cond_dropout,
                'pose_t': torch.randint(0, steps, (batch_size,), generator=generator),
                'pose_noise': torch.randn(shape, generator=generator),
                'joint_t': torch.randint(0, steps, (batch_size,), generator=generator),
                'joint_noise': torch.randn(shape, generator=generator)}

    def forward(self, batch: dict, draws: dict | None = None) -> tuple[torch.Tensor, dict]:
        """The training loss (DistributedDataParallel synchronises gradients through forward)."""
        return self.loss(batch, draws)

    def loss(self, batch: dict, draws: dict | None = None) -> tuple[torch.Tensor, dict]:
        """batch: a training batch (dataset.augment; unnormalised); draws: self.draw's, drawn
        here when not given. Returns (total, {name: value})."""
        device = batch['q'].device
        draws = {k: v.to(device) for k, v in (draws or self.draw(batch['q'].shape[0])).items()}
        cond = self.encoder(batch, draws['drop'])
        deviation = pose_deviation(batch['poses'], batch['start_pose'], batch['goal_pose'])
        motion = joint_motion(batch['joints'], batch['q'])
        l_pose, _ = self.pose.loss(deviation, cond, {0: deviation[:, 0], -1: deviation[:, -1]},
                                   t=draws['pose_t'], noise=draws['pose_noise'])
        l_joint, motion_hat = self.joint.loss(motion, cond, {0: motion[:, 0]}, self._joint_reference(batch),
                                              t=draws['joint_t'], noise=draws['joint_noise'])
        joints_hat = joints_from_motion(motion_hat, batch['q'])
        l_fk = fk_pose_loss(joints_hat, batch['poses'])
        b1, b2, b3 = self.config.loss_weights
        total = b1 * l_pose + b2 * l_joint + b3 * l_fk
        parts = {'pose': l_pose.item(), 'joint': l_joint.item(), 'joint_to_pose': l_fk.item()}
        if self.config.goal_loss_weight:
            # The FK term above weighs the goal as 1 of 64 waypoints; the goal is what the segment is for.
            l_goal = goal_loss(joints_hat[:, -1], batch['goal_pose'], self.config.goal_loss)
            total = total + self.config.goal_loss_weight * l_goal
            parts['goal'] = l_goal.item()
        if self.config.smooth_loss_weight:
            # The joint method executes the raw sample: its wiggle is the arm's.
            l_smooth = smoothness_loss(motion_hat, motion)
            total = total + self.config.smooth_loss_weight * l_smooth
            parts['smooth'] = l_smooth.item()
        return total, parts

    @torch.no_grad()
    def sample(self, batch: dict, sampler: str = 'ddpm', steps: int | None = None, guidance: float | None = None,
               generator: torch.Generator | None = None, which=('pose', 'joint'), goal_guidance: int = 0) -> dict:
        """Conditions (B, ...) -> {'poses': (B, T, 7) xyz + quat xyzw, 'joints': (B, T, 7) rad}.

        ``goal_guidance`` > 0: at every step the joint diffuser's x0 estimate is pulled onto the
        goal pose by that many Gauss-Newton steps on its last waypoint (refine.pull_to_goal): the
        goal, which the pose diffuser inpaints, imposed on the joint diffuser through kinematics.
        """
        guidance = self.config.guidance if guidance is None else guidance
        b = batch['q'].shape[0]
        device = batch['q'].device
        cond = self.encoder(batch, torch.zeros(b, dtype=torch.bool, device=device))
        null = self.encoder(batch, torch.ones(b, dtype=torch.bool, device=device)) if guidance != 1.0 else None
        out = {}
        if 'pose' in which:
            zero = torch.zeros_like(batch['start_pose'])
            deviation = self.pose.sample(cond, {0: zero, -1: zero}, null, guidance, sampler, steps, generator)
            out['poses'] = poses_from_deviation(deviation, batch['start_pose'], batch['goal_pose'])
        if 'joint' in which:
            known = {0: torch.zeros_like(batch['q'])}
            guide = _goal_guide(batch, goal_guidance) if goal_guidance else None
            motion = self.joint.sample(cond, known, null, guidance, sampler, steps, generator,
                                       self._joint_reference(batch), guide)
            joints = joints_from_motion(motion, batch['q'])
            out['joints'] = torch.maximum(torch.minimum(joints, _UPPER.to(joints)), _LOWER.to(joints))
        return out


def _goal_guide(batch: dict, steps: int):
    """The joint diffuser's guide for TrajectoryDiffusion.sample: a motion estimate (B, T, 7) ->
    the same with its end pulled onto batch['goal_pose'] by ``steps`` Gauss-Newton steps."""
    def guide(motion: torch.Tensor) -> torch.Tensor:
        joints = joints_from_motion(motion, batch['q']).cpu()        # the kinematics run on the CPU
        pulled = pull_to_goal(joints, batch['goal_pose'].cpu(), steps).to(motion.device)
        return joint_motion(pulled, batch['q'])
    return guide


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def as_batch(arrays: dict) -> dict:
    """numpy / sequences (unbatched) -> float32 tensors with a leading batch dim of 1."""
    return {k: torch.as_tensor(np.asarray(v, dtype=np.float32))[None] for k, v in arrays.items()}
