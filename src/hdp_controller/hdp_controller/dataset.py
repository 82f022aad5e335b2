"""Episodes -> RK-Diffuser training samples (the paper's data preparation).

Each successful episode is cut at its keyframes (hdp_msgs_py.keyframes, the
rule and delta the high level uses too); every keyframe is relabelled as the
goal of the segment that ends there. A segment's joint path is resampled to
HORIZON waypoints evenly spaced by joint-space arc length (the rests and
gripper waits inside it carry no motion to learn), and its pose trajectory is
the forward kinematics of those waypoints, so poses and joints agree exactly.

Conditions per segment: the start state (joints, velocities, gripper), the
trajectory rank |p_end - p_start| / EE path length, and the front camera's
world-frame points at the segment start, cropped to the workspace.

Start/end augmentation (paper appendix; the official code ships it off and
users could not reproduce the paper): each draw starts k ~ U{0..5}
waypoints late and ends k' ~ U{0..5} early, re-interpolated to HORIZON, so
the policy tolerates start states and NBPs that are slightly off.

Preprocessing is cached in one .npz per data directory and settings.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import multiprocessing
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from hdp_motion.kinematics import continuous_quats, fk_pose
from hdp_msgs_py import topics
from hdp_msgs_py.conversions import transform_to_matrix
from hdp_msgs_py.episodes import list_episodes, read_episode
from hdp_msgs_py.keyframes import DEFAULT_STOPPING_DELTA, segments

from .low_level import HORIZON
from .observation import points_from_messages

CACHE_VERSION = 1
MAX_AUGMENT = 5              # k ~ U{0..MAX_AUGMENT} waypoints at each end
# Pushing against a hinge, the arm can stop several times at one pose and the
# keyframe rule marks each stop: such segments carry no motion to learn.
MIN_TRAVEL = 0.01            # rad of joint-space arc length


@dataclasses.dataclass
class Segments:
    """All segments of a dataset, stacked (S segments).

    joints, poses: (S, HORIZON, 7); q0/qd0: (S, 7) start joints and velocities;
    gripper: (S, 2) start width (m) and open (0/1); rank: (S,); points: (S, N, 3);
    task: (S,) task names; seed: (S,) episode seeds.
    """
    joints: np.ndarray
    poses: np.ndarray
    qd0: np.ndarray
    gripper: np.ndarray
    rank: np.ndarray
    points: np.ndarray
    task: np.ndarray
    seed: np.ndarray

    def __len__(self) -> int:
        return len(self.joints)

    def select(self, mask: np.ndarray) -> Segments:
        return Segments(**{f.name: getattr(self, f.name)[mask] for f in dataclasses.fields(self)})

    def moving(self, min_travel: float = MIN_TRAVEL) -> Segments:
        """The segments whose joints travel at least ``min_travel`` rad (joint-space arc length)."""
        travel = np.linalg.norm(np.diff(self.joints, axis=1), axis=2).sum(axis=1)
        return self.select(travel >= min_travel)

    def training_seeds(self) -> dict[str, list[int]]:
        return {str(t): sorted({int(s) for s in self.seed[self.task == t]}) for t in np.unique(self.task)}


def resample_by_arc_length(path: np.ndarray, n: int) -> np.ndarray:
    """(L, D) path -> (n, D) waypoints evenly spaced along its arc length (constant if it never moves)."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    if arc[-1] <= 1e-9:
        return np.repeat(path[:1], n, axis=0)
    targets = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(targets, arc, path[:, j]) for j in range(path.shape[1])], axis=1)


def trajectory_rank(positions: np.ndarray) -> float:
    """|p_end - p_start| / travelled length of an (L, 3) path, in (0, 1]; 1 for no motion."""
    length = np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()
    if length <= 1e-6:
        return 1.0
    return float(np.clip(np.linalg.norm(positions[-1] - positions[0]) / length, 1e-3, 1.0))


