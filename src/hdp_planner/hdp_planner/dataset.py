"""Episodes -> next-best-pose samples: (observation, instruction, proprio) -> (pose, gripper) at the next keyframe.

Every recorded camera frame is an observation (the collector records the
start and every rest, so these are the keyframes; frames between keyframes,
where a recording has them, are PerAct's demo augmentation for free). Its
target is the first keyframe after it: the end-effector pose (PyBullet
forward kinematics of panda_grasptarget, world frame) and the commanded
gripper state there. A frame within KEYFRAME_SNAP of a keyframe shows that
keyframe's rest, so it targets the one after. A keyframe that asks for
nothing (the hand already there, within NO_OP_DISTANCE and NO_OP_ANGLE, and
the gripper as it is) is skipped: those come from the expert stalling
against a hinge, and a high level that learnt to predict them would stall
the hierarchy in place. An arm's stop that a gripper change follows at the
same pose is one goal, the change's (``merge_stops_into_gripper_changes``).

Decoding bags is slow, so each episode's samples (workspace points and
colours, proprio, targets, and the camera frames they came from) are cached as
one npz under the cache directory, keyed by the bag's size and modification
time. The frames are kept for depth augmentation (``depth_augmentation``): a
degraded depth image is unprojected again at draw time, as the agent would see it.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from hdp_msgs_py import topics
from hdp_msgs_py.conversions import Intrinsics, camera_info_to_intrinsics, image_to_numpy, transform_to_matrix
from hdp_data.episodes import list_episodes, read_episode
from hdp_data.workspace import WORKSPACE

from . import language, rotations
from .depth_augmentation import DepthAugmentation, augment_depth, perturbed_extrinsics
from .model import hand_pose, hand_vector, proprio_vector
from .voxels import scene_points

CACHE_VERSION = 5           # 5: camera frames kept (4: stops merged into gripper changes; 3: FK by hdp_motion)
KEYFRAME_SNAP = 0.02          # s
NO_OP_DISTANCE = 0.01         # m
NO_OP_ANGLE = math.radians(5)
FRAME_PAIRING = 0.05          # s: a camera's frame this close counts as the same moment
WORLD_FRAME = 'world'

TRANSLATION_RANGE = 0.125     # m, each axis
YAW_RANGE = 45                # deg
YAW_STEP = 5                  # deg
MAX_REDRAWS = 10


def _depth_metres(msg) -> np.ndarray:
    depth = image_to_numpy(msg)
    return depth * np.float32(0.001) if msg.encoding == '16UC1' else depth.astype(np.float32)


def camera_frames(episode) -> list[tuple[float, dict]]:
    """[(t, camera -> (rgb (H, W, 3) uint8, depth (H, W) float32 m))] at each frame of the first camera
    that every camera has a colour and depth frame for, taken within FRAME_PAIRING of it.

    Frames are paired by their capture stamps (header.stamp) and placed at the first camera's
    bag time: `ros2 bag record` stamps each message on arrival, and the cameras' frames arrive
    apart (a simulator renders them one after the other).
    """
    streams = {}
    for camera in topics.CAMERAS:
        colour = list(episode.messages(topics.color_image(camera)))
        depth = list(episode.messages(topics.depth_image(camera)))
        streams[camera] = (colour, depth, _captured(colour), _captured(depth))
    frames = []
    first_colour, _, first_captured, _ = streams[topics.CAMERAS[0]]
    for (t, _), captured in zip(first_colour, first_captured):
        frame = {}
        for camera, (colour, depth, colour_t, depth_t) in streams.items():
            i, j = np.abs(colour_t - captured).argmin(), np.abs(depth_t - captured).argmin()
            if abs(colour_t[i] - captured) > FRAME_PAIRING or abs(depth_t[j] - captured) > FRAME_PAIRING:
                break
            rgb = image_to_numpy(colour[i][1])
            frame[camera] = (rgb[..., ::-1] if colour[i][1].encoding == 'bgr8' else rgb, _depth_metres(depth[j][1]))
        else:
            frames.append((t, frame))
    return frames


def _captured(messages) -> np.ndarray:
    """(N,) s: the header stamps of [(t, Image)]."""
    return np.array([msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 for _, msg in messages])


def camera_geometry(episode) -> tuple[dict, dict]:
    """(camera -> Intrinsics, camera -> (4, 4) camera-to-world) from the bag's camera infos and /tf_static."""
    intrinsics, to_world = {}, {}
    for camera in topics.CAMERAS:
        info = episode.camera_info(camera)
        transform = episode.tf_static.get(info.header.frame_id)
        if transform is None or transform.header.frame_id != WORLD_FRAME:
            raise ValueError(f'{episode.path}: no /tf_static from {WORLD_FRAME!r} to {info.header.frame_id!r}')
        intrinsics[camera] = camera_info_to_intrinsics(info)
        to_world[camera] = transform_to_matrix(transform)
    return intrinsics, to_world


