"""`hdp bench transport`: camera streams through our runtime vs raw Cyclone DDS."""

from __future__ import annotations

import json
import random

from ..transport_bench import receive


def configure(parser) -> None:
    """Two processes, two cameras x (rgb8 + 16UC1) as fast as possible: Hz, latency, throughput."""
    parser.add_argument('--seconds', type=float, default=10.0, help='measuring time per mode (default 10)')
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.add_argument('--idl-seconds', type=float, default=3.0,
                        help="time for the cyclonedds-python IdlStruct reference (0 skips it)")
    parser.add_argument('--domain-id', type=int, default=None,
                        help='DDS domain for the run (default: a random one in 150..229)')
    parser.add_argument('--json', action='store_true', help='print the figures as JSON')
    parser.set_defaults(func=run)


def run(args) -> int:
    domain = args.domain_id if args.domain_id is not None else random.randint(150, 229)
    results = {}
    for mode, seconds in (('raw', args.seconds), ('ours', args.seconds), ('idl', args.idl_seconds)):
        if seconds > 0:
            results[mode] = receive(mode, seconds, args.width, args.height, domain)
    ours, raw = results['ours'], results['raw']
    report = {
        'image': f'{args.width}x{args.height}', 'streams': 4, 'results': results,
        'throughput_ratio_vs_raw': round(ours['throughput_mb_s'] / raw['throughput_mb_s'], 3)
        if raw['throughput_mb_s'] else None,
        'targets': {'min_hz >= 30': ours['min_hz'] >= 30,
                    'p99 <= 30 ms': ours['latency_p99_ms'] is not None and ours['latency_p99_ms'] <= 30,
                    'throughput >= 0.8 x raw': bool(raw['throughput_mb_s'])
                    and ours['throughput_mb_s'] >= 0.8 * raw['throughput_mb_s']},
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"transport: 4 streams of {report['image']} (2 x rgb8 + 2 x 16UC1), sensor-data QoS, "
          f"{args.seconds:g} s per mode\n")
    print('| mode | min Hz | Hz per stream | p50 ms | p99 ms | MB/s |')
    print('|---|---|---|---|---|---|')
    for mode, r in results.items():
        per_stream = ' / '.join(f"{s['hz']:.1f}" for s in r['streams'].values())
        print(f"| {mode} | {r['min_hz']:.1f} | {per_stream} | {r['latency_p50_ms']} | "
              f"{r['latency_p99_ms']} | {r['throughput_mb_s']} |")
    print(f"\nthroughput ours / raw: {report['throughput_ratio_vs_raw']}")
    for target, met in report['targets'].items():
        print(f"  {'met' if met else 'MISSED'}: {target}")
    return 0
