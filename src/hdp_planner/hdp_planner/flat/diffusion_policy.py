"""Diffusion Policy (Chi et al., RSS 2023), CNN variant, small enough for a CPU.

The network is real-stanford/diffusion_policy's ConditionalUnet1D (a 1D temporal U-Net over
the action chunk, FiLM-conditioned at every residual block on the diffusion step and the
observation), written compactly here because diffusers' UNet1DModel takes no global condition;
the noise schedule and samplers are diffusers' (DDPMScheduler for training, DDIMScheduler for
sampling), as the paper's code uses them. Epsilon prediction, squared-cosine schedule, 100
training steps, 10 DDIM steps at inference, actions min-max normalised to [-1, 1] and clipped.

Observation -> global condition: per observation step, each camera's CNN ending in a spatial
softmax (its keypoints' coordinates) and the proprioception; concatenated over the n_obs steps,
then the instruction's pooled embedding.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import nn

from .encoders import (ACTION_DIM, CAMERAS, PROPRIO_DIM, ActionNormaliser, CameraBackbone, FlatModelConfig,
                       SpatialSoftmax, instruction_encoder, random_shift)


@dataclasses.dataclass(frozen=True)
class DiffusionPolicyConfig(FlatModelConfig):
    """Diffusion Policy's defaults at 10 Hz: 2 observation steps, 16 predicted, 8 executed.
    down_dims: the U-Net's widths (the paper's 256, 512, 1024, scaled down for a CPU)."""
    n_obs: int = 2
    horizon: int = 16
    n_action_steps: int = 8
    keypoints: int = 32
    down_dims: tuple = (32, 64, 128)
    kernel_size: int = 5
    n_groups: int = 8
    step_embed_dim: int = 64
    train_timesteps: int = 100
    inference_steps: int = 10

    def __post_init__(self):
        super().__post_init__()
        if self.horizon % 2 ** (len(self.down_dims) - 1):
            raise ValueError(f'horizon {self.horizon} must be divisible by 2^(len(down_dims) - 1) = '
                             f'{2 ** (len(self.down_dims) - 1)}')


class SinusoidalPosEmb(nn.Module):
    """(B,) diffusion steps -> (B, dim) sinusoidal embeddings."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        frequencies = torch.exp(torch.arange(half, device=x.device) * -(math.log(10000) / (half - 1)))
        angles = x.float()[:, None] * frequencies[None]
        return torch.cat([angles.sin(), angles.cos()], -1)


class Conv1dBlock(nn.Module):
    """(B, in, T) -> (B, out, T): Conv1d, GroupNorm, Mish."""

    def __init__(self, inp: int, out: int, kernel_size: int, n_groups: int = 8):
        super().__init__()
        self.block = nn.Sequential(nn.Conv1d(inp, out, kernel_size, padding=kernel_size // 2),
                                   nn.GroupNorm(n_groups, out), nn.Mish())

    def forward(self, x):
        return self.block(x)


class ConditionalResidualBlock1D(nn.Module):
    """(B, in, T), cond (B, cond_dim) -> (B, out, T): two Conv1dBlocks, the second's input FiLM-modulated
    (per-channel scale and bias from the condition), plus a 1x1 residual."""

    def __init__(self, inp: int, out: int, cond_dim: int, kernel_size: int = 5, n_groups: int = 8):
        super().__init__()
        self.blocks = nn.ModuleList([Conv1dBlock(inp, out, kernel_size, n_groups),
                                     Conv1dBlock(out, out, kernel_size, n_groups)])
        self.out_channels = out
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * out))
        self.residual = nn.Conv1d(inp, out, 1) if inp != out else nn.Identity()

    def forward(self, x, cond):
        h = self.blocks[0](x)
        scale, bias = self.cond_encoder(cond)[..., None].chunk(2, dim=1)     # (B, out, 1) each
        h = self.blocks[1](scale * h + bias)
        return h + self.residual(x)


