"""Low-level evaluation in the paper's Table 2 setting: oracle next-best poses, one policy per run.

For each (task, seed) the scripted expert runs once on that seed's scene;
its keyframes, found by the same rule and at the same 120 Hz joint-state
rate as the training data, give the oracle next-best poses (NBPs). A method
then starts from the same scene and, for each NBP in turn, observes (front
camera points, arm state), plans a joint trajectory to the NBP through
controller_node's own planning (segment_planning.plan_segment: the same
request, timing and joint-limit checks; one draw and no reach tolerance, the
paper's setting), which runs through the experts' own execution path, and
applies the NBP's gripper action. An episode succeeds when the task's success condition holds after a
segment (RLBench ends an episode at success); a plan that fails ends it.
Seeds where the expert itself fails are skipped, not counted against a method.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import sys
import time

import numpy as np
from tqdm import tqdm

from hdp_controller.inputs import SegmentRefused
from hdp_controller.low_level import Scene, start_episode
from hdp_controller.observation import CAMERA_SIZE, N_POINTS
from hdp_controller.segment_planning import plan_segment
from hdp_motion import panda
from hdp_motion.rotations import quat_angle
from hdp_learning import distributed
from hdp_msgs_py import conversions
from hdp_data.depth_filters import DepthFilter, FilterSettings
from hdp_data.keyframes import discover_keyframes
from hdp_sim_bridge import experts
from hdp_sim_bridge.cameras import CameraRig
from hdp_sim_bridge.collect import JOINT_STATE_EVERY
from hdp_sim_bridge.sensor_model import SensorSettings
from hdp_sim_bridge.tasks import TASKS
from hdp_sim_bridge.world import PandaWorld

from .observation import front_camera, front_points, segment_request


@dataclasses.dataclass
class OracleEpisode:
    """One evaluation scene and its oracle NBPs: [(pose (7,) xyz + quat xyzw, gripper_open)]."""
    task: str
    seed: int
    variation: int
    instruction: str
    expert_success: bool
    expert_reason: str
    nbps: list


@dataclasses.dataclass
class EpisodeRecord:
    """How one method did on one oracle episode.

    failure: None on success, else the plan's failure ('ik_error', 'no_path', ...)
    or 'not_completed' (every segment ran, the success condition never held).
    plan_times: s per planned segment. joint_paths: per executed segment, the
    (K, 7) joint waypoints it ran (current joints first), as lists for JSON.
    grasps_lost: grasps the world broke by overload (a path fighting a hinge).
    reach_errors: per planned segment, (m, deg) from the plan's last waypoint to its NBP.
    plan_stats: per planned segment, the plan's scalar extras (rkd: draws, from_start, timings).
    """
    method: str
    task: str
    seed: int
    success: bool = False
    ik_error: bool = False
    failure: str | None = None
    grasps_lost: int = 0
    plan_times: list = dataclasses.field(default_factory=list)
    joint_paths: list = dataclasses.field(default_factory=list)
    reach_errors: list = dataclasses.field(default_factory=list)
    plan_stats: list = dataclasses.field(default_factory=list)


# --- oracle -------------------------------------------------------------------------

def _commanded_open(stamps: np.ndarray, commands: list) -> np.ndarray:
    """(T,) bool: the last gripper command at or before each frame's step (open before any),
    as hdp_data.episodes reads a bag's gripper commands."""
    gripper_open = np.ones(len(stamps), dtype=bool)       # the world resets with it open
    for step, is_open in commands:
        gripper_open[stamps >= step] = is_open
    return gripper_open


