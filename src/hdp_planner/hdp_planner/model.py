"""The next-best-pose network: a two-level coarse-to-fine 3D U-Net agent (C2F-ARM with language).

Level 1 scores every voxel of a coarse grid over the workspace; level 2
voxelises a cube around the chosen coarse voxel and scores its voxels,
regresses a sub-voxel offset, and reads the orientation (3 x 72 Euler bins)
and the gripper action off the features at its chosen voxel plus globally
pooled ones. Both levels are FiLM-conditioned on the pooled instruction and
the proprioception (the fine level also on where its cube is). PerAct's
collision head is left out: the low level handles collisions.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from hdp_motion import panda
from hdp_data.workspace import WORKSPACE

from . import rotations, voxels
from .language import MAX_WORDS, InstructionEncoder, WordEncoder

# The arm state the network is conditioned on. 'joints': gripper open, 7 joint positions. 'hand':
# gripper open, the hand's position and orientation in the world frame, which the training
# augmentation moves with the scene (joint positions cannot follow a moved scene, so under
# augmentation they contradict where the cloud shows the hand).
PROPRIO_DIMS = {'joints': 8, 'hand': 10}
# 'words': WordEncoder, learned over the task vocabulary. 'minilm': frozen all-MiniLM-L6-v2 and a
# learned projection (sentence_encoder; imported only when chosen, it loads transformers).
LANGUAGE_ENCODERS = ('words', 'minilm')


def proprio_vector(joint_positions, gripper_open) -> np.ndarray:
    """(..., 8) float32: gripper open as +-1, then joint positions scaled to [-1, 1] over the Panda's limits."""
    q = np.asarray(joint_positions, dtype=np.float64)
    scaled = 2 * (q - panda.LOWER) / (panda.UPPER - panda.LOWER) - 1
    gripper = np.where(np.asarray(gripper_open, dtype=bool), 1.0, -1.0)[..., None]
    return np.concatenate([gripper, scaled], -1).astype(np.float32)


def hand_pose(joint_positions) -> tuple[np.ndarray, np.ndarray]:
    """xyz (N, 3) m and quaternions (N, 4) xyzw of panda_grasptarget for (N, 7) joint positions."""
    from hdp_motion import kinematics           # pytorch-kinematics: loaded only by what needs the hand
    pose = kinematics.fk_pose(torch.as_tensor(np.asarray(joint_positions, dtype=np.float64))).numpy()
    return pose[:, :3], pose[:, 3:]


