"""The closed-loop hierarchy in the sim: the paper's Table 1 setting.

Each episode runs the graph's own logic in one process (closed_loop.InProcessGraph):
planner_node's PlannerLoop observes both rendered cameras and the arm, predicts a next-best
pose and gripper action; controller_node's SegmentController plans a joint trajectory to it,
which the simulated robot follows as sim_bridge_node does, then the gripper acts. The episode
ends with the planner's outcome for the instruction: success, a refusal, a failed segment or
the segment budget, by the nodes' rules and with their parameters (closed_loop.GraphSettings).

Agents (Table 1 rows):  hdp = agent + RK-Diffuser, nbp_planner = agent +
planner (PerAct + Planner), nbp_joint = agent + joint diffusion (PerAct +
Diffuser), nbp_joint_guided = agent + the joint diffuser with goal guidance (joint_guided).
Every agent runs on the same seeds and instructions.

The flat rows (FLAT_AGENTS: diffusion_policy, act; hdp_planner.flat) have no next-best poses:
every control period (0.1 s) the policy is shown both cameras, the arm's joints and gripper,
and the instruction, and answers with absolute joint targets and a gripper state; each target
is streamed to the arm over one period, linearly interpolated per physics step as a joint
trajectory controller interpolates a trajectory's points, the gripper commanded when it
changes. The episode ends on success or after FLAT_MAX_SECONDS of sim time. Cameras: by
default each policy sees them as its training episodes held them (FlatPolicy.cameras_as_trained):
'every' renders a frame every control step (episodes recorded with `hdp collect --camera-rate
10`); 'rest' renders one at the start and whenever the arm comes to rest after moving (the
collector's rule without a camera rate), the last one shown otherwise.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from tqdm import tqdm

from hdp_controller.low_level import start_episode
from hdp_controller.methods import LEARNED
from hdp_controller.observation import CAMERA_SIZE
from hdp_data import instructions
from hdp_learning import distributed
from hdp_planner import language
from hdp_sim_bridge import experts
from hdp_sim_bridge.bridge import SimBridge
from hdp_sim_bridge.cameras import CameraRig, default_cameras
from hdp_sim_bridge.sensor_model import SensorSettings
from hdp_sim_bridge.tasks import TASKS
from hdp_sim_bridge.world import TIME_STEP, PandaWorld

from .closed_loop import GraphSettings, InProcessGraph
from .low_level_eval import check_seed_hygiene, world_scene

AGENTS = {'hdp': 'rkd', 'nbp_planner': 'planner', 'nbp_joint': 'joint', 'nbp_joint_guided': 'joint_guided'}
# The flat rows: name -> the hdp_planner.flat policy (and its checkpoint models/flat_<name>.pt).
FLAT_AGENTS = {'diffusion_policy': 'diffusion_policy', 'act': 'act'}
# s of sim time per flat episode: 2.5 x the longest demonstration (open_oven, ~12 s); the
# hierarchical rows' budget is 8 segments, which their experts' 2-7 segments of 3-12 s fit.
FLAT_MAX_SECONDS = 30.0
FLAT_CAMERAS = ('rest', 'every')
# seen: training phrasings; heldout: the one kept out of training; paraphrase: the paraphrase set
# (other verbs, word orders, object names); nonsense: made-up words (below). Each set is a row of
# the table, so `--phrasings seen,heldout,paraphrase` (or all) reports them side by side.
PHRASINGS = (*instructions.EVALUATION_PHRASINGS, 'nonsense')
# Made-up words for 'nonsense' instructions: one word of the task's own instruction is kept, so
# the planner's vocabulary check lets them through and only the agent's confidence can refuse.
PSEUDO_WORDS = ('blick', 'zorf', 'quib', 'flom', 'trask', 'wunt', 'glimp', 'sprov', 'dax', 'vurl')


@dataclasses.dataclass
class HierarchyRecord:
    agent: str
    task: str
    seed: int
    phrasing: str
    instruction: str
    success: bool = False
    ik_error: bool = False
    outcome: str | None = None           # the planner's Outcome result (hierarchical rows)
    failure: str | None = None
    segments: int = 0
    confidences: list = dataclasses.field(default_factory=list)    # the agent's, per prediction
    reach_errors: list = dataclasses.field(default_factory=list)   # (m, deg) plan end to NBP, per plan
    predict_times: list = dataclasses.field(default_factory=list)
    plan_times: list = dataclasses.field(default_factory=list)       # s, all draws of a plan together
    plan_draws: list = dataclasses.field(default_factory=list)       # draws per plan (plan_attempts)
    sim_seconds: float = 0.0
    status: list = dataclasses.field(default_factory=list)           # the nodes' status lines, in order


@dataclasses.dataclass
class FlatRecord(HierarchyRecord):
    """A flat agent's episode: segments stays 0; control_steps periods ran, queries of the policy
    (predict_times per query), camera_frames rendered and shown, sim_seconds simulated,
    joint_travel_rad the arm's summed |joint change| per period."""
    control_steps: int = 0
    queries: int = 0
    camera_frames: int = 0
    joint_travel_rad: float = 0.0


