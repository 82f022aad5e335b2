"""The one set of rules every HDP checkpoint is written and read by; torch is imported only inside.

A checkpoint is a torch file holding one plain dict:

    {'format': kind (str), 'version': int, <the package's fields>: tensors and plain containers}

'format' names the kind of model (the field name both released checkpoints use),
'version' the layout of the package's fields. A checkpoint is untrusted input:

- written atomically: into ``<name>.partial`` in the same directory, then renamed
  over ``<name>``, so a crash mid-save leaves the previous checkpoint whole;
- refused unread when larger than MAX_BYTES;
- read with ``torch.load(weights_only=True)``: tensors and plain containers only,
  never pickled code;
- refused unless its kind, version and named fields are the reader's, and its
  weights match, name for name and shape for shape, the model its config builds.

Every refusal is one CheckpointError line naming the file. Each package keeps the
model-specific part (its fields, building its model) in its own ``checkpoint.py``.
"""

from __future__ import annotations

import os
import pickle
import reprlib
import zipfile
from pathlib import Path

MAX_BYTES = 512 * 1024 ** 2
PARTIAL_SUFFIX = '.partial'
# What torch.load raises for a truncated, damaged or hostile file (its own messages
# suggest weights_only=False, which must never be followed for a checkpoint). OSError: a zip
# cut short after its header ("[Errno 22] Invalid argument" from torch's file reader).
# Random bytes make torch.load raise any of these (IndexError and KeyError in ~8% of 300 tries).
_UNREADABLE = (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, OSError, zipfile.BadZipFile, IndexError,
               KeyError)


class CheckpointError(ValueError):
    """A file that is not a readable checkpoint of the expected kind; the message names the file."""


def models_dir() -> Path:
    """$HDP_MODELS_DIR, else the repository's models/ folder (the released checkpoints)."""
    return Path(os.environ.get('HDP_MODELS_DIR') or Path(__file__).resolve().parents[3] / 'models')


def default_path(name: str) -> Path:
    """The released checkpoint ``name`` (e.g. 'rk_diffuser.pt') in models_dir()."""
    return models_dir() / name


def resolve(path_or_name) -> Path:
    """A checkpoint path as given, or, for a bare file name that is not a file here, the released
    checkpoint of that name in models_dir() (a parameter file can then name one on any host)."""
    path = Path(path_or_name)
    if path.parent == Path('.') and not path.is_file():
        return default_path(path.name)
    return path


def save(path, payload: dict) -> None:
    """Write ``payload`` (with str 'format' and int 'version') to ``path`` atomically."""
    import torch
    if not isinstance(payload.get('format'), str) or not isinstance(payload.get('version'), int):
        raise ValueError("a checkpoint payload needs a str 'format' and an int 'version'")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        with open(partial, 'wb') as file:
            torch.save(payload, file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def load(path, expected_kind: str, version: int, fields: dict | None = None) -> dict:
    """The payload at ``path`` (tensors on the CPU) after checking its size, kind, version and
    ``fields`` (name -> type each must have); CheckpointError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f'{path}: no such checkpoint')
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise CheckpointError(f'{path}: {size} bytes is over the {MAX_BYTES}-byte checkpoint limit')
    payload = _read_weights_only(path)
    found_kind, found_version = _kind_and_version(payload)
    # reprlib: what a file declares is shown short and on one line, whatever it holds.
    if found_kind != expected_kind:
        found = f'a {reprlib.repr(found_kind)} one' if isinstance(found_kind, str) else 'no checkpoint kind'
        raise CheckpointError(f'{path} is not a {expected_kind!r} checkpoint (it holds {found})')
    if found_version != version:
        raise CheckpointError(f'{path}: {expected_kind!r} version {reprlib.repr(found_version)}, '
                              f'this code reads {version}')
    for name, kind in (fields or {}).items():
        if not isinstance(payload.get(name), kind):
            raise CheckpointError(f'{path}: {name!r} is missing or not of type {kind.__name__}')
    return payload


def load_weights(path, model, weights: dict) -> None:
    """Copy the state dict ``weights`` into ``model`` (a torch module built from the checkpoint's
    config) if it has the model's names and shapes and finite values; CheckpointError otherwise."""
    import torch
    expected = model.state_dict()
    missing, unexpected = sorted(set(expected) - set(weights)), sorted(set(weights) - set(expected))
    if missing or unexpected:
        raise CheckpointError(f'{path}: weights do not match the config (missing {missing[:3]}, '
                              f'unexpected {unexpected[:3]})')
    for name, tensor in weights.items():
        if not isinstance(tensor, torch.Tensor) or tensor.shape != expected[name].shape:
            found = tuple(tensor.shape) if isinstance(tensor, torch.Tensor) else type(tensor).__name__
            raise CheckpointError(f'{path}: weights do not match the config: {name} has the wrong shape '
                                  f'{found}, the config asks for {tuple(expected[name].shape)}')
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise CheckpointError(f'{path}: {name} has NaN or infinite values')
    model.load_state_dict(weights)


def _read_weights_only(path: Path):
    """torch.load(weights_only=True) of ``path``, its failures as one-line CheckpointErrors."""
    import torch
    try:
        return torch.load(path, map_location='cpu', weights_only=True)
    except _UNREADABLE as err:
        # A whole torch file (a zip) the weights-only unpickler refuses holds code or objects.
        holds_objects = isinstance(err, pickle.UnpicklingError) and zipfile.is_zipfile(path)
        reason = ('it holds objects other than tensors and plain containers' if holds_objects
                  else 'truncated, damaged or of another format')
        raise CheckpointError(f'{path} is not a readable checkpoint (not a loadable torch file: {reason})') from None


def _kind_and_version(payload) -> tuple:
    """(kind, version) a payload declares. The agent's first checkpoints (models/hdp_nbp_agent.pt)
    have no 'version': their format carries it, 'hdp_planner.next_best_pose/1'."""
    if not isinstance(payload, dict):
        return None, None
    kind, version = payload.get('format'), payload.get('version')
    if version is None and isinstance(kind, str) and '/' in kind:
        kind, _, number = kind.rpartition('/')
        version = int(number) if number.isdigit() else number
    return kind, version
