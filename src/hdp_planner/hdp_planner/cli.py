"""`hdp train high-level`, `hdp eval high-level-offline` and `hdp bench language`: the high-level agent's commands."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _threads(args) -> None:
    import torch
    if args.threads:
        torch.set_num_threads(args.threads)


def configure_train(parser) -> None:
    """Train the next-best-pose agent on recorded episodes; continues --out if it exists with the same options."""
    parser.add_argument('--data', type=Path, required=True, help='directory of episode bags')
    parser.add_argument('--out', type=Path, required=True, help='checkpoint to write (and continue)')
    parser.add_argument('--config', type=Path,
                        help='YAML file with "model:" (ModelConfig) and/or "train:" (TrainConfig) sections '
                             '(hdp_learning.config; unknown keys are refused), e.g. the released agent\'s '
                             'src/hdp_planner/config/hdp_nbp_agent.yaml; the flags below override it')
    parser.add_argument('--steps', type=int, help='optimiser steps (default 6000)')
    parser.add_argument('--batch', type=int, help='samples per step, over all processes (default 16)')
    parser.add_argument('--lr', type=float, help='peak learning rate (default 5e-4)')
    parser.add_argument('--seed', type=int, help='seed (default 0)')
    parser.add_argument('--val-data', type=Path, help='episodes for validation metrics (held-out seeds)')
    parser.add_argument('--val-every', type=int, help='steps between validations (default 1000)')
    parser.add_argument('--cache', type=Path, help='decoded-sample cache (default: <data>_cache)')
    parser.add_argument('--init', type=Path, help='start from this checkpoint\'s weights (fine-tuning: fresh optimiser '
                        'and schedule; its training seeds are recorded too)')
    parser.add_argument('--language-encoder', choices=('words', 'minilm'),
                        help='words: learned over the task vocabulary (default); minilm: frozen pretrained '
                             'all-MiniLM-L6-v2 sentence encoder and a learned projection')
    parser.add_argument('--device', default='cpu',
                        help='cpu (default), cuda, cuda:N, or auto: cuda when present; under torchrun with cuda, '
                             'each process takes the GPU of its local rank')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.set_defaults(func=run_train)


def resolve_train_config(args) -> dict:
    """{'model': ModelConfig, 'train': TrainConfig} of a `hdp train high-level` command: the
    dataclasses' defaults (the vocabulary: the task phrasings'), then --config, then the flags;
    SystemExit with one line for a configuration refused."""
    from hdp_learning.config import ConfigError, load_sections

    from .language import task_vocabulary
    from .model import ModelConfig
    from .train import TrainConfig
    try:
        configs = load_sections(
            args.config, {'model': ModelConfig, 'train': TrainConfig},
            defaults={'model': {'vocabulary': tuple(task_vocabulary())}},
            overrides={'model': {'language_encoder': args.language_encoder},
                       'train': {'steps': args.steps, 'batch': args.batch, 'lr': args.lr, 'seed': args.seed,
                                 'val_every': args.val_every}})
    except ConfigError as err:
        raise SystemExit(f'hdp train high-level: bad configuration: {err}') from None
    train = configs['train']
    if min(train.steps, train.batch, train.val_every, train.save_every) < 1 or train.lr <= 0:
        raise SystemExit('hdp train high-level: steps, batch, val_every and save_every must be >= 1 and lr > 0')
    return configs


def run_train(args) -> int:
    import dataclasses
    import os

    from hdp_learning.config import as_dict
    from hdp_learning.distributed import torch_device, world_size
    from hdp_data.episodes import EpisodeError

    from .checkpoint import CheckpointError
    from .train import train
    configs = resolve_train_config(args)
    if configs['train'].batch % world_size():
        raise SystemExit(f'hdp train high-level: batch {configs["train"].batch} does not split over '
                         f'{world_size()} processes')
    _threads(args)
    if os.environ.get('RANK', '0') == '0':
        print(json.dumps(as_dict(configs)), flush=True)
    try:
        train(args.data, args.out, **dataclasses.asdict(configs['train']), val_data=args.val_data,
              device=torch_device(args.device), cache=args.cache, model_config=configs['model'], init=args.init)
    except (CheckpointError, EpisodeError, FileNotFoundError, ValueError) as err:
        # ValueError: a device torch does not have, the sentence encoder's package missing, ...
        print(f'hdp train high-level: {err}', file=sys.stderr)
        return 1
    if os.environ.get('RANK', '0') == '0':
        print(f'checkpoint: {args.out}')
    return 0


def configure_eval(parser) -> None:
    """Offline metrics of a next-best-pose checkpoint on recorded episodes (translation, rotation, gripper)."""
    parser.add_argument('--checkpoint', type=Path, required=True)
    parser.add_argument('--data', type=Path, required=True, help='directory of episode bags (held-out seeds)')
    parser.add_argument('--cache', type=Path, help='decoded-sample cache (default: <data>_cache)')
    parser.add_argument('--device', default='cpu', help='cpu or cuda (default cpu)')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.add_argument('--by-keyframe', action='store_true',
                        help="also a row per task and keyframe of its episodes (where a task's predictions go wrong)")
    parser.add_argument('--json', type=Path, help='also write the metrics here')
    parser.set_defaults(func=run_eval)


def run_eval(args) -> int:
    from .checkpoint import CheckpointError, load_model
    from .dataset import KeyframeDataset
    from .evaluate import PHRASING_LABELS, format_metrics, keyframe_metrics, sample_errors, task_metrics
    _threads(args)
    try:
        model, checkpoint = load_model(args.checkpoint, args.device)
    except CheckpointError as err:
        print(err, file=sys.stderr)
        return 1
    try:
        dataset = KeyframeDataset.from_directory(args.data, args.cache, proprio=model.config.proprio)
    except (FileNotFoundError, ValueError) as err:
        print(f'hdp eval high-level-offline: {err}', file=sys.stderr)
        return 1
    results = {}
    for phrasing, label in PHRASING_LABELS.items():
        errors = sample_errors(model, dataset, phrasing)
        results[label] = task_metrics(dataset, errors)
        print(f'\n{args.checkpoint} (step {checkpoint["step"]}) on {args.data}, {label}:\n'
              f'{format_metrics(results[label])}')
        if args.by_keyframe:
            results[f'{label}, by keyframe'] = keyframe_metrics(dataset, errors)
            print(f'\nby keyframe:\n{format_metrics(results[f"{label}, by keyframe"])}')
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


def configure_bench_language(parser) -> None:
    """Start-up and per-instruction cost of the agent's language encoders (words, minilm) on the CPU."""
    parser.add_argument('--threads', type=int, default=1, help='torch CPU threads (default 1)')
    parser.set_defaults(func=run_bench_language)


