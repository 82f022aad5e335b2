"""Next-best-pose agent checkpoints: plain dicts of tensors plus a JSON-able config.

    {'format': FORMAT, 'version': VERSION, 'config': {'model': ..., 'train': ...},
     'model': state dict, 'optimizer': state dict, 'step': int, 'metrics': {...},
     'training_seeds': {task: [seed, ...]}}

Written and read by hdp_learning.checkpoints (atomic writes, size cap, weights-only
loading, one CheckpointError); the released models/hdp_nbp_agent.pt predates the
'version' field and reads as version 1. The config rebuilds the network with no
other file; loading checks every tensor's name and shape against that network.
"""

from __future__ import annotations

from hdp_learning import checkpoints
from hdp_learning.checkpoints import CheckpointError

from .model import ModelConfig, NextBestPoseNet

FORMAT = 'hdp_planner.next_best_pose'
VERSION = 1
FIELDS = {'config': dict, 'model': dict, 'step': int, 'metrics': dict, 'training_seeds': dict}


def save(path, model: NextBestPoseNet, optimizer, step: int, train_config: dict, metrics: dict,
         training_seeds: dict) -> None:
    """Write atomically (a crash mid-save leaves the previous checkpoint intact)."""
    checkpoints.save(path, {'format': FORMAT, 'version': VERSION,
                            'config': {'model': model.config.to_dict(), 'train': train_config},
                            'model': model.state_dict(),
                            'optimizer': optimizer.state_dict() if optimizer is not None else {},
                            'step': int(step), 'metrics': metrics, 'training_seeds': training_seeds})


def load(path) -> dict:
    """The checkpoint dict at ``path`` (tensors on the CPU); CheckpointError if it is not one."""
    checkpoint = checkpoints.load(path, FORMAT, VERSION, FIELDS)
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
    checkpoints.load_weights(path, model, checkpoint['model'])
    return model


def load_model(path, device='cpu') -> tuple[NextBestPoseNet, dict]:
    """(network in eval mode on ``device``, checkpoint dict) of the checkpoint at ``path``."""
    checkpoint = load(path)
    return build_model(checkpoint, path).to(device).eval(), checkpoint