def episode_instruction(task_name: str, seed: int, variation: int, phrasing: str) -> str:
    """The instruction of one evaluation episode: a phrasing seen in training, a held-out one, a
    paraphrase, or 'nonsense': the seen one with every word but one content word made up."""
    if phrasing not in PHRASINGS:
        raise ValueError(f'unknown phrasing {phrasing!r}; phrasings: {", ".join(PHRASINGS)}')
    text = instructions.evaluation_instruction(task_name, seed, variation, 'seen' if phrasing == 'nonsense' else phrasing)
    return nonsense(text, np.random.default_rng([seed, 1])) if phrasing == 'nonsense' else text


def nonsense(text: str, rng: np.random.Generator) -> str:
    """``text`` with one of its content words kept and every other word made up (PSEUDO_WORDS)."""
    from hdp_planner.planner_logic import FILLER_WORDS
    tokens = language.words(text)
    content = [i for i, w in enumerate(tokens) if w not in FILLER_WORDS]
    keep = int(rng.choice(content))
    return ' '.join(w if i == keep else str(rng.choice(PSEUDO_WORDS)) for i, w in enumerate(tokens))


def run_episode(name: str, agent, low_level, task_name: str, seed: int, phrasing: str = 'seen',
                settings: GraphSettings | None = None, camera_size=CAMERA_SIZE,
                world: PandaWorld | None = None) -> HierarchyRecord:
    """One closed-loop episode through planner_node's and controller_node's own logic
    (closed_loop.InProcessGraph): whatever they refuse, time out or end is what the record says.

    settings: the nodes' parameters (the graph's by default). The record's outcome and failure
    are the planner's Outcome result and reason (failure None on success)."""
    settings = settings or GraphSettings()
    if world is None:
        with PandaWorld() as own:
            return run_episode(name, agent, low_level, task_name, seed, phrasing, settings, camera_size, own)
    bridge = SimBridge(*camera_size, world=world, sensor=settings.sensor)
    episode = bridge.reset(task_name, seed)
    start_episode(low_level, seed)
    record = HierarchyRecord(name, task_name, seed, phrasing,
                             episode_instruction(task_name, seed, episode['variation'], phrasing))
    graph = InProcessGraph(bridge, agent, low_level, needs_points=low_level.name in LEARNED, settings=settings,
                           scene=lambda: world_scene(world, bridge.task))
    budget_s = settings.max_segments * (settings.result_timeout_s + settings.camera_timeout_s) + 60.0
    log = graph.run(record.instruction, max_sim_s=budget_s)
    record.outcome, record.success = log.outcome.result, log.outcome.result == 'succeeded'
    record.failure = None if record.success else log.outcome.reason
    record.segments = log.outcome.segments
    record.confidences = [round(p.confidence, 4) for p in log.predictions]
    record.predict_times = [p.seconds for p in log.predictions]
    record.plan_times = [plan.seconds for plan in log.plans]
    record.plan_draws = [plan.draws for plan in log.plans]
    record.reach_errors = [tuple(round(e, 4) for e in plan.reach_error) for plan in log.plans
                           if plan.reach_error is not None]
    record.ik_error = bool(log.failed_plan is not None and log.failed_plan.ik_error)
    record.sim_seconds = log.sim_seconds
    record.status = log.status
    return record


