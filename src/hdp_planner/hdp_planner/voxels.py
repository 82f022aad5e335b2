"""Both cameras' RGB-D -> world-frame coloured points -> PerAct-style voxel grids.

A grid is (B, CHANNELS, S, S, S) over an axis-aligned box, axes ordered
x, y, z; voxel (i, j, k) has flat index (i * S + j) * S + k. Channels:
  0-2  mean xyz of the voxel's points, normalised to [-1, 1] over the box
  3-5  mean RGB in [-1, 1]
  6    occupancy (1 where any point fell)
  7-9  the voxel's own index, normalised to [-1, 1]
Empty voxels are 0 except for their index. The coarse grid spans WORKSPACE;
the fine grid a cube of +-FINE_HALF_EXTENT around a centre (the coarse
prediction at inference).
"""

from __future__ import annotations

import numpy as np
import torch

from hdp_msgs_py.conversions import depth_to_points
from hdp_data.workspace import WORKSPACE, in_workspace

VOXELS = 16
FINE_HALF_EXTENT = 0.12        # m
CHANNELS = 10


def camera_points(rgb: np.ndarray, depth_m: np.ndarray, intrinsics, camera_to_world) -> tuple[np.ndarray, np.ndarray]:
    """World points of one aligned RGB-D frame: xyz (N, 3) float32 and their colours (N, 3) uint8.

    rgb: (H, W, 3) uint8; depth_m: (H, W) float metres (0 or non-finite = no reading).
    """
    depth = np.asarray(depth_m)
    xyz = depth_to_points(depth, intrinsics, camera_to_world)
    colours = np.asarray(rgb)[np.isfinite(depth) & (depth > 0)]    # same row-major order as xyz
    return xyz, colours


def scene_points(frames: dict, intrinsics: dict, camera_to_world: dict) -> tuple[np.ndarray, np.ndarray]:
    """All cameras' points inside WORKSPACE (above the table): xyz (N, 3) float32, colours (N, 3) uint8.

    frames: camera -> (rgb (H, W, 3) uint8, depth (H, W) float m); intrinsics and
    camera_to_world ((4, 4)) keyed the same way.
    """
    clouds = [camera_points(rgb, depth, intrinsics[cam], camera_to_world[cam])
              for cam, (rgb, depth) in sorted(frames.items())]
    xyz = np.concatenate([c[0] for c in clouds])
    colours = np.concatenate([c[1] for c in clouds])
    keep = in_workspace(xyz)
    return xyz[keep], colours[keep]


def workspace_bounds(batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3) lower and upper corners of WORKSPACE for B grids."""
    bounds = torch.as_tensor(WORKSPACE, dtype=torch.float32)
    return bounds[0].expand(batch, 3), bounds[1].expand(batch, 3)


def fine_bounds(centre: torch.Tensor, half_extent: float = FINE_HALF_EXTENT) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3) lower and upper corners of the fine cube around (B, 3) centres."""
    return centre - half_extent, centre + half_extent


def voxel_size(lower: torch.Tensor, upper: torch.Tensor, size: int = VOXELS) -> torch.Tensor:
    """(B, 3) edge lengths of a voxel in m."""
    return (upper - lower) / size


def voxel_of(xyz: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
             size: int = VOXELS) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat voxel index (B,) int64 of (B, 3) positions, clamped into the grid, and their
    sub-voxel offsets (B, 3) in [0, 1) voxel units (outside the grid they saturate)."""
    cell = (xyz - lower) / voxel_size(lower, upper, size)
    ijk = cell.floor().clamp(0, size - 1)
    offset = (cell - ijk).clamp(0, 1 - 1e-6)
    ijk = ijk.long()
    return (ijk[:, 0] * size + ijk[:, 1]) * size + ijk[:, 2], offset


def position_of(index: torch.Tensor, offset: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
                size: int = VOXELS) -> torch.Tensor:
    """(B, 3) world positions of flat voxel indices (B,) plus offsets (B, 3) in voxel units
    (0.5 = the voxel centre)."""
    ijk = torch.stack([index // (size * size), (index // size) % size, index % size], -1)
    return lower + (ijk.to(lower.dtype) + offset) * voxel_size(lower, upper, size)


def voxelise(xyz: torch.Tensor, rgb: torch.Tensor, batch: torch.Tensor, lower: torch.Tensor,
             upper: torch.Tensor, size: int = VOXELS) -> torch.Tensor:
    """(B, CHANNELS, S, S, S) grids of a batch of point clouds, one scatter-add for all.

    xyz: (P, 3) float points of all clouds; rgb: (P, 3) colours in [-1, 1];
    batch: (P,) int64 cloud of each point; lower, upper: (B, 3) grid corners.
    Points outside their grid are dropped.
    """
    n = lower.shape[0]
    lo, extent = lower[batch], (upper - lower)[batch]
    unit = (xyz - lo) / extent                                   # [0, 1) inside the grid
    ijk = (unit * size).floor().long()
    inside = ((ijk >= 0) & (ijk < size)).all(1)
    ijk, batch = ijk[inside], batch[inside]
    flat = ((batch * size + ijk[:, 0]) * size + ijk[:, 1]) * size + ijk[:, 2]
    features = torch.cat([unit[inside] * 2 - 1, rgb[inside], torch.ones_like(unit[inside, :1])], 1)
    sums = torch.zeros(n * size ** 3, 7, dtype=xyz.dtype, device=xyz.device).index_add_(0, flat, features)
    count = sums[:, 6:]
    axis = torch.linspace(-1, 1, size, dtype=xyz.dtype, device=xyz.device)
    index = torch.stack(torch.meshgrid(axis, axis, axis, indexing='ij'), -1).view(-1, 3)
    cells = torch.cat([sums[:, :6] / count.clamp(min=1), (count > 0).to(xyz.dtype), index.repeat(n, 1)], 1)
    # A channels-last (3D) view: the layout the convolutions are fastest with on CPU.
    return cells.view(n, size, size, size, CHANNELS).permute(0, 4, 1, 2, 3)


def collate_clouds(clouds, device='cpu') -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One (xyz (P, 3) float32, rgb (P, 3) in [-1, 1], batch (P,) int64) of B (xyz (N, 3), rgb (N, 3) uint8) clouds."""
    xyz = torch.as_tensor(np.concatenate([c[0] for c in clouds]), dtype=torch.float32, device=device)
    rgb = torch.as_tensor(np.concatenate([c[1] for c in clouds]), device=device).float() / 127.5 - 1
    batch = torch.repeat_interleave(torch.arange(len(clouds), device=device),
                                    torch.as_tensor([len(c[0]) for c in clouds], device=device))
    return xyz, rgb, batch
