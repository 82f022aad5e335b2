"""Flat-policy checkpoints: plain dicts of tensors plus a JSON-able config.

    {'format': FORMAT, 'version': VERSION, 'policy': 'diffusion_policy' | 'act',
     'config': {'model': ..., 'train': ...}, 'model': state dict (the action normaliser's range
     included; the frozen sentence encoder's weights never), 'optimizer': state dict, 'step': int,
     'metrics': {...}, 'training_seeds': {task: [seed, ...]},
     'compute': [{'from_step', 'to_step', 'seconds', 'threads', 'fresh_optimizer'}, ...]}

'optimizer' is {} in a finished run's checkpoint and in one saved by a time-boxed run
(``hdp train flat --stop-after-minutes``), which keeps it the size of a released file; 'compute'
has one entry per training run that wrote the file (older files: none), so what a checkpoint
cost is read from the checkpoint.

Written and read by hdp_learning.checkpoints (atomic writes, size cap, weights-only loading, one
CheckpointError line); the config rebuilds the network with no other file, and loading checks
every tensor's name and shape against it. Evaluation refuses the training seeds.
"""

from __future__ import annotations

from hdp_learning import checkpoints
from hdp_learning.checkpoints import CheckpointError

from . import POLICIES

FORMAT = 'hdp_planner.flat_policy'
VERSION = 1
FIELDS = {'policy': str, 'config': dict, 'model': dict, 'step': int, 'metrics': dict, 'training_seeds': dict}


def config_class(policy: str):
    """The model config dataclass of ``policy``; ValueError naming the policies otherwise."""
    if policy == 'diffusion_policy':
        from .diffusion_policy import DiffusionPolicyConfig
        return DiffusionPolicyConfig
    if policy == 'act':
        from .act import ACTConfig
        return ACTConfig
    raise ValueError(f'unknown flat policy {policy!r}; policies: {", ".join(POLICIES)}')


def build_network(policy: str, config):
    """A fresh network of ``policy`` for its model config."""
    if policy == 'diffusion_policy':
        from .diffusion_policy import DiffusionPolicyNet
        return DiffusionPolicyNet(config)
    from .act import ACTNet
    config_class(policy)
    return ACTNet(config)


def save(path, policy: str, model, optimizer, step: int, train_config: dict, metrics: dict,
         training_seeds: dict, compute: list | None = None) -> None:
    """Write atomically (a crash mid-save leaves the previous checkpoint intact). Without ``optimizer``
    (a finished or time-boxed run) the parameters are stored as float16, halving the file for git;
    buffers (the action range) stay float32."""
    weights = model.state_dict()
    if optimizer is None:
        parameters = {name for name, _ in model.named_parameters()}
        weights = {k: v.half() if k in parameters and v.is_floating_point() else v for k, v in weights.items()}
    checkpoints.save(path, {'format': FORMAT, 'version': VERSION, 'policy': policy,
                            'config': {'model': model.config.to_dict(), 'train': train_config},
                            'model': weights,
                            'optimizer': optimizer.state_dict() if optimizer is not None else {},
                            'step': int(step), 'metrics': metrics, 'training_seeds': training_seeds,
                            'compute': list(compute or [])})


def thread_hours(stored: dict) -> float:
    """CPU-thread-hours of training a loaded checkpoint records (sum of seconds x threads)."""
    return sum(run['seconds'] * run['threads'] for run in stored.get('compute', [])) / 3600


def load(path, policy: str | None = None) -> dict:
    """The checkpoint dict at ``path`` (tensors on the CPU); CheckpointError if it is not a flat-policy
    checkpoint (of ``policy``, when given)."""
    stored = checkpoints.load(path, FORMAT, VERSION, FIELDS)
    if stored['policy'] not in POLICIES:
        raise CheckpointError(f'{path}: unknown flat policy {stored["policy"][:40]!r}; policies: {", ".join(POLICIES)}')
    if policy is not None and stored['policy'] != policy:
        raise CheckpointError(f'{path} holds a {stored["policy"]!r} policy, not {policy!r}')
    seeds = stored['training_seeds']
    if not all(isinstance(t, str) and isinstance(s, list) and all(isinstance(i, int) for i in s)
               for t, s in seeds.items()):
        raise CheckpointError(f'{path}: training_seeds must map task names to lists of seeds')
    return stored


def model_config(stored: dict, path='checkpoint'):
    """The model config a loaded checkpoint records; CheckpointError when it is not a valid one."""
    try:
        return config_class(stored['policy']).from_dict(stored['config']['model'])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f'{path}: invalid model config: {err!r}') from None


def build_model(stored: dict, path='checkpoint'):
    """The network a loaded checkpoint describes, with its weights, after checking names and shapes."""
    model = build_network(stored['policy'], model_config(stored, path))
    checkpoints.load_weights(path, model, stored['model'])
    return model
