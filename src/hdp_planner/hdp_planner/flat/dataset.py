"""Episodes -> flat-policy samples: (observation history, action chunk) at the flat control rate.

The flat baselines act every CONTROL_PERIOD_S (10 Hz, Diffusion Policy's rate on its real and
robomimic tasks); an episode of T seconds gives T / 0.1 control steps (our demonstrations last
3-12 s: 30-120 steps). At step k:

- observation: both cameras' RGB downscaled (64 x 48 from the episodes' 128 x 96 by default),
  proprioception (joint positions, the commanded gripper state, the gripper width), at steps
  k - n_obs + 1 .. k (clamped at the episode's start);
- action chunk: the demonstration's absolute joint positions and commanded gripper state at
  steps k + 1 .. k + horizon, the last one repeated past the episode's end (``is_pad`` marks
  those), as Diffusion Policy pads and ACT masks.

The recorded episodes hold joint states at 120 Hz; the image of step k is the latest camera frame
at or before it. Episodes recorded with `hdp collect --camera-rate 10` (or faster) hold a frame
every control step, so the image is current; plain ones hold frames only at the first frame and
where the expert rests (where keyframes are found), so the image shows the scene as last seen at
rest, the arm in it where it last stopped. Proprioception is always current. The checkpoint
records the lowest camera rate of its episodes and the harness (hdp_eval.hierarchy_eval) shows
the policy its cameras at that rate by default.

Decoding bags is slow, so each episode's flat arrays are cached as one npz under
``<data>_flat_cache``, keyed by the bag's files (size, mtime), the image size and the period.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from hdp_motion import panda
from hdp_msgs_py import topics
from hdp_data.episodes import list_episodes, read_episode

from .. import language
from ..agent import downscale
from ..model import proprio_vector

CACHE_VERSION = 2
CONTROL_PERIOD_S = 0.1            # the flat policies' control step (10 Hz)
CAMERAS = topics.CAMERAS          # ('front', 'side')
PROPRIO_DIM = 9                   # gripper open +-1, 7 scaled joints, gripper width scaled to [-1, 1]
ACTION_DIM = 8                    # 7 absolute joint targets (rad), gripper open (+1) / closed (-1)


def proprio(joint_positions, gripper_open, gripper_width) -> np.ndarray:
    """(..., 9) float32: the agent's proprio_vector (gripper open +-1, joints scaled to [-1, 1] over the
    Panda's limits) and the measured gripper width scaled to [-1, 1] over 0 .. 0.08 m."""
    width = 2 * np.asarray(gripper_width, dtype=np.float64) / panda.GRIPPER_OPEN_WIDTH - 1
    return np.concatenate([proprio_vector(joint_positions, gripper_open), width[..., None]], -1).astype(np.float32)


def actions(joint_positions, gripper_open) -> np.ndarray:
    """(..., 8) float32 actions: absolute joint targets (rad), then +1 open / -1 closed."""
    gripper = np.where(np.asarray(gripper_open, dtype=bool), 1.0, -1.0)[..., None]
    return np.concatenate([np.asarray(joint_positions, dtype=np.float64), gripper], -1).astype(np.float32)


