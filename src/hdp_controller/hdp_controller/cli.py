"""`hdp train low-level`: train RK-Diffuser on recorded episodes."""

from __future__ import annotations

import argparse
import dataclasses
import json

import yaml


def configure_train(parser: argparse.ArgumentParser) -> None:
    parser.description = ('Train RK-Diffuser (pose + joint diffusers, distilled through differentiable '
                          'Panda kinematics) on the successful episodes in DATA. Resumes when OUT.resume exists.')
    parser.add_argument('--data', required=True, help='directory of rosbag2 episodes (hdp collect)')
    parser.add_argument('--out', required=True, help='checkpoint to write (OUT.resume holds the training state)')
    parser.add_argument('--config', help='YAML file with "model:" (RKDConfig) and/or "train:" (TrainConfig) keys')
    parser.add_argument('--steps', type=int, help='training steps (overrides the config)')
    parser.add_argument('--batch-size', type=int, help='batch size (overrides the config)')
    parser.add_argument('--seed', type=int, help='seed (overrides the config)')
    parser.add_argument('--device', default='cpu',
                        help='cpu (default), cuda, cuda:N, or auto: cuda when present; under torchrun with cuda, '
                             'each process takes the GPU of its local rank')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.add_argument('--init', help='start from the weights of this checkpoint (fine-tuning: fresh optimiser '
                        'and schedule; the model config must match)')
    parser.add_argument('--cache', help='preprocessing cache directory (default DATA/.cache)')
    parser.set_defaults(func=_train)


def _train(args) -> int:
    import torch

    from .distributed import torch_device
    from .train import TrainConfig, train
    values = {}
    if args.config:
        with open(args.config, encoding='utf-8') as f:
            values = yaml.safe_load(f) or {}
        if not isinstance(values, dict) or set(values) - {'model', 'train'}:
            raise SystemExit(f'{args.config}: expected a mapping with "model" and/or "train" keys')
    try:
        from .rk_diffuser import RKDConfig      # torch: only once a command runs
        model_config = RKDConfig.from_dict(values.get('model') or {})
        train_values = dict(values.get('train') or {})
        for key in ('steps', 'batch_size', 'seed'):
            if getattr(args, key) is not None:
                train_values[key] = getattr(args, key)
        train_config = TrainConfig(**train_values)
    except (TypeError, ValueError) as err:
        raise SystemExit(f'hdp train low-level: bad configuration: {err}') from None
    if train_config.steps < 1 or train_config.batch_size < 1:
        raise SystemExit('hdp train low-level: --steps and --batch-size must be >= 1')
    if args.threads:
        torch.set_num_threads(args.threads)
    print(json.dumps({'model': dataclasses.asdict(model_config), 'train': dataclasses.asdict(train_config)}))
    try:
        out = train(args.data, args.out, model_config, train_config, torch_device(args.device), args.cache,
                    init=args.init)
    except ValueError as err:
        raise SystemExit(f'hdp train low-level: {err}') from None
    print(f'wrote {out}')
    return 0
