"""RK-Diffuser checkpoints: one torch file that rebuilds its model with no other file.

    {'format': FORMAT, 'version': VERSION, 'config': RKDConfig as a dict, 'model': EMA state dict,
     'training': {...}, 'training_seeds': {task: [seed, ...]}}

Written and read by hdp_learning.checkpoints (atomic writes, size cap, weights-only
loading, one CheckpointError); this module adds the RK-Diffuser's fields and model.
Training also writes ``OUT.resume`` (RESUME_FORMAT) under the same rules.
"""

from __future__ import annotations

import dataclasses

from hdp_learning import checkpoints
from hdp_learning.checkpoints import CheckpointError

from .rk_diffuser import RKDConfig, RKDiffuser

FORMAT = 'hdp_rk_diffuser'
VERSION = 2      # 2: the joint diffuser generates motion from the start joints
RESUME_FORMAT = FORMAT + '.resume'   # raw weights, EMA, optimiser, schedule and RNG state
FIELDS = {'config': dict, 'model': dict}
RESUME_FIELDS = {'model_config': dict, 'train_config': dict, 'raw_model': dict, 'ema': dict, 'optimizer': dict,
                 'schedule': dict, 'step': int}


def save(path, model: RKDiffuser, extra: dict) -> None:
    """Write atomically: the EMA ``model`` weights, its config, and ``extra``
    (training state, seeds, metrics: plain containers and tensors only)."""
    checkpoints.save(path, {'format': FORMAT, 'version': VERSION, 'config': dataclasses.asdict(model.config),
                            'model': model.state_dict(), **extra})


def read(path) -> dict:
    """The checkpoint's contents, structure-checked (no model built)."""
    return checkpoints.load(path, FORMAT, VERSION, FIELDS)


def load_model(path) -> tuple[RKDiffuser, dict]:
    """(model in eval mode, the checkpoint's payload) after checking every tensor's shape."""
    payload = read(path)
    try:
        model = RKDiffuser(RKDConfig.from_dict(payload['config']))
    except (TypeError, ValueError) as err:
        raise CheckpointError(f'{path}: bad config: {err}') from None
    checkpoints.load_weights(path, model, payload['model'])
    return model.eval(), payload


def save_resume(path, state: dict) -> None:
    """Write the training ``state`` (plain containers and tensors) atomically."""
    checkpoints.save(path, {'format': RESUME_FORMAT, 'version': VERSION, **state})


def read_resume(path) -> dict:
    """The training state at ``path`` (tensors on the CPU), structure-checked."""
    return checkpoints.load(path, RESUME_FORMAT, VERSION, RESUME_FIELDS)