def episode_flat_samples(episode, width: int, height: int, period: float = CONTROL_PERIOD_S) -> dict:
    """One episode at the flat rate, K control steps:
    joint_positions (K, 7) float32, gripper_open (K,) bool, gripper_width (K,) float32 at each step;
    frame_index (K,) the latest camera frame at or before each step; images_<camera> (F, height, width, 3)
    uint8 for every frame; plus task, variation, seed and camera_rate_hz (the recording's rate of frames
    between rests, 0: rests only)."""
    from ..dataset import camera_frames
    js = episode.joint_states
    count = int(np.floor((js.t[-1] - js.t[0]) / period + 1e-9)) + 1
    times = js.t[0] + period * np.arange(count)
    state = np.clip(np.searchsorted(js.t, times + 1e-9, side='right') - 1, 0, len(js.t) - 1)
    frames = camera_frames(episode)
    if not frames:
        raise ValueError(f'{episode.path}: no sample: no moment with every camera\'s colour and depth')
    frame_t = np.array([t for t, _ in frames])
    frame_index = np.clip(np.searchsorted(frame_t, times + 1e-6, side='right') - 1, 0, len(frames) - 1)
    samples = {
        'joint_positions': js.position[state].astype(np.float32).reshape(-1, 7),
        'gripper_open': js.gripper_open[state].astype(bool),
        'gripper_width': js.gripper_width[state].astype(np.float32),
        'frame_index': frame_index.astype(np.int64),
        'task': np.array(episode.metadata['task']),
        'variation': np.array(int(episode.metadata.get('variation', 0))),
        'seed': np.array(int(episode.metadata.get('seed', -1))),
        'camera_rate_hz': np.array(float(episode.metadata.get('camera_rate_hz', 0.0))),
    }
    for camera in CAMERAS:
        samples[f'images_{camera}'] = np.stack([downscale(frame[camera][0], width, height) for _, frame in frames])
    return samples


def _fingerprint(bag: Path, width: int, height: int, period: float) -> str:
    files = sorted(p for p in bag.iterdir() if p.is_file())
    return (f'flat v{CACHE_VERSION} {width}x{height} {period:g}s:' +
            ','.join(f'{p.name}:{p.stat().st_size}:{p.stat().st_mtime_ns}' for p in files))


def default_cache_dir(data_dir) -> Path:
    """The flat cache next to the data: <data>_flat_cache."""
    data_dir = Path(data_dir)
    return data_dir.with_name(data_dir.name + '_flat_cache')


def load_flat_samples(bag: Path, cache_dir: Path, width: int, height: int, period: float = CONTROL_PERIOD_S) -> dict:
    """episode_flat_samples of ``bag``, from the cache when it is current, else decoded and cached."""
    cached = cache_dir / f'{bag.name}_{width}x{height}_{round(period * 1000)}ms.npz'
    fingerprint = _fingerprint(bag, width, height, period)
    if cached.is_file():
        with np.load(cached) as stored:
            if str(stored['fingerprint']) == fingerprint:
                return {k: stored[k] for k in stored.files if k != 'fingerprint'}
    samples = episode_flat_samples(read_episode(bag), width, height, period)
    cache_dir.mkdir(parents=True, exist_ok=True)
    partial = cached.with_suffix('.partial.npz')
    np.savez(partial, fingerprint=np.array(fingerprint), **samples)
    partial.replace(cached)
    return samples


@dataclasses.dataclass
class Batch:
    """A batch of B samples as numpy arrays.

    images: (B, n_obs, n_cameras, 3, height, width) uint8; proprio: (B, n_obs, 9) float32;
    instructions: B strings; actions: (B, horizon, 8) float32; is_pad: (B, horizon) bool (past the
    episode's end); tasks: B task names.
    """
    images: np.ndarray
    proprio: np.ndarray
    instructions: list
    actions: np.ndarray
    is_pad: np.ndarray
    tasks: list


