"""Training loop for RK-Diffuser: seeded, resumable, CPU by default, one process or many.

Writes ``OUT`` (the EMA weights + config + provenance: what inference and the
release need), ``OUT.resume`` (raw weights, optimiser and schedule) and the
training curves (``<OUT stem>_curves.csv``: losses and learning rate, and with
validation episodes the EMA model's losses on them at every save).
Starting again with the same OUT, data and config continues from
``OUT.resume``; a different config refuses to mix.

Launched by ``torchrun``, it trains with DistributedDataParallel (gloo on
the CPU, NCCL on CUDA; several machines through torchrun's rendezvous).
Every step's global batch and all its random numbers come from a generator
seeded by (seed, step) on every rank, and rank r takes rows r, r + N, ...:
N processes compute the step one process would, split N ways, so a run
does not depend on how many processes ran it, and resumes without RNG state.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from diffusers.optimization import get_cosine_schedule_with_warmup
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from tqdm import tqdm

from hdp_learning import checkpoints, distributed
from hdp_learning.curves import CurveLog, curves_path
from hdp_data.episodes import union_of_seeds

from . import checkpoint
from .dataset import SegmentDataset, augment, draw_augmentation, load_segments
from .rk_diffuser import RKDConfig, RKDiffuser, parameter_count


CURVE_EVERY = 50       # steps per row of the training curves (means over them)


@dataclasses.dataclass
class TrainConfig:
    steps: int = 8000
    batch_size: int = 32
    lr: float = 3e-4
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    ema_decay: float = 0.995
    save_every: int = 500
    seed: int = 0
    goal_augment: float = 0.0      # rad: dataset.draw_augmentation's goal_sigma (0: off, as the first releases)


def batch_rows(n: int, batch_size: int, seed: int, step: int) -> torch.Tensor:
    """The dataset rows of global batch ``step``: epochs of permutations seeded by (seed, epoch),
    the last incomplete batch of each dropped."""
    per_epoch = n // batch_size
    if per_epoch == 0:
        raise ValueError(f'{n} segments are fewer than one batch of {batch_size}')
    epoch, index = divmod(step, per_epoch)
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))
    return order[index * batch_size:(index + 1) * batch_size]


def step_batch(dataset, model: RKDiffuser, train_config: TrainConfig, step: int, rank: int = 0,
               world: int = 1) -> tuple[dict, dict]:
    """(batch, draws) of ``step`` for process ``rank`` of ``world``: rows rank, rank + world, ...
    of the global batch, every random number drawn for the whole batch, then sliced."""
    generator = torch.Generator().manual_seed(train_config.seed * 1_000_003 + step)
    size = train_config.batch_size
    draws = model.draw(size, generator)
    augmentation = draw_augmentation(size, generator, train_config.goal_augment)
    mine = batch_rows(len(dataset), size, train_config.seed, step)[rank::world]
    items = [dataset[int(i)] for i in mine]
    batch = {k: torch.stack([item[k] for item in items]) for k in items[0]}
    batch = augment(batch, {k: v[rank::world] for k, v in augmentation.items()})
    return batch, {k: v[rank::world] for k, v in draws.items()}


def validation_losses(model: RKDiffuser, dataset, device: str, batch_size: int = 64) -> dict:
    """{'val_<part>': mean} of ``model``'s loss parts on ``dataset`` as recorded (no augmentation,
    no condition dropout) with noise and diffusion steps seeded the same at every call, so the
    rows of a run compare with each other."""
    generator = torch.Generator().manual_seed(0)
    sums, count = {}, 0
    was_training = model.training
    model.eval()
    with torch.no_grad():
        for start in range(0, len(dataset), batch_size):
            items = [dataset[i] for i in range(start, min(start + batch_size, len(dataset)))]
            batch = augment({k: torch.stack([item[k] for item in items]) for k in items[0]})
            draws = model.draw(len(items), generator)
            draws['drop'][:] = False
            _, parts = model.loss({k: v.to(device) for k, v in batch.items()}, draws)
            for name, value in parts.items():
                sums[name] = sums.get(name, 0.0) + value * len(items)
            count += len(items)
    model.train(was_training)
    return {f'val_{name}': total / count for name, total in sums.items()}


def train(data_dir, out, model_config: RKDConfig, train_config: TrainConfig, device: str = 'cpu',
          cache_dir=None, init=None, val_data=None, log=print) -> Path:
    """Train and write ``out``. ``init``: a checkpoint whose weights start the
    run (fine-tuning with a fresh optimiser and schedule); its config must match.
    ``val_data``: episodes (or their segments file) never trained on, for the curves."""
    out = Path(out)
    resume_path = out.with_name(out.name + '.resume')
    rank, world, device = distributed.start(device)
    if rank:
        log = _quiet                  # one process reports
    if train_config.batch_size % world:
        raise ValueError(f'batch size {train_config.batch_size} does not split over {world} processes')
    torch.manual_seed(train_config.seed)        # the initial weights: the same on every rank
    # Tiny gradients in the Mish/GELU backward turn denormal after warm-up and
    # made CPU steps ~15x slower; flushing them to zero costs no accuracy.
    torch.set_flush_denormal(True)
    # The resume file is read (and refused when damaged or of another run) before the data.
    state = checkpoint.read_resume(resume_path) if resume_path.is_file() else None
    all_segments = load_segments(data_dir, model_config.n_points, cache_dir)
    segs = all_segments.moving()
    log(f'{len(all_segments) - len(segs)} of {len(all_segments)} segments dropped: the arm does not move in them')
    dataset = SegmentDataset(segs)
    validation = None
    if val_data is not None:
        val_segs = load_segments(val_data, model_config.n_points, cache_dir).moving()
        shared = sorted(val_segs.episodes() & segs.episodes())
        if shared:
            raise ValueError(f'validation data {val_data} holds training episodes '
                             f'({", ".join(f"{t} {s}" for t, s in shared[:3])}...)')
        validation = SegmentDataset(val_segs)
        log(f'validating on {len(val_segs)} segments at every save')
    model = RKDiffuser(model_config).to(device)
    init_info = _load_init(model, model_config, init) if init else None
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(train_config.ema_decay))
    optimizer = torch.optim.AdamW(model.parameters(), lr=train_config.lr, weight_decay=train_config.weight_decay)
    schedule = get_cosine_schedule_with_warmup(optimizer, train_config.warmup_steps, train_config.steps)
    step, elapsed = 0, 0.0
    if state is not None:
        saved = (state['model_config'], state['train_config'], state.get('init'))
        wanted = (dataclasses.asdict(model_config), dataclasses.asdict(train_config), init_info)
        if any(_plain(a) != _plain(b) for a, b in zip(saved, wanted)):
            raise checkpoint.CheckpointError(f'{resume_path} was written with another configuration; '
                                             'delete it or pass the same --config/--steps/--init to resume')
        checkpoints.load_weights(resume_path, model, state['raw_model'])
        try:
            ema.load_state_dict(state['ema'])
            optimizer.load_state_dict(state['optimizer'])
            schedule.load_state_dict(state['schedule'])
        except (KeyError, TypeError, ValueError, RuntimeError) as err:
            raise checkpoint.CheckpointError(f'{resume_path}: a damaged training state '
                                             f'({type(err).__name__} restoring it)') from None
        step, elapsed = state['step'], state['elapsed_s']
        log(f'resuming from {resume_path} at step {step}')
    log(f'{len(segs)} segments from {len(np.unique(np.char.add(segs.task, segs.seed.astype(str))))} episodes; '
        f'{parameter_count(model) / 1e6:.2f} M parameters' + (f'; process {rank} of {world}' if world > 1 else ''))
    net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    lead = rank == 0                  # the one process that logs and writes
    curves = CurveLog(curves_path(out), resume_step=step) if lead else None
    model.train()
    started = time.monotonic() - elapsed
    losses = []
    with tqdm(total=train_config.steps, initial=step, desc='training RK-Diffuser', unit='step',
              disable=not lead) as bar:
        while step < train_config.steps:
            batch, draws = step_batch(dataset, model, train_config, step, rank, world)
            loss, parts = net({k: v.to(device) for k, v in batch.items()}, draws)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            schedule.step()
            ema.update_parameters(model)
            step += 1
            losses.append(parts)
            bar.update(1)
            bar.set_postfix({k: f'{np.mean([p[k] for p in losses[-50:]]):.4f}' for k in parts})
            saving = step % train_config.save_every == 0 or step == train_config.steps
            if lead and (step % CURVE_EVERY == 0 or saving):
                scores = validation_losses(ema.module, validation, device) if saving and validation is not None else {}
                curves.add(step, lr=schedule.get_last_lr()[0],
                           **{k: float(np.mean([p[k] for p in losses[-CURVE_EVERY:]])) for k in parts}, **scores)
            if saving:
                digests = distributed.gather(distributed.weights_digest(model), world)
                if len(set(digests)) > 1:
                    raise RuntimeError(f'the {world} processes hold different weights at step {step}')
                elapsed = time.monotonic() - started
                if lead:
                    _save(out, resume_path, model, ema, optimizer, schedule, step, elapsed, model_config,
                          train_config, segs, data_dir, losses[-50:], init_info, digests)
    del net                           # before the process group: distributed.stop
    distributed.stop(world)
    return out


def _quiet(*_args, **_kwargs) -> None:
    pass


def _load_init(model, model_config: RKDConfig, init) -> dict:
    """Copy ``init``'s weights into ``model``; returns its provenance for the new checkpoint."""
    init_model, payload = checkpoint.load_model(init)
    if _plain(dataclasses.asdict(init_model.config)) != _plain(dataclasses.asdict(model_config)):
        raise ValueError(f'{init} has another model config; pass the same --config')
    model.load_state_dict(init_model.state_dict())
    training = payload.get('training') or {}
    return {'path': str(init), 'step': int(training.get('step', 0)),
            'wall_time_s': float(training.get('wall_time_s', 0.0)),
            'training_seeds': payload.get('training_seeds') or {}}


def _plain(value):
    """Config dicts compared after a save/load round trip (tuples come back as lists)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _save(out, resume_path, model, ema, optimizer, schedule, step, elapsed, model_config, train_config,
          segs, data_dir, recent, init_info, digests):
    ema_model = ema.module
    ema_model.config = model_config
    checkpoint.save(out, ema_model, {
        'training': {'step': step, 'steps': train_config.steps, 'wall_time_s': elapsed,
                     'train_config': dataclasses.asdict(train_config), 'data': str(data_dir),
                     'segments': len(segs), 'init': init_info, 'processes': len(digests),
                     'weights_sha256': digests[0],
                     'final_losses': {k: float(np.mean([r[k] for r in recent])) for k in recent[0]}},
        'training_seeds': union_of_seeds(segs.training_seeds(), (init_info or {}).get('training_seeds'))})
    state = {'step': step, 'elapsed_s': elapsed, 'raw_model': model.state_dict(), 'ema': ema.state_dict(),
             'optimizer': optimizer.state_dict(), 'schedule': schedule.state_dict(),
             'model_config': dataclasses.asdict(model_config),
             'train_config': dataclasses.asdict(train_config), 'init': init_info}
    checkpoint.save_resume(resume_path, state)
