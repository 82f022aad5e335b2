"""ACT: Action Chunking with Transformers (Zhao et al., RSS 2023), small enough for a CPU.

A conditional VAE over action chunks, built from torch.nn.Transformer pieces as the paper's
code (DETR-style) is:

- encoder (training only): [CLS, proprio, action_1 .. action_H] -> transformer encoder -> the
  CLS output -> (mu, log sigma^2) of a latent z (dim latent_dim); padded actions are masked;
- decoder: [z, proprio, instruction] tokens and each camera's feature map (8 x 6 cells, 2D
  sine positions plus a camera embedding) -> transformer encoder; H learned queries ->
  transformer decoder -> H actions.

Loss: L1 between the normalised predicted and demonstrated actions (padding masked) + kl_weight
x KL(q(z) || N(0, I)); at inference z = 0. ACT's chunk of 100 at 50 Hz is 2 s; here 20 at
10 Hz, with its temporal ensembling (a query every step, exp(-m i) weights with m scaled from
0.01 per 50 Hz step to 0.05 per 10 Hz step) done by policy.FlatPolicy.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from .encoders import (ACTION_DIM, CAMERAS, PROPRIO_DIM, ActionNormaliser, CameraBackbone, FlatModelConfig,
                       instruction_encoder, random_shift)


@dataclasses.dataclass(frozen=True)
class ACTConfig(FlatModelConfig):
    """ACT at 10 Hz: one observation step, a 20-step chunk, temporal ensembling (ensemble > 0: the
    weights' decay per step; 0 runs n_action_steps of each chunk open-loop instead).
    The paper's d_model 512, 4 encoder / 7 decoder layers, scaled down."""
    n_obs: int = 1
    horizon: int = 20
    n_action_steps: int = 1
    ensemble: float = 0.05
    d_model: int = 128
    heads: int = 4
    encoder_layers: int = 2
    decoder_layers: int = 2
    feedforward: int = 512
    latent_dim: int = 32
    dropout: float = 0.1
    kl_weight: float = 10.0

    def __post_init__(self):
        super().__post_init__()
        if self.n_obs != 1:
            raise ValueError('ACT observes one step (n_obs 1)')
        if self.d_model % self.heads or self.ensemble < 0:
            raise ValueError('d_model must be divisible by heads, and ensemble >= 0')


def sine_positions_2d(h: int, w: int, dim: int) -> torch.Tensor:
    """(h * w, dim) DETR-style 2D sine position embeddings: half the channels for y, half for x."""
    quarter = dim // 4
    frequencies = 1.0 / (10000 ** (torch.arange(quarter) / quarter))
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing='ij')
    parts = []
    for coordinate in (ys.flatten(), xs.flatten()):
        angles = coordinate[:, None] * frequencies[None]
        parts += [angles.sin(), angles.cos()]
    return torch.cat(parts, -1)


def sine_positions_1d(n: int, dim: int) -> torch.Tensor:
    """(n, dim) transformer sine position embeddings."""
    half = dim // 2
    angles = torch.arange(n, dtype=torch.float32)[:, None] / (10000 ** (torch.arange(half) / half))[None]
    return torch.cat([angles.sin(), angles.cos()], -1)


def _encoder(config: ACTConfig, layers: int) -> nn.TransformerEncoder:
    layer = nn.TransformerEncoderLayer(config.d_model, config.heads, config.feedforward, config.dropout,
                                       batch_first=True, norm_first=True)
    return nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)


