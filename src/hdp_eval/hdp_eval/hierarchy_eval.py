"""The closed-loop hierarchy in the sim: the paper's Table 1 setting.

Per segment the agent re-observes (both cameras rendered, the arm state),
predicts a next-best pose and gripper action; the low-level method plans a
joint trajectory to it, which runs through the experts' execution path
(low_level_eval), then the gripper acts. The episode ends on the
task's success condition, a planning failure, or the segment budget.

Agents (Table 1 rows):  hdp = agent + RK-Diffuser, nbp_planner = agent +
planner (PerAct + Planner), nbp_joint = agent + joint diffusion (PerAct +
Diffuser). Every agent runs on the same seeds and instructions.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from tqdm import tqdm

from hdp_controller.controller_logic import reach_error
from hdp_controller.observation import CAMERA_SIZE, N_POINTS
from hdp_planner import language
from hdp_sim_bridge import experts
from hdp_sim_bridge.cameras import default_cameras
from hdp_sim_bridge.tasks import TASKS
from hdp_sim_bridge.world import PandaWorld

from .low_level_eval import check_seed_hygiene, execute_segment, world_scene
from .observation import front_points, segment_request

AGENTS = {'hdp': 'rkd', 'nbp_planner': 'planner', 'nbp_joint': 'joint'}
# seen: training phrasings; heldout: the one kept out of training; paraphrase: the paraphrase set
# (other verbs, word orders, object names); nonsense: made-up words (below). Each set is a row of
# the table, so `--phrasings seen,heldout,paraphrase` (or all) reports them side by side.
PHRASINGS = ('seen', 'heldout', 'paraphrase', 'nonsense')
TEMPLATES = {'heldout': language.heldout_phrasings, 'paraphrase': language.paraphrase_phrasings}
# Made-up words for 'nonsense' instructions: one word of the task's own instruction is kept, so
# the planner's vocabulary check lets them through and only the agent's confidence can refuse.
PSEUDO_WORDS = ('blick', 'zorf', 'quib', 'flom', 'trask', 'wunt', 'glimp', 'sprov', 'dax', 'vurl')
MAX_SEGMENTS = 8


@dataclasses.dataclass
class HierarchyRecord:
    agent: str
    task: str
    seed: int
    phrasing: str
    instruction: str
    success: bool = False
    ik_error: bool = False
    failure: str | None = None
    segments: int = 0
    confidences: list = dataclasses.field(default_factory=list)    # the agent's, per prediction
    reach_errors: list = dataclasses.field(default_factory=list)   # (m, deg) plan end to NBP, per plan
    predict_times: list = dataclasses.field(default_factory=list)
    plan_times: list = dataclasses.field(default_factory=list)


def episode_instruction(task_name: str, seed: int, variation: int, phrasing: str) -> str:
    """The instruction of one evaluation episode: a phrasing seen in training, a held-out one, a
    paraphrase, or 'nonsense': the seen one with every word but one content word made up."""
    if phrasing not in PHRASINGS:
        raise ValueError(f'unknown phrasing {phrasing!r}; phrasings: {", ".join(PHRASINGS)}')
    templates = TEMPLATES.get(phrasing, language.training_phrasings)(task_name)
    text = language.instruction(task_name, variation, templates, np.random.default_rng(seed))
    return nonsense(text, np.random.default_rng([seed, 1])) if phrasing == 'nonsense' else text


def nonsense(text: str, rng: np.random.Generator) -> str:
    """``text`` with one of its content words kept and every other word made up (PSEUDO_WORDS)."""
    from hdp_planner.planner_logic import FILLER_WORDS
    tokens = language.words(text)
    content = [i for i, w in enumerate(tokens) if w not in FILLER_WORDS]
    keep = int(rng.choice(content))
    return ' '.join(w if i == keep else str(rng.choice(PSEUDO_WORDS)) for i, w in enumerate(tokens))


def run_episode(name: str, agent, low_level, task_name: str, seed: int, phrasing: str = 'seen',
                max_segments: int = MAX_SEGMENTS, camera_size=CAMERA_SIZE, world: PandaWorld | None = None,
                min_confidence: float = 0.0, reach_tolerance: tuple[float, float] | None = None) -> HierarchyRecord:
    """One closed-loop episode, refusing what planner_node and controller_node refuse.

    min_confidence: a first prediction below it refuses the instruction (failure 'refused: low
    confidence'). reach_tolerance: (m, deg); a plan ending farther from its NBP is refused
    (failure 'refused: NBP not reachable'), as controller_node's reach_tolerance_m/deg do.
    Either way nothing moves.
    """
    if world is None:
        with PandaWorld() as own:
            return run_episode(name, agent, low_level, task_name, seed, phrasing, max_segments, camera_size, own,
                               min_confidence, reach_tolerance)
    task, _, variation = experts.reachable_scene(world, task_name, seed)
    record = HierarchyRecord(name, task_name, seed, phrasing, episode_instruction(task_name, seed, variation, phrasing))
    cameras = default_cameras(*camera_size)
    rng = np.random.default_rng(seed)
    for _ in range(max_segments):
        frames = {cam: camera.render(world.client) for cam, camera in cameras.items()}
        started = time.perf_counter()
        nbp = agent.predict(frames, {c: cam.intrinsics for c, cam in cameras.items()},
                            {c: cam.camera_to_world for c, cam in cameras.items()}, record.instruction,
                            (world.joint_positions(), world.gripper_commanded_open))
        record.predict_times.append(time.perf_counter() - started)
        record.confidences.append(round(float(nbp.confidence), 4))
        if record.segments == 0 and nbp.confidence < min_confidence:
            record.failure = 'refused: low confidence'
            return record
        request = segment_request(world, np.r_[nbp.xyz, nbp.quat], nbp.gripper_open,
                                  front_points(world, cameras['front'], N_POINTS, rng))
        started = time.perf_counter()
        plan = low_level.plan(request, world_scene(world, task))
        record.plan_times.append(time.perf_counter() - started)
        record.segments += 1
        if not plan.ok:
            record.failure, record.ik_error = plan.failure or 'no_plan', bool(plan.ik_error)
            return record
        record.reach_errors.append(tuple(round(e, 4) for e in reach_error(plan.joints[-1], request.goal_pose)))
        if reach_tolerance is not None and any(e > t for e, t in zip(record.reach_errors[-1], reach_tolerance)):
            record.failure = 'refused: NBP not reachable'
            return record
        execute_segment(world, task, plan.joints, request.gripper_open, nbp.gripper_open)
        if task.success(world):
            record.success = True
            return record
    record.failure = 'segment budget spent'
    return record


def evaluate(agent, low_levels: dict, tasks, episodes: int, seed_start: int, phrasings=('seen',),
             max_segments: int = MAX_SEGMENTS, progress: bool = True, min_confidence: float = 0.0,
             reach_tolerance: tuple[float, float] | None = None) -> dict:
    """Every (agent row, task, seed, phrasing) once; JSON-able results with per-task rates."""
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise ValueError(f'unknown task(s) {unknown}; tasks: {", ".join(TASKS)}')
    if episodes < 1 or seed_start < 0:
        raise ValueError(f'need episodes >= 1 and seed_start >= 0, got {episodes} and {seed_start}')
    seeds = range(seed_start, seed_start + episodes)
    check_seed_hygiene({'the next-best-pose agent': agent, **low_levels}, tasks, seeds)
    jobs = [(name, task, seed, phrasing) for name in low_levels for task in tasks for seed in seeds
            for phrasing in phrasings]
    records = []
    with PandaWorld() as world:
        for name, task, seed, phrasing in tqdm(jobs, desc='hierarchy episodes', unit='episode', disable=not progress):
            records.append(run_episode(name, agent, low_levels[name], task, seed, phrasing, max_segments,
                                       world=world, min_confidence=min_confidence, reach_tolerance=reach_tolerance))
    results = {'tasks': list(tasks), 'seeds': [seeds[0], seeds[-1]], 'phrasings': list(phrasings),
               'min_confidence': min_confidence, 'reach_tolerance': reach_tolerance, 'agents': {}}
    for name in low_levels:
        results['agents'][name] = {}
        for phrasing in phrasings:
            per_task = {}
            for task in tasks:
                mine = [r for r in records if r.agent == name and r.task == task and r.phrasing == phrasing]
                per_task[task] = {'success_rate': float(np.mean([r.success for r in mine])),
                                  'records': [dataclasses.asdict(r) for r in mine]}
            results['agents'][name][phrasing] = per_task
    times = [t for r in records for t in r.predict_times]
    results['agent_predict_ms_p50'] = round(1000 * float(np.median(times)), 1) if times else None
    return results


def markdown_table(results: dict) -> str:
    """Rows: agent (x phrasing set), columns: tasks + overall; cells success %."""
    tasks = results['tasks']
    lines = ['| agent | phrasings | ' + ' | '.join(tasks) + ' | overall |',
             '|---|---|' + '---|' * (len(tasks) + 1)]
    for name, per_phrasing in results['agents'].items():
        for phrasing, per_task in per_phrasing.items():
            rates = [per_task[t]['success_rate'] for t in tasks]
            lines.append(f'| {name} | {phrasing} | ' + ' | '.join(f'{100 * r:.0f}' for r in rates) +
                         f' | {100 * np.mean(rates):.1f} |')
    return '\n'.join(lines)
