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
    parser.add_argument('--steps', type=int, default=6000, help='optimiser steps (default 6000)')
    parser.add_argument('--batch', type=int, default=16, help='samples per step (default 16)')
    parser.add_argument('--lr', type=float, default=5e-4, help='peak learning rate (default 5e-4)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--val-data', type=Path, help='episodes for validation metrics (held-out seeds)')
    parser.add_argument('--val-every', type=int, default=1000, help='steps between validations (default 1000)')
    parser.add_argument('--cache', type=Path, help='decoded-sample cache (default: <data>_cache)')
    parser.add_argument('--init', type=Path, help='start from this checkpoint\'s weights (fine-tuning: fresh optimiser '
                        'and schedule; its training seeds are recorded too)')
    parser.add_argument('--language-encoder', choices=('words', 'minilm'), default='words',
                        help='words: learned over the task vocabulary (default); minilm: frozen pretrained '
                             'all-MiniLM-L6-v2 sentence encoder and a learned projection')
    parser.add_argument('--device', default='cpu', help='cpu or cuda (default cpu)')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.set_defaults(func=run_train)


def run_train(args) -> int:
    from hdp_msgs_py.episodes import EpisodeError

    from .checkpoint import CheckpointError
    from .sentence_encoder import SentenceEncoderUnavailable
    from .train import train
    if min(args.steps, args.batch, args.val_every) < 1 or args.lr <= 0:
        raise SystemExit('--steps, --batch and --val-every must be >= 1 and --lr > 0')
    _threads(args)
    try:
        train(args.data, args.out, args.steps, args.batch, args.lr, args.seed, args.val_data, args.device,
              args.cache, val_every=args.val_every, init=args.init, language_encoder=args.language_encoder)
    except (CheckpointError, EpisodeError, FileNotFoundError, SentenceEncoderUnavailable) as err:
        print(err, file=sys.stderr)
        return 1
    print(f'checkpoint: {args.out}')
    return 0


def configure_eval(parser) -> None:
    """Offline metrics of a next-best-pose checkpoint on recorded episodes (translation, rotation, gripper)."""
    parser.add_argument('--checkpoint', type=Path, required=True)
    parser.add_argument('--data', type=Path, required=True, help='directory of episode bags (held-out seeds)')
    parser.add_argument('--cache', type=Path, help='decoded-sample cache (default: <data>_cache)')
    parser.add_argument('--device', default='cpu', help='cpu or cuda (default cpu)')
    parser.add_argument('--threads', type=int, help='torch CPU threads (default: torch decides)')
    parser.add_argument('--json', type=Path, help='also write the metrics here')
    parser.set_defaults(func=run_eval)


def run_eval(args) -> int:
    from .checkpoint import CheckpointError, load_model
    from .dataset import KeyframeDataset
    from .evaluate import PHRASING_LABELS, format_metrics, offline_metrics
    _threads(args)
    try:
        model, checkpoint = load_model(args.checkpoint, args.device)
    except CheckpointError as err:
        print(err, file=sys.stderr)
        return 1
    try:
        dataset = KeyframeDataset.from_directory(args.data, args.cache)
    except FileNotFoundError as err:
        print(err, file=sys.stderr)
        return 1
    results = {}
    for phrasing, label in PHRASING_LABELS.items():
        results[label] = offline_metrics(model, dataset, phrasing)
        print(f'\n{args.checkpoint} (step {checkpoint["step"]}) on {args.data}, {label}:\n'
              f'{format_metrics(results[label])}')
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

    from hdp_msgs_py import instructions

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
