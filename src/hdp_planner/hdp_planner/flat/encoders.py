"""What both flat policies share: their config's observation part, a small CNN per camera, the
instruction encoder (the next-best-pose agent's: frozen MiniLM or learned words), action
normalisation and image augmentation.

Diffusion Policy and ACT use a ResNet-18 per camera; on a 2-core CPU both get a small
convolutional backbone instead (GroupNorm, as Diffusion Policy replaces BatchNorm), 64 x 48
images in, an 8 x 6 feature map out (three stride-2 stages).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import nn

from .. import language
from .dataset import ACTION_DIM, CAMERAS, CONTROL_PERIOD_S, PROPRIO_DIM

LANGUAGE_ENCODERS = ('minilm', 'words')
SHIFT_PAD = 4            # pixels: DrQ-style random shift, Diffusion Policy's crop scaled to 64 x 48


@dataclasses.dataclass(frozen=True)
class FlatModelConfig:
    """The observation and rate part of both policies' configs (the ``model:`` section).

    n_obs: observation steps the policy sees (k - n_obs + 1 .. k); horizon: action steps it predicts
    (k + 1 .. k + horizon); n_action_steps: how many of them run before it is asked again.
    vocabulary: the word encoder's (filled by the trainer when empty); unused by minilm.
    """
    image_width: int = 64
    image_height: int = 48
    control_period_s: float = CONTROL_PERIOD_S
    n_obs: int = 1
    horizon: int = 16
    n_action_steps: int = 8
    language_encoder: str = 'minilm'
    language_dim: int = 64
    vocabulary: tuple = ()
    channels: tuple = (32, 64, 64)

    def __post_init__(self):
        if self.language_encoder not in LANGUAGE_ENCODERS:
            raise ValueError(f'language_encoder {self.language_encoder!r} is not one of {LANGUAGE_ENCODERS}')
        if min(self.n_obs, self.horizon, self.n_action_steps, self.image_width, self.image_height) < 1:
            raise ValueError('n_obs, horizon, n_action_steps and the image size must be >= 1')
        if self.n_action_steps > self.horizon:
            raise ValueError(f'n_action_steps {self.n_action_steps} exceeds the horizon {self.horizon}')
        if self.control_period_s <= 0:
            raise ValueError('control_period_s must be > 0')

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict):
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - fields
        if unknown:
            raise ValueError(f'unknown model config keys {sorted(unknown)}')
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def instruction_encoder(config: FlatModelConfig) -> language.InstructionEncoder:
    """The hierarchy's instruction encoders: 'minilm' (the frozen sentence encoder + a learned
    projection) or 'words' (learned over ``config.vocabulary``); output dim ``config.language_dim``."""
    if config.language_encoder == 'minilm':
        from ..sentence_encoder import SentenceEncoder
        return SentenceEncoder(config.language_dim)
    return language.WordEncoder(config.vocabulary or tuple(language.task_vocabulary()), config.language_dim)


class CameraBackbone(nn.Module):
    """(N, 3, H, W) uint8 -> (N, channels[-1], H / 8, W / 8) float features: a stride-2 5x5 stem and
    two stride-2 stages of two 3x3 convolutions, GroupNorm and ReLU."""

    def __init__(self, channels=(32, 64, 64)):
        super().__init__()
        layers, previous = [nn.Conv2d(3, channels[0], 5, 2, 2), nn.GroupNorm(8, channels[0]), nn.ReLU()], channels[0]
        for width in channels[1:]:
            layers += [nn.Conv2d(previous, width, 3, 2, 1), nn.GroupNorm(8, width), nn.ReLU(),
                       nn.Conv2d(width, width, 3, 1, 1), nn.GroupNorm(8, width), nn.ReLU()]
            previous = width
        self.net = nn.Sequential(*layers)
        self.out_channels = previous

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.net(images.float() / 127.5 - 1.0)


class SpatialSoftmax(nn.Module):
    """(N, C, h, w) -> (N, 2 x keypoints): the expected image coordinates of ``keypoints`` learned
    attention maps (robomimic's, which Diffusion Policy's image encoder ends in)."""

    def __init__(self, channels: int, keypoints: int):
        super().__init__()
        self.keypoints = nn.Conv2d(channels, keypoints, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        n, _, h, w = features.shape
        attention = self.keypoints(features).flatten(2).softmax(-1)                   # (N, K, h * w)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h, device=features.device),
                                torch.linspace(-1, 1, w, device=features.device), indexing='ij')
        grid = torch.stack([xs.flatten(), ys.flatten()], -1)                           # (h * w, 2)
        return (attention @ grid).reshape(n, -1)


def random_shift(images: torch.Tensor, generator: torch.Generator | None = None, pad: int = SHIFT_PAD) -> torch.Tensor:
    """(N, 3, H, W) images each shifted by up to ``pad`` pixels (edge-replicated), as DrQ and
    Diffusion Policy's random crop augment; dtype kept."""
    n, _, h, w = images.shape
    padded = nn.functional.pad(images.float(), (pad, pad, pad, pad), mode='replicate')
    dx = torch.randint(0, 2 * pad + 1, (n,), generator=generator)
    dy = torch.randint(0, 2 * pad + 1, (n,), generator=generator)
    rows = (dy[:, None] + torch.arange(h)[None]).to(images.device)                     # (N, H)
    cols = (dx[:, None] + torch.arange(w)[None]).to(images.device)                     # (N, W)
    index = torch.arange(n, device=images.device)[:, None, None]
    shifted = padded.permute(0, 2, 3, 1)[index, rows[:, :, None], cols[:, None, :]]    # (N, H, W, 3)
    return shifted.permute(0, 3, 1, 2).to(images.dtype)