class ConditionalUnet1D(nn.Module):
    """Noisy actions (B, T, input_dim), diffusion steps (B,), global condition (B, cond_dim) ->
    predicted noise (B, T, input_dim). T must be divisible by 2^(len(down_dims) - 1)."""

    def __init__(self, input_dim: int, global_cond_dim: int, step_embed_dim: int = 64,
                 down_dims=(64, 128, 256), kernel_size: int = 5, n_groups: int = 8):
        super().__init__()
        self.step_encoder = nn.Sequential(SinusoidalPosEmb(step_embed_dim),
                                          nn.Linear(step_embed_dim, 4 * step_embed_dim), nn.Mish(),
                                          nn.Linear(4 * step_embed_dim, step_embed_dim))
        cond_dim = step_embed_dim + global_cond_dim
        dims = [input_dim, *down_dims]
        block = lambda i, o: ConditionalResidualBlock1D(i, o, cond_dim, kernel_size, n_groups)  # noqa: E731
        self.down = nn.ModuleList()
        for index, (inp, out) in enumerate(zip(dims[:-1], dims[1:])):
            last = index == len(down_dims) - 1
            self.down.append(nn.ModuleList([block(inp, out), block(out, out),
                                            nn.Conv1d(out, out, 3, 2, 1) if not last else nn.Identity()]))
        self.mid = nn.ModuleList([block(down_dims[-1], down_dims[-1]), block(down_dims[-1], down_dims[-1])])
        self.up = nn.ModuleList()
        for index, (inp, out) in enumerate(zip(reversed(dims[2:]), reversed(dims[1:-1]))):
            self.up.append(nn.ModuleList([block(2 * inp, out), block(out, out),
                                          nn.ConvTranspose1d(out, out, 4, 2, 1)]))
        self.final = nn.Sequential(Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
                                   nn.Conv1d(down_dims[0], input_dim, 1))

    def forward(self, sample: torch.Tensor, steps: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        x = sample.transpose(1, 2)                                                     # (B, input_dim, T)
        cond = torch.cat([self.step_encoder(steps.expand(len(sample))), global_cond], -1)
        skips = []
        for first, second, downsample in self.down:
            x = second(first(x, cond), cond)
            skips.append(x)
            x = downsample(x)
        for block in self.mid:
            x = block(x, cond)
        for first, second, upsample in self.up:
            x = upsample(second(first(torch.cat([x, skips.pop()], 1), cond), cond))
        return self.final(x).transpose(1, 2)


def _scheduler(kind: str, config: DiffusionPolicyConfig):
    from diffusers import DDIMScheduler, DDPMScheduler
    cls = DDPMScheduler if kind == 'ddpm' else DDIMScheduler
    return cls(num_train_timesteps=config.train_timesteps, beta_schedule='squaredcos_cap_v2', clip_sample=True,
               prediction_type='epsilon')


class DiffusionPolicyNet(nn.Module):
    """Observations (images (B, n_obs, 2, 3, h, w) uint8, proprio (B, n_obs, 9), instructions) ->
    action chunks (B, horizon, 8): absolute joint targets (rad) and gripper (+1 open, -1 closed)."""

    def __init__(self, config: DiffusionPolicyConfig):
        super().__init__()
        self.config = config
        self.backbones = nn.ModuleList([CameraBackbone(config.channels) for _ in CAMERAS])
        self.keypoints = nn.ModuleList([SpatialSoftmax(b.out_channels, config.keypoints) for b in self.backbones])
        self.language = instruction_encoder(config)
        self.normaliser = ActionNormaliser()
        obs_dim = len(CAMERAS) * 2 * config.keypoints + PROPRIO_DIM
        self.unet = ConditionalUnet1D(ACTION_DIM, config.n_obs * obs_dim + config.language_dim, config.step_embed_dim,
                                      config.down_dims, config.kernel_size, config.n_groups)
        self.train_scheduler = _scheduler('ddpm', config)
        self.sample_scheduler = _scheduler('ddim', config)

    def condition(self, obs: dict, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, n_obs x (cameras x 2 x keypoints + 9) + language_dim) global condition; images shifted at
        random while training."""
        images = obs['images']
        b, n = images.shape[:2]
        features = []
        for c, (backbone, keypoints) in enumerate(zip(self.backbones, self.keypoints)):
            frames = images[:, :, c].flatten(0, 1)                                    # (B n_obs, 3, h, w)
            if self.training:
                frames = random_shift(frames, generator)
            features.append(keypoints(backbone(frames)).reshape(b, n, -1))
        per_step = torch.cat([*features, obs['proprio'].float()], -1)                 # (B, n_obs, obs_dim)
        _, pooled = self.language(obs['instructions'])
        return torch.cat([per_step.flatten(1), pooled.to(per_step.device)], -1)

    def losses(self, batch: dict, generator: torch.Generator | None = None) -> dict:
        """{'noise_mse', 'total'}: the U-Net's epsilon error at random diffusion steps (means over the batch)."""
        actions = self.normaliser.normalise(batch['actions'].float())
        cond = self.condition(batch, generator)
        noise = torch.randn(actions.shape, generator=generator).to(actions.device)
        steps = torch.randint(0, self.config.train_timesteps, (len(actions),), generator=generator).to(actions.device)
        noisy = self.train_scheduler.add_noise(actions, noise, steps)
        loss = nn.functional.mse_loss(self.unet(noisy, steps, cond), noise)
        return {'noise_mse': loss, 'total': loss}

    @torch.no_grad()
    def predict(self, obs: dict, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, horizon, 8) actions sampled with DDIM (config.inference_steps), denormalised."""
        cond = self.condition(obs)
        scheduler = self.sample_scheduler
        scheduler.set_timesteps(self.config.inference_steps)
        x = torch.randn((len(cond), self.config.horizon, ACTION_DIM), generator=generator).to(cond.device)
        for t in scheduler.timesteps:
            eps = self.unet(x, t.reshape(1).to(cond.device), cond)
            x = scheduler.step(eps, t, x).prev_sample
        return self.normaliser.denormalise(x.clamp(-1, 1))
