"""NextBestPoseAgent: camera frames + instruction + robot state -> the next end-effector pose.

What planner_node calls; no ROS in here. One prediction is a few tens of
milliseconds on one CPU core.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from hdp_msgs_py.conversions import Intrinsics, camera_info_to_intrinsics, transform_to_matrix

from . import checkpoint
from .model import NextBestPoseNet, proprio_vector
from .voxels import collate_clouds, scene_points


class NextBestPose(NamedTuple):
    """xyz (3,) m and quat (4,) xyzw in the world frame, the gripper action after arriving,
    confidence in [0, 1] (probability of the chosen coarse voxel x that of the fine one), and
    the cloud it was predicted from: xyz (N, 3) float32 m in the world, colours (N, 3) uint8."""
    xyz: np.ndarray
    quat: np.ndarray
    gripper_open: bool
    confidence: float
    cloud: tuple[np.ndarray, np.ndarray] | None = None


class NextBestPoseAgent:

    def __init__(self, model: NextBestPoseNet, device='cpu', training_seeds: dict | None = None):
        self.model = model.to(device).eval()
        self.device = device
        self.training_seeds = training_seeds or {}     # task -> seeds: evaluation refuses them

    @classmethod
    def from_checkpoint(cls, path, device='cpu') -> NextBestPoseAgent:
        """The agent of a checkpoint written by `hdp train high-level`; CheckpointError if it is not one."""
        model, stored = checkpoint.load_model(path, device)
        return cls(model, device, stored['training_seeds'])

    def predict(self, rgb_depth_per_camera: dict, camera_infos: dict, camera_to_world: dict,
                instruction: str, proprio) -> NextBestPose:
        """The next-best pose for one observation.

        rgb_depth_per_camera: camera -> (rgb (H, W, 3) uint8, depth (H, W): uint16 mm or float m).
        camera_infos: camera -> sensor_msgs/CameraInfo or Intrinsics.
        camera_to_world: camera -> (4, 4) matrix or geometry_msgs Transform(Stamped).
        proprio: (joint positions (7,) rad, gripper open: bool).
        """
        frames, intrinsics, to_world = {}, {}, {}
        for camera, (rgb, depth) in rgb_depth_per_camera.items():
            depth = np.asarray(depth)
            frames[camera] = (rgb, depth * 0.001 if depth.dtype == np.uint16 else depth.astype(np.float32))
            info = camera_infos[camera]
            intrinsics[camera] = info if isinstance(info, Intrinsics) else camera_info_to_intrinsics(info)
            transform = camera_to_world[camera]
            to_world[camera] = transform if isinstance(transform, np.ndarray) else transform_to_matrix(transform)
        points = scene_points(frames, intrinsics, to_world)
        xyz, rgb, cloud = collate_clouds([points], self.device)
        joint_positions, gripper_open = proprio
        proprio_tensor = torch.as_tensor(proprio_vector(joint_positions, gripper_open)[None], device=self.device)
        prediction = self.model.predict(xyz, rgb, cloud, [instruction], proprio_tensor)
        return NextBestPose(prediction.xyz[0].cpu().numpy().astype(np.float64), prediction.quat[0],
                            bool(prediction.gripper_open[0]), float(prediction.confidence[0]), points)
