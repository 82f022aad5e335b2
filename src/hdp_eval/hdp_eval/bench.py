"""`hdp bench controller`: NBP -> JointTrajectory latency of RK-Diffuser, full vs fast sampler.

Both samplers run the same oracle episodes (low_level_eval.evaluate, seeds of
the caller's choosing, never training seeds). The latency of a segment is
what controller_node spends between a next-best pose and a publishable
trajectory: sampling both diffusers, refinement, timing, message building and
the checks (hdp_controller.segment_planning.plan_segment, which the Table 2
harness plans through). Torch runs on --threads CPU threads.
"""

from __future__ import annotations

import json
import time

import numpy as np

def configure(parser) -> None:
    parser.description = ('Latency (p50/p95, NBP -> JointTrajectory) and success of RK-Diffuser with the '
                          '100-step DDPM sampler and the fast sampler (DDIM, unguided), on the same '
                          'evaluation seeds.')
    parser.add_argument('--checkpoint', help='RK-Diffuser checkpoint (default: the released one)')
    parser.add_argument('--tasks', default='all', help='comma-separated tasks, "all" (default) or "first_six"')
    parser.add_argument('--episodes', type=int, default=5, help='episodes per task (default 5)')
    parser.add_argument('--seed-start', type=int, default=3000, help='first evaluation seed (default 3000)')
    parser.add_argument('--fast-steps', type=int, help='DDIM steps (default: policy.FAST_STEPS)')
    parser.add_argument('--threads', type=int, default=2, help='torch CPU threads (default 2)')
    parser.add_argument('--device', default='cpu', help='where the diffusers sample: cpu (default), cuda, cuda:N, auto')
    parser.add_argument('--json', action='store_true', help='print the figures as JSON instead of a table')
    parser.set_defaults(func=run)


def run(args) -> int:
    import torch
    from hdp_controller.policy import FAST_STEPS, load_policy
    from hdp_data.instructions import task_names

    from .low_level_eval import evaluate
    try:
        tasks = task_names(args.tasks)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    if args.episodes < 1 or args.threads < 1:
        raise SystemExit('--episodes and --threads must be >= 1')
    torch.set_num_threads(args.threads)
    fast_steps = args.fast_steps or FAST_STEPS
    try:
        methods = {'rkd_ddpm_100': load_policy('rkd', args.checkpoint, 'ddpm', device=args.device),
                   f'rkd_ddim_{fast_steps}': load_policy('rkd', args.checkpoint, 'ddim', steps=fast_steps,
                                                         device=args.device)}
    except ValueError as err:
        raise SystemExit(f'hdp bench controller: {err}') from None
    started = time.monotonic()
    try:
        results = evaluate(methods, tasks, args.episodes, args.seed_start, workers=1)
    except ValueError as err:
        raise SystemExit(f'hdp bench controller: {err}') from None
    figures = {'threads': args.threads, 'device': args.device, 'tasks': tasks, 'seeds': results['seeds'], 'methods': {}}
    for name, per_task in results['methods'].items():
        latencies = [t for task in per_task.values() for r in task['records'] for t in r['plan_times']]
        figures['methods'][name] = {
            'latency_p50_ms': round(1000 * float(np.percentile(latencies, 50)), 1),
            'latency_p95_ms': round(1000 * float(np.percentile(latencies, 95)), 1),
            'segments': len(latencies),
            'success_rate': float(np.mean([r['success'] for task in per_task.values() for r in task['records']]))}
    full, fast = (figures['methods'][n] for n in methods)
    figures['success_lost_points'] = round(100 * (full['success_rate'] - fast['success_rate']), 1)
    figures['wall_s'] = round(time.monotonic() - started, 1)
    if args.json:
        print(json.dumps(figures, indent=1))
        return 0
    print('| sampler | p50 ms | p95 ms | segments | success |\n|---|---|---|---|---|')
    for name, row in figures['methods'].items():
        print(f"| {name} | {row['latency_p50_ms']} | {row['latency_p95_ms']} | {row['segments']} | "
              f"{100 * row['success_rate']:.0f}% |")
    print(f"\nsuccess lost by the fast sampler: {figures['success_lost_points']} points "
          f"(seeds {results['seeds'][0]}-{results['seeds'][1]}, {args.threads} threads, {figures['wall_s']} s)")
    return 0