def frame_keys(camera: str) -> tuple[str, str, str, str]:
    """The sample keys of one camera's frames: depth, colour, intrinsics, camera-to-world."""
    return f'depth_{camera}', f'colour_{camera}', f'intrinsics_{camera}', f'camera_to_world_{camera}'


def merge_stops_into_gripper_changes(xyz, quat, gripper_open) -> np.ndarray:
    """(K,) bool: which of K consecutive keyframes (hand xyz (K, 3), quat (K, 4), gripper (K,))
    are goals. A keyframe whose successor changes the gripper at the same pose (within NO_OP_DISTANCE
    and NO_OP_ANGLE) is not: ARM's rule, at RLBench's 20 Hz, sees the arm's stop and the gripper's
    change as one frame; at our 120 Hz they can land two frames apart, and the stop, still open,
    would label a grasp 'open' in some episodes and 'closed' in others."""
    xyz, quat, gripper_open = np.asarray(xyz), np.asarray(quat), np.asarray(gripper_open, dtype=bool)
    same_pose = ((np.linalg.norm(np.diff(xyz, axis=0), axis=1) <= NO_OP_DISTANCE)
                 & (rotations.angle_between(quat[1:], quat[:-1]) <= NO_OP_ANGLE))
    return np.append(~(same_pose & (gripper_open[1:] != gripper_open[:-1])), True)


def episode_samples(episode) -> dict:
    """One episode's samples as arrays, n of them:
    xyz (P, 3) float32 and rgb (P, 3) uint8 workspace points of all n observations, split at
    starts (n + 1,); joint_positions (n, 7), gripper_open (n,) at each observation;
    target_xyz (n, 3), target_quat (n, 4), target_open (n,) at the keyframe after it;
    task, variation and seed; and per camera C the frames the points came from (frame_keys):
    depth_C (n, H, W) float32 m, colour_C (n, H, W, 3) uint8, intrinsics_C [fx, fy, cx, cy, W, H],
    camera_to_world_C (4, 4)."""
    js = episode.joint_states
    keyframes = np.array(episode.keyframes(), dtype=np.int64)
    keyframe_xyz, keyframe_quat = hand_pose(js.position[keyframes])
    goals = merge_stops_into_gripper_changes(keyframe_xyz, keyframe_quat, js.gripper_open[keyframes])
    keyframes, keyframe_xyz, keyframe_quat = keyframes[goals], keyframe_xyz[goals], keyframe_quat[goals]
    intrinsics, to_world = camera_geometry(episode)
    clouds, state, target, kept = [], [], [], []
    for t, frame in camera_frames(episode):
        now = max(int(np.searchsorted(js.t, t, side='right')) - 1, 0)      # the state the frame shows
        xyz, quat = hand_pose(js.position[now][None])
        acts = ((np.linalg.norm(keyframe_xyz - xyz, axis=1) > NO_OP_DISTANCE)
                | (rotations.angle_between(keyframe_quat, quat) > NO_OP_ANGLE)
                | (js.gripper_open[keyframes] != js.gripper_open[now]))
        later = np.flatnonzero((js.t[keyframes] > t + KEYFRAME_SNAP) & acts)
        if not len(later):
            continue
        clouds.append(scene_points(frame, intrinsics, to_world))
        kept.append(frame)
        state.append(now)
        target.append(later[0])
    if not clouds:
        raise ValueError(f'{episode.path}: no sample: no frame with every camera\'s colour and depth '
                         f'before a keyframe the arm still has to reach ({len(keyframes)} keyframes)')
    target_xyz, target_quat = keyframe_xyz[target].reshape(-1, 3), keyframe_quat[target].reshape(-1, 4)
    target = keyframes[target]
    frames = {}
    for camera in topics.CAMERAS:
        depth, colour, geometry, pose = frame_keys(camera)
        i = intrinsics[camera]
        frames.update({depth: np.stack([f[camera][1] for f in kept]).astype(np.float32),
                       colour: np.stack([f[camera][0] for f in kept]).astype(np.uint8),
                       geometry: np.array([i.fx, i.fy, i.cx, i.cy, i.width, i.height]),
                       pose: np.asarray(to_world[camera], dtype=np.float64)})
    return {
        'xyz': np.concatenate([c[0] for c in clouds]).reshape(-1, 3).astype(np.float32),
        'rgb': np.concatenate([c[1] for c in clouds]).reshape(-1, 3).astype(np.uint8),
        'starts': np.cumsum([0] + [len(c[0]) for c in clouds]),
        'joint_positions': js.position[state].reshape(-1, 7),
        'gripper_open': js.gripper_open[state].astype(bool),
        'target_xyz': target_xyz, 'target_quat': target_quat,
        'target_open': js.gripper_open[target].astype(bool),
        'task': np.array(episode.metadata['task']),
        'variation': np.array(int(episode.metadata.get('variation', 0))),
        'seed': np.array(int(episode.metadata.get('seed', -1))),
        **frames,
    }


