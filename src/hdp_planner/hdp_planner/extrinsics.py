"""Check and refine a camera's extrinsics against the robot's own body, without ROS.

A hand-eye calibration a few millimetres and a degree off shifts every point a camera sees by 1-2
cm at the workspace (issue 40). The camera sees the robot too, and the robot's surface is known
exactly from the joint states and the URDF (hdp_motion.body); so the robot pixels of one depth
frame pin down where the camera really is. ``refine_extrinsics`` registers them to the robot's
surface with gated point-to-plane ICP and returns the corrected camera_to_world, or refuses: when
too little of the robot is in view, when the fit does not hold, or when the correction is too large
to be a calibration error (then the camera has moved, or the joint states are wrong, and someone
must say so rather than the planner silently absorbing it).

The correction E is rigid and in the camera's own frame: camera_to_world_true = camera_to_world @ E,
as hdp_sim_bridge's sensor model applies a calibration error.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from hdp_motion.body import body_surface
from hdp_motion.panda import ROBOT_BASE
from hdp_msgs_py.conversions import Intrinsics

MAX_PIXELS = 40_000          # depth pixels looked at, by a stride: 640x480 every 3rd (34k), 128x96 all
MAX_POINTS = 3_000           # robot points registered: 640x480 shows ~30k (3k at stride 3), 128x96 ~1k
GATES_MM = (50.0, 35.0, 25.0, 18.0, 13.0)    # correspondence gate per iteration, then final_gate_mm
MAX_ITERATIONS = 25          # ~10 suffice for a 5 mm / 1 deg error
CONVERGED_MM, CONVERGED_DEG = 0.01, 0.001    # an update this small ends the iterations
GATE_SIGMAS = 4.0            # the gate never cuts closer than this many robust sigmas of the residual
SPACING = 0.015              # m: slack for the model's sample spacing (~1.1 cm) in the 3D gate
CLEARANCE = 0.03             # m above the robot's mount where the robot's and the mount's points part
# Of the fit's scaled 6x6 normal matrix: whole-arm views measure 3-12, a third of the arm ~25, a
# single link 17-150 (fits off by up to 1 cm even on ideal depth): beyond this one direction is weak.
MAX_CONDITION = 30.0


@dataclasses.dataclass(frozen=True)
class ExtrinsicRefinement:
    """The outcome of one refinement.

    camera_to_world: (4, 4) the corrected pose when accepted, else the given one, unchanged.
    translation_mm, rotation_deg: size of the correction found (camera centre shift, turn angle);
    0 when none was fitted. residual_mm: RMS point-to-plane distance of the robot points used to the
    robot's surface after the fit (nan when none was fitted). points: robot points used;
    inlier_share: their share of the depth points near the robot and above its mount. condition:
    condition number of the fit's scaled normal matrix (large: some direction is barely seen).
    accepted: whether camera_to_world was corrected; why: the reason when not, '' otherwise.
    """
    camera_to_world: np.ndarray
    translation_mm: float
    rotation_deg: float
    residual_mm: float
    points: int
    inlier_share: float
    condition: float
    accepted: bool
    why: str = ''


def refine_extrinsics(depth_m: np.ndarray, intrinsics: Intrinsics, camera_to_world, joint_positions,
                      finger_width: float, *, final_gate_mm: float = 10.0, min_points: int = 300,
                      max_translation_mm: float = 30.0, max_rotation_deg: float = 5.0,
                      max_residual_mm: float = 10.0, min_inlier_share: float = 0.85) -> ExtrinsicRefinement:
    """Refine ``camera_to_world`` (4, 4) (the /tf_static pose of the optical frame) from one depth
    frame (H, W) float m (0 or non-finite: no reading) taken with ``intrinsics`` while the arm stood
    at ``joint_positions`` (7,) rad with the fingers ``finger_width`` m apart (the sum of the two
    finger joints).

    The correspondence gate shrinks from 50 mm to ``final_gate_mm``, or to GATE_SIGMAS robust sigmas
    of the residual where depth noise is larger. Refused (accepted False, pose unchanged) with fewer
    than ``min_points`` robot points, when the visible surface leaves a direction unconstrained
    (MAX_CONDITION), when the correction exceeds ``max_translation_mm`` or ``max_rotation_deg``, or
    when the fit does not hold: RMS residual above ``max_residual_mm`` or less than
    ``min_inlier_share`` of the depth points near the robot on its surface.
    """
    nominal = np.asarray(camera_to_world, dtype=np.float64)
    observed = _depth_points(np.asarray(depth_m), intrinsics)
    # The robot's surface in the nominal camera frame, only where it faces the camera: back faces
    # cannot be seen and would only offer wrong correspondences.
    world_to_camera = np.linalg.inv(nominal)
    points, normals = body_surface(joint_positions, finger_width)
    model = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    model_normals = normals @ world_to_camera[:3, :3].T
    facing = np.einsum('ij,ij->i', model, model_normals) < 0
    # The robot stands on its mount (a table, a plate): the plane z = 0 of its base link, here world z
    # = ROBOT_BASE z. Near that plane the mount's points lie right beside the base's: drop both.
    above = points[:, 2] > ROBOT_BASE[2] + CLEARANCE
    model, model_normals = model[facing & above], model_normals[facing & above]
    # Height above the mount of a nominal-camera-frame point p: mount @ (p, 1).
    mount = np.append(nominal[2, :3], nominal[2, 3] - ROBOT_BASE[2])

    observed = _near(observed, model, GATES_MM[0] * 1e-3)
    if len(observed) > MAX_POINTS:          # evenly over the raster order: spread over the robot
        observed = observed[np.linspace(0, len(observed) - 1, MAX_POINTS).round().astype(int)]

    def refused(why, translation_mm=0.0, rotation_deg=0.0, residual_mm=math.nan, points=0, inlier_share=0.0,
                condition=math.nan):
        return ExtrinsicRefinement(nominal.copy(), translation_mm, rotation_deg, residual_mm, points,
                                   inlier_share, condition, False, why)

    if len(observed) < min_points:
        return refused(f'only {len(observed)} depth points near where the robot should be (need '
                       f'{min_points}): the robot is out of view or hidden')

    correction, residual, used, share, condition = _icp(observed, model, model_normals, mount,
                                                        final_gate_mm * 1e-3)
    translation_mm = float(np.linalg.norm(correction[:3, 3]) * 1e3)
    rotation_deg = _angle_deg(correction[:3, :3])
    rms_mm = residual * 1e3
    result = dict(translation_mm=translation_mm, rotation_deg=rotation_deg, residual_mm=rms_mm, points=used,
                  inlier_share=share, condition=condition)
    if used < min_points:
        return refused(f'only {used} depth points fit the robot model (need {min_points}): the robot is '
                       'out of view, hidden, or not where the joint states put it', **result)
    if not condition <= MAX_CONDITION:
        return refused(f'the robot in view does not constrain all six degrees of freedom '
                       f'(condition number {condition:.0f} > {MAX_CONDITION:.0f})', **result)
    if translation_mm > max_translation_mm or rotation_deg > max_rotation_deg:
        return refused(f'correction {translation_mm:.1f} mm / {rotation_deg:.2f} deg exceeds '
                       f'{max_translation_mm:g} mm / {max_rotation_deg:g} deg: the camera has moved '
                       '(or the joint states are wrong); calibrate it again', **result)
    if rms_mm > max_residual_mm or share < min_inlier_share:
        return refused(f'the depth does not fit the robot model ({share:.0%} of the points near it fit, '
                       f'need {min_inlier_share:.0%}; residual {rms_mm:.1f} mm rms, limit '
                       f'{max_residual_mm:g} mm): wrong joint states, a grasped or occluding object, '
                       'or bad depth', **result)
    return ExtrinsicRefinement(nominal @ correction, accepted=True, **result)


def _depth_points(depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(N, 3) float64 optical-frame points of every s-th pixel of each s-th row (s keeps N below
    MAX_PIXELS), in raster order."""
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f'depth must be float metres, got {depth.dtype} (16UC1 millimetres: multiply by 0.001)')
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f'depth has shape {depth.shape}, intrinsics are for (H, W) = '
                         f'{(intrinsics.height, intrinsics.width)}')
    stride = max(1, math.ceil(math.sqrt(depth.size / MAX_PIXELS)))
    z = depth[::stride, ::stride].astype(np.float64)
    v, u = np.nonzero(np.isfinite(z) & (z > 0))
    z = z[v, u]
    return np.stack([(u * stride - intrinsics.cx) * z / intrinsics.fx,
                     (v * stride - intrinsics.cy) * z / intrinsics.fy, z], axis=1)