def oracle_episode(task_name: str, seed: int, world: PandaWorld | None = None) -> OracleEpisode:
    """Run the expert on ``seed``'s scene exactly as ``hdp collect`` does (without cameras)
    and turn its keyframes into oracle NBPs: the EE pose and commanded gripper state at
    each keyframe after frame 0. No NBPs when the expert fails."""
    if world is None:
        with PandaWorld() as own:
            return oracle_episode(task_name, seed, own)
    task, rng, variation = experts.reachable_scene(world, task_name, seed)
    instruction = task.instruction(rng)    # before the expert, as collect: it continues this rng
    frames, commands, steps = [], [], [0]

    def record_frame():
        frames.append((steps[0], world.joint_velocities(), np.concatenate(world.ee_pose())))

    def on_step():
        steps[0] += 1
        if steps[0] % JOINT_STATE_EVERY == 0:
            record_frame()

    def on_gripper(is_open):
        commands.append((steps[0], bool(is_open)))

    record_frame()
    result = experts.run_expert(world, task, rng, on_step, on_gripper=on_gripper)
    nbps = []
    if result.success:
        stamps, velocities, poses = (np.array(column) for column in zip(*frames))
        gripper_open = _commanded_open(stamps, commands)
        nbps = distinct_nbps([(poses[k], bool(gripper_open[k])) for k in discover_keyframes(velocities, gripper_open)])
    return OracleEpisode(task_name, seed, variation, instruction, result.success, result.reason, nbps)


def distinct_nbps(nbps: list, position_tol: float = 0.002, angle_tol: float = np.radians(2.0)) -> list:
    """Drop each NBP equal to the one before it (pose within the tolerances, same gripper
    action): pushing against a hinge the arm stops several times at one pose, the keyframe
    rule marks every stop, and such a segment asks for no motion at all."""
    kept = []
    for pose, is_open in nbps:
        if kept and kept[-1][1] == is_open and np.linalg.norm(pose[:3] - kept[-1][0][:3]) < position_tol and \
                quat_angle(pose[3:], kept[-1][0][3:]) < angle_tol:
            continue
        kept.append((pose, is_open))
    return kept


# --- one episode --------------------------------------------------------------------------

def world_scene(world: PandaWorld, task) -> Scene:
    """What a planner collision-checks against, as the experts' straight moves into contact:
    the table and every task body except the one held and those the task is about (the
    goal of a grasp touches them), with the held body carried along."""
    held = world.grasped_body()
    obstacles = (world.table,) + tuple(b for b in world.task_bodies
                                       if b != held and b not in task.touched)
    attached = None if held is None else (held, world.grasped_link())
    return Scene(client=world.client_id, robot=world.robot, obstacles=obstacles, attached=attached)


def _nothing(*_):
    pass


def execute_segment(world, task, joints, was_open: bool, goal_open: bool,
                    config: experts.ExpertConfig | None = None) -> np.ndarray:
    """Run joint waypoints (K, 7) as the experts do, then the gripper action if it changes;
    returns the executed path (K + 1, 7), starting from where the arm really is (a learned
    trajectory need not start exactly there)."""
    path = np.vstack([world.joint_positions(), joints])
    experts.follow(world, task, path, config or experts.ExpertConfig(), _nothing, _nothing, hold=0.0)
    if goal_open != was_open:
        experts.actuate(world, task, 'open' if goal_open else 'close', _nothing, _nothing)
    return path