class ACTNet(nn.Module):
    """Observations (images (B, 1, 2, 3, h, w) uint8, proprio (B, 1, 9), instructions) -> action chunks
    (B, horizon, 8): absolute joint targets (rad) and gripper (+1 open, -1 closed)."""

    def __init__(self, config: ACTConfig):
        super().__init__()
        self.config = config
        d = config.d_model
        self.normaliser = ActionNormaliser()
        self.language = instruction_encoder(config)
        # The CVAE encoder.
        self.cls = nn.Parameter(torch.zeros(1, 1, d))
        self.encoder_proprio = nn.Linear(PROPRIO_DIM, d)
        self.encoder_action = nn.Linear(ACTION_DIM, d)
        self.vae_encoder = _encoder(config, config.encoder_layers)
        self.latent = nn.Linear(d, 2 * config.latent_dim)
        self.register_buffer('encoder_positions', sine_positions_1d(config.horizon + 2, d)[None], persistent=False)
        # The decoder's inputs.
        self.backbones = nn.ModuleList([CameraBackbone(config.channels) for _ in CAMERAS])
        self.image_projection = nn.ModuleList([nn.Conv2d(b.out_channels, d, 1) for b in self.backbones])
        self.camera_embedding = nn.Parameter(torch.zeros(len(CAMERAS), d))
        self.latent_projection = nn.Linear(config.latent_dim, d)
        self.proprio_projection = nn.Linear(PROPRIO_DIM, d)
        self.language_projection = nn.Linear(config.language_dim, d)
        self.token_embedding = nn.Parameter(torch.zeros(3, d))          # z, proprio, instruction
        self.encoder = _encoder(config, config.encoder_layers)
        layer = nn.TransformerDecoderLayer(d, config.heads, config.feedforward, config.dropout, batch_first=True,
                                           norm_first=True)
        self.decoder = nn.TransformerDecoder(layer, config.decoder_layers)
        self.queries = nn.Parameter(torch.zeros(config.horizon, d))
        self.head = nn.Linear(d, ACTION_DIM)
        for p in (self.cls, self.camera_embedding, self.token_embedding, self.queries):
            nn.init.normal_(p, std=0.02)

    def encode_actions(self, proprio: torch.Tensor, actions: torch.Tensor, is_pad: torch.Tensor):
        """(mu, logvar), each (B, latent_dim), of normalised actions (B, H, 8) given proprio (B, 9)."""
        tokens = torch.cat([self.cls.expand(len(actions), -1, -1), self.encoder_proprio(proprio)[:, None],
                            self.encoder_action(actions)], 1) + self.encoder_positions
        mask = torch.cat([torch.zeros(len(actions), 2, dtype=torch.bool, device=actions.device), is_pad], 1)
        return self.latent(self.vae_encoder(tokens, src_key_padding_mask=mask)[:, 0]).chunk(2, -1)

    def decode(self, obs: dict, z: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, horizon, 8) normalised actions for observations and latents z (B, latent_dim)."""
        images = obs['images'][:, -1]                                                  # (B, C, 3, h, w)
        tokens = []
        for c, (backbone, projection) in enumerate(zip(self.backbones, self.image_projection)):
            frames = images[:, c]
            if self.training:
                frames = random_shift(frames, generator)
            features = projection(backbone(frames))                                    # (B, d, h', w')
            positions = sine_positions_2d(*features.shape[2:], self.config.d_model).to(features.device)
            tokens.append(features.flatten(2).transpose(1, 2) + positions + self.camera_embedding[c])
        _, pooled = self.language(obs['instructions'])
        proprio = obs['proprio'][:, -1].float()
        first = torch.stack([self.latent_projection(z), self.proprio_projection(proprio),
                             self.language_projection(pooled.to(proprio.device))], 1) + self.token_embedding
        memory = self.encoder(torch.cat([first, *tokens], 1))
        queries = (self.queries + sine_positions_1d(self.config.horizon, self.config.d_model).to(memory.device))
        return self.head(self.decoder(queries.expand(len(memory), -1, -1), memory))

    def losses(self, batch: dict, generator: torch.Generator | None = None) -> dict:
        """{'l1', 'kl', 'total'}: masked L1 of the normalised chunk, KL of the latent, l1 + kl_weight x kl."""
        actions = self.normaliser.normalise(batch['actions'].float())
        is_pad = batch['is_pad']
        mu, logvar = self.encode_actions(batch['proprio'][:, -1].float(), actions, is_pad)
        z = mu + (0.5 * logvar).exp() * torch.randn(mu.shape, generator=generator).to(mu.device)
        predicted = self.decode(batch, z, generator)
        valid = (~is_pad).float()[..., None]
        l1 = ((predicted - actions).abs() * valid).sum() / (valid.sum() * ACTION_DIM).clamp(min=1)
        kl = (-0.5 * (1 + logvar - mu ** 2 - logvar.exp())).sum(-1).mean()
        return {'l1': l1, 'kl': kl, 'total': l1 + self.config.kl_weight * kl}

    @torch.no_grad()
    def predict(self, obs: dict, generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, horizon, 8) actions with z = 0 (the prior's mean), denormalised."""
        z = torch.zeros(len(obs['proprio']), self.config.latent_dim, device=obs['proprio'].device)
        return self.normaliser.denormalise(self.decode(obs, z).clamp(-1, 1))