def episode_segments(path: Path, n_points: int, stopping_delta: float = DEFAULT_STOPPING_DELTA) -> list[dict]:
    """The segments of one episode as dicts of arrays (see Segments)."""
    episode = read_episode(path)
    js = episode.joint_states
    camera_to_world = transform_to_matrix(episode.tf_static[_front_frame(episode)].transform)
    info = episode.camera_info('front')
    rng = np.random.default_rng(int(episode.metadata.get('seed', 0)))
    out = []
    for start, end in segments(episode.keyframes(stopping_delta)):
        joints = resample_by_arc_length(js.position[start:end + 1], HORIZON)
        poses = fk_pose(torch.from_numpy(joints))
        poses[:, 3:] = continuous_quats(poses[:, 3:])
        poses = poses.numpy()
        depth = episode.frames_near(float(js.t[start]))[topics.depth_image('front')][1]
        out.append(dict(
            joints=joints, poses=poses, qd0=js.velocity[start],
            gripper=np.array([js.gripper_width[start], float(js.gripper_open[start])]),
            rank=trajectory_rank(poses[:, :3]),
            points=points_from_messages(depth, info, camera_to_world, n_points, rng),
            task=str(episode.metadata.get('task', '')), seed=int(episode.metadata.get('seed', -1))))
    return out


def _front_frame(episode) -> str:
    frame = episode.camera_info('front').header.frame_id
    if frame not in episode.tf_static:
        raise ValueError(f'{episode.path}: no /tf_static transform for the front camera frame {frame!r}')
    return frame


def load_segments(data_dir, n_points: int = 1024, cache_dir=None, workers: int = 2) -> Segments:
    """Every segment of the successful episodes in ``data_dir``, from the cache when it is current
    (else preprocessed by ``workers`` processes)."""
    paths = list_episodes(data_dir)
    if not paths:
        raise ValueError(f'no successful episodes in {data_dir}')
    key = hashlib.sha256(json.dumps([CACHE_VERSION, n_points, HORIZON, DEFAULT_STOPPING_DELTA] + [
        [p.name, sum(f.stat().st_mtime_ns for f in p.iterdir())] for p in paths]).encode()).hexdigest()[:16]
    cache = Path(cache_dir or Path(data_dir) / '.cache') / f'rkd_segments_{key}.npz'
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as data:
            return Segments(**{name: data[name] for name in data.files})
    job = functools.partial(episode_segments, n_points=n_points)
    with multiprocessing.get_context('spawn').Pool(workers) as pool:
        rows = [seg for segs in tqdm(pool.imap(job, paths, chunksize=4), total=len(paths),
                                     desc='preprocessing episodes', unit='episode') for seg in segs]
    kinds = {'task': str, 'seed': np.int64}
    segs = Segments(**{f.name: np.array([r[f.name] for r in rows], dtype=kinds.get(f.name, np.float32))
                       for f in dataclasses.fields(Segments)})
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix('.tmp.npz')
    np.savez(tmp, **dataclasses.asdict(segs))
    tmp.replace(cache)
    return segs


def _interpolate(traj: np.ndarray, start: float, end: float) -> np.ndarray:
    """(HORIZON, D) trajectory -> HORIZON waypoints between fractional indices start..end."""
    t = np.linspace(start, end, HORIZON)
    return np.stack([np.interp(t, np.arange(len(traj)), traj[:, j]) for j in range(traj.shape[1])], axis=1)


class SegmentDataset(torch.utils.data.Dataset):
    """Training samples: trajectories and conditions as float32 tensors (unnormalised).

    Per item: joints, poses (HORIZON, 7); q (7,), qd (7,), gripper (2,),
    start_pose, goal_pose (7,), rank (1,), points (N, 3).
    """

    def __init__(self, segs: Segments, augment: bool = True, seed: int = 0):
        self.segs, self.augment = segs, augment
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.segs)

    def __getitem__(self, i: int) -> dict:
        joints, poses = self.segs.joints[i], self.segs.poses[i]
        if self.augment:
            k_start, k_end = self.rng.integers(0, MAX_AUGMENT + 1, size=2)
            joints = _interpolate(joints, k_start, HORIZON - 1 - k_end)
            poses = _interpolate(poses, k_start, HORIZON - 1 - k_end)
            poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
        item = dict(joints=joints, poses=poses, q=joints[0], qd=self.segs.qd0[i], gripper=self.segs.gripper[i],
                    start_pose=poses[0], goal_pose=poses[-1], rank=self.segs.rank[i:i + 1],
                    points=self.segs.points[i])
        return {k: torch.as_tensor(np.asarray(v, dtype=np.float32)) for k, v in item.items()}