def execute_flat_step(world: PandaWorld, task, command: np.ndarray, target: np.ndarray, steps: int) -> np.ndarray:
    """One control period of a flat policy: the gripper commanded if ``target[7]`` (+1 open, -1
    closed) changes it, then the arm streamed from ``command`` (7,) to ``target[:7]`` over ``steps``
    physics steps, linearly (a joint trajectory controller between two points). Returns the new command."""
    goal_open = bool(target[7] > 0)
    if goal_open != world.gripper_commanded_open:
        world.command_gripper(goal_open)
    goal = np.asarray(target[:7], dtype=float)
    for j in range(steps):
        world.command_arm(command + (j + 1) / steps * (goal - command))
        world.step()
        task.on_step(world)
    return goal


def run_flat_episode(name: str, policy, task_name: str, seed: int, phrasing: str = 'seen',
                     max_seconds: float = FLAT_MAX_SECONDS, camera_size=CAMERA_SIZE, world: PandaWorld | None = None,
                     cameras_when: str = 'rest', sensor: SensorSettings = SensorSettings()) -> FlatRecord:
    """One closed-loop episode of a flat policy (hdp_planner.flat.FlatPolicy): the same scene and
    instruction as run_episode's; see the module docstring. sensor: the cameras' sensor model and
    calibration error (colour is all a flat policy sees; frames are shown as they are taken)."""
    from hdp_planner.flat.policy import FlatObservation
    if cameras_when not in FLAT_CAMERAS:
        raise ValueError(f'cameras_when must be one of {FLAT_CAMERAS}, got {cameras_when!r}')
    if world is None:
        with PandaWorld() as own:
            return run_flat_episode(name, policy, task_name, seed, phrasing, max_seconds, camera_size, own,
                                    cameras_when, sensor)
    task, _, variation = experts.reachable_scene(world, task_name, seed)
    record = FlatRecord(name, task_name, seed, phrasing, episode_instruction(task_name, seed, variation, phrasing))
    rig = CameraRig(default_cameras(*camera_size), sensor)
    rig.start_episode(seed)
    policy.reset(record.instruction, seed)
    period_steps = max(1, round(policy.control_period_s / TIME_STEP))
    start, command = world.sim_time, world.joint_positions()
    images, moved, queue = None, False, []
    while world.sim_time - start < max_seconds - 1e-9:
        q = world.joint_positions()
        still = world.arm_reference_settled and np.max(np.abs(world.joint_velocities())) < experts.SETTLE_VELOCITY
        moved = moved or not still
        if images is None or cameras_when == 'every' or (still and moved):
            images = {c: rig.render(world.client, c, round(world.sim_time / TIME_STEP))[0] for c in rig.cameras}
            record.camera_frames += 1
            moved = False
        observation = FlatObservation(images, q, world.gripper_commanded_open, world.gripper_width())
        if not queue:
            started = time.perf_counter()
            queue = list(policy.act(observation))
            record.predict_times.append(time.perf_counter() - started)
            record.queries += 1
        else:
            policy.observe(observation)
        command = execute_flat_step(world, task, command, queue.pop(0), period_steps)
        record.control_steps += 1
        record.joint_travel_rad += float(np.abs(world.joint_positions() - q).sum())
        if task.success(world):
            record.success = True
            break
    else:
        record.failure = 'time budget spent'
    record.sim_seconds = round(world.sim_time - start, 3)
    record.joint_travel_rad = round(record.joint_travel_rad, 4)
    return record


