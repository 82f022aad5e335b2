"""`hdp bench transport`: camera streams through rclpy on Fast DDS, its raw ceiling, and Cyclone."""

from __future__ import annotations

import argparse
import json
import os
import random
import sys

from ..transport_bench import MODES, TARGET_HZ, TARGET_P99_MS, receive


def configure(parser) -> None:
    """Two processes, two cameras x (rgb8 + 16UC1) as fast as possible: Hz, latency, throughput."""
    parser.add_argument('--seconds', type=float, default=10.0, help='measuring time per mode (default 10)')
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.add_argument('--modes', type=_modes, default=MODES, metavar='M[,M...]',
                        help=f"modes to run, in order (default {','.join(MODES)})")
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS domain for the run (default: ROS_DOMAIN_ID, else a random one in 150..229)')
    parser.add_argument('--json', action='store_true', help='print the figures as JSON')
    parser.set_defaults(func=run)


def _modes(text: str) -> tuple[str, ...]:
    modes = tuple(m.strip() for m in text.split(',') if m.strip())
    unknown = [m for m in modes if m not in MODES]
    if unknown or not modes:
        raise argparse.ArgumentTypeError(f"unknown mode(s) {', '.join(unknown) or '(none)'}; "
                                         f"choose from {', '.join(MODES)}")
    return modes


def _domain(args) -> int:
    if args.domain_id is not None:
        return args.domain_id
    if os.environ.get('ROS_DOMAIN_ID', '').strip():
        return int(os.environ['ROS_DOMAIN_ID'])
    return random.randint(150, 229)    # a domain of its own: other graphs on this host stay out


def run(args) -> int:
    domain = _domain(args)
    results = {}
    for mode in args.modes:
        print(f'bench transport: {mode}, {args.seconds:g} s on ROS domain {domain} ...', file=sys.stderr, flush=True)
        results[mode] = receive(mode, args.seconds, args.width, args.height, domain)
    ratio = None
    if {'rclpy', 'raw'} <= results.keys() and results['raw']['throughput_mb_s']:
        ratio = round(results['rclpy']['throughput_mb_s'] / results['raw']['throughput_mb_s'], 3)
    report = {'image': f'{args.width}x{args.height}', 'streams': 4, 'domain_id': domain,
              'results': results, 'throughput_ratio_rclpy_vs_raw': ratio}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_table(report, args.seconds)
    return 0


def _print_table(report: dict, seconds: float) -> None:
    print(f"transport: 4 streams of {report['image']} (2 x rgb8 + 2 x 16UC1), sensor-data QoS, "
          f"{seconds:g} s per mode\n")
    print('| mode | min Hz | Hz per stream | p50 ms | p99 ms | MB/s | targets |')
    print('|---|---|---|---|---|---|---|')
    for mode, r in report['results'].items():
        per_stream = ' / '.join(f"{s['hz']:.1f}" for s in r['streams'].values())
        missed = [target for target, met in r['targets'].items() if not met]
        print(f"| {mode} | {r['min_hz']:.1f} | {per_stream} | {r['latency_p50_ms']} | "
              f"{r['latency_p99_ms']} | {r['throughput_mb_s']} | "
              f"{'MISSED ' + ', '.join(missed) if missed else 'met'} |")
    print(f'\ntargets: min_hz >= {TARGET_HZ:g} on every stream, p99 <= {TARGET_P99_MS:g} ms')
    if report['throughput_ratio_rclpy_vs_raw'] is not None:
        print(f"throughput rclpy / raw: {report['throughput_ratio_rclpy_vs_raw']}")
