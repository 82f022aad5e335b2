"""NextBestPoseAgent: camera frames + instruction + robot state -> the next end-effector pose.

What planner_node calls; no ROS in here. One prediction is a few tens of
milliseconds on one CPU core.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import torch

from hdp_data import instructions, workspace
from hdp_motion import panda
from hdp_msgs_py.conversions import Intrinsics, camera_info_to_intrinsics, transform_to_matrix

from . import checkpoint
from .grounding import InstructionGrounding, Reading
from .model import NextBestPoseNet, hand_pose, hand_vector, proprio_vector
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


def downscale(rgb, width: int, height: int) -> np.ndarray:
    """(height, width, 3) uint8: ``rgb`` (H, W, 3) uint8 area-averaged (torch's 'area' interpolation)."""
    rgb = np.asarray(rgb)
    if rgb.shape[:2] == (height, width):
        return rgb.astype(np.uint8)
    image = torch.from_numpy(np.array(rgb, dtype=np.float32)).permute(2, 0, 1)[None]
    small = torch.nn.functional.interpolate(image, size=(height, width), mode='area')
    return small[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


def resample_frame(rgb: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics,
                   size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """One RGB-D frame as the camera would have taken it at ``size`` (width, height): colour
    area-averaged, depth sampled at the nearest pixel (never a depth mixed across an edge), the
    intrinsics scaled. rgb (H, W, 3) uint8, depth (H, W) any dtype; unchanged at its own size."""
    width, height = size
    if (intrinsics.width, intrinsics.height) == (width, height):
        return rgb, depth, intrinsics
    sx, sy = width / intrinsics.width, height / intrinsics.height
    rgb = downscale(rgb, width, height)
    rows = np.minimum(((np.arange(height) + 0.5) / sy).astype(int), intrinsics.height - 1)
    cols = np.minimum(((np.arange(width) + 0.5) / sx).astype(int), intrinsics.width - 1)
    depth = np.asarray(depth)[rows[:, None], cols[None, :]]
    scaled = Intrinsics(intrinsics.fx * sx, intrinsics.fy * sy, (intrinsics.cx + 0.5) * sx - 0.5,
                        (intrinsics.cy + 0.5) * sy - 0.5, width, height)
    return rgb, depth, scaled


class NextBestPoseAgent:
    """camera_size: (width, height) the agent was trained at; frames of another size are resampled
    to it (resample_frame), so a 640 x 480 camera shows it what 128 x 96 training frames showed:
    thin parts (a drawer handle) fill the voxels as they did in training. None: frames as they come.
    grounding: reads each instruction as a training one first (grounding.py); None: as it comes."""

    def __init__(self, model: NextBestPoseNet, device='cpu', training_seeds: dict | None = None,
                 camera_size: tuple[int, int] | None = None, grounding: InstructionGrounding | None = None):
        self.model = model.to(device).eval()
        self.device = device
        self.training_seeds = training_seeds or {}     # task -> seeds: evaluation refuses them
        self.camera_size = camera_size
        self.grounding = grounding

    @classmethod
    def from_checkpoint(cls, path, device='cpu', camera_size: tuple[int, int] | None = None,
                        ground_instructions: bool = True) -> NextBestPoseAgent:
        """The agent of a checkpoint written by `hdp train high-level`; CheckpointError if it is not one.
        Instructions are grounded (``ground_instructions``) for agents reading them with the frozen
        sentence encoder, over the tasks the checkpoint was trained on."""
        model, stored = checkpoint.load_model(path, device)
        tasks = sorted(t for t in stored['training_seeds'] if t in instructions.TASKS)
        grounding = None
        if ground_instructions and model.config.language_encoder == 'minilm' and tasks:
            grounding = InstructionGrounding(tasks)
        return cls(model, device, stored['training_seeds'], camera_size, grounding)

    @property
    def vocabulary(self) -> tuple[str, ...] | None:
        """The words it can read (a learned word encoder knows only its vocabulary), or None: a
        sentence encoder reads any words, and its confidence alone refuses what it cannot act on."""
        config = self.model.config
        return tuple(config.vocabulary) if config.language_encoder == 'words' else None

    def read(self, instruction: str) -> Reading:
        """What the agent is given for ``instruction``: grounding.Reading."""
        if self.grounding is None:
            return Reading(instruction, False, None, 0.0)
        return self.grounding.read(instruction)

    def warm_up(self) -> float:
        """One prediction on a synthetic view (a grey table seen from above), so the first real
        instruction does not pay for torch's first calls; returns its seconds."""
        width, height = self.camera_size or (128, 96)
        intrinsics = Intrinsics(fx=width, fy=width, cx=width / 2, cy=height / 2, width=width, height=height)
        above_table = np.diag([1.0, -1.0, -1.0, 1.0])            # optical z pointing down
        above_table[:3, 3] = [*workspace.TABLE_CENTER_XY, workspace.TABLE_TOP_Z + 1.0]
        frame = (np.full((height, width, 3), 128, np.uint8), np.full((height, width), 1000, np.uint16))
        started = time.perf_counter()
        self.predict({'warm_up': frame}, {'warm_up': intrinsics}, {'warm_up': above_table},
                     instructions.evaluation_instruction('reach_target', 0, 0), (panda.HOME, True))
        return time.perf_counter() - started

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
            info = camera_infos[camera]
            intrinsics[camera] = info if isinstance(info, Intrinsics) else camera_info_to_intrinsics(info)
            if self.camera_size:
                rgb, depth, intrinsics[camera] = resample_frame(rgb, depth, intrinsics[camera], self.camera_size)
            frames[camera] = (rgb, depth * 0.001 if depth.dtype == np.uint16 else depth.astype(np.float32))
            transform = camera_to_world[camera]
            to_world[camera] = transform if isinstance(transform, np.ndarray) else transform_to_matrix(transform)
        points = scene_points(frames, intrinsics, to_world)
        xyz, rgb, cloud = collate_clouds([points], self.device)
        joint_positions, gripper_open = proprio
        if self.model.config.proprio == 'hand':
            vector = hand_vector(*hand_pose(np.asarray(joint_positions)[None]), [gripper_open])
        else:
            vector = proprio_vector(joint_positions, gripper_open)[None]
        proprio_tensor = torch.as_tensor(vector, device=self.device)
        prediction = self.model.predict(xyz, rgb, cloud, [self.read(instruction).text], proprio_tensor)
        return NextBestPose(prediction.xyz[0].cpu().numpy().astype(np.float64), prediction.quat[0],
                            bool(prediction.gripper_open[0]), float(prediction.confidence[0]), points)
