"""Training a flat policy (Diffusion Policy or ACT): the seeded, resumable loop.

Each step draws a task-balanced batch seeded by (seed, step) (samples, instructions; torch's
noise, latents and image shifts likewise), so a continued run is the uninterrupted one. AdamW,
linear warmup then cosine decay to FINAL_LR_FRACTION, gradients clipped at norm 1. Every
CURVE_EVERY steps the mean losses and the learning rate go to the curves CSV beside the
checkpoint; with validation data, every val_every steps the policy's own predicted chunks on a
fixed set of validation samples are scored (mean joint-target error in rad over the chunk,
gripper accuracy) and logged too. The checkpoint records the training seeds and each run's
compute; its last save drops the optimiser state (a finished run is not continued), so a released
one is weights only. A time-boxed run (``stop_after_s``) saves weights only too, so a long run can
travel between machines in files a repository takes; the next run continues it with fresh AdamW
moments (the schedule and the batches go on from the step), and the checkpoint records where.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from hdp_learning.curves import CurveLog, curves_path

from .. import language
from . import checkpoint
from .dataset import FlatDataset
from .encoders import observation_tensors

CURVE_EVERY = 50
FINAL_LR_FRACTION = 0.1
VAL_SEED = 12345


@dataclasses.dataclass
class FlatTrainConfig:
    """The ``train:`` section of ``hdp train flat --config``; the defaults are Diffusion Policy's
    optimiser (lr 1e-4, weight decay 1e-6, 500 warmup steps) with a CPU-sized batch."""
    steps: int = 20000
    batch: int = 32
    lr: float = 1e-4
    weight_decay: float = 1e-6
    warmup: int = 500
    seed: int = 0
    save_every: int = 500
    val_every: int = 2000
    val_samples: int = 128

    def __post_init__(self):
        if min(self.steps, self.batch, self.save_every, self.val_every, self.val_samples) < 1 or self.lr <= 0 \
                or self.warmup < 0 or self.weight_decay < 0:
            raise ValueError('steps, batch, save_every, val_every and val_samples must be >= 1, lr > 0, '
                             'warmup and weight_decay >= 0')


def learning_rate(step: int, config: FlatTrainConfig) -> float:
    """Linear warmup to config.lr, then cosine decay to FINAL_LR_FRACTION x lr at config.steps."""
    if step < config.warmup:
        return config.lr * (step + 1) / config.warmup
    progress = min(1.0, (step - config.warmup) / max(1, config.steps - config.warmup))
    return config.lr * (FINAL_LR_FRACTION + (1 - FINAL_LR_FRACTION) * 0.5 * (1 + math.cos(math.pi * progress)))


def validation_metrics(model, dataset: FlatDataset, samples: int = 128, device='cpu', batch: int = 32) -> dict:
    """The policy's predicted chunks on ``samples`` fixed samples (seen phrasings): mean |joint target
    error| in rad over the chunk's real (not padded) steps, and the gripper's accuracy there."""
    rng = np.random.default_rng(VAL_SEED)
    chosen = dataset.draw(samples, rng)
    was_training = model.training
    model.eval()
    errors, correct, counted = 0.0, 0.0, 0.0
    generator = torch.Generator().manual_seed(VAL_SEED)
    for start in range(0, len(chosen), batch):
        b = dataset.batch(chosen[start:start + batch], rng)
        predicted = model.predict(observation_tensors(b, device), generator).cpu().numpy()
        valid = ~b.is_pad
        errors += float((np.abs(predicted[..., :7] - b.actions[..., :7]).mean(-1) * valid).sum())
        correct += float((((predicted[..., 7] >= 0) == (b.actions[..., 7] > 0)) * valid).sum())
        counted += float(valid.sum())
    model.train(was_training)
    return {'joint_error_rad': errors / max(counted, 1), 'gripper_accuracy': correct / max(counted, 1)}


def _differences(now: dict, stored: dict) -> list[str]:
    return [f'{section}.{key}: {stored.get(section, {}).get(key)!r} -> {value!r}'
            for section, values in now.items() for key, value in values.items()
            if stored.get(section, {}).get(key) != value]


def train(policy: str, data, out, model_config=None, train_config: FlatTrainConfig | None = None, val_data=None,
          device: str = 'cpu', cache=None, log=print, progress: bool = True, workers: int = 1,
          stop_after_s: float | None = None) -> dict:
    """Train (or continue training) the flat ``policy`` checkpoint at ``out``; returns the last metrics.

    An existing ``out`` is continued when its policy and config match this run's (data, model,
    train: save_every and val_every aside); another is refused with the differences named.
    ``workers``: processes decoding the episodes the cache lacks. ``stop_after_s``: stop after that
    many seconds of training and save without the optimiser's moments (see the module docstring).
    """
    from tqdm import tqdm
    if stop_after_s is not None and stop_after_s <= 0:
        raise ValueError(f'stop_after_s must be > 0, got {stop_after_s}')
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    train_config = train_config or FlatTrainConfig()
    model_config = model_config or checkpoint.config_class(policy)()
    if model_config.language_encoder == 'words' and not model_config.vocabulary:
        model_config = dataclasses.replace(model_config, vocabulary=tuple(language.task_vocabulary()))
    shape = dict(n_obs=model_config.n_obs, horizon=model_config.horizon, width=model_config.image_width,
                 height=model_config.image_height, period=model_config.control_period_s)
    dataset = FlatDataset.from_directory(data, cache_dir=cache, progress=progress, workers=workers, **shape)
    val = FlatDataset.from_directory(val_data, progress=progress, **shape) if val_data else None
    torch.manual_seed(train_config.seed)            # the initial weights
    model = checkpoint.build_network(policy, model_config).to(device)
    compared = {k: v for k, v in dataclasses.asdict(train_config).items() if k not in ('save_every', 'val_every')}
    recorded = {'data': str(Path(data).resolve()), 'data_camera_rate_hz': dataset.camera_rate_hz(), **compared}
    decay, no_decay = [], []
    for name, parameter in model.named_parameters():
        (no_decay if parameter.ndim < 2 else decay).append(parameter)
    optimizer = torch.optim.AdamW([{'params': decay, 'weight_decay': train_config.weight_decay},
                                   {'params': no_decay, 'weight_decay': 0.0}], lr=train_config.lr)
    step, metrics, compute, fresh_optimizer = 0, {}, [], True
    if out.exists():
        stored = checkpoint.load(out)
        wanted = json.loads(json.dumps({'model': model_config.to_dict(), 'train': recorded}))
        changed = _differences(wanted, stored['config'])
        if stored['policy'] != policy:
            changed.insert(0, f'policy: {stored["policy"]!r} -> {policy!r}')
        if changed:
            raise checkpoint.CheckpointError(f'{out} was trained with another config ({"; ".join(changed)}); '
                                             'choose another --out or the same options')
        model.load_state_dict(checkpoint.build_model(stored, out).state_dict())
        step, metrics, compute = stored['step'], stored['metrics'], list(stored.get('compute', []))
        fresh_optimizer = not stored['optimizer']           # finished or time-boxed: weights only
        try:
            if step < train_config.steps and not fresh_optimizer:
                optimizer.load_state_dict(stored['optimizer'])
        except (KeyError, TypeError, ValueError, RuntimeError) as err:
            raise checkpoint.CheckpointError(f'{out}: a damaged optimiser state ({type(err).__name__} '
                                             'restoring it)') from None
        log(f'continuing {out} from step {step} ({checkpoint.thread_hours(stored):.2f} CPU-thread-hours so far)'
            + (' with fresh AdamW moments (saved without them)' if fresh_optimizer and step < train_config.steps
               else ''))
    else:
        model.normaliser.fit(*dataset.action_range())
    training_seeds = dataset.training_seeds()
    per_task = ', '.join(f'{t}: {(dataset.tasks == t).sum()}' for t in np.unique(dataset.tasks))
    log(f'{policy}: {len(dataset)} training samples at {1 / model_config.control_period_s:g} Hz ({per_task}), '
        f'camera frames {f"at {dataset.camera_rate_hz():g} Hz" if dataset.camera_rate_hz() else "at rests only"}'
        f'{f"; {len(val)} validation samples" if val else ""}; '
        f'{sum(p.numel() for p in model.parameters() if p.requires_grad):,} trained parameters')
    model.train()
    curves = CurveLog(curves_path(out), resume_step=step)
    started, running, counted = time.monotonic(), {}, 0
    this_run = {'from_step': step, 'to_step': step, 'seconds': 0.0, 'threads': torch.get_num_threads(),
                'fresh_optimizer': fresh_optimizer}

    def save(with_optimizer: bool) -> None:
        this_run.update(to_step=step, seconds=round(time.monotonic() - started, 3))
        checkpoint.save(out, policy, model, optimizer if with_optimizer else None, step, recorded, metrics,
                        training_seeds, [*compute, this_run])

    with tqdm(total=train_config.steps, initial=step, unit='step', disable=not progress, mininterval=30) as bar:
        while step < train_config.steps:
            for group in optimizer.param_groups:
                group['lr'] = learning_rate(step, train_config)
            rng = np.random.default_rng([train_config.seed, step])
            generator = torch.Generator().manual_seed(train_config.seed * 1_000_003 + step)
            batch = dataset.batch(dataset.draw(train_config.batch, rng), rng)
            parts = model.losses(observation_tensors(batch, device), generator)
            optimizer.zero_grad(set_to_none=True)
            parts['total'].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            step += 1
            for name, value in parts.items():
                running[name] = running.get(name, 0.0) + float(value.detach())
            counted += 1
            bar.update()
            if step % CURVE_EVERY == 0 or step == train_config.steps:
                means = {k: v / counted for k, v in running.items()}
                bar.write(f'step {step}: ' + ' '.join(f'{k} {v:.4f}' for k, v in means.items())
                          + f' ({(time.monotonic() - started) / 60:.1f} min)')
                curves.add(step, lr=learning_rate(step - 1, train_config), **means)
                running, counted = {}, 0
            if val and (step % train_config.val_every == 0 or step == train_config.steps):
                metrics = {'step': step, 'validation': validation_metrics(model, val, train_config.val_samples, device)}
                bar.write(f'validation at step {step}: {json.dumps(metrics["validation"])}')
                curves.add(step, **{f'val_{k}': v for k, v in metrics['validation'].items()})
            if step % train_config.save_every == 0 or step == train_config.steps:
                # The last save drops the optimiser's moments (twice the weights): a finished run is
                # not continued, and the released checkpoint stays a few MB.
                save(with_optimizer=step < train_config.steps)
            if stop_after_s is not None and time.monotonic() - started >= stop_after_s and step < train_config.steps:
                save(with_optimizer=False)
                spent = checkpoint.thread_hours({'compute': [*compute, this_run]})
                bar.write(f'stopped at step {step} after {stop_after_s / 60:g} min ({spent:.2f} CPU-thread-hours in '
                          f'all); saved {out} without the optimiser moments: the same command continues it')
                break
    return metrics