def _fingerprint(bag: Path) -> str:
    files = sorted(p for p in bag.iterdir() if p.is_file())
    return f'v{CACHE_VERSION}:' + ','.join(f'{p.name}:{p.stat().st_size}:{p.stat().st_mtime_ns}' for p in files)


def default_cache_dir(data_dir) -> Path:
    """The cache next to the data: <data>_cache."""
    data_dir = Path(data_dir)
    return data_dir.with_name(data_dir.name + '_cache')


def load_samples(bag: Path, cache_dir: Path) -> dict:
    """episode_samples of ``bag``, from the cache when it is current, else decoded and cached."""
    cached = cache_dir / f'{bag.name}.npz'
    fingerprint = _fingerprint(bag)
    if cached.is_file():
        with np.load(cached) as stored:
            if str(stored['fingerprint']) == fingerprint:
                return {k: stored[k] for k in stored.files if k != 'fingerprint'}
    samples = episode_samples(read_episode(bag))
    cache_dir.mkdir(parents=True, exist_ok=True)
    partial = cached.with_suffix('.partial.npz')
    np.savez(partial, fingerprint=np.array(fingerprint), **samples)
    partial.replace(cached)
    return samples


def yaw_about_centre(xyz, angle: float, centre=None) -> np.ndarray:
    """(N, 3) points turned by ``angle`` rad about the vertical axis through ``centre`` (default: the workspace's)."""
    centre = WORKSPACE.mean(0) if centre is None else np.asarray(centre)
    c, s = math.cos(angle), math.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ((np.asarray(xyz) - centre) @ rotation.T + centre).astype(np.float32)


class SceneMove(NamedTuple):
    """What augmentation does to a sample: a world-frame yaw about the workspace centre, then a shift."""
    angle: float = 0.0              # rad
    shift: tuple = (0.0, 0.0, 0.0)  # m

    def points(self, xyz) -> np.ndarray:
        """(N, 3) float32 points moved."""
        return yaw_about_centre(xyz, self.angle) + np.asarray(self.shift, dtype=np.float32)

    def orientations(self, quat) -> np.ndarray:
        """(..., 4) xyzw orientations turned with the scene."""
        return rotations.yaw_quat(quat, self.angle)