def run_episode(policy, oracle: OracleEpisode, camera_size=CAMERA_SIZE, n_points: int = N_POINTS,
                world: PandaWorld | None = None, config: experts.ExpertConfig | None = None,
                name: str | None = None, sensor: SensorSettings = SensorSettings(),
                depth_filter: FilterSettings | None = None) -> EpisodeRecord:
    """Replay ``oracle``'s NBPs with ``policy`` on the same scene; see the module docstring.

    camera_size: (width, height) of the front camera, the training data's by default.
    config: execution settings (velocity scale), the experts' by default.
    name: the record's method (default policy.name), when one policy runs under several names.
    sensor: the front camera's sensor model and calibration error (its latency does not apply: the
    arm is at rest when each segment's frame is taken); ideal by default.
    depth_filter: the post-processing chain the front depth goes through (hdp_data.depth_filters),
    one per episode, its temporal history over the episode's frames; None: off.
    """
    if world is None:
        with PandaWorld() as own:
            return run_episode(policy, oracle, camera_size, n_points, own, config, name, sensor, depth_filter)
    config = config or experts.ExpertConfig()
    task, _, _ = experts.reachable_scene(world, oracle.task, oracle.seed)
    start_episode(policy, oracle.seed)
    camera = front_camera(*camera_size)
    rig = CameraRig({camera.name: camera}, sensor)
    rig.start_episode(oracle.seed)                # the same frames for every method
    rng = np.random.default_rng(oracle.seed)      # point subsampling: the same for every method
    camera_filter = None if depth_filter is None else DepthFilter(depth_filter)
    record = EpisodeRecord(name or policy.name, oracle.task, oracle.seed)
    for segment, (goal_pose, goal_open) in enumerate(oracle.nbps):
        points = front_points(world, camera, n_points, rng, rig, frame=segment, depth_filter=camera_filter)
        request = segment_request(world, goal_pose, goal_open, points)
        try:
            trajectory, report = plan_segment(policy, request, panda.ARM_JOINTS, config.velocity_scale,
                                              scene=world_scene(world, task))
        except SegmentRefused as err:
            if err.report is not None:
                record.plan_times.append(err.report.seconds)
            record.failure = err.report.failure if err.report and err.report.failure else str(err)
            record.ik_error = bool(err.report and err.report.ik_error)
            return record
        record.plan_times.append(report.seconds)
        record.reach_errors.append([round(e, 4) for e in report.reach_error])
        record.plan_stats.append(report.stats)
        joints = conversions.parse_joint_trajectory(trajectory)[1][1:]     # the timed path, after the start
        path = execute_segment(world, task, joints, request.gripper_open, goal_open, config)
        record.joint_paths.append(path.round(5).tolist())
        record.grasps_lost = world.grasp_lost_count
        if task.success(world):
            record.success = True
            return record
    record.failure = 'not_completed'
    return record


# --- many episodes, many methods ---------------------------------------------------------

def _seed_ranges(seeds) -> str:
    """'3-5, 9' for [3, 4, 5, 9]."""
    runs, seeds = [], sorted(seeds)
    for seed in seeds:
        if runs and seed == runs[-1][1] + 1:
            runs[-1][1] = seed
        else:
            runs.append([seed, seed])
    return ', '.join(str(a) if a == b else f'{a}-{b}' for a, b in runs)


def check_seed_hygiene(methods: dict, tasks, seeds) -> None:
    """ValueError when an evaluation seed of a task is one a method's checkpoint trained on."""
    for name, policy in methods.items():
        trained = getattr(policy, 'training_seeds', None) or {}
        for task in tasks:
            overlap = set(seeds) & set(trained.get(task, ()))
            if overlap:
                raise ValueError(f'{name} was trained on {task} seeds {_seed_ranges(overlap)}, which are '
                                 'also evaluation seeds: choose another --seed-start')


def _oracle_job(job, methods, world) -> OracleEpisode:
    return oracle_episode(*job, world=world)


def _episode_job(job, methods, world) -> EpisodeRecord:
    name, oracle, camera_size, n_points, sensor, depth_filter = job
    return run_episode(methods[name], oracle, camera_size, n_points, world, name=name, sensor=sensor,
                       depth_filter=depth_filter)


_worker: dict = {}       # per worker process: the methods and a world kept between episodes


def _init_worker(methods: dict) -> None:
    if 'torch' in sys.modules:       # a learned policy came with the methods: one thread per worker
        sys.modules['torch'].set_num_threads(1)
    _worker.update(methods=methods, world=PandaWorld())


def _run_in_worker(item):
    function, job = item
    return function(job, _worker['methods'], _worker['world'])


@contextlib.contextmanager
def _job_runner(methods: dict, workers: int):
    """Yields run(function, jobs) -> iterator of function(job, methods, world), in job order."""
    if workers <= 1:
        with PandaWorld() as world:
            yield lambda function, jobs: (function(job, methods, world) for job in jobs)
        return
    with multiprocessing.get_context('spawn').Pool(workers, _init_worker, (methods,)) as pool:
        yield lambda function, jobs: pool.imap(_run_in_worker, [(function, job) for job in jobs])


