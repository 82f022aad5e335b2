"""`hdp train flat --policy diffusion_policy|act`: the flat baselines' training command."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from . import POLICIES


def configure_train(parser) -> None:
    """Train a flat baseline (Diffusion Policy or ACT) on recorded episodes; continues --out if it
    exists with the same options."""
    parser.add_argument('--policy', choices=POLICIES, required=True)
    parser.add_argument('--data', type=Path, required=True, help='directory of episode bags')
    parser.add_argument('--out', type=Path, required=True, help='checkpoint to write (and continue)')
    parser.add_argument('--config', type=Path,
                        help='YAML file with "model:" (the policy\'s config) and/or "train:" (FlatTrainConfig) '
                             'sections, e.g. src/hdp_planner/config/flat_<policy>.yaml; the flags below override it')
    parser.add_argument('--steps', type=int, help='optimiser steps (default 20000)')
    parser.add_argument('--batch', type=int, help='samples per step (default 32)')
    parser.add_argument('--lr', type=float, help='peak learning rate (default 1e-4)')
    parser.add_argument('--seed', type=int, help='seed (default 0)')
    parser.add_argument('--val-data', type=Path, help='episodes for validation metrics (held-out seeds)')
    parser.add_argument('--val-every', type=int, help='steps between validations (default 2000)')
    parser.add_argument('--language-encoder', choices=('minilm', 'words'),
                        help='minilm: the frozen pretrained sentence encoder (default); words: learned words')
    parser.add_argument('--cache', type=Path, help='decoded-sample cache (default: <data>_flat_cache)')
    parser.add_argument('--workers', type=int, default=1,
                        help='processes decoding the episodes the cache lacks (default 1)')
    parser.add_argument('--stop-after-minutes', type=float,
                        help='stop after this much training and save the weights without the optimiser moments '
                             '(a file the size of a released one); the same command continues it')
    parser.add_argument('--device', default='cpu', help='cpu (default), cuda, cuda:N or auto')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.set_defaults(func=run_train)


def resolve_config(args) -> dict:
    """{'model': the policy's config, 'train': FlatTrainConfig}: defaults, then --config, then the flags;
    SystemExit with one line for a configuration refused."""
    from hdp_learning.config import ConfigError, load_sections

    from .checkpoint import config_class
    from .train import FlatTrainConfig
    try:
        return load_sections(
            args.config, {'model': config_class(args.policy), 'train': FlatTrainConfig},
            overrides={'model': {'language_encoder': args.language_encoder},
                       'train': {'steps': args.steps, 'batch': args.batch, 'lr': args.lr, 'seed': args.seed,
                                 'val_every': args.val_every}})
    except ConfigError as err:
        raise SystemExit(f'hdp train flat: bad configuration: {err}') from None


def run_train(args) -> int:
    import torch

    from hdp_learning.checkpoints import CheckpointError
    from hdp_learning.config import as_dict
    from hdp_learning.distributed import torch_device
    from hdp_data.episodes import EpisodeError

    from .train import train
    configs = resolve_config(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(json.dumps({'policy': args.policy, **as_dict(configs)}), flush=True)
    try:
        train(args.policy, args.data, args.out, configs['model'], configs['train'], val_data=args.val_data,
              device=torch_device(args.device), cache=args.cache, workers=args.workers,
              stop_after_s=None if args.stop_after_minutes is None else 60 * args.stop_after_minutes)
    except (CheckpointError, EpisodeError, FileNotFoundError, ValueError) as err:
        print(f'hdp train flat: {err}', file=sys.stderr)
        return 1
    print(f'checkpoint: {args.out}')
    return 0