def run_bench_language(args) -> int:
    import statistics
    import time

    import torch

    from hdp_data import instructions

    from .language import paraphrase_phrasings, task_vocabulary
    from .model import LANGUAGE_ENCODERS, ModelConfig, NextBestPoseNet
    from .sentence_encoder import SentenceEncoderUnavailable
    _threads(args)
    # Strings no encoder has seen in this process: every task's paraphrases, first variation.
    texts = [t.format(*[instructions.TASKS[task].variations[0]] * t.count('{}'))
             for task in instructions.TASKS for t in paraphrase_phrasings(task)]

    def median_ms(encoder) -> float:
        times = []
        for text in texts:
            started = time.perf_counter()
            encoder([text])                      # one instruction, as the planner sends it
            times.append(time.perf_counter() - started)
        return 1000 * statistics.median(times)

    print(f'{len(texts)} instructions, one at a time, {torch.get_num_threads()} thread(s)')
    for name in LANGUAGE_ENCODERS:
        started = time.perf_counter()
        try:
            model = NextBestPoseNet(ModelConfig(vocabulary=tuple(task_vocabulary()), language_encoder=name)).eval()
        except SentenceEncoderUnavailable as err:
            print(f'{name}: {err}')
            return 1
        startup = time.perf_counter() - started
        with torch.no_grad():
            first, again = median_ms(model.language), median_ms(model.language)
        print(f'{name}: agent built in {startup:.2f} s; per instruction {first:.2f} ms the first time, '
              f'{again:.2f} ms repeated (medians)')
    return 0
