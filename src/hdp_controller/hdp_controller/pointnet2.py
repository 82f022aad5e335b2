"""PointNet++ encoder (Qi et al. 2017), single-scale grouping, pure torch.

Set abstraction: farthest-point sampling picks centroids, a ball query
gathers up to K neighbours of each, a shared MLP embeds the neighbours'
offsets (and features), max-pooling summarises each ball. Two levels, then
a global set abstraction over what remains.
"""

from __future__ import annotations

import torch
from torch import nn


def farthest_point_sample(xyz: torch.Tensor, m: int) -> torch.Tensor:
    """(B, N, 3) -> (B, m) indices of points spread by iterative farthest-point sampling.

    Starts from point 0 so the result is deterministic.
    """
    b, n, _ = xyz.shape
    idx = torch.zeros(b, m, dtype=torch.long, device=xyz.device)
    distance = torch.full((b, n), float('inf'), device=xyz.device)
    farthest = torch.zeros(b, dtype=torch.long, device=xyz.device)
    rows = torch.arange(b, device=xyz.device)
    for i in range(m):
        idx[:, i] = farthest
        centroid = xyz[rows, farthest][:, None]                       # (B, 1, 3)
        distance = torch.minimum(distance, ((xyz - centroid) ** 2).sum(-1))
        farthest = distance.argmax(-1)
    return idx


def ball_query(xyz: torch.Tensor, centroids: torch.Tensor, radius: float, k: int) -> torch.Tensor:
    """Indices (B, M, k) of up to k points of xyz (B, N, 3) within radius of each centroid (B, M, 3).

    Balls with fewer than k points repeat their nearest point (always itself for a
    sampled centroid), as in the reference implementation.
    """
    d2 = torch.cdist(centroids, xyz) ** 2                              # (B, M, N)
    k = min(k, xyz.shape[1])
    nearest_d2, nearest = d2.topk(k, dim=-1, largest=False)            # sorted ascending
    return torch.where(nearest_d2 <= radius ** 2, nearest, nearest[..., :1])


def gather(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """points (B, N, C), idx (B, ...) -> (B, ..., C)."""
    b = points.shape[0]
    flat = idx.reshape(b, -1)
    out = torch.gather(points, 1, flat[..., None].expand(-1, -1, points.shape[-1]))
    return out.reshape(*idx.shape, points.shape[-1])


def shared_mlp(channels: list[int]) -> nn.Sequential:
    layers = []
    for c_in, c_out in zip(channels[:-1], channels[1:]):
        layers += [nn.Linear(c_in, c_out), nn.LayerNorm(c_out), nn.GELU()]
    return nn.Sequential(*layers)


class SetAbstraction(nn.Module):
    """(xyz (B, N, 3), features (B, N, C) or None) -> (centroids (B, M, 3), features (B, M, C'))."""

    def __init__(self, n_centroids: int, radius: float, k: int, channels: list[int]):
        super().__init__()
        self.n_centroids, self.radius, self.k = n_centroids, radius, k
        self.mlp = shared_mlp(channels)

    def forward(self, xyz: torch.Tensor, features: torch.Tensor | None):
        centroids = gather(xyz, farthest_point_sample(xyz, self.n_centroids))
        idx = ball_query(xyz, centroids, self.radius, self.k)
        grouped = (gather(xyz, idx) - centroids[:, :, None]) / self.radius   # (B, M, k, 3)
        if features is not None:
            grouped = torch.cat([grouped, gather(features, idx)], dim=-1)
        return centroids, self.mlp(grouped).max(dim=2).values


class PointNet2Encoder(nn.Module):
    """(B, N, 3) points in normalised workspace coordinates (about [-1, 1]) -> (B, out_dim).

    Radii are in those coordinates: 0.1 and 0.2 of the half-extent are ~3 and
    ~6 cm on our workspace.
    """

    def __init__(self, out_dim: int = 128, width: int = 32):
        super().__init__()
        self.sa1 = SetAbstraction(128, 0.1, 16, [3, width, width, 2 * width])
        self.sa2 = SetAbstraction(32, 0.25, 16, [3 + 2 * width, 2 * width, 2 * width, 4 * width])
        self.global_mlp = shared_mlp([3 + 4 * width, 4 * width, out_dim])

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        xyz1, f1 = self.sa1(xyz, None)
        xyz2, f2 = self.sa2(xyz1, f1)
        return self.global_mlp(torch.cat([xyz2, f2], dim=-1)).max(dim=1).values
