"""`hdp eval ladder`: the robustness ladder (issue 40), the same episodes under cameras ever
further from ideal, every rung in one run:

    ideal -> d415 (depth noise, holes and flying pixels, colour jitter; hdp_sim_bridge.sensor_model)
          -> + calibration error (each camera renders from a pose off from /tf_static's)
          -> + latency (frames delivered after their exposure stamp) at a D415's frame rate

On each rung: Table 1's rows (the hierarchy and the flat baselines, hierarchy_eval.evaluate)
and Table 2's (low-level methods on oracle NBPs, low_level_eval.evaluate, whose front camera
gets the same sensor model and calibration error; latency means nothing there, as nothing
moves while it plans). Every rung runs the same tasks and seeds.
"""

from __future__ import annotations

import collections
import dataclasses
import re

import numpy as np

from hdp_sim_bridge.sensor_model import SensorSettings, profile_named

from . import hierarchy_eval, low_level_eval
from .closed_loop import GraphSettings


@dataclasses.dataclass(frozen=True)
class Rung:
    name: str
    sensor: SensorSettings
    camera_hz: float | None = None     # None: the graph's camera rate


RUNG_KEYS = ('ideal', 'd415', 'calibration', 'latency')


def rungs(extrinsic_mm: float = 5.0, extrinsic_deg: float = 1.0, latency_ms: float = 60.0,
          camera_hz: float = 15.0, only=RUNG_KEYS) -> list[Rung]:
    """The four rungs of issue 40, each adding one thing to the one before; ``only``: those of
    RUNG_KEYS to keep, in the ladder's order."""
    unknown = set(only) - set(RUNG_KEYS)
    if unknown:
        raise ValueError(f"unknown rung(s) {', '.join(sorted(unknown))}: choose from {', '.join(RUNG_KEYS)}")
    d415 = profile_named('d415')
    ladder = [Rung('ideal', SensorSettings()),
              Rung('d415', SensorSettings(d415)),
              Rung(f'+ {extrinsic_mm:g} mm / {extrinsic_deg:g} deg', SensorSettings(d415, extrinsic_mm, extrinsic_deg)),
              Rung(f'+ {latency_ms:g} ms at {camera_hz:g} Hz',
                   SensorSettings(d415, extrinsic_mm, extrinsic_deg, latency_ms), camera_hz)]
    return [rung for key, rung in zip(RUNG_KEYS, ladder) if key in only]


def evaluate(agent, low_levels: dict, table2: dict, tasks, episodes: int, seed_start: int, ladder: list[Rung],
             settings: GraphSettings = GraphSettings(), flat: dict | None = None, progress: bool = True) -> dict:
    """Every rung of ``ladder`` in turn; JSON-able results: per rung its sensor and each table's
    results as hierarchy_eval.evaluate and low_level_eval.evaluate give them (None without rows).

    low_levels / flat: Table 1's hierarchical and flat rows (hierarchy_eval.evaluate); table2:
    name -> LowLevelPolicy for Table 2; settings: the nodes' parameters, whose sensor and camera
    rate each rung replaces."""
    if not ladder:
        raise ValueError('the ladder needs at least one rung')
    out = {'tasks': list(tasks), 'seeds': [seed_start, seed_start + episodes - 1], 'rungs': []}
    for rung in ladder:
        rung_settings = dataclasses.replace(settings, sensor=rung.sensor, **(
            {'camera_hz': rung.camera_hz} if rung.camera_hz is not None else {}))
        table1 = (hierarchy_eval.evaluate(agent, low_levels, tasks, episodes, seed_start, ('seen',), rung_settings,
                                          progress, flat) if low_levels or flat else None)
        low = (low_level_eval.evaluate(table2, tasks, episodes, seed_start, progress=progress, sensor=rung.sensor,
                                       depth_filter=settings.depth_filter) if table2 else None)
        out['rungs'].append({'name': rung.name, 'sensor': dataclasses.asdict(rung.sensor),
                             'camera_hz': rung_settings.camera_hz, 'table1': table1, 'table2': low})
    return out


def overall(results: dict) -> dict[str, list[float]]:
    """Row name -> its success % on each rung (the mean over tasks), Table 2's rows named 'X (Table 2)'."""
    tasks, rows = results['tasks'], {}
    for rung in results['rungs']:
        if rung['table1']:
            for name, per_phrasing in rung['table1']['agents'].items():
                rates = [per_phrasing['seen'][t]['success_rate'] for t in tasks]
                rows.setdefault(name, []).append(100 * float(np.mean(rates)))
        if rung['table2']:
            for name, per_task in rung['table2']['methods'].items():
                rated = [per_task[t]['success_rate'] for t in tasks if per_task[t]['episodes']]
                rows.setdefault(f'{name} (Table 2)', []).append(100 * float(np.mean(rated)) if rated else float('nan'))
    return rows


