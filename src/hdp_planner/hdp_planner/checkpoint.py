"""Checkpoints: plain dicts of tensors plus a JSON-able config, loadable with weights_only=True.

    {'format': FORMAT, 'config': {'model': ..., 'train': ...}, 'model': state dict,
     'optimizer': state dict, 'step': int, 'metrics': {...},
     'training_seeds': {task: [seed, ...]}}

The config rebuilds the network with no other file; loading checks every
tensor's name and shape against that network before using any of it.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path

import torch

from .model import ModelConfig, NextBestPoseNet

FORMAT = 'hdp_planner.next_best_pose/1'


class CheckpointError(ValueError):
    """A file that is not a readable, consistent next-best-pose checkpoint."""


def save(path, model: NextBestPoseNet, optimizer, step: int, train_config: dict, metrics: dict,
         training_seeds: dict) -> None:
    """Write atomically (a crash mid-save leaves the previous checkpoint intact)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    checkpoint = {'format': FORMAT,
                  'config': {'model': model.config.to_dict(), 'train': train_config},
                  'model': model.state_dict(),
                  'optimizer': optimizer.state_dict() if optimizer is not None else {},
                  'step': int(step), 'metrics': metrics, 'training_seeds': training_seeds}
    partial = path.with_name(path.name + '.partial')
    torch.save(checkpoint, partial)
    os.replace(partial, path)


def load(path) -> dict:
    """The checkpoint dict at ``path``, read with weights_only=True; CheckpointError if it is not one."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f'{path}: no such checkpoint')
    try:
        checkpoint = torch.load(path, map_location='cpu', weights_only=True)
    except (RuntimeError, pickle.UnpicklingError, EOFError, zipfile.BadZipFile, ValueError, OSError) as err:
        raise CheckpointError(f'{path} is not a readable checkpoint (truncated or not a torch file?): {err}') from None
    if not isinstance(checkpoint, dict) or checkpoint.get('format') != FORMAT:
        raise CheckpointError(f'{path} is not a {FORMAT} checkpoint')
    for key, kind in (('config', dict), ('model', dict), ('step', int), ('metrics', dict),
                      ('training_seeds', dict)):
        if not isinstance(checkpoint.get(key), kind):
            raise CheckpointError(f'{path}: {key!r} is missing or not a {kind.__name__}')
    seeds = checkpoint['training_seeds']
    if not all(isinstance(t, str) and isinstance(s, list) and all(isinstance(i, int) for i in s)
               for t, s in seeds.items()):
        raise CheckpointError(f'{path}: training_seeds must map task names to lists of seeds')
    return checkpoint


def build_model(checkpoint: dict, path='checkpoint') -> NextBestPoseNet:
    """The network a loaded checkpoint describes, with its weights, after checking names and shapes."""
    try:
        model = NextBestPoseNet(ModelConfig.from_dict(checkpoint['config']['model']))
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f'{path}: invalid model config: {err!r}') from None
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    stored = checkpoint['model']
    found = {k: tuple(v.shape) for k, v in stored.items() if isinstance(v, torch.Tensor)}
    problems = sorted(set(expected) ^ set(stored)) + [
        f'{k}: {found.get(k)} != {shape}' for k, shape in expected.items() if k in stored and found.get(k) != shape]
    if problems:
        raise CheckpointError(f'{path}: weights do not match the config: {problems[:5]}'
                              f'{" ..." if len(problems) > 5 else ""}')
    if not all(torch.isfinite(v).all() for v in stored.values() if v.is_floating_point()):
        raise CheckpointError(f'{path}: weights contain NaN or infinity')
    model.load_state_dict(stored)
    return model


def load_model(path, device='cpu') -> tuple[NextBestPoseNet, dict]:
    """(network in eval mode on ``device``, checkpoint dict) of the checkpoint at ``path``."""
    checkpoint = load(path)
    return build_model(checkpoint, path).to(device).eval(), checkpoint