def hand_vector(hand_xyz, hand_quat, gripper_open) -> np.ndarray:
    """(..., 10) float32: gripper open as +-1, the hand's position scaled to [-1, 1] over the
    workspace, the first two columns of its rotation matrix (continuous, unlike a quaternion)."""
    lower, upper = WORKSPACE
    position = 2 * (np.asarray(hand_xyz, dtype=np.float64) - lower) / (upper - lower) - 1
    axes = rotations.quat_to_matrix(hand_quat)[..., :, :2]
    gripper = np.where(np.asarray(gripper_open, dtype=bool), 1.0, -1.0)[..., None]
    return np.concatenate([gripper, position, axes.swapaxes(-1, -2).reshape(*position.shape[:-1], 6)],
                          -1).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Everything needed to rebuild the network; stored in every checkpoint as a plain dict."""
    vocabulary: tuple
    grid_size: int = voxels.VOXELS
    channels: tuple = (16, 32, 64)
    language_dim: int = 64
    max_words: int = MAX_WORDS
    fine_half_extent: float = voxels.FINE_HALF_EXTENT
    head_hidden: int = 256
    language_encoder: str = 'words'      # checkpoints from before the choice existed are 'words'
    proprio: str = 'joints'              # and 'joints'
    language_noise: float = 0.0          # 'minilm' in training: sentence_encoder.SentenceEncoder

    def __post_init__(self):
        if self.language_encoder not in LANGUAGE_ENCODERS:
            raise ValueError(f'language_encoder {self.language_encoder!r} is not one of {LANGUAGE_ENCODERS}')
        if self.language_noise < 0 or (self.language_noise and self.language_encoder != 'minilm'):
            raise ValueError(f"language_noise must be >= 0, and 0 unless language_encoder is 'minilm', "
                             f'got {self.language_noise!r}')
        if self.proprio not in PROPRIO_DIMS:
            raise ValueError(f'proprio {self.proprio!r} is not one of {tuple(PROPRIO_DIMS)}')

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> ModelConfig:
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - fields
        if unknown:
            raise ValueError(f'unknown model config keys {sorted(unknown)}')
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def instruction_encoder(config: ModelConfig) -> InstructionEncoder:
    """The language encoder ``config`` names, its output dim ``config.language_dim``."""
    if config.language_encoder == 'minilm':
        from .sentence_encoder import SentenceEncoder
        return SentenceEncoder(config.language_dim, config.language_noise)
    return WordEncoder(config.vocabulary, config.language_dim, config.max_words)


class ConvFiLM(nn.Module):
    """conv3 (stride) -> GroupNorm -> FiLM(condition) -> SiLU."""

    def __init__(self, in_channels: int, out_channels: int, condition_dim: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv3d(in_channels, out_channels, 3, stride, 1)
        self.norm = nn.GroupNorm(min(8, out_channels // 4), out_channels)
        self.film = nn.Linear(condition_dim, 2 * out_channels)
        nn.init.zeros_(self.film.weight)        # start unconditioned
        nn.init.zeros_(self.film.bias)

    def forward(self, x: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(condition)[:, :, None, None, None].chunk(2, 1)
        return F.silu(self.norm(self.conv(x)) * (1 + scale) + shift)


class UNet3D(nn.Module):
    """(B, C_in, S, S, S) grid -> (per-voxel features (B, c0, S, S, S), bottleneck (B, c2, S/4, S/4, S/4)).

    Full-resolution 3D convolutions dominate the cost on a CPU, so the full
    resolution gets one thin convolution on the way down and one on the way
    up, and skips are added (1x1 lateral projections) rather than concatenated.
    """

    def __init__(self, in_channels: int, channels: tuple, condition_dim: int):
        super().__init__()
        c0, c1, c2 = channels
        self.enc0 = ConvFiLM(in_channels, c0, condition_dim)
        self.down1 = ConvFiLM(c0, c1, condition_dim, stride=2)
        self.enc1 = ConvFiLM(c1, c1, condition_dim)
        self.down2 = ConvFiLM(c1, c2, condition_dim, stride=2)
        self.enc2 = ConvFiLM(c2, c2, condition_dim)
        self.lateral1 = nn.Conv3d(c2, c1, 1)
        self.dec1 = ConvFiLM(c1, c1, condition_dim)
        self.lateral0 = nn.Conv3d(c1, c0, 1)
        self.dec0 = ConvFiLM(c0, c0, condition_dim)

    def forward(self, grid: torch.Tensor, condition: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        e0 = self.enc0(grid, condition)
        e1 = self.enc1(self.down1(e0, condition), condition)
        bottleneck = self.enc2(self.down2(e1, condition), condition)
        d1 = self.dec1(F.interpolate(self.lateral1(bottleneck), scale_factor=2) + e1, condition)
        d0 = self.dec0(F.interpolate(self.lateral0(d1), scale_factor=2) + e0, condition)
        return d0, bottleneck


@dataclasses.dataclass
class Prediction:
    """Next-best poses of a batch: xyz (B, 3) m, quat (B, 4) xyzw, gripper_open (B,) bool,
    confidence (B,) = p(coarse voxel) x p(fine voxel)."""
    xyz: torch.Tensor
    quat: np.ndarray
    gripper_open: torch.Tensor
    confidence: torch.Tensor


class NextBestPoseNet(nn.Module):

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        c0, _, c2 = config.channels
        self.language = instruction_encoder(config)
        self.proprio = nn.Sequential(nn.Linear(PROPRIO_DIMS[config.proprio], 64), nn.SiLU(), nn.Linear(64, 64))
        condition_dim = config.language_dim + 64
        self.coarse = UNet3D(voxels.CHANNELS, config.channels, condition_dim)
        self.coarse_heatmap = nn.Conv3d(c0, 1, 1)
        self.fine = UNet3D(voxels.CHANNELS, config.channels, condition_dim + 3)
        self.fine_heatmap = nn.Conv3d(c0, 1 + 3, 1)           # logit, sub-voxel offset
        self.pose_head = nn.Sequential(
            nn.Linear(c0 + 2 * c2 + condition_dim + 3, config.head_hidden), nn.SiLU(),
            nn.Linear(config.head_hidden, 3 * rotations.BINS + 2))
        self.to(memory_format=torch.channels_last_3d)     # ~20% faster 3D convolutions on CPU

    def condition(self, instructions, proprio: torch.Tensor) -> torch.Tensor:
        """(B, language_dim + 64) from B instructions and (B, PROPRIO_DIMS[config.proprio]) proprio vectors."""
        _, pooled = self.language(instructions)
        return torch.cat([pooled, self.proprio(proprio)], 1)

    def coarse_logits(self, grid: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        """(B, S^3) translation logits over the coarse grid."""
        features, _ = self.coarse(grid, condition)
        return self.coarse_heatmap(features).flatten(1)

    def fine_outputs(self, grid: torch.Tensor, condition: torch.Tensor, centre: torch.Tensor,
                     index: torch.Tensor | None = None) -> dict:
        """Fine-level outputs for (B, C, S, S, S) cubes around (B, 3) centres (m).

        Rotation, gripper and offset are read at ``index`` (B,) flat voxels, the
        ground truth in training, else each cube's argmax. Returns logits (B, S^3),
        index (B,), offset (B, 3) in [0, 1] voxel units, rotation (B, 3, BINS), gripper (B, 2).
        """
        lower, upper = (b.to(centre.device) for b in voxels.workspace_bounds(len(centre)))
        condition = torch.cat([condition, (centre - lower) / (upper - lower) * 2 - 1], 1)
        features, bottleneck = self.fine(grid, condition)
        heatmap = self.fine_heatmap(features).flatten(2)             # (B, 4, S^3)
        logits = heatmap[:, 0]
        if index is None:
            index = logits.argmax(1)
        rows = torch.arange(len(index), device=index.device)
        local = features.flatten(2)[rows, :, index]                 # (B, c0)
        pooled = torch.cat([bottleneck.flatten(2).amax(2), bottleneck.flatten(2).mean(2)], 1)
        head = self.pose_head(torch.cat([local, pooled, condition], 1))
        return {'logits': logits, 'index': index, 'offset': torch.sigmoid(heatmap[rows, 1:, index]),
                'rotation': head[:, :3 * rotations.BINS].view(-1, 3, rotations.BINS),
                'gripper': head[:, 3 * rotations.BINS:]}

    @torch.no_grad()
    def predict(self, xyz: torch.Tensor, rgb: torch.Tensor, batch: torch.Tensor, instructions,
                proprio: torch.Tensor) -> Prediction:
        """Coarse-to-fine inference for B clouds given as voxels.collate_clouds returns them."""
        size, n = self.config.grid_size, len(instructions)
        condition = self.condition(instructions, proprio)
        lower, upper = voxels.workspace_bounds(n)
        lower, upper = lower.to(xyz.device), upper.to(xyz.device)
        coarse = self.coarse_logits(voxels.voxelise(xyz, rgb, batch, lower, upper, size), condition)
        coarse_index = coarse.argmax(1)
        centre = voxels.position_of(coarse_index, torch.full((n, 3), 0.5, device=xyz.device), lower, upper, size)
        fine_lower, fine_upper = voxels.fine_bounds(centre, self.config.fine_half_extent)
        fine = self.fine_outputs(voxels.voxelise(xyz, rgb, batch, fine_lower, fine_upper, size),
                                 condition, centre)
        position = voxels.position_of(fine['index'], fine['offset'], fine_lower, fine_upper, size)
        position = torch.maximum(torch.minimum(position, upper), lower)   # a fine cube at the edge reaches out
        confidence = (coarse.softmax(1).gather(1, coarse_index[:, None])[:, 0]
                      * fine['logits'].softmax(1).gather(1, fine['index'][:, None])[:, 0])
        quat = rotations.bins_to_quat(fine['rotation'].argmax(2).cpu().numpy())
        return Prediction(position, quat, fine['gripper'].argmax(1) == 1, confidence)