def _nearest(query: np.ndarray, model: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Index (N,) of the nearest of ``model`` (M, 3) to each of ``query`` (N, 3), and its distance (N,)."""
    # float32 about the model's centre: cdist's |a|^2 + |b|^2 - 2ab then loses < 0.1 mm at 1 m ranges.
    centre = model.mean(axis=0)
    m = torch.as_tensor(model - centre, dtype=torch.float32)
    q = torch.as_tensor(query - centre, dtype=torch.float32)
    index = torch.cat([torch.cdist(part, m).argmin(dim=1) for part in q.split(chunk)]).numpy()
    return index, np.linalg.norm(query - model[index], axis=1)


def _near(points: np.ndarray, model: np.ndarray, gate: float) -> np.ndarray:
    """The ``points`` (N, 3) within ``gate`` m of ``model`` (M, 3). Most pixels are table and floor:
    a voxel test (cells of ``gate``, the model's cells and their neighbours) drops them before the
    exact distances."""
    code = np.array([1 << 42, 1 << 21, 1])        # one int64 per cell; linear, so neighbours add up
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing='ij'), -1).reshape(-1, 3)

    def keys(p):                                   # cell indices stay within +-2^20 (+-50 km at 5 cm)
        return np.floor(p / gate).astype(np.int64) @ code
    occupied = np.unique(keys(model)[:, None] + offsets @ code)
    candidates = points[np.isin(keys(points), occupied)]
    if len(candidates) == 0:
        return candidates
    return candidates[_nearest(candidates, model)[1] < gate]


def _icp(observed, model, normals, mount, final_gate):
    """Gated point-to-plane ICP with Tukey weights of ``observed`` (N, 3) onto ``model`` (M, 3) with
    outward ``normals`` (M, 3); ``mount`` (4,): height above the mount of a point p is mount @ (p, 1).

    Returns (E (4, 4) with model ~ E @ observed, RMS residual m, points used, their share of the
    points above the mount, condition number of the last normal matrix). Correspondences go
    observed -> model (every observed point has a surface under it; many model points are hidden)
    and are gated; nothing more is trimmed (with stereo noise, dropping the worst share pulls the
    fit towards its start), Tukey's weights take the rest of the outliers.
    """
    correction = np.eye(4)
    gate = GATES_MM[0] * 1e-3
    residual, used, share, condition = math.nan, 0, 0.0, math.nan
    for iteration in range(MAX_ITERATIONS):
        moved = observed @ correction[:3, :3].T + correction[:3, 3]
        index, distance = _nearest(moved, model)
        r = np.einsum('ij,ij->i', moved - model[index], normals[index])
        # The nearest sample may lie up to a sample spacing aside of the surface point under an
        # observed one, so the gate is on the distance to its plane, with SPACING of slack in 3D.
        above = moved @ mount[:3] + mount[3] > CLEARANCE
        keep = (distance < gate + SPACING) & (np.abs(r) < gate) & above
        used, share = int(keep.sum()), float(keep.sum() / max(above.sum(), 1))
        if used < 6:
            break
        p, n, r = moved[keep], normals[index[keep]], r[keep]
        residual = float(np.sqrt(np.mean(r ** 2)))
        sigma = 1.4826 * float(np.median(np.abs(r)))            # robust spread of the depth noise
        weight = np.clip(1 - (r / (4.685 * sigma + 1e-9)) ** 2, 0, None) ** 2      # Tukey's biweight
        # Rotation about the points' centroid, scaled by their spread: the six unknowns then have
        # comparable units (m) and the normal matrix's condition number measures geometry alone.
        centroid = p.mean(axis=0)
        scale = float(np.sqrt(np.mean(np.sum((p - centroid) ** 2, axis=1))))
        jacobian = np.concatenate([np.cross(p - centroid, n) / scale, n], axis=1)      # (K, 6)
        normal_matrix = jacobian.T @ (jacobian * weight[:, None])
        eigen = np.linalg.eigvalsh(normal_matrix)
        condition = float(eigen[-1] / max(eigen[0], 1e-300))
        step = -np.linalg.lstsq(normal_matrix, jacobian.T @ (weight * r), rcond=None)[0]
        correction = _rigid(step[:3] / scale, step[3:], centroid) @ correction
        # From wide (the error may shift points by several cm) to tight (only the surface), never
        # tighter than GATE_SIGMAS robust sigmas: noisy depth keeps its inliers.
        scheduled = GATES_MM[iteration + 1] * 1e-3 if iteration + 1 < len(GATES_MM) else final_gate
        gate = max(scheduled, GATE_SIGMAS * sigma)
        if (iteration + 1 >= len(GATES_MM) and np.linalg.norm(step[3:]) < CONVERGED_MM * 1e-3
                and np.linalg.norm(step[:3]) / scale < math.radians(CONVERGED_DEG)):
            break
    return correction, residual, used, share, condition


def _rigid(rotation_vector: np.ndarray, translation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(4, 4): turn by ``rotation_vector`` (3,) rad about ``centre`` (3,), then shift by ``translation`` (3,)."""
    angle = float(np.linalg.norm(rotation_vector))
    k = np.array([[0, -rotation_vector[2], rotation_vector[1]], [rotation_vector[2], 0, -rotation_vector[0]],
                  [-rotation_vector[1], rotation_vector[0], 0]])
    if angle > 0:
        k = k / angle
    rotation = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k       # Rodrigues
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = centre + translation - rotation @ centre
    return out


def _angle_deg(rotation: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0)))
