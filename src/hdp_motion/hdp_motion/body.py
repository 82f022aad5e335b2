"""The Panda's surface as world-frame points with outward normals, for given joint states.

What a camera should see of the robot: points sampled on the meshes that pybullet_data's
franka_panda URDF draws (the visual meshes of link1-6, the hand and the fingers; the collision
meshes of link0 and link7, which the URDF uses as their visuals), posed by the forward kinematics
of every link of that URDF and ROBOT_BASE. Each mesh is sampled once per process, area-weighted
and deterministically; a pose then costs one forward kinematics and a matrix product per link.
"""

from __future__ import annotations

import functools
import os

import numpy as np
import pybullet_data
import pytorch_kinematics as pk
import torch

from .kinematics import _quiet_urdf_parser
from .panda import ROBOT_BASE

URDF_DIR = os.path.join(pybullet_data.getDataPath(), 'franka_panda')
# Samples per m^2 of mesh surface: ~1.3 cm apart, ~7000 points on the whole robot (0.9 m^2).
SAMPLES_PER_M2 = 8000.0


def load_obj(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (F, 3) int64 (0-based) of a Wavefront OBJ's v/f lines.

    Polygons are fanned into triangles; texture and normal indices are ignored (normals come
    from the counter-clockwise winding, which faces outwards in these meshes).
    """
    vertices, faces = [], []
    with open(path) as f:
        for line in f:
            if line.startswith('v '):
                vertices.append(line.split()[1:4])
            elif line.startswith('f '):
                corners = [int(c.split('/')[0]) for c in line.split()[1:]]
                faces.extend((corners[0], corners[i], corners[i + 1]) for i in range(1, len(corners) - 1))
    v = np.array(vertices, dtype=np.float64)
    tri = np.array(faces, dtype=np.int64)
    return v, np.where(tri < 0, tri + len(v), tri - 1)      # OBJ indices: 1-based, or negative from the end


def sample_mesh(vertices: np.ndarray, triangles: np.ndarray, density: float = SAMPLES_PER_M2,
                seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and outward unit normals (N, 3) on a triangle mesh, N = density x area.

    Stratified by area (sample i falls in the triangle that holds the (i + 0.5) / N quantile of the
    cumulative area), so coverage is even and the result depends only on the mesh and ``seed``.
    """
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = max(1, int(round(density * area.sum())))
    face = np.searchsorted(np.cumsum(area), (np.arange(n) + 0.5) / n * area.sum())
    face = np.minimum(face, len(area) - 1)
    r1, r2 = np.random.default_rng(seed).random((2, n))
    s = np.sqrt(r1)                              # uniform over the triangle
    points = (1 - s)[:, None] * a[face] + (s * (1 - r2))[:, None] * b[face] + (s * r2)[:, None] * c[face]
    normals = cross[face] / np.maximum(2 * area[face], 1e-12)[:, None]
    return points, normals


@functools.lru_cache(maxsize=None)
def _chain() -> pk.Chain:
    with open(os.path.join(URDF_DIR, 'panda.urdf'), 'rb') as f:
        urdf = f.read()
    with _quiet_urdf_parser():
        return pk.build_chain_from_urdf(urdf).to(dtype=torch.float64)


@functools.lru_cache(maxsize=None)
def link_surfaces() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Link name -> (points (N, 3), normals (N, 3)) in the link's URDF frame, every visual mesh of
    the URDF sampled with its visual origin applied. Cached per process (the OBJ files take ~1 s)."""
    chain = _chain()
    surfaces = {}
    for name in chain.get_frame_names(exclude_fixed=False):
        link = chain.find_frame(name).link
        parts = []
        for visual in link.visuals:
            if visual.geom_type != 'mesh':
                continue
            path = os.path.join(URDF_DIR, visual.geom_param[0].replace('package://', ''))
            points, normals = sample_mesh(*load_obj(path))
            origin = visual.offset.get_matrix()[0].to(torch.float64).numpy()
            parts.append((points @ origin[:3, :3].T + origin[:3, 3], normals @ origin[:3, :3].T))
        if parts:
            surfaces[link.name] = (np.concatenate([p for p, _ in parts]), np.concatenate([n for _, n in parts]))
    return surfaces


def link_poses(joint_positions, finger_width: float) -> dict[str, np.ndarray]:
    """Link name -> (4, 4) world pose of every URDF link for arm joints (7,) rad and a gripper
    opening ``finger_width`` m (the distance between the fingers: each finger joint is half)."""
    q = np.asarray(joint_positions, dtype=np.float64)
    if q.shape != (7,):
        raise ValueError(f'joint_positions must be 7 arm joints, got shape {q.shape}')
    fingers = [finger_width / 2] * 2
    th = torch.as_tensor(np.concatenate([q, fingers]), dtype=torch.float64)[None]
    base = np.eye(4)
    base[:3, 3] = ROBOT_BASE
    return {name: base @ pose.get_matrix()[0].numpy() for name, pose in _chain().forward_kinematics(th).items()}


def body_surface(joint_positions, finger_width: float) -> tuple[np.ndarray, np.ndarray]:
    """The robot's surface in the world frame: points (N, 3) m and outward unit normals (N, 3),
    float64, for arm joints (7,) rad and a gripper opening ``finger_width`` m. N is fixed
    (the same samples every call, in link order link0 .. rightfinger)."""
    poses = link_poses(joint_positions, finger_width)
    points, normals = [], []
    for name, (p, n) in link_surfaces().items():
        pose = poses[name]
        points.append(p @ pose[:3, :3].T + pose[:3, 3])
        normals.append(n @ pose[:3, :3].T)
    return np.concatenate(points), np.concatenate(normals)