def evaluate(methods: dict, tasks, episodes: int, seed_start: int, workers: int = 1,
             camera_size=CAMERA_SIZE, n_points: int = N_POINTS, progress: bool = True,
             sensor: SensorSettings = SensorSettings(), depth_filter: FilterSettings | None = None) -> dict:
    """Every method on the same oracle episodes: seeds seed_start .. seed_start + episodes - 1 per task.
    sensor: the front camera's sensor model and calibration error; depth_filter: the chain its depth
    goes through, None for none (run_episode).

    methods: name -> LowLevelPolicy. Returns a JSON-able dict: per method, per
    task, the success and IK-error rates over the episodes the expert solved
    and every EpisodeRecord; the skipped seeds per task. Raises ValueError on
    unknown tasks, episodes < 1, negative seeds or training-seed overlap.
    """
    tasks = list(tasks)
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise ValueError(f'unknown task(s) {unknown}; tasks: {", ".join(TASKS)}')
    if episodes < 1 or seed_start < 0:
        raise ValueError(f'need episodes >= 1 and seed_start >= 0, got {episodes} and {seed_start}')
    seeds = range(seed_start, seed_start + episodes)
    check_seed_hygiene(methods, tasks, seeds)
    start = time.monotonic()
    # Under torchrun each process takes every world-th episode; all gather every result.
    rank, world, _ = distributed.start()
    progress = progress and rank == 0
    with _job_runner(methods, workers) as run:
        jobs = [(task, seed) for task in tasks for seed in seeds][rank::world]
        oracles = list(tqdm(run(_oracle_job, jobs), total=len(jobs), desc='expert demos',
                            unit='episode', disable=not progress))
        usable = [o for o in oracles if o.expert_success]
        jobs = [(name, oracle, tuple(camera_size), n_points, sensor, depth_filter)
                for name in methods for oracle in usable]
        records = list(tqdm(run(_episode_job, jobs), total=len(jobs), desc='evaluation',
                            unit='episode', disable=not progress))
    skipped = [(o.task, o.seed, o.expert_reason) for o in oracles if not o.expert_success]
    if world > 1:
        skipped = sorted(s for part in distributed.gather(skipped, world) for s in part)
        records = [r for part in distributed.gather(records, world) for r in part]
        records.sort(key=lambda r: (list(methods).index(r.method), tasks.index(r.task), r.seed))
    results = {'tasks': tasks, 'seeds': [seed_start, seed_start + episodes - 1],
               'camera_size': list(camera_size), 'n_points': n_points, 'sensor': dataclasses.asdict(sensor),
               'depth_filter': None if depth_filter is None else dataclasses.asdict(depth_filter),
               'workers': workers, 'processes': world,
               'skipped': {task: [{'seed': seed, 'reason': reason} for t, seed, reason in skipped if t == task]
                           for task in tasks},
               'methods': {}}
    for name in methods:
        results['methods'][name] = {}
        for task in tasks:
            mine = [r for r in records if r.method == name and r.task == task]
            results['methods'][name][task] = {
                'episodes': len(mine),
                'success_rate': float(np.mean([r.success for r in mine])) if mine else None,
                'ik_error_rate': float(np.mean([r.ik_error for r in mine])) if mine else None,
                'mean_plan_time_s': float(np.mean([t for r in mine for t in r.plan_times]))
                if any(r.plan_times for r in mine) else None,
                'records': [dataclasses.asdict(r) for r in mine]}
    results['wall_s'] = round(time.monotonic() - start, 1)
    return results


def markdown_table(results: dict) -> str:
    """One row per method, one column per task plus 'overall' (the mean over tasks),
    cells 'success% / IK-error%' as in the paper's Table 2; 'n/a' where the expert
    solved no episode of a task."""
    tasks = results['tasks']
    rows = ['| method | ' + ' | '.join(tasks) + ' | overall |', '|---' * (len(tasks) + 2) + '|']
    for name, per_task in results['methods'].items():
        rated = [per_task[t] for t in tasks if per_task[t]['episodes']]
        cells = [_cell(per_task[t]['success_rate'], per_task[t]['ik_error_rate'])
                 if per_task[t]['episodes'] else 'n/a' for t in tasks]
        overall = (_cell(np.mean([r['success_rate'] for r in rated]),
                         np.mean([r['ik_error_rate'] for r in rated])) if rated else 'n/a')
        rows.append(f'| {name} | ' + ' | '.join(cells) + f' | {overall} |')
    return '\n'.join(rows)


def _cell(success_rate: float, ik_error_rate: float) -> str:
    return f'{100 * success_rate:.0f}% / {100 * ik_error_rate:.0f}%'
