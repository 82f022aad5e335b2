"""Quaternion arithmetic in numpy (torch's is in hdp_motion.kinematics). Quaternions are (x, y, z, w)."""

from __future__ import annotations

import numpy as np


def quat_angle(qa, qb) -> np.ndarray:
    """(...,) angle in rad, in [0, pi], of the rotation between (..., 4) quaternions.

    Sign-invariant (q and -q are one rotation) and normalising, as
    kinematics.pose_error is for torch tensors.
    """
    a = np.asarray(qa, dtype=np.float64)
    b = np.asarray(qb, dtype=np.float64)
    dot = np.abs(np.sum(a * b, -1)) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return 2 * np.arccos(np.clip(dot, 0.0, 1.0))     # clip: rounding can put |dot| just above 1


def quat_to_matrix(quat) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (normalised first)."""
    q = np.asarray(quat, dtype=np.float64)
    x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
