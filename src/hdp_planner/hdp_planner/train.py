"""Training the next-best-pose network: batches, losses, the loop, resumable checkpoints.

Level 1 learns the ground-truth coarse voxel; level 2 sees a cube around the
ground truth moved by up to FINE_JITTER per axis (so it learns to correct a
coarse guess) and learns the voxel, offset, rotation bins and gripper there.
Cross-entropy on every discrete head (rotation: one per Euler axis), L1 on
the offset, summed. AdamW with a short warmup and a cosine decay.

Launched by ``torchrun``, it trains with DistributedDataParallel (gloo on the
CPU, NCCL on CUDA), as the low level does: every step's global batch and all
its random numbers (samples, augmentation, instructions, fine-cube jitter:
numpy, seeded by (seed, step); word dropout: torch, seeded likewise) are drawn
alike on every rank, and rank r takes rows r, r + N, ... of the batch's grids
and labels. The language encoder reads every instruction of the global batch,
so its word dropout draws what one process draws, and the condition keeps the
rank's rows. The network normalises with GroupNorm (per sample), and every
loss is a mean over rows, so N processes compute the step one process would,
split N ways: a run does not depend on how many processes ran it, and resumes
without RNG state.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from hdp_learning import distributed
from hdp_learning.curves import CurveLog, curves_path
from hdp_data.episodes import union_of_seeds

from . import checkpoint, rotations, voxels
from .dataset import KeyframeDataset
from .depth_augmentation import DepthAugmentation
from .evaluate import format_metrics, offline_metrics
from .language import task_vocabulary
from .model import ModelConfig, NextBestPoseNet

FINE_JITTER = 0.09        # m, each axis; < FINE_HALF_EXTENT so the target stays inside the cube
WARMUP_STEPS = 200
FINAL_LR_FRACTION = 0.1


@dataclasses.dataclass
class TrainConfig:
    """The hyper-parameters of ``train`` (the ``train:`` section of ``hdp train high-level --config``);
    the defaults are train()'s."""
    steps: int = 6000
    batch: int = 16              # the global batch: split over the processes under torchrun
    lr: float = 5e-4
    seed: int = 0
    val_every: int = 1000
    save_every: int = 250
    # Probability that a training frame's depth is degraded as a D415's (depth_augmentation.py); 0: off.
    depth_augmentation: float = 0.0
    # The largest calibration error given to the cameras of those frames (depth_augmentation.py); 0: none.
    extrinsic_augmentation_mm: float = 0.0
    extrinsic_augmentation_deg: float = 0.0

    def __post_init__(self):
        self.sensing()                   # refuses values out of range

    def sensing(self) -> DepthAugmentation:
        """The augmentation of training frames this config asks for."""
        if (self.extrinsic_augmentation_mm or self.extrinsic_augmentation_deg) and not self.depth_augmentation:
            raise ValueError('extrinsic_augmentation_mm/_deg perturb the frames depth_augmentation degrades: '
                             'set depth_augmentation > 0')
        return DepthAugmentation(probability=self.depth_augmentation, extrinsic_error_mm=self.extrinsic_augmentation_mm,
                                 extrinsic_error_deg=self.extrinsic_augmentation_deg)


