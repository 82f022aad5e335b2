"""Differentiable Panda forward kinematics (pytorch-kinematics) and rotation helpers.

The end effector is ``panda_grasptarget`` (0.105 m beyond the hand flange),
the link the sim's IK, the experts and the next-best poses all use; the
chain is pybullet_data's Panda URDF with its base at the world-frame robot
base (on the table top). Quaternions are xyzw, as in ROS and PyBullet.
"""

from __future__ import annotations

import contextlib
import functools
import os

import pybullet_data
import pytorch_kinematics as pk
import pytorch_kinematics.urdf_parser_py.xml_reflection.core as urdf_core
import torch

from .panda import EE_LINK, ROBOT_BASE


@contextlib.contextmanager
def _quiet_urdf_parser():
    """pybullet's URDF carries tags (contact, collision material) the parser warns about."""
    previous, urdf_core.on_error = urdf_core.on_error, lambda message: None
    try:
        yield
    finally:
        urdf_core.on_error = previous


@functools.lru_cache(maxsize=None)
def panda_chain(dtype: torch.dtype, device: str) -> pk.SerialChain:
    with open(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'), 'rb') as f:
        urdf = f.read()
    with _quiet_urdf_parser():
        chain = pk.build_serial_chain_from_urdf(urdf, EE_LINK)
    return chain.to(dtype=dtype, device=device)


def forward_kinematics(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World-frame panda_grasptarget pose of joint positions q (..., 7) rad.

    Returns (position (..., 3) m, rotation matrix (..., 3, 3)); differentiable in q.
    """
    chain = panda_chain(q.dtype, str(q.device))
    matrix = chain.forward_kinematics(q.reshape(-1, 7)).get_matrix()
    position = matrix[:, :3, 3] + torch.tensor(ROBOT_BASE, dtype=q.dtype, device=q.device)
    return position.reshape(*q.shape[:-1], 3), matrix[:, :3, :3].reshape(*q.shape[:-1], 3, 3)


def quat_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions xyzw (normalised here) -> (..., 3, 3) rotation matrices."""
    x, y, z, w = torch.nn.functional.normalize(quat, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quat.shape[:-1], 3, 3)


def matrix_to_quat(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions xyzw with w >= 0."""
    wxyz = pk.matrix_to_quaternion(matrix)
    wxyz = torch.where(wxyz[..., :1] < 0, -wxyz, wxyz)
    return torch.cat([wxyz[..., 1:], wxyz[..., :1]], dim=-1)


def fk_pose(q: torch.Tensor) -> torch.Tensor:
    """(..., 7) joints -> (..., 7) pose xyz + quaternion xyzw (w >= 0)."""
    position, rotation = forward_kinematics(q)
    return torch.cat([position, matrix_to_quat(rotation)], dim=-1)


def pose_error(pose_a: torch.Tensor, pose_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Translation error (m) and rotation angle (rad) between (..., 7) poses; sign-invariant in q."""
    translation = torch.linalg.norm(pose_a[..., :3] - pose_b[..., :3], dim=-1)
    qa = torch.nn.functional.normalize(pose_a[..., 3:], dim=-1)
    qb = torch.nn.functional.normalize(pose_b[..., 3:], dim=-1)
    dot = (qa * qb).sum(-1).abs().clamp(max=1.0)
    return translation, 2 * torch.acos(dot)


def continuous_quats(quats: torch.Tensor) -> torch.Tensor:
    """(..., T, 4) -> the same rotations with signs chosen so neighbours have dot >= 0,
    starting from w >= 0: a trajectory a network can regress without jumps."""
    out = [torch.where(quats[..., 0, 3:] < 0, -quats[..., 0, :], quats[..., 0, :])]
    for t in range(1, quats.shape[-2]):
        q = quats[..., t, :]
        signs = torch.where((q * out[-1]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        out.append(q * signs)
    return torch.stack(out, dim=-2)
