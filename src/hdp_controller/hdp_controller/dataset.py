"""Episodes -> RK-Diffuser training samples (the paper's data preparation).

Each successful episode is cut at its keyframes (hdp_data.keyframes, the
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
the policy tolerates start states and NBPs that are slightly off. Kinematic
goal augmentation (ours, off unless configured) bends half the segments to
nearby goals. Both are drawn per batch from a generator the training loop
seeds per step, so a step's batch is the same in one process or split over many.

Preprocessing is cached in one .npz per data directory and settings.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import multiprocessing
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from hdp_motion import panda
from hdp_motion.kinematics import continuous_quats, fk_pose
from hdp_msgs_py import topics
from hdp_msgs_py.conversions import transform_to_matrix
from hdp_data.episodes import list_episodes, read_episode
from hdp_data.keyframes import DEFAULT_STOPPING_DELTA, segments

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

    def episodes(self) -> set[tuple[str, int]]:
        """(task, seed) of every episode the segments come from."""
        return {(str(t), int(s)) for t, s in zip(self.task, self.seed)}

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
    (else preprocessed by ``workers`` processes). ``data_dir`` may also be a preprocessed segments
    file (a cache .npz), so training can run where the episodes are not."""
    if Path(data_dir).is_file():
        return read_segments(data_dir, n_points)
    paths = list_episodes(data_dir)
    if not paths:
        raise ValueError(f'no successful episodes in {data_dir}')
    key = hashlib.sha256(json.dumps([CACHE_VERSION, n_points, HORIZON, DEFAULT_STOPPING_DELTA] + [
        [p.name, sum(f.stat().st_mtime_ns for f in p.iterdir())] for p in paths]).encode()).hexdigest()[:16]
    cache = Path(cache_dir or Path(data_dir) / '.cache') / f'rkd_segments_{key}.npz'
    if cache.is_file():
        return read_segments(cache, n_points)
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


def read_segments(path, n_points: int) -> Segments:
    """A segments .npz (untrusted: no pickles, every field checked) -> Segments, floats as float32."""
    names = [f.name for f in dataclasses.fields(Segments)]
    try:
        with np.load(path, allow_pickle=False) as data:
            if sorted(data.files) != sorted(names):
                raise ValueError(f'{path}: not a segments file (fields {sorted(data.files)})')
            arrays = {name: data[name] for name in names}
    except (OSError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f'{path}: unreadable segments file ({err})') from None
    s = len(arrays['joints'])
    shapes = {'joints': (s, HORIZON, 7), 'poses': (s, HORIZON, 7), 'qd0': (s, 7), 'gripper': (s, 2),
              'rank': (s,), 'points': (s, n_points, 3), 'task': (s,), 'seed': (s,)}
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            raise ValueError(f'{path}: {name} has shape {arrays[name].shape}, expected {shape} '
                             f'({n_points} points, {HORIZON} waypoints)')
    if arrays['task'].dtype.kind != 'U' or arrays['seed'].dtype.kind not in 'iu':
        raise ValueError(f'{path}: task must be strings and seed integers')
    floats = {name: np.asarray(arrays[name], np.float32) for name in names if name not in ('task', 'seed')}
    if not all(np.isfinite(v).all() for v in floats.values()):
        raise ValueError(f'{path}: non-finite values')
    return Segments(**{**arrays, **floats})


def draw_augmentation(batch_size: int, generator: torch.Generator | None = None,
                      goal_sigma: float = 0.0) -> dict:
    """Every random number ``augment`` uses for a batch of ``batch_size``:
    trims (B, 2) waypoints cut at the start and end, k ~ U{0..MAX_AUGMENT};
    bends (B, 7) rad, N(0, goal_sigma^2) for half the segments, zero for the rest."""
    trims = torch.randint(0, MAX_AUGMENT + 1, (batch_size, 2), generator=generator)
    chosen = torch.rand(batch_size, generator=generator) < 0.5
    bends = goal_sigma * torch.randn(batch_size, 7, generator=generator) * chosen[:, None]
    return {'trims': trims, 'bends': bends}