def training_batch(items, config: ModelConfig, rng: np.random.Generator, device='cpu', rank: int = 0,
                   world: int = 1) -> dict:
    """Tensors for ``losses`` from the dataset Items of a (global) batch: both grids, the fine cube
    centres and the labels of rows rank, rank + world, ... (the jitter drawn for every row, then
    sliced); the instructions and proprio vectors of every row, and which rows are this process's."""
    size = config.grid_size
    jitter = rng.uniform(-FINE_JITTER, FINE_JITTER, (len(items), 3))[rank::world]
    mine = items[rank::world]
    xyz, rgb, cloud = voxels.collate_clouds([(i.xyz, i.rgb) for i in mine], device)
    target = torch.as_tensor(np.stack([i.target_xyz for i in mine]), dtype=torch.float32, device=device)
    lower, upper = (b.to(device) for b in voxels.workspace_bounds(len(mine)))
    coarse_index, _ = voxels.voxel_of(target, lower, upper, size)
    centre = target + torch.as_tensor(jitter, dtype=torch.float32, device=device)
    fine_lower, fine_upper = voxels.fine_bounds(centre, config.fine_half_extent)
    fine_index, offset = voxels.voxel_of(target, fine_lower, fine_upper, size)
    return {
        'instructions': [i.instruction for i in items],
        'proprio': torch.as_tensor(np.stack([i.proprio for i in items]), device=device),
        'rows': slice(rank, None, world),
        'coarse_grid': voxels.voxelise(xyz, rgb, cloud, lower, upper, size),
        'coarse_index': coarse_index,
        'fine_grid': voxels.voxelise(xyz, rgb, cloud, fine_lower, fine_upper, size),
        'centre': centre, 'fine_index': fine_index, 'offset': offset,
        'rotation': torch.as_tensor(rotations.quat_to_bins(np.stack([i.target_quat for i in mine])), device=device),
        'gripper': torch.as_tensor([int(i.target_open) for i in mine], device=device),
    }


def losses(model: NextBestPoseNet, batch: dict) -> dict:
    """Per-head losses (means over the batch's rows) and their sum under 'total'. The condition
    is computed for every instruction and kept for ``batch['rows']`` (all when absent)."""
    condition = model.condition(batch['instructions'], batch['proprio'])[batch.get('rows', slice(None))]
    coarse = model.coarse_logits(batch['coarse_grid'], condition)
    fine = model.fine_outputs(batch['fine_grid'], condition, batch['centre'], batch['fine_index'])
    parts = {
        'coarse': F.cross_entropy(coarse, batch['coarse_index']),
        'fine': F.cross_entropy(fine['logits'], batch['fine_index']),
        'offset': F.l1_loss(fine['offset'], batch['offset']),
        'rotation': 3 * F.cross_entropy(fine['rotation'].reshape(-1, rotations.BINS), batch['rotation'].reshape(-1)),
        'gripper': F.cross_entropy(fine['gripper'], batch['gripper']),
    }
    parts['total'] = sum(parts.values())
    return parts


class _Losses(torch.nn.Module):
    """The agent with ``losses`` as its forward: what DistributedDataParallel wraps, so that a
    backward pass averages the gradients of every process."""

    def __init__(self, model: NextBestPoseNet):
        super().__init__()
        self.model = model

    def forward(self, batch: dict) -> dict:
        return losses(self.model, batch)


def learning_rate(step: int, steps: int, peak: float) -> float:
    """Linear warmup to ``peak``, then cosine decay to FINAL_LR_FRACTION x peak at ``steps``."""
    if step < WARMUP_STEPS:
        return peak * (step + 1) / WARMUP_STEPS
    progress = min(1.0, (step - WARMUP_STEPS) / max(1, steps - WARMUP_STEPS))
    return peak * (FINAL_LR_FRACTION + (1 - FINAL_LR_FRACTION) * 0.5 * (1 + math.cos(math.pi * progress)))


def _differences(now: dict, stored: dict) -> list[str]:
    """'section.key: stored -> now' for every config value that differs."""
    return [f'{section}.{key}: {stored.get(section, {}).get(key)!r} -> {value!r}'
            for section, values in now.items() for key, value in values.items()
            if stored.get(section, {}).get(key) != value]


def _stored_model_config(stored: dict, path) -> dict:
    """A checkpoint's model config with every field this version has (an older one lacks
    language_encoder: it reads as 'words'), for comparing with this run's."""
    try:
        return json.loads(json.dumps(ModelConfig.from_dict(stored['config']['model']).to_dict()))
    except (KeyError, TypeError, ValueError) as err:
        raise checkpoint.CheckpointError(f'{path}: invalid model config: {err!r}') from None


