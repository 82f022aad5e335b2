"""`hdp train low-level`: train RK-Diffuser on recorded episodes."""

from __future__ import annotations

import argparse
import json


def configure_train(parser: argparse.ArgumentParser) -> None:
    parser.description = ('Train RK-Diffuser (pose + joint diffusers, distilled through differentiable '
                          'Panda kinematics) on the successful episodes in DATA. Resumes when OUT.resume exists.')
    parser.add_argument('--data', required=True, help='directory of rosbag2 episodes (hdp collect), or its '
                        'preprocessed segments file (DATA/.cache/rkd_segments_*.npz) to train where the episodes are not')
    parser.add_argument('--out', required=True, help='checkpoint to write (OUT.resume holds the training state)')
    parser.add_argument('--config', help='YAML file with "model:" (RKDConfig) and/or "train:" (TrainConfig) '
                        'sections (hdp_learning.config; unknown keys are refused)')
    parser.add_argument('--steps', type=int, help='training steps (overrides the config)')
    parser.add_argument('--batch-size', type=int, help='batch size (overrides the config)')
    parser.add_argument('--seed', type=int, help='seed (overrides the config)')
    parser.add_argument('--device', default='cpu',
                        help='cpu (default), cuda, cuda:N, or auto: cuda when present; under torchrun with cuda, '
                             'each process takes the GPU of its local rank')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.add_argument('--init', help='start from the weights of this checkpoint (fine-tuning: fresh optimiser '
                        'and schedule; the model config must match)')
    parser.add_argument('--val-data', help='validation episodes (or their segments file), never trained on: the EMA '
                        'model\'s losses on them go into the curves at every save (val_* columns)')
    parser.add_argument('--cache', help='preprocessing cache directory (default DATA/.cache)')
    parser.set_defaults(func=_train)


def _train(args) -> int:
    import torch

    from hdp_learning.config import ConfigError, as_dict, load_sections
    from hdp_learning.distributed import torch_device

    from .rk_diffuser import RKDConfig      # torch: only once a command runs
    from .train import TrainConfig, train
    try:
        configs = load_sections(args.config, {'model': RKDConfig, 'train': TrainConfig}, overrides={
            'train': {'steps': args.steps, 'batch_size': args.batch_size, 'seed': args.seed}})
    except ConfigError as err:
        raise SystemExit(f'hdp train low-level: bad configuration: {err}') from None
    model_config, train_config = configs['model'], configs['train']
    if train_config.steps < 1 or train_config.batch_size < 1:
        raise SystemExit('hdp train low-level: --steps and --batch-size must be >= 1')
    if args.threads:
        torch.set_num_threads(args.threads)
    print(json.dumps(as_dict(configs)))
    try:
        out = train(args.data, args.out, model_config, train_config, torch_device(args.device), args.cache,
                    init=args.init, val_data=args.val_data)
    except ValueError as err:
        raise SystemExit(f'hdp train low-level: {err}') from None
    print(f'wrote {out}')
    return 0
