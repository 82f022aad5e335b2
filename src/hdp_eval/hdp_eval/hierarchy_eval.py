"""The closed-loop hierarchy in the sim: the paper's Table 1 setting.

Per segment the agent re-observes (both cameras rendered, the arm state),
predicts a next-best pose and gripper action; the low-level method plans a
joint trajectory to it, which runs through the experts' execution path
(low_level_eval), then the gripper acts. The episode ends on the
task's success condition, a planning failure, or the segment budget.

Agents (Table 1 rows):  hdp = agent + RK-Diffuser, nbp_planner = agent +
planner (PerAct + Planner), nbp_joint = agent + joint diffusion (PerAct +
Diffuser). Every agent runs on the same seeds and instructions.

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

from hdp_controller.controller_logic import plan_within_reach, reach_error
from hdp_controller.low_level import start_episode
from hdp_controller.observation import CAMERA_SIZE, N_POINTS
from hdp_msgs_py import distributed, instructions
from hdp_planner import language
from hdp_sim_bridge import experts
from hdp_sim_bridge.cameras import default_cameras
from hdp_sim_bridge.tasks import TASKS
from hdp_sim_bridge.world import TIME_STEP, PandaWorld

from .low_level_eval import check_seed_hygiene, execute_segment, world_scene
from .observation import front_points, segment_request

AGENTS = {'hdp': 'rkd', 'nbp_planner': 'planner', 'nbp_joint': 'joint'}
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
    plan_times: list = dataclasses.field(default_factory=list)       # s, all draws of a plan together
    plan_draws: list = dataclasses.field(default_factory=list)       # draws per plan (plan_attempts)


@dataclasses.dataclass
class FlatRecord(HierarchyRecord):
    """A flat agent's episode: segments stays 0; control_steps periods ran, queries of the policy
    (predict_times per query), camera_frames rendered and shown, sim_seconds simulated,
    joint_travel_rad the arm's summed |joint change| per period."""
    control_steps: int = 0
    queries: int = 0
    camera_frames: int = 0
    sim_seconds: float = 0.0
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


def think(world, task, seconds: float) -> None:
    """Let the world run ``seconds`` with the arm holding its last command, as it runs in the graph
    while the agent and the low level think: what they saw is that much older when the arm moves."""
    for _ in range(round(seconds / TIME_STEP)):
        world.step()
        task.on_step(world)


