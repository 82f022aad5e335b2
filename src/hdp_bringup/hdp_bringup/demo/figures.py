"""The demo's figures over episodes: stage times (p50/p95), episode time, CPU per node."""

from __future__ import annotations

import numpy as np

from ..launch_cli import MANAGER, NODES
from .episode_log import STAGES

STAGE_LABELS = {'observe_predict_s': 'observe + predict (result -> NBP)',
                'controller_s': 'controller (NBP -> trajectory)',
                'execution_s': 'execution (trajectory -> result)',
                'first_trajectory_s': 'responsiveness (instruction -> first trajectory)',
                'episode_s': 'episode (instruction -> success)'}


def stats(values) -> dict:
    """{'n', 'p50', 'p95', 'mean', 'max'} of some seconds; None each when there are none."""
    values = np.asarray([v for v in values if v is not None], dtype=float)
    if not len(values):
        return {'n': 0, 'p50': None, 'p95': None, 'mean': None, 'max': None}
    return {'n': int(len(values)), 'p50': round(float(np.percentile(values, 50)), 3),
            'p95': round(float(np.percentile(values, 95)), 3), 'mean': round(float(values.mean()), 3),
            'max': round(float(values.max()), 3)}


def figures(episodes: list[dict]) -> dict:
    """The issue's figures over episodes as summary.json holds them: stage times over all their
    segments, episode time over the successful ones, CPU per node over all of them."""
    segments = [s for e in episodes for s in e['segments']]
    out = {stage: stats(s[stage] for s in segments) for stage in STAGES}
    out['first_trajectory_s'] = stats(e['segments'][0]['trajectory_s'] for e in episodes if e['segments'])
    out['episode_s'] = stats(e['success_s'] for e in episodes if e['success'])
    wall = sum(e['wall_s'] for e in episodes)
    cpu = {}
    for name in (*NODES, MANAGER):
        spent = [e['cpu'][name]['cpu_s'] for e in episodes if name in e['cpu']]
        if spent:
            cpu[name] = {'cpu_s': round(sum(spent), 3), 'cpu_percent': round(100.0 * sum(spent) / wall, 1)}
    out['cpu'] = cpu
    out['episodes'] = len(episodes)
    out['succeeded'] = sum(bool(e['success']) for e in episodes)
    return out


def format_figures(figs: dict) -> str:
    """The figures as the table `hdp demo` prints and the README quotes."""
    def cell(value):
        return '-' if value is None else f'{value:.2f}'
    lines = [f"{figs['succeeded']} of {figs['episodes']} episodes succeeded, "
             f"{figs['observe_predict_s']['n']} segments; wall-clock seconds",
             '', '| stage | n | p50 | p95 | mean | max |', '|---|---|---|---|---|---|']
    for key in (*STAGES, 'first_trajectory_s', 'episode_s'):
        s = figs[key]
        lines.append(f"| {STAGE_LABELS[key]} | {s['n']} | {cell(s['p50'])} | {cell(s['p95'])} | "
                     f"{cell(s['mean'])} | {cell(s['max'])} |")
    lines += ['', '| node | CPU s | mean CPU % (100 = one core) |', '|---|---|---|']
    lines += [f"| {name} | {c['cpu_s']:.1f} | {c['cpu_percent']:.0f} |" for name, c in figs['cpu'].items()]
    return '\n'.join(lines)


