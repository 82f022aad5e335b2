"""FlatPolicy: what the evaluation harness (and a node, one day) calls at the flat control rate.

    policy = FlatPolicy.from_checkpoint('models/flat_diffusion_policy.pt')
    policy.reset('open the middle drawer')
    chunk = policy.act(observation)     # (N, 8): N joint targets (rad), gripper +1 open / -1 closed
    # run chunk[0] over one control period, observe, policy.observe(observation), run chunk[1], ...
    # and call act again once the chunk is spent.

Every observation the policy is given (``act`` or ``observe``) is one control step
(config.control_period_s, 0.1 s). Diffusion Policy keeps the last n_obs of them, predicts
``horizon`` targets and returns the first n_action_steps (8 of 16); ACT with temporal ensembling
is asked every step and returns one target, the exp(-m i)-weighted mean (i = 0 the oldest) of
what every chunk still covering the next step predicted for it. chunk[i] is the target for the
end of the i-th control period from now.
"""

from __future__ import annotations

import collections
import copy
from typing import NamedTuple

import numpy as np
import torch

from . import checkpoint
from .dataset import CAMERAS, downscale, proprio
from .encoders import observation_tensors


# The inference choices with_execution may change (those a policy's config has).
EXECUTION_FIELDS = ('n_action_steps', 'ensemble', 'inference_steps')


class FlatObservation(NamedTuple):
    """What a flat policy sees at one control step: images camera -> (H, W, 3) uint8 RGB (any size:
    area-downscaled to the policy's), joint positions (7,) rad, the commanded gripper state, the
    measured gripper width (m)."""
    images: dict
    joint_positions: np.ndarray
    gripper_open: bool
    gripper_width: float


class _History(NamedTuple):
    images: np.ndarray
    proprio: np.ndarray
    instructions: list


class FlatPolicy:

    def __init__(self, name: str, model, device='cpu', training_seeds: dict | None = None, seed: int = 0,
                 data_camera_rate_hz: float = 0.0):
        self.name = name
        self.data_camera_rate_hz = data_camera_rate_hz   # frames between rests in its training episodes
        self.model = model.to(device).eval()
        self.config = model.config
        self.device = device
        self.training_seeds = training_seeds or {}      # task -> seeds: evaluation refuses them
        self.seed = seed
        self.reset('')

    @classmethod
    def from_checkpoint(cls, path, device='cpu', policy: str | None = None) -> FlatPolicy:
        """The policy of a checkpoint written by `hdp train flat`; CheckpointError if it is not one
        (or not of ``policy``)."""
        stored = checkpoint.load(path, policy)
        rate = stored['config'].get('train', {}).get('data_camera_rate_hz', 0.0)
        if not isinstance(rate, (int, float)) or not 0 <= rate < 1e4:
            raise checkpoint.CheckpointError(f'{path}: data_camera_rate_hz must be a rate in Hz, got {rate!r}')
        return cls(stored['policy'], checkpoint.build_model(stored, path), device, stored['training_seeds'],
                   data_camera_rate_hz=float(rate))

    def with_execution(self, **changes) -> FlatPolicy:
        """This policy, its weights shared, with other inference choices of its config: ``ensemble``
        and ``n_action_steps`` (ACT: temporal ensembling, or the chunk's first N steps open-loop),
        ``inference_steps`` (Diffusion Policy's DDIM steps). ValueError for another field or a bad value."""
        import dataclasses
        allowed = set(self.execution)
        unknown = set(changes) - allowed
        if unknown:
            raise ValueError(f'{self.name}: cannot change {sorted(unknown)} at inference; it can change {sorted(allowed)}')
        if changes.get('inference_steps', 1) < 1:
            raise ValueError(f'{self.name}: inference_steps must be >= 1')
        config = dataclasses.replace(self.config, **changes)        # its own checks: steps <= horizon...
        other = copy.copy(self)
        other.model = copy.copy(self.model)                         # the same parameters, another config
        other.model.config = other.config = config
        other.reset('')
        return other

    @property
    def execution(self) -> dict:
        """The inference choices this policy runs with (those of EXECUTION_FIELDS its config has)."""
        return {k: getattr(self.config, k) for k in EXECUTION_FIELDS if hasattr(self.config, k)}

    @property
    def control_period_s(self) -> float:
        return float(self.config.control_period_s)

    @property
    def cameras_as_trained(self) -> str:
        """'every' when its training episodes held a frame every control step, else 'rest' (frames at
        the start and at rests): when the harness should show it new frames by default."""
        return 'every' if self.data_camera_rate_hz * self.control_period_s >= 1 - 1e-6 else 'rest'

    def reset(self, instruction: str, seed: int | None = None) -> None:
        """A new episode: forget the observations and chunks; sampling noise from ``seed``."""
        self.instruction = instruction
        self.history = collections.deque(maxlen=self.config.n_obs)
        self.chunks: list[tuple[int, np.ndarray]] = []      # (step queried, (horizon, 8)) for ensembling
        self.step = -1
        self.generator = torch.Generator().manual_seed(self.seed if seed is None else seed)
        self._last_images = {}

    def _images(self, images: dict) -> np.ndarray:
        """(cameras, 3, h, w) uint8; an image object seen the step before is not downscaled again."""
        out = []
        for camera in CAMERAS:
            rgb = images[camera]
            cached = self._last_images.get(camera)
            if cached is None or cached[0] is not rgb:
                cached = (rgb, downscale(rgb, self.config.image_width, self.config.image_height))
                self._last_images[camera] = cached
            out.append(cached[1].transpose(2, 0, 1))
        return np.stack(out)

    def observe(self, observation: FlatObservation) -> None:
        """Record the observation of the next control step without asking for actions."""
        self.step += 1
        self.history.append((self._images(observation.images),
                             proprio(observation.joint_positions, observation.gripper_open,
                                     observation.gripper_width)))

    def act(self, observation: FlatObservation) -> np.ndarray:
        """Observe, then (N, 8) float64: the next N joint targets (rad) and gripper (+1 open, -1 closed)."""
        self.observe(observation)
        frames = list(self.history)
        frames = [frames[0]] * (self.config.n_obs - len(frames)) + frames      # padded with the first, as DP
        history = _History(np.stack([f[0] for f in frames])[None], np.stack([f[1] for f in frames])[None],
                           [self.instruction])
        with torch.no_grad():
            chunk = self.model.predict(observation_tensors(history, self.device), self.generator)[0].cpu().numpy()
        chunk = chunk.astype(np.float64)
        ensemble = getattr(self.config, 'ensemble', 0.0)
        if ensemble > 0:
            self.chunks = [(t, c) for t, c in self.chunks if self.step - t < self.config.horizon] + [(self.step, chunk)]
            predictions = np.stack([c[self.step - t] for t, c in self.chunks])           # oldest first
            weights = np.exp(-ensemble * np.arange(len(predictions)))
            out = (weights[:, None] * predictions).sum(0, keepdims=True) / weights.sum()
        else:
            out = chunk[:self.config.n_action_steps].copy()
        out[:, 7] = np.where(out[:, 7] >= 0, 1.0, -1.0)
        return out
