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

import dataclasses

import numpy as np

from hdp_sim_bridge.sensor_model import SensorSettings, profile_named

from . import hierarchy_eval, low_level_eval
from .closed_loop import GraphSettings


@dataclasses.dataclass(frozen=True)
class Rung:
    name: str
    sensor: SensorSettings
    camera_hz: float | None = None     # None: the graph's camera rate


def rungs(extrinsic_mm: float = 5.0, extrinsic_deg: float = 1.0, latency_ms: float = 60.0,
          camera_hz: float = 15.0) -> list[Rung]:
    """The four rungs of issue 40, each adding one thing to the one before."""
    d415 = profile_named('d415')
    return [Rung('ideal', SensorSettings()),
            Rung('d415', SensorSettings(d415)),
            Rung(f'+ {extrinsic_mm:g} mm / {extrinsic_deg:g} deg', SensorSettings(d415, extrinsic_mm, extrinsic_deg)),
            Rung(f'+ {latency_ms:g} ms at {camera_hz:g} Hz', SensorSettings(d415, extrinsic_mm, extrinsic_deg, latency_ms),
                 camera_hz)]


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
    return '\n'.join(lines)