def run_episode(name: str, agent, low_level, task_name: str, seed: int, phrasing: str = 'seen',
                max_segments: int = MAX_SEGMENTS, camera_size=CAMERA_SIZE, world: PandaWorld | None = None,
                min_confidence: float = 0.0, reach_tolerance: tuple[float, float] | None = None,
                think_s: float = 0.0, plan_attempts: int = 1) -> HierarchyRecord:
    """One closed-loop episode, refusing what planner_node and controller_node refuse.

    min_confidence: a first prediction below it refuses the instruction (failure 'refused: low
    confidence'). reach_tolerance: (m, deg); a plan ending farther from its NBP after
    ``plan_attempts`` draws is refused (failure 'refused: NBP not reachable'), as controller_node's
    reach_tolerance_m/deg and plan_attempts do (controller_logic.plan_within_reach).
    Either way nothing moves. think_s: sim seconds between each observation and its segment's
    motion (think); 0 freezes the world meanwhile.
    """
    if world is None:
        with PandaWorld() as own:
            return run_episode(name, agent, low_level, task_name, seed, phrasing, max_segments, camera_size, own,
                               min_confidence, reach_tolerance, think_s, plan_attempts)
    task, _, variation = experts.reachable_scene(world, task_name, seed)
    start_episode(low_level, seed)
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
        plan, draws = plan_within_reach(low_level, request, reach_tolerance, plan_attempts, world_scene(world, task))
        record.plan_times.append(time.perf_counter() - started)
        record.plan_draws.append(draws)
        record.segments += 1
        if not plan.ok:
            record.failure, record.ik_error = plan.failure or 'no_plan', bool(plan.ik_error)
            return record
        record.reach_errors.append(tuple(round(e, 4) for e in reach_error(plan.joints[-1], request.goal_pose)))
        if reach_tolerance is not None and any(e > t for e, t in zip(record.reach_errors[-1], reach_tolerance)):
            record.failure = 'refused: NBP not reachable'
            return record
        think(world, task, think_s)
        execute_segment(world, task, plan.joints, request.gripper_open, nbp.gripper_open)
        if task.success(world):
            record.success = True
            return record
    record.failure = 'segment budget spent'
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
                     cameras_when: str = 'rest') -> FlatRecord:
    """One closed-loop episode of a flat policy (hdp_planner.flat.FlatPolicy): the same scene and
    instruction as run_episode's; see the module docstring."""
    from hdp_planner.flat.policy import FlatObservation
    if cameras_when not in FLAT_CAMERAS:
        raise ValueError(f'cameras_when must be one of {FLAT_CAMERAS}, got {cameras_when!r}')
    if world is None:
        with PandaWorld() as own:
            return run_flat_episode(name, policy, task_name, seed, phrasing, max_seconds, camera_size, own,
                                    cameras_when)
    task, _, variation = experts.reachable_scene(world, task_name, seed)
    record = FlatRecord(name, task_name, seed, phrasing, episode_instruction(task_name, seed, variation, phrasing))
    cameras = default_cameras(*camera_size)
    policy.reset(record.instruction, seed)
    period_steps = max(1, round(policy.control_period_s / TIME_STEP))
    start, command = world.sim_time, world.joint_positions()
    images, moved, queue = None, False, []
    while world.sim_time - start < max_seconds - 1e-9:
        q = world.joint_positions()
        still = world.arm_reference_settled and np.max(np.abs(world.joint_velocities())) < experts.SETTLE_VELOCITY
        moved = moved or not still
        if images is None or cameras_when == 'every' or (still and moved):
            images = {c: camera.render(world.client)[0] for c, camera in cameras.items()}
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
             max_segments: int = MAX_SEGMENTS, progress: bool = True, min_confidence: float = 0.0,
             reach_tolerance: tuple[float, float] | None = None, flat: dict | None = None,
             flat_max_seconds: float = FLAT_MAX_SECONDS, flat_cameras: str | None = None,
             think_s: float = 0.0, plan_attempts: int = 1) -> dict:
    """Every (agent row, task, seed, phrasing) once; JSON-able results with per-task rates.

    flat: name -> FlatPolicy, rows run by run_flat_episode (``agent`` may be None when there are
    no hierarchical rows)."""
    flat = flat or {}
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
                                                world=world, cameras_when=cameras_when[name]))
                continue
            records.append(run_episode(name, agent, low_levels[name], task, seed, phrasing, max_segments,
                                       world=world, min_confidence=min_confidence, reach_tolerance=reach_tolerance,
                                       think_s=think_s, plan_attempts=plan_attempts))
    if world_size > 1:
        order = {job: i for i, job in enumerate(jobs)}
        records = sorted((r for part in distributed.gather(records, world_size) for r in part),
                         key=lambda r: order[(r.agent, r.task, r.seed, r.phrasing)])
    results = {'tasks': list(tasks), 'seeds': [seeds[0], seeds[-1]], 'phrasings': list(phrasings),
               'min_confidence': min_confidence, 'reach_tolerance': reach_tolerance, 'plan_attempts': plan_attempts,
               'think_s': think_s,
               # The instruction grounding's min_similarity; None: instructions given as they are.
               'grounding': getattr(getattr(agent, 'grounding', None), 'min_similarity', None),
               'processes': world_size,
               'agents': {}}
    if flat:
        results['flat'] = {'max_seconds': flat_max_seconds, 'cameras': cameras_when,
                           'control_period_s': {name: policy.control_period_s for name, policy in flat.items()}}
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