class ActionNormaliser(nn.Module):
    """Actions (..., 8) <-> [-1, 1] per dimension over the training data's range (buffers: they
    travel in the checkpoint). Ranges narrower than MIN_SPAN are widened to it."""
    MIN_SPAN = 1e-2

    def __init__(self):
        super().__init__()
        self.register_buffer('low', -torch.ones(ACTION_DIM))
        self.register_buffer('high', torch.ones(ACTION_DIM))

    def fit(self, low, high) -> None:
        low, high = torch.as_tensor(np.asarray(low), dtype=torch.float32), torch.as_tensor(np.asarray(high),
                                                                                           dtype=torch.float32)
        middle, half = (low + high) / 2, ((high - low) / 2).clamp(min=self.MIN_SPAN / 2)
        self.low.copy_(middle - half)
        self.high.copy_(middle + half)

    def normalise(self, actions: torch.Tensor) -> torch.Tensor:
        return 2 * (actions - self.low) / (self.high - self.low) - 1

    def denormalise(self, normalised: torch.Tensor) -> torch.Tensor:
        return (normalised + 1) / 2 * (self.high - self.low) + self.low


def observation_tensors(batch, device='cpu') -> dict:
    """A dataset Batch (or the policy's own observation history) as tensors on ``device``:
    images (B, n_obs, C, 3, h, w) uint8, proprio (B, n_obs, 9), instructions, and, when present,
    actions (B, horizon, 8) and is_pad (B, horizon)."""
    out = {'images': torch.as_tensor(batch.images, device=device),
           'proprio': torch.as_tensor(batch.proprio, device=device),
           'instructions': list(batch.instructions)}
    if getattr(batch, 'actions', None) is not None:
        out['actions'] = torch.as_tensor(batch.actions, device=device)
        out['is_pad'] = torch.as_tensor(batch.is_pad, device=device)
    return out


__all__ = ['ACTION_DIM', 'CAMERAS', 'PROPRIO_DIM', 'FlatModelConfig', 'CameraBackbone', 'SpatialSoftmax',
           'ActionNormaliser', 'instruction_encoder', 'random_shift', 'observation_tensors']
