"""Orientations as PerAct's discrete Euler bins, and the world-frame yaw they are augmented by.

Euler angles are extrinsic x-y-z in the world frame, R = Rz(c) Ry(b) Rx(a),
each in [-180, 180) degrees and discretised into ``BINS`` bins of
``BIN_DEGREES`` centred on multiples of 5 deg (bin i <-> i * 5 - 180 deg).
The convention locks (b = +-90 deg) only when the hand's x axis is vertical,
which no task's grasp asks for; the top-down and pitched grasps the experts
use stay far from it.

Quaternions are (x, y, z, w). Everything is vectorised over leading axes.
"""

from __future__ import annotations

import numpy as np

from hdp_motion.rotations import quat_angle, quat_to_matrix

BIN_DEGREES = 5
BINS = 360 // BIN_DEGREES

angle_between = quat_angle      # (...,) geodesic angle in rad between two (..., 4) orientations


def euler_to_quat(euler) -> np.ndarray:
    """(..., 4) unit quaternions with w >= 0 of (..., 3) extrinsic xyz Euler angles (rad)."""
    half = np.asarray(euler, dtype=np.float64) / 2
    (ca, cb, cc), (sa, sb, sc) = np.moveaxis(np.cos(half), -1, 0), np.moveaxis(np.sin(half), -1, 0)
    q = np.stack([sa * cb * cc - ca * sb * sc,
                  ca * sb * cc + sa * cb * sc,
                  ca * cb * sc - sa * sb * cc,
                  ca * cb * cc + sa * sb * sc], -1)
    return np.where(q[..., 3:] < 0, -q, q)


def quat_to_euler(quat) -> np.ndarray:
    """(..., 3) extrinsic xyz Euler angles (rad, in [-pi, pi]) of (..., 4) quaternions.

    At the lock (|b| = 90 deg) a is set to 0 and c carries the whole yaw.
    """
    m = quat_to_matrix(quat)
    b = -np.arcsin(np.clip(m[..., 2, 0], -1.0, 1.0))
    locked = np.abs(m[..., 2, 0]) > 1 - 1e-9
    a = np.where(locked, 0.0, np.arctan2(m[..., 2, 1], m[..., 2, 2]))
    c = np.where(locked, np.arctan2(-m[..., 0, 1], m[..., 1, 1]), np.arctan2(m[..., 1, 0], m[..., 0, 0]))
    return np.stack([a, b, c], -1)


def euler_to_bins(euler) -> np.ndarray:
    """(..., 3) int64 bins of (..., 3) Euler angles in rad (nearest multiple of 5 deg)."""
    degrees = np.degrees(np.asarray(euler, dtype=np.float64))
    return np.round((degrees + 180.0) / BIN_DEGREES).astype(np.int64) % BINS


def bins_to_euler(bins) -> np.ndarray:
    """(..., 3) Euler angles in rad of (..., 3) integer bins."""
    return np.radians(np.asarray(bins, dtype=np.float64) * BIN_DEGREES - 180.0)


def quat_to_bins(quat) -> np.ndarray:
    """(..., 3) int64 rotation labels of (..., 4) quaternions."""
    return euler_to_bins(quat_to_euler(quat))


def bins_to_quat(bins) -> np.ndarray:
    """(..., 4) quaternions of (..., 3) rotation bins."""
    return euler_to_quat(bins_to_euler(bins))


def yaw_quat(quat, angle) -> np.ndarray:
    """(..., 4) orientations turned by ``angle`` rad about the world z axis: q' = Rz(angle) q.

    The world-frame rotation that matches rotating the scene's points about a
    vertical axis (PerAct rotates in the gripper frame instead, which
    mislabels pitched grasps).
    """
    q = np.asarray(quat, dtype=np.float64)
    s, c = np.sin(np.asarray(angle) / 2), np.cos(np.asarray(angle) / 2)
    x, y, z, w = np.moveaxis(q, -1, 0)
    # Hamilton product (0, 0, s, c) * (x, y, z, w)
    return np.stack([c * x - s * y, c * y + s * x, c * z + s * w, c * w - s * z], -1)


def flip_about_approach(quat) -> np.ndarray:
    """(..., 4) the same grasp with the wrist turned 180 deg about the hand's z axis: q' = q * Rz(pi)."""
    x, y, z, w = np.moveaxis(np.asarray(quat, dtype=np.float64), -1, 0)
    # Hamilton product (x, y, z, w) * (0, 0, 1, 0)
    return np.stack([y, -x, w, -z], -1)