def draw_move(target_xyz, rng: np.random.Generator) -> SceneMove:
    """A yaw of +-45 deg in 5 deg steps and a shift of up to +-12.5 cm per axis, redrawn until
    ``target_xyz`` (3,) stays in the workspace (no move after MAX_REDRAWS)."""
    for _ in range(MAX_REDRAWS):
        angle = math.radians(YAW_STEP * rng.integers(-YAW_RANGE // YAW_STEP, YAW_RANGE // YAW_STEP + 1))
        move = SceneMove(angle, tuple(rng.uniform(-TRANSLATION_RANGE, TRANSLATION_RANGE, 3)))
        moved = move.points(np.asarray(target_xyz)[None])[0]
        if np.all(moved > WORKSPACE[0]) and np.all(moved < WORKSPACE[1]):
            return move
    return SceneMove()


@dataclasses.dataclass
class Item:
    """One sample ready for the model: xyz (N, 3) float32, rgb (N, 3) uint8, proprio (8,),
    instruction, target_xyz (3,), target_quat (4,), target_open, task."""
    xyz: np.ndarray
    rgb: np.ndarray
    proprio: np.ndarray
    instruction: str
    target_xyz: np.ndarray
    target_quat: np.ndarray
    target_open: bool
    task: str


class KeyframeDataset:
    """Samples of many episodes (dicts as episode_samples returns them); each Item's proprio is the
    ``proprio`` kind of model.PROPRIO_DIMS. depth_augmentation: how augmented items degrade their
    depth first (off by default; the episodes then need their frames)."""

    def __init__(self, episodes: list[dict], proprio: str = 'joints',
                 depth_augmentation: DepthAugmentation = DepthAugmentation()):
        self.episodes = episodes
        self.proprio = proprio
        self.depth_augmentation = depth_augmentation
        self._hand_poses = {}                  # episode -> hand_pose of its observations, on first use
        self.index = np.array([(e, s) for e, episode in enumerate(episodes)
                               for s in range(len(episode['target_open']))], dtype=np.int64).reshape(-1, 2)
        self.tasks = np.array([str(episodes[e]['task']) for e, _ in self.index])

    @classmethod
    def from_directory(cls, data_dir, cache_dir=None, progress: bool = True, proprio: str = 'joints',
                       depth_augmentation: DepthAugmentation = DepthAugmentation()) -> KeyframeDataset:
        """Every successful episode under ``data_dir``, decoded once and cached (default: <data_dir>_cache)."""
        from tqdm import tqdm
        bags = list_episodes(data_dir)
        if not bags:
            raise FileNotFoundError(f'no successful episodes in {data_dir}')
        cache_dir = Path(cache_dir) if cache_dir else default_cache_dir(data_dir)
        return cls([load_samples(bag, cache_dir)
                    for bag in tqdm(bags, desc='episodes', unit='episode', disable=not progress)], proprio,
                   depth_augmentation)

    def training_seeds(self) -> dict[str, list[int]]:
        """task -> the sorted seeds of its episodes: what evaluation must stay away from."""
        seeds: dict[str, set] = {}
        for episode in self.episodes:
            seeds.setdefault(str(episode['task']), set()).add(int(episode['seed']))
        return {task: sorted(s) for task, s in sorted(seeds.items())}

    def __len__(self) -> int:
        return len(self.index)

    def draw(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """(count,) sample indices, each task equally likely whatever its number of keyframes."""
        names = np.unique(self.tasks)
        chosen = names[rng.integers(len(names), size=count)]
        return np.array([rng.choice(np.flatnonzero(self.tasks == name)) for name in chosen])

    def item(self, i: int, rng: np.random.Generator, augmented: bool = False, heldout: bool = False) -> Item:
        """Sample ``i`` with an instruction drawn from the training (or held-out) phrasings of its
        task, and, when ``augmented``, its depth degraded (with the depth_augmentation's probability)
        and a random yaw and shift of scene and target."""
        e, s = self.index[i]
        episode = self.episodes[e]
        start, stop = episode['starts'][s], episode['starts'][s + 1]
        xyz, rgb = episode['xyz'][start:stop], episode['rgb'][start:stop]
        chance = self.depth_augmentation.probability
        if augmented and chance and rng.random() < chance:     # no draw when off: the items stay as they were
            xyz, rgb = self._degraded_points(episode, s, rng)
        target_xyz, target_quat = episode['target_xyz'][s], episode['target_quat'][s]
        move = draw_move(target_xyz, rng) if augmented else SceneMove()
        if augmented:
            xyz, target_xyz, target_quat = (move.points(xyz), move.points(target_xyz[None])[0],
                                            move.orientations(target_quat))
        task = str(episode['task'])
        phrasings = language.heldout_phrasings(task) if heldout else language.training_phrasings(task)
        return Item(xyz, rgb, self._proprio(e, s, move),
                    language.instruction(task, int(episode['variation']), phrasings, rng),
                    np.asarray(target_xyz, dtype=np.float32), np.asarray(target_quat, dtype=np.float64),
                    bool(episode['target_open'][s]), task)

    def _degraded_points(self, episode: dict, s: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Observation ``s``'s workspace points from its frames with each camera's depth degraded and
        its extrinsics perturbed."""
        frames, intrinsics, to_world = {}, {}, {}
        for camera in topics.CAMERAS:
            depth, colour, geometry, pose = frame_keys(camera)
            if depth not in episode:
                raise ValueError(f'a {episode["task"]} episode (seed {int(episode["seed"])}) has no camera frames: '
                                 'depth augmentation needs samples cached with them (CACHE_VERSION 5)')
            fx, fy, cx, cy, width, height = episode[geometry]
            intrinsics[camera] = Intrinsics(fx, fy, cx, cy, int(width), int(height))
            frames[camera] = (episode[colour][s], augment_depth(episode[depth][s], fx, self.depth_augmentation, rng))
            to_world[camera] = perturbed_extrinsics(episode[pose], self.depth_augmentation, rng)
        return scene_points(frames, intrinsics, to_world)

    def _proprio(self, e: int, s: int, move: SceneMove) -> np.ndarray:
        episode = self.episodes[e]
        if self.proprio == 'joints':
            return proprio_vector(episode['joint_positions'][s], episode['gripper_open'][s])
        if e not in self._hand_poses:
            self._hand_poses[e] = hand_pose(episode['joint_positions'])
        hand_xyz, hand_quat = (pose[s] for pose in self._hand_poses[e])
        return hand_vector(move.points(hand_xyz[None])[0], move.orientations(hand_quat), episode['gripper_open'][s])
