"""Where training and evaluation run: the torch device, and processes launched by torchrun
(its environment: RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR...).

``hdp train low-level`` and ``hdp train high-level`` (DistributedDataParallel) and
the evaluations (episodes sharded over the ranks, one result gathered on rank 0) use
the same launcher, and every trainer (``hdp train flat`` too) its device, so a
run on several processes or machines is ``torchrun [--nnodes ...] --nproc-per-node
N -m hdp_tools.cli.main <the same hdp command>``. Without torchrun there is one
process and nothing here starts a process group. torch is imported inside the
functions only (as in ``checkpoints``): hdp_learning needs no torch at import.
"""

from __future__ import annotations

import atexit
import hashlib
import os


def torch_device(name: str) -> str:
    """'cpu', 'cuda', 'cuda:N' or 'auto' (CUDA when there is one) -> a device torch has here;
    ValueError naming what is missing otherwise."""
    import torch
    if name == 'auto':
        return 'cuda' if torch.cuda.is_available() else 'cpu'
    if name != 'cpu' and not (name == 'cuda' or name.startswith('cuda:')):
        raise ValueError(f'device {name!r}: use cpu, cuda, cuda:N or auto')
    if name.startswith('cuda') and not torch.cuda.is_available():
        raise ValueError(f'device {name!r} asked for, but torch sees no CUDA device here')
    return name


def world_size() -> int:
    return int(os.environ.get('WORLD_SIZE', '1'))


def start(device: str = 'cpu') -> tuple[int, int, str]:
    """(rank, world size, this process's device), joining torchrun's process group if it launched
    us: NCCL on CUDA (one GPU per local rank), gloo on the CPU."""
    import torch
    world = world_size()
    if world == 1:
        return 0, 1, device
    if device.startswith('cuda'):
        device = f'cuda:{int(os.environ.get("LOCAL_RANK", "0"))}'
        torch.cuda.set_device(device)
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group('nccl' if device.startswith('cuda') else 'gloo')
        # Callers that return without stop() (the evaluations, whose group the ladder reuses) leave
        # here: a group left to the interpreter's teardown frees gloo's threads while they are still
        # joinable, and the process aborts ("terminate called without an active exception").
        atexit.register(stop, world)
    return torch.distributed.get_rank(), world, device


def gather(value, world: int) -> list:
    """Every rank's ``value`` (any picklable object), in rank order, on every rank."""
    if world == 1:
        return [value]
    import torch
    values = [None] * world
    torch.distributed.all_gather_object(values, value)
    return values


def barrier(world: int) -> None:
    """Wait until every rank has come here."""
    if world > 1:
        import torch
        torch.distributed.barrier()


def weights_digest(model) -> str:
    """sha256 of every tensor of ``model``'s state dict: equal on every rank, or the ranks have diverged."""
    digest = hashlib.sha256()
    for tensor in model.state_dict().values():
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def stop(world: int) -> None:
    """Leave the process group. Release DistributedDataParallel wrappers first: a DDP reducer
    that outlives the group frees it holding the GIL, while gloo's worker thread needs the GIL to
    free its last work's tensors, and the process hangs at exit (3 two-process runs in 37)."""
    if world > 1:
        import torch
        if torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
