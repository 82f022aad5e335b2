"""RK-Diffuser checkpoints: one torch file that rebuilds its model with no other file.

A checkpoint is untrusted input: it is loaded with ``weights_only=True``
(tensors and plain containers only, no pickled code), its size is capped
before reading, and its structure, config and every tensor's shape are
checked against the model it describes before any weight is used.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from .rk_diffuser import RKDConfig, RKDiffuser

FORMAT = 'hdp_rk_diffuser'
VERSION = 2      # 2: the joint diffuser generates motion from the start joints
MAX_BYTES = 512 * 1024 ** 2


class CheckpointError(ValueError):
    pass


def save(path, model: RKDiffuser, extra: dict) -> None:
    """Write atomically: the EMA ``model`` weights, its config, and ``extra``
    (training state, seeds, metrics: plain containers and tensors only)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {'format': FORMAT, 'version': VERSION, 'config': dataclasses.asdict(model.config),
               'model': model.state_dict(), **extra}
    tmp = path.with_name(path.name + '.tmp')
    torch.save(payload, tmp)
    tmp.replace(path)


def read(path) -> dict:
    """The checkpoint's contents, structure-checked (no model built)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f'{path}: no such checkpoint')
    if path.stat().st_size > MAX_BYTES:
        raise CheckpointError(f'{path}: {path.stat().st_size} bytes is over the {MAX_BYTES}-byte limit')
    try:
        payload = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as err:      # torch raises many types for a damaged or hostile file
        raise CheckpointError(f'{path}: not a loadable weights-only checkpoint ({err})') from None
    if not isinstance(payload, dict) or payload.get('format') != FORMAT:
        raise CheckpointError(f'{path}: not an RK-Diffuser checkpoint (format {FORMAT!r} expected)')
    if payload.get('version') != VERSION:
        raise CheckpointError(f'{path}: checkpoint version {payload.get("version")!r}, this code reads {VERSION}')
    for key, kind in (('config', dict), ('model', dict)):
        if not isinstance(payload.get(key), kind):
            raise CheckpointError(f'{path}: missing or malformed {key!r}')
    return payload


def load_model(path) -> tuple[RKDiffuser, dict]:
    """(model in eval mode, the checkpoint's payload) after checking every tensor's shape."""
    payload = read(path)
    try:
        config = RKDConfig.from_dict(payload['config'])
        model = RKDiffuser(config)
    except (TypeError, ValueError) as err:
        raise CheckpointError(f'{path}: bad config: {err}') from None
    expected = model.state_dict()
    weights = payload['model']
    if set(weights) != set(expected):
        missing, unexpected = sorted(set(expected) - set(weights)), sorted(set(weights) - set(expected))
        raise CheckpointError(f'{path}: weights do not match the config (missing {missing[:3]}, '
                              f'unexpected {unexpected[:3]})')
    for name, tensor in weights.items():
        if not isinstance(tensor, torch.Tensor) or tensor.shape != expected[name].shape:
            raise CheckpointError(f'{path}: {name} has the wrong shape or type')
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise CheckpointError(f'{path}: {name} has non-finite values')
    model.load_state_dict(weights)
    return model.eval(), payload