def evaluate(agent, low_levels: dict, tasks, episodes: int, seed_start: int, phrasings=('seen',),
             settings: GraphSettings | None = None, progress: bool = True, flat: dict | None = None,
             flat_max_seconds: float = FLAT_MAX_SECONDS, flat_cameras: str | None = None) -> dict:
    """Every (agent row, task, seed, phrasing) once; JSON-able results with per-task rates.

    settings: the nodes' parameters for the hierarchical rows (the graph's by default).
    flat: name -> FlatPolicy, rows run by run_flat_episode (``agent`` may be None when there are
    no hierarchical rows)."""
    flat, settings = flat or {}, settings or GraphSettings()
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise ValueError(f'unknown task(s) {unknown}; tasks: {", ".join(TASKS)}')
    if episodes < 1 or seed_start < 0:
        raise ValueError(f'need episodes >= 1 and seed_start >= 0, got {episodes} and {seed_start}')
    if set(flat) & set(low_levels) or not (flat or low_levels):
        raise ValueError('need at least one agent row, each either hierarchical or flat')
    if flat_cameras not in (None, *FLAT_CAMERAS) or flat_max_seconds <= 0:
        raise ValueError(f'flat_cameras must be one of {FLAT_CAMERAS} (None: as each policy was trained) '
                         'and flat_max_seconds > 0')
    cameras_when = {name: flat_cameras or policy.cameras_as_trained for name, policy in flat.items()}
    seeds = range(seed_start, seed_start + episodes)
    check_seed_hygiene({**({'the next-best-pose agent': agent} if low_levels else {}), **low_levels, **flat},
                       tasks, seeds)
    rows = [*low_levels, *flat]
    jobs = [(name, task, seed, phrasing) for name in rows for task in tasks for seed in seeds
            for phrasing in phrasings]
    start = time.monotonic()
    # Under torchrun each process takes every world-th episode; all gather every record.
    rank, world_size, _ = distributed.start()
    records = []
    with PandaWorld() as world:
        for name, task, seed, phrasing in tqdm(jobs[rank::world_size], desc='hierarchy episodes', unit='episode',
                                               disable=not progress or rank > 0):
            if name in flat:
                records.append(run_flat_episode(name, flat[name], task, seed, phrasing, flat_max_seconds,
                                                world=world, cameras_when=cameras_when[name], sensor=settings.sensor))
                continue
            records.append(run_episode(name, agent, low_levels[name], task, seed, phrasing, settings, world=world))
    if world_size > 1:
        order = {job: i for i, job in enumerate(jobs)}
        records = sorted((r for part in distributed.gather(records, world_size) for r in part),
                         key=lambda r: order[(r.agent, r.task, r.seed, r.phrasing)])
    results = {'tasks': list(tasks), 'seeds': [seeds[0], seeds[-1]], 'phrasings': list(phrasings),
               'graph': dataclasses.asdict(settings),
               # The instruction grounding's min_similarity; None: instructions given as they are.
               'grounding': getattr(getattr(agent, 'grounding', None), 'min_similarity', None),
               'processes': world_size,
               'agents': {}}
    if flat:
        results['flat'] = {'max_seconds': flat_max_seconds, 'cameras': cameras_when,
                           'control_period_s': {name: policy.control_period_s for name, policy in flat.items()},
                           # the inference choices each ran (FlatPolicy.with_execution can change them)
                           'execution': {name: policy.execution for name, policy in flat.items()}}
    for name in rows:
        results['agents'][name] = {}
        for phrasing in phrasings:
            per_task = {}
            for task in tasks:
                mine = [r for r in records if r.agent == name and r.task == task and r.phrasing == phrasing]
                per_task[task] = {'success_rate': float(np.mean([r.success for r in mine])),
                                  'records': [dataclasses.asdict(r) for r in mine]}
            results['agents'][name][phrasing] = per_task
    times = [t for r in records if r.agent not in flat for t in r.predict_times]
    results['agent_predict_ms_p50'] = round(1000 * float(np.median(times)), 1) if times else None
    for name in flat:
        times = [t for r in records if r.agent == name for t in r.predict_times]
        results['flat'].setdefault('predict_ms_p50', {})[name] = round(1000 * float(np.median(times)), 1) \
            if times else None
    results['wall_s'] = round(time.monotonic() - start, 1)
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
