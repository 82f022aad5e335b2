"""Scripted experts: reach each task waypoint, come to rest, actuate the gripper.

Like RLBench's demos: a linear path when possible, else OMPL RRT-Connect, and
hinge-following arcs passed through without stopping. Some approach paths are
deliberately left unsmoothed, so demonstrations vary in trajectory rank.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from hdp_motion import panda, planning, timing

from .trajectory_follower import ActiveTrajectory
from .world import TIME_STEP

SETTLE_VELOCITY = 0.01     # rad/s: "at rest", below the keyframe stopping delta
# Physics steps the arm must stay still before it counts as arrived: episodes record joint states
# every 2nd step (collect.JOINT_STATE_EVERY), and a stillness of one step (an arm jittering as it
# pushes a toilet seat) is invisible to the keyframe rule, which would then find no keyframe there.
STILL_STEPS = 2
MIN_REST_S = 0.3           # rest at a waypoint with nothing else to do there
GRIPPER_S = 0.5            # time given to the fingers


# Starting postures for IK: hand down (HOME), hand level and forward (elbow up,
# wrist bent back), hand pitched forward-down.
SEED_POSTURES = (panda.HOME,
                 np.array([0.0, 0.3, 0.0, -2.0, 0.0, 3.4, 0.785]),
                 np.array([0.0, 0.1, 0.0, -2.3, 0.0, 2.9, 0.785]))


class ExpertFailure(RuntimeError):
    """No path to a waypoint (planning or IK failed)."""


@dataclasses.dataclass
class ExpertConfig:
    velocity_scale: float = 0.5        # of the Panda's joint velocity limits
    unsmoothed_probability: float = 0.3
    rrt_timeout: float = 5.0


def via_path(world, poses, q_start) -> np.ndarray:
    """Joint path through a chain of poses, each IK seeded by the previous: (N,7)."""
    path, q = [q_start], q_start
    for xyz, quat in poses:
        q = planning.solve_ik(_cid(world), world.robot, xyz, quat, q)
        if q is None or np.max(np.abs(q - path[-1])) > 0.5:
            raise ExpertFailure('no continuous IK solution along the arc')
        path.append(q)
    return timing.resample_path(np.array(path), max(2, 8 * len(path)))


def _cid(world) -> int:
    return world.client_id


def _held_free_body(world) -> int | None:
    """The grasped body if it moves freely with the hand (a cup), not an articulated link."""
    body = world.grasped_body()
    return body if body is not None and world.grasped_link() == -1 else None


def plan(world, task, waypoint, rng, config: ExpertConfig, q_goal=None) -> np.ndarray:
    """A joint path (N,7) to the waypoint; ``q_goal`` pins the arm configuration to end in."""
    q_start = world.joint_positions()
    held = _held_free_body(world)
    obstacles = [world.table] + [b for b in world.task_bodies if b != held]
    if waypoint.path == 'via':
        return via_path(world, waypoint.poses, q_start)
    xyz, quat = waypoint.poses[0]
    if waypoint.path == 'linear':
        # Straight moves go into contact (grasps) or carry what is held: only the
        # table and what is not being handled may stop them.
        others = [b for b in obstacles if b not in (held, world.grasped_body()) and b not in task.touched]
        path = planning.linear_path(_cid(world), world.robot, q_start, xyz, quat,
                                  obstacles=[world.table] + others, attached=held)
        if path is None:
            raise ExpertFailure(f'no straight-line path to {np.round(xyz, 3).tolist()}')
        return path
    if q_goal is None:
        q_goal = planning.solve_ik(_cid(world), world.robot, xyz, quat, q_start)
        if q_goal is None:
            raise ExpertFailure(f'no IK solution for {np.round(xyz, 3).tolist()}')
    # As RLBench: a straight line when there is one, else RRT-Connect. A share of
    # demos take the planner's unsimplified path anyway, so trajectory rank varies.
    sub_optimal = rng.random() < config.unsmoothed_probability
    if not sub_optimal:
        path = planning.linear_path(_cid(world), world.robot, q_start, xyz, quat, obstacles=obstacles,
                                  attached=held)
        if path is not None and np.max(np.abs(path[-1] - q_goal)) < 0.1:
            return path
    path = planning.rrt_connect(_cid(world), world.robot, q_start, q_goal, obstacles,
                              timeout=config.rrt_timeout, seed=int(rng.integers(2**31)),
                              simplify=not sub_optimal, attached=held)
    if path is None:
        raise ExpertFailure(f'no collision-free path to {np.round(xyz, 3).tolist()}')
    return path


def follow(world, task, path: np.ndarray, config: ExpertConfig, on_step, on_arrive, hold: float) -> None:
    """Track a time-parameterised joint path, then wait for the arm to stop (see ``rest``).

    The path is streamed a target per step, sampled the way the bridge samples a
    JointTrajectory with velocities (a cubic spline), so demonstrations and
    policies move the arm alike.
    """
    times = timing.time_parameterize(path, velocity_scale=config.velocity_scale)
    velocities = timing.path_velocities(path, times, config.velocity_scale)
    trajectory = ActiveTrajectory(world.sim_time, times, path, velocities)
    while world.sim_time < trajectory.end_time:
        world.command_arm(trajectory.sample(world.sim_time + TIME_STEP))
        _step(world, task, on_step)
    rest(world, task, path[-1], on_step, on_arrive, hold)


def rest(world, task, q_final, on_step, on_arrive, hold: float, timeout: float = 3.0) -> None:
    """Hold ``q_final`` until the arm is still there (or blocked on the way); ``on_arrive``
    fires at the first still step (the keyframe the rule will find), then the arm stays
    still ``hold`` s more. An arm turning round on its way is not still.

    A waypoint followed by a gripper action or ending the demo holds 0 s, so the
    stop and the gripper change (or the last frame) are one keyframe, not two.
    """
    world.command_arm(q_final)
    start, still_since, still_steps, arrived = world.sim_time, None, 0, False
    while world.sim_time - start < timeout:
        _step(world, task, on_step)
        if world.arm_reference_settled and np.max(np.abs(world.joint_velocities())) < SETTLE_VELOCITY:
            still_steps += 1
            if still_since is None:
                still_since = world.sim_time
            if not arrived and still_steps >= STILL_STEPS:  # once: an arm pressed on a contact stops and starts again
                arrived = True
                on_arrive()
            if arrived and world.sim_time - still_since >= hold:
                return
        else:
            still_since, still_steps = None, 0
    if not arrived:
        on_arrive()      # never quite still (e.g. pushing against a hinge): carry on from here


def actuate(world, task, action: str, on_step, on_gripper) -> None:
    world.command_gripper(action == 'open')
    on_gripper(action == 'open')
    start = world.sim_time
    while world.sim_time - start < GRIPPER_S:
        _step(world, task, on_step)


def _step(world, task, on_step) -> None:
    world.step()
    task.on_step(world)
    on_step()


def _ik_chain(world, waypoints, q_first_seed, free_seeds) -> tuple[float, list | None]:
    """IK through every pose in order, each seeded by the last; straight lines in full.

    A waypoint after the first that the arm reaches by planning ('any') may need another
    arm configuration (the hand turned over to press from above): when the previous
    solution does not lead to it within a small change, it is solved from ``free_seeds``
    and the planner gets there. Returns (the smallest distance to a joint limit along the
    chain, each waypoint's joint goal), or (-inf, None) when some pose is out of reach.
    """
    q_prev, q = world.joint_positions(), q_first_seed
    margin, goals = np.inf, []
    for waypoint in waypoints:
        for xyz, quat in waypoint.poses:
            if waypoint.path == 'linear' and goals:   # the whole line, as executed
                line = planning.linear_path(_cid(world), world.robot, q, xyz, quat, obstacles=[world.table])
                q = None if line is None else line[-1]
            else:
                q = planning.solve_ik(_cid(world), world.robot, xyz, quat, q)
            if goals and waypoint.path == 'any' and (q is None or np.max(np.abs(q - q_prev)) > 0.5):
                q = _closest_solution(world, xyz, quat, free_seeds, q_prev)
            elif goals and q is not None and np.max(np.abs(q - q_prev)) > 0.5:
                q = None
            if q is None:
                return -np.inf, None
            margin = min(margin, float(np.min(np.minimum(q - panda.LOWER, panda.UPPER - q))))
            q_prev = q
        goals.append(q)
    return margin, goals


def _closest_solution(world, xyz, quat, seeds, q_near) -> np.ndarray | None:
    solutions = [q for q in (planning.solve_ik(_cid(world), world.robot, xyz, quat, seed) for seed in seeds)
                 if q is not None]
    return min(solutions, key=lambda q: np.max(np.abs(q - q_near)), default=None)


def choose_waypoints(world, task) -> tuple[list, list | None]:
    """The waypoints and their joint goals that keep the arm farthest from its limits.

    Tries both grasp flips (the wrist turned 180 deg) and IK seeds from the
    current arm and from SEED_POSTURES turned towards the object, as a person
    would pick a comfortable way to hold before reaching.
    """
    origin, _, _ = task.frame()
    yaw = np.clip(np.arctan2(origin[1], origin[0]), panda.LOWER[0], panda.UPPER[0])
    seeds = [world.joint_positions()]
    for posture in SEED_POSTURES:        # each turned towards the object
        seeds.append(np.concatenate([[yaw], posture[1:]]))
    # and a few around the first: pybullet's IK finds far-off wrist angles only
    # from a nearby start
    jitter = np.random.default_rng(0).normal(0.0, 0.4, (4, 7))
    seeds += list(np.clip(seeds[1] + jitter, panda.LOWER, panda.UPPER))
    valid = planning.collision_checker(_cid(world), world.robot, [world.table] + world.task_bodies)
    best = (-np.inf, task.waypoints(world), None)
    for flip in (False, True):
        waypoints = task.waypoints(world, flip)
        for seed in seeds:
            margin, goals = _ik_chain(world, waypoints, seed, seeds[1:])
            if goals:
                with planning.preserved_state(_cid(world), world.robot):
                    if not valid(goals[0]):      # the first goal must be free to plan to
                        continue
            if margin > best[0]:
                best = (margin, waypoints, goals)
    return best[1], best[2]


@dataclasses.dataclass
class ExpertResult:
    success: bool
    reason: str = ''        # why it failed: no path, or the success condition did not hold


def run_expert(world, task, rng: np.random.Generator, on_step=lambda: None, on_rest=lambda: None,
               on_gripper=lambda is_open: None, config: ExpertConfig | None = None) -> ExpertResult:
    """Execute the task's waypoints, then check the task's success condition.

    ``on_step`` runs after every physics step (recording), ``on_rest`` when
    the arm comes to rest at a waypoint and at the very end (camera frames at
    the keyframes), ``on_gripper``
    with each gripper command (True: open).
    """
    config = config or ExpertConfig()
    waypoints, goals = choose_waypoints(world, task)
    for i, waypoint in enumerate(waypoints):
        try:
            path = plan(world, task, waypoint, rng, config, None if goals is None else goals[i])
        except ExpertFailure as err:
            return ExpertResult(False, f'waypoint {i}: {err}')
        last = i == len(waypoints) - 1
        hold = 0.0 if waypoint.gripper or last else MIN_REST_S
        follow(world, task, path, config, on_step, on_rest, hold)
        if waypoint.gripper:
            actuate(world, task, waypoint.gripper, on_step, on_gripper)
    if waypoints and waypoints[-1].gripper:
        on_rest()                     # the final frame, after the fingers have moved
    if task.success(world):
        return ExpertResult(True)
    lost = f', grasp lost {world.grasp_lost_count}x' if world.grasp_lost_count else ''
    return ExpertResult(False, f'success condition not met{lost}')


def reachable_scene(world, task_name: str, seed: int, variation: int | None = None, attempts: int = 40):
    """Reset the world to a scene of ``task_name`` that the arm can reach, drawn from ``seed``.

    Layouts are redrawn from the same generator until the expert's waypoints
    have an IK solution, as RLBench resamples scenes whose demos fail: a task
    placed out of reach tests nothing. Deterministic: one seed, one scene.
    Returns (task, rng, variation); the rng continues for the instruction and
    the expert.
    """
    from .tasks import make_task
    rng = np.random.default_rng(seed)
    task = make_task(task_name)
    variation = int(rng.integers(len(task.variations))) if variation is None else variation
    for _ in range(attempts):
        world.reset(seed)
        task.reset(world, rng, variation)
        if choose_waypoints(world, task)[1] is not None:
            break
    return task, rng, variation