def augment(batch: dict, draws: dict | None = None) -> dict:
    """A batch of SegmentDataset items -> a training batch with q, start_pose and goal_pose.

    With ``draws`` (draw_augmentation): each segment starts trims[:, 0] waypoints late and
    ends trims[:, 1] early, re-interpolated to HORIZON (start/end augmentation), and
    segments with non-zero bends get their goal moved by kinematic goal augmentation
    (bend_goals). Without: the segments as recorded.
    """
    joints, poses, rank = batch['joints'], batch['poses'], batch['rank']
    if draws is not None:
        joints, poses = trim(joints, draws['trims']), trim(poses, draws['trims'])
        poses = torch.cat([poses[..., :3], nn.functional.normalize(poses[..., 3:], dim=-1)], dim=-1)
        joints, poses, rank = bend_goals(joints, poses, rank, draws['bends'])
    return {**batch, 'joints': joints, 'poses': poses, 'rank': rank, 'q': joints[:, 0],
            'start_pose': poses[:, 0], 'goal_pose': poses[:, -1]}


def trim(trajectories: torch.Tensor, trims: torch.Tensor) -> torch.Tensor:
    """(B, T, D) trajectories, (B, 2) waypoints to cut at each end -> (B, T, D) linearly
    interpolated between fractional indices trims[:, 0] .. T - 1 - trims[:, 1]."""
    b, t, d = trajectories.shape
    first, last = trims[:, :1].to(trajectories), t - 1 - trims[:, 1:].to(trajectories)
    index = first + torch.linspace(0, 1, t, device=trajectories.device)[None] * (last - first)
    lower = index.floor().long().clamp(max=t - 2)
    weight = (index - lower)[..., None]

    def at(i):
        return torch.gather(trajectories, 1, i[..., None].expand(-1, -1, d))
    return at(lower) * (1 - weight) + at(lower + 1) * weight


def bend_goals(joints: torch.Tensor, poses: torch.Tensor, rank: torch.Tensor,
               bends: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Kinematic goal augmentation: joints (B, T, 7), poses (B, T, 7), rank (B, 1), bends (B, 7).

    A segment with a non-zero bend dq has its joint path bent by the ramp s * dq
    (s from 0 at the start to 1 at the goal), then its poses and rank recomputed
    through FK. The demonstrations show each goal once; this shows the joint
    diffuser the goal -> final joints map (the Panda's kinematics) in a
    neighbourhood around every one of them.
    """
    bent = (bends != 0).any(-1)
    if not bent.any():
        return joints, poses, rank
    ramp = torch.linspace(0, 1, joints.shape[1], device=joints.device)[None, :, None]
    moved = (joints + ramp * bends[:, None]).clamp(_LOWER.to(joints), _UPPER.to(joints))
    fk = fk_pose(moved)
    fk = torch.cat([fk[..., :3], continuous_quats(fk[..., 3:])], dim=-1)
    travelled = torch.linalg.norm(torch.diff(fk[..., :3], dim=1), dim=-1).sum(1)
    straight = torch.linalg.norm(fk[:, -1, :3] - fk[:, 0, :3], dim=-1)
    new_rank = (straight / travelled.clamp(min=1e-6)).clamp(1e-3, 1)[:, None]
    pick = bent[:, None, None]
    return (torch.where(pick, moved, joints), torch.where(pick, fk, poses),
            torch.where(bent[:, None], new_rank, rank))


_LOWER = torch.tensor(panda.LOWER, dtype=torch.float32)
_UPPER = torch.tensor(panda.UPPER, dtype=torch.float32)


class SegmentDataset(torch.utils.data.Dataset):
    """Segments as recorded, float32 tensors (unnormalised); ``augment`` turns a batch of
    them into training samples.

    Per item: joints, poses (HORIZON, 7); qd (7,), gripper (2,), rank (1,), points (N, 3).
    """

    def __init__(self, segs: Segments):
        self.segs = segs

    def __len__(self) -> int:
        return len(self.segs)

    def __getitem__(self, i: int) -> dict:
        item = dict(joints=self.segs.joints[i], poses=self.segs.poses[i], qd=self.segs.qd0[i],
                    gripper=self.segs.gripper[i], rank=self.segs.rank[i:i + 1], points=self.segs.points[i])
        return {k: torch.as_tensor(np.asarray(v, dtype=np.float32)) for k, v in item.items()}
