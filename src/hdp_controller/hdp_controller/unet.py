"""Diffuser's temporal U-Net (Janner et al. 2022): Conv1D over the horizon.

Residual temporal blocks (kernel 5, GroupNorm 8, Mish), each adding the
embedding of (diffusion step, conditions); 3 down levels (the last keeps
the length), a middle, 3 up levels with skip connections.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """(B,) steps -> (B, dim)."""
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=t.device) * -(math.log(10000) / (half - 1)))
        angles = t.float()[:, None] * freqs[None]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class Conv1dBlock(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel: int = 5, groups: int = 8):
        super().__init__(nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2), nn.GroupNorm(groups, c_out), nn.Mish())


class ResidualTemporalBlock(nn.Module):
    """x (B, c_in, T), emb (B, E) -> (B, c_out, T)."""

    def __init__(self, c_in: int, c_out: int, emb_dim: int, kernel: int = 5):
        super().__init__()
        self.block1, self.block2 = Conv1dBlock(c_in, c_out, kernel), Conv1dBlock(c_out, c_out, kernel)
        self.emb = nn.Sequential(nn.Mish(), nn.Linear(emb_dim, c_out))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.block1(x) + self.emb(emb)[:, :, None]
        return self.block2(h) + self.skip(x)


class TemporalUnet(nn.Module):
    """x (B, T, D) noisy trajectory, t (B,) step, cond (B, C), local (B, T, L) or None -> (B, T, D).

    ``local``: per-waypoint conditions (``local_dim`` channels) read beside x, where the
    global ``cond`` only shifts every waypoint's features alike.
    T must be divisible by 2 ** (len(dim_mults) - 1).
    """

    def __init__(self, transition_dim: int, cond_dim: int, dim: int = 32, dim_mults=(1, 2, 4), local_dim: int = 0):
        super().__init__()
        dims = [transition_dim + local_dim] + [dim * m for m in dim_mults]
        emb_dim = dim * 4
        self.time_mlp = nn.Sequential(SinusoidalPosEmb(dim), nn.Linear(dim, emb_dim), nn.Mish(),
                                      nn.Linear(emb_dim, emb_dim))
        self.cond_mlp = nn.Sequential(nn.Linear(cond_dim, emb_dim), nn.Mish(), nn.Linear(emb_dim, emb_dim))
        self.downs, self.ups = nn.ModuleList(), nn.ModuleList()
        levels = list(zip(dims[:-1], dims[1:]))
        for i, (c_in, c_out) in enumerate(levels):
            last = i == len(levels) - 1
            self.downs.append(nn.ModuleList([
                ResidualTemporalBlock(c_in, c_out, emb_dim), ResidualTemporalBlock(c_out, c_out, emb_dim),
                nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1)]))
        mid = dims[-1]
        self.mid1, self.mid2 = ResidualTemporalBlock(mid, mid, emb_dim), ResidualTemporalBlock(mid, mid, emb_dim)
        for c_in, c_out in reversed(levels[1:]):
            self.ups.append(nn.ModuleList([
                ResidualTemporalBlock(c_out * 2, c_in, emb_dim), ResidualTemporalBlock(c_in, c_in, emb_dim),
                nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1)]))
        self.final = nn.Sequential(Conv1dBlock(dim, dim), nn.Conv1d(dim, transition_dim, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                local: torch.Tensor | None = None) -> torch.Tensor:
        emb = self.time_mlp(t) + self.cond_mlp(cond)
        h = (x if local is None else torch.cat([x, local], dim=-1)).transpose(1, 2)
        skips = []
        for block1, block2, down in self.downs:
            h = block2(block1(h, emb), emb)
            skips.append(h)
            h = down(h)
        h = self.mid2(self.mid1(h, emb), emb)
        # As in Diffuser, the full-resolution skip of the first level is not used.
        for block1, block2, up in self.ups:
            h = block2(block1(torch.cat([h, skips.pop()], dim=1), emb), emb)
            h = up(h)
        return self.final(h).transpose(1, 2)