class FlatDataset:
    """Samples (episode, control step) of many episodes (dicts as episode_flat_samples returns them),
    every step that has a next one."""

    def __init__(self, episodes: list[dict], n_obs: int, horizon: int):
        if n_obs < 1 or horizon < 1:
            raise ValueError(f'need n_obs >= 1 and horizon >= 1, got {n_obs} and {horizon}')
        self.episodes, self.n_obs, self.horizon = episodes, n_obs, horizon
        self.index = np.array([(e, k) for e, episode in enumerate(episodes)
                               for k in range(len(episode['frame_index']) - 1)], dtype=np.int64).reshape(-1, 2)
        if not len(self.index):
            raise ValueError('no flat sample: every episode is a single control step')
        self.tasks = np.array([str(episodes[e]['task']) for e, _ in self.index])
        self._by_task = {name: np.flatnonzero(self.tasks == name) for name in np.unique(self.tasks)}

    @classmethod
    def from_directory(cls, data_dir, n_obs: int, horizon: int, width: int, height: int,
                       period: float = CONTROL_PERIOD_S, cache_dir=None, progress: bool = True,
                       workers: int = 1) -> FlatDataset:
        """Every successful episode under ``data_dir``, decoded once and cached (default: <data_dir>_flat_cache);
        ``workers`` processes decode the episodes the cache lacks."""
        from concurrent.futures import ProcessPoolExecutor
        from functools import partial

        from tqdm import tqdm
        bags = list_episodes(data_dir)
        if not bags:
            raise FileNotFoundError(f'no successful episodes in {data_dir}')
        if workers < 1:
            raise ValueError(f'workers must be >= 1, got {workers}')
        cache_dir = Path(cache_dir) if cache_dir else default_cache_dir(data_dir)
        load = partial(load_flat_samples, cache_dir=cache_dir, width=width, height=height, period=period)
        bar = partial(tqdm, total=len(bags), desc='episodes', unit='episode', disable=not progress)
        if workers == 1:
            return cls([load(bag) for bag in bar(bags)], n_obs, horizon)
        with ProcessPoolExecutor(workers) as pool:
            return cls(list(bar(pool.map(load, bags, chunksize=4))), n_obs, horizon)

    def __len__(self) -> int:
        return len(self.index)

    def training_seeds(self) -> dict[str, list[int]]:
        """task -> the sorted seeds of its episodes: what evaluation must stay away from."""
        seeds: dict[str, set] = {}
        for episode in self.episodes:
            seeds.setdefault(str(episode['task']), set()).add(int(episode['seed']))
        return {task: sorted(s) for task, s in sorted(seeds.items())}

    def camera_rate_hz(self) -> float:
        """The lowest camera rate between rests over the episodes (0: some hold frames at rests only)."""
        return min(float(e['camera_rate_hz']) for e in self.episodes)

    def action_range(self) -> tuple[np.ndarray, np.ndarray]:
        """(low (8,), high (8,)) of the actions over every episode: each joint's min and max, the gripper's
        -1 .. 1. What the networks normalise actions to [-1, 1] with (Diffusion Policy's min-max)."""
        joints = np.concatenate([e['joint_positions'] for e in self.episodes])
        return (np.r_[joints.min(0), -1.0].astype(np.float32), np.r_[joints.max(0), 1.0].astype(np.float32))

    def draw(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """(count,) sample indices, each task equally likely whatever its number of steps."""
        names = np.array(list(self._by_task))
        chosen = names[rng.integers(len(names), size=count)]
        return np.array([rng.choice(self._by_task[name]) for name in chosen])

    def batch(self, indices, rng: np.random.Generator, heldout: bool = False) -> Batch:
        """The samples ``indices``, each with an instruction drawn from its task's training (or
        held-out) phrasings, as the next-best-pose agent's dataset draws them."""
        images, state, chunks, pads, texts, tasks = [], [], [], [], [], []
        for i in indices:
            e, k = self.index[i]
            episode = self.episodes[e]
            last = len(episode['frame_index']) - 1
            seen = np.clip(np.arange(k - self.n_obs + 1, k + 1), 0, last)
            ahead = np.arange(k + 1, k + 1 + self.horizon)
            frames = episode['frame_index'][seen]
            images.append(np.stack([episode[f'images_{c}'][frames] for c in CAMERAS], 1))   # (n_obs, C, h, w, 3)
            state.append(proprio(episode['joint_positions'][seen], episode['gripper_open'][seen],
                                 episode['gripper_width'][seen]))
            clipped = np.minimum(ahead, last)
            chunks.append(actions(episode['joint_positions'][clipped], episode['gripper_open'][clipped]))
            pads.append(ahead > last)
            task = str(episode['task'])
            phrasings = language.heldout_phrasings(task) if heldout else language.training_phrasings(task)
            texts.append(language.instruction(task, int(episode['variation']), phrasings, rng))
            tasks.append(task)
        return Batch(np.stack(images).transpose(0, 1, 2, 5, 3, 4), np.stack(state), texts, np.stack(chunks),
                     np.stack(pads), tasks)