def train(data, out, steps: int = 6000, batch: int = 16, lr: float = 5e-4, seed: int = 0, val_data=None,
          device: str = 'cpu', cache=None, save_every: int = 250, val_every: int = 1000,
          model_config: ModelConfig | None = None, init=None, log=print, progress: bool = True,
          language_encoder: str = 'words', depth_augmentation: float = 0.0, extrinsic_augmentation_mm: float = 0.0,
          extrinsic_augmentation_deg: float = 0.0) -> dict:
    """Train (or continue training) the checkpoint at ``out``; returns the last validation metrics.

    An existing ``out`` is continued when its config matches this run's
    (data, steps, batch, lr, seed, init, model); a different config is refused.
    ``init``: a checkpoint whose weights start the run (fine-tuning with a fresh
    optimiser and schedule); its model config must match, and its training seeds
    are recorded with this data's. ``language_encoder`` ('words' or 'minilm') is used when
    ``model_config`` is not given. ``depth_augmentation``: the probability that a training frame's
    depth is degraded as a D415's first (depth_augmentation.py; 0, off, by default), and
    ``extrinsic_augmentation_mm/_deg`` the largest calibration error its cameras then get. Under
    torchrun (see the module docstring) ``batch`` is the global batch and must split evenly; rank 0 alone logs, validates, writes curves and
    checkpoints, and the ranks compare their weights at every save.
    """
    from tqdm import tqdm
    out = Path(out)
    rank, world, device = distributed.start(device)
    lead = rank == 0                  # the one process that logs and writes
    if not lead:
        log, progress = _quiet, False
    if batch % world:
        raise ValueError(f'batch {batch} does not split over {world} processes')
    if not lead:
        distributed.barrier(world)    # the lead decodes and caches the episodes; the others then read its cache
    model_config = model_config or ModelConfig(vocabulary=tuple(task_vocabulary()), language_encoder=language_encoder)
    dataset = KeyframeDataset.from_directory(data, cache, progress, model_config.proprio,
                                             TrainConfig(depth_augmentation=depth_augmentation,
                                                         extrinsic_augmentation_mm=extrinsic_augmentation_mm,
                                                         extrinsic_augmentation_deg=extrinsic_augmentation_deg).sensing())
    val = (KeyframeDataset.from_directory(val_data, progress=progress, proprio=model_config.proprio)
           if val_data and lead else None)
    if lead:
        distributed.barrier(world)
    train_config = {'data': str(Path(data).resolve()), 'steps': steps, 'batch': batch, 'lr': lr, 'seed': seed}
    augmentation = {'depth_augmentation': depth_augmentation, 'extrinsic_augmentation_mm': extrinsic_augmentation_mm,
                    'extrinsic_augmentation_deg': extrinsic_augmentation_deg}
    train_config.update({k: v for k, v in augmentation.items() if v})  # recorded when on: older runs resume as they were
    torch.manual_seed(seed)           # the initial weights: from the seed, the same on every rank
    model = NextBestPoseNet(model_config).to(device)
    init_seeds = {}
    if init is not None:
        start = checkpoint.load(init)
        if _stored_model_config(start, init) != json.loads(json.dumps(model_config.to_dict())):
            raise checkpoint.CheckpointError(f'{init} has another model config; it cannot start this run')
        model.load_state_dict(checkpoint.build_model(start, init).state_dict())
        train_config['init'] = {'path': str(Path(init).resolve()), 'step': start['step']}
        init_seeds = start['training_seeds']
        log(f'starting from the weights of {init} (step {start["step"]})')
    training_seeds = union_of_seeds(dataset.training_seeds(), init_seeds)
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    step, metrics = 0, {}
    if out.exists():
        stored = checkpoint.load(out)
        wanted = {'model': model_config.to_dict(), 'train': train_config}
        changed = _differences(json.loads(json.dumps(wanted)),
                               {**stored['config'], 'model': _stored_model_config(stored, out)})
        if 'init' in stored['config']['train'] and 'init' not in train_config:
            changed.append(f"train.init: {stored['config']['train']['init']!r} -> None")
        if changed:
            raise checkpoint.CheckpointError(f'{out} was trained with another config ({"; ".join(changed)}); '
                                             'choose another --out or the same options')
        model.load_state_dict(checkpoint.build_model(stored, out).state_dict())
        try:
            optimizer.load_state_dict(stored['optimizer'])
        except (KeyError, TypeError, ValueError, RuntimeError) as err:
            raise checkpoint.CheckpointError(f'{out}: a damaged optimiser state ({type(err).__name__} '
                                             'restoring it)') from None
        step, metrics = stored['step'], stored['metrics']
        log(f'continuing {out} from step {step}')
    per_task = ', '.join(f'{t}: {(dataset.tasks == t).sum()}' for t in np.unique(dataset.tasks))
    log(f'{len(dataset)} training samples ({per_task}){f"; {len(val)} validation samples" if val else ""}; '
        f'{sum(p.numel() for p in model.parameters()):,} parameters'
        + (f'; {world} processes of {batch // world} samples each' if world > 1 else ''))
    net = _Losses(model)
    if world > 1:
        # The 1x1x1 convolutions' weights are channels_last: their gradients' strides differ from
        # DDP's buckets only in size-1 dimensions (the same memory), which DDP warns of.
        warnings.filterwarnings('ignore', message='Grad strides do not match bucket view strides')
        net = torch.nn.parallel.DistributedDataParallel(net)
    model.train()
    curves = CurveLog(curves_path(out), resume_step=step) if lead else None
    started, running, counted = time.monotonic(), {}, 0
    with tqdm(total=steps, initial=step, unit='step', disable=not progress, mininterval=30) as bar:
        while step < steps:
            for group in optimizer.param_groups:
                group['lr'] = learning_rate(step, steps, lr)
            # Seeded per (seed, step), alike on every rank: a continued run is the uninterrupted one,
            # and N processes draw the global batch one process draws.
            rng = np.random.default_rng([seed, step])
            torch.manual_seed(seed * 1_000_003 + step)
            items = [dataset.item(i, rng, augmented=True) for i in dataset.draw(batch, rng)]
            parts = net(training_batch(items, model_config, rng, device, rank, world))
            optimizer.zero_grad(set_to_none=True)
            parts['total'].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            step += 1
            values = torch.stack([value.detach() for value in parts.values()])
            if world > 1:                 # the global batch's losses, for the log and the curves
                torch.distributed.all_reduce(values)
                values /= world
            for name, value in zip(parts, values.tolist()):
                running[name] = running.get(name, 0.0) + value
            counted += 1
            bar.update()
            if lead and (step % 100 == 0 or step == steps):
                bar.write(f'step {step}: ' + ' '.join(f'{k} {v / counted:.3f}' for k, v in running.items())
                          + f' ({(time.monotonic() - started) / 60:.1f} min)')
                curves.add(step, lr=learning_rate(step - 1, steps, lr), **{k: v / counted for k, v in running.items()})
                running, counted = {}, 0
            if val and (step % val_every == 0 or step == steps):
                metrics = {'step': step, 'validation': offline_metrics(model, val)}
                bar.write(f'validation at step {step}:\n{format_metrics(metrics["validation"])}')
                overall = metrics['validation']['overall']
                curves.add(step, **{f'val_{k}': overall[k] for k in ('translation_cm', 'rotation_symmetric_deg',
                                                                    'gripper_accuracy')})
            if step % save_every == 0 or step == steps:
                digests = distributed.gather(distributed.weights_digest(model), world)
                if len(set(digests)) > 1:
                    raise RuntimeError(f'the {world} processes hold different weights at step {step}')
                if lead:              # what ran it is recorded, not compared when continuing
                    checkpoint.save(out, model, optimizer, step,
                                    {**train_config, 'processes': world, 'weights_sha256': digests[0]},
                                    metrics, training_seeds)
    del net                           # before the process group: distributed.stop
    distributed.stop(world)
    return metrics


def _quiet(*_args, **_kwargs) -> None:
    pass