def _records(rung: dict) -> dict[str, dict[tuple, dict]]:
    """Row name -> (task, seed) -> its episode record on ``rung`` (Table 2's rows named as in overall)."""
    rows = {}
    for name, per_phrasing in ((rung['table1'] or {}).get('agents') or {}).items():
        rows[name] = {(r['task'], r['seed']): r for per_task in per_phrasing['seen'].values()
                      for r in per_task['records']}
    for name, per_task in ((rung['table2'] or {}).get('methods') or {}).items():
        rows[f'{name} (Table 2)'] = {(r['task'], r['seed']): r for t in per_task.values() for r in t['records']}
    return rows


def reason_kind(failure: str | None) -> str:
    """A failure reason without its particulars (numbers, names in quotes or brackets), so that
    the same cause on other episodes counts as one."""
    text = re.sub(r'\(.*?\)|\[.*?\]|\'.*?\'|"[^"]*"', '', failure or 'none given')
    text = re.sub(r'-?\d+(\.\d+)?', 'N', text)
    return ' '.join(text.split())[:80]


def losses(results: dict) -> list[dict]:
    """Where each rung after the first loses the episodes the first rung's row won: per rung and
    row, the lost and the gained episodes, and the lost ones counted by task, by the segments
    the hierarchy had run when they ended (the keyframes it got through) and by reason."""
    first = _records(results['rungs'][0])
    out = []
    for rung in results['rungs'][1:]:
        for name, episodes in _records(rung).items():
            base = first.get(name, {})
            lost = [r for key, r in episodes.items() if key in base and base[key]['success'] and not r['success']]
            gained = [r for key, r in episodes.items() if key in base and not base[key]['success'] and r['success']]
            out.append({'rung': rung['name'], 'row': name, 'lost': len(lost), 'gained': len(gained),
                        'episodes': [(r['task'], r['seed']) for r in lost],
                        'by_task': dict(collections.Counter(r['task'] for r in lost).most_common()),
                        # Table 2 follows the oracle's keyframes, so only Table 1's records count segments.
                        'by_segments_run': dict(sorted(collections.Counter(
                            r['segments'] for r in lost if 'segments' in r).items())),
                        'by_reason': dict(collections.Counter(reason_kind(r['failure']) for r in lost).most_common())})
    return out


def least_confident_success(results: dict) -> dict[str, float]:
    """Table 1's row -> the lowest first-NBP confidence among its successes on any rung: a
    planner_node min_confidence above it would have refused a success (choose it on validation
    seeds, with --min-confidence 0, as planner_node's README says)."""
    lowest = {}
    for rung in results['rungs']:
        for name, per_phrasing in ((rung['table1'] or {}).get('agents') or {}).items():
            firsts = [r['confidences'][0] for per_task in per_phrasing['seen'].values()
                      for r in per_task['records'] if r['success'] and r['confidences']]
            if firsts:
                lowest[name] = min(lowest.get(name, 1.0), *firsts)
    return lowest


def _counts(counter: dict) -> str:
    return ', '.join(f'{key} {n}' for key, n in counter.items())


def losses_markdown(results: dict) -> str:
    """losses() as one bullet per rung and row that lost or gained anything."""
    lines = []
    for loss in losses(results):
        if not (loss['lost'] or loss['gained']):
            continue
        line = (f"- **{loss['row']}, {loss['rung']}**: lost {loss['lost']} of the first rung's successes, "
                f"gained {loss['gained']}.")
        if loss['lost']:
            line += f" By task: {_counts(loss['by_task'])}."
            if loss['by_segments_run']:
                line += f" By segments run before the end: {_counts(loss['by_segments_run'])}."
            line += ' Reasons: ' + '; '.join(f'{v} x "{k}"' for k, v in loss['by_reason'].items()) + '.'
        lines.append(line)
    return '\n'.join(lines)


def markdown_table(results: dict) -> str:
    """Rows: Table 1's agents and Table 2's methods; columns: the rungs, then the last rung's gap
    to ideal (points); cells success %. Then each rung's per-task table."""
    names = [rung['name'] for rung in results['rungs']]
    lines = ['| row | ' + ' | '.join(names) + ' | last - first |', '|---|' + '---|' * (len(names) + 1)]
    for row, values in overall(results).items():
        lines.append(f'| {row} | ' + ' | '.join(f'{v:.1f}' for v in values) + f' | {values[-1] - values[0]:+.1f} |')
    for rung in results['rungs']:
        lines += ['', f"**{rung['name']}** (cameras at {rung['camera_hz']:g} Hz)", '']
        if rung['table1']:
            lines.append(hierarchy_eval.markdown_table(rung['table1']))
        if rung['table2']:
            lines += ['', low_level_eval.markdown_table(rung['table2'])]
    lowest = least_confident_success(results)
    if lowest:
        lines += ['', 'Least confident first NBP of a success (a min_confidence above it refuses a success): ' +
                  ', '.join(f'{name} {value:.3f}' for name, value in lowest.items())]
    where = losses_markdown(results)
    if where:
        lines += ['', f"**Where the rungs lose episodes** (against {results['rungs'][0]['name']}, same seeds)", '',
                  where]
    return '\n'.join(lines)
