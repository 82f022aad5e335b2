"""Low-level baselines of the paper's Table 2 that need no joint-space model.

``PlannerPolicy``: RLBench's EndEffectorPoseViaPlanning, a straight line in
Cartesian space when it is collision free, else OMPL RRT-Connect to an IK
goal. ``PoseIKPolicy``: a pose trajectory (from the pose diffuser) turned
into joints by IK waypoint by waypoint; a waypoint IK cannot reach is an IK
error, as RLBench's IKError.

Both plan in the Scene they are given (the simulated world itself during
evaluation); without one, in a private PyBullet scene holding only the Panda
and the table, which is all a real robot's controller knows of its cell.
"""

from __future__ import annotations

import functools

import numpy as np

from hdp_motion import panda, planning
from hdp_motion.rotations import quat_angle
from hdp_data import workspace

from .low_level import PlanResult, Scene, SegmentRequest, start_episode


@functools.cache
def standalone_scene() -> Scene:
    """A per-process kinematic PyBullet scene: the Panda and the table it stands on, the only
    obstacle a planner knows of without perception."""
    table = ((*workspace.TABLE_CENTER_XY, workspace.TABLE_TOP_Z - workspace.TABLE_HALF_EXTENTS[2]),
             workspace.TABLE_HALF_EXTENTS)
    client, robot, obstacles = planning.kinematic_scene([table])
    return Scene(client=client, robot=robot, obstacles=obstacles)


def _free_attached_body(scene: Scene) -> int | None:
    """The held body when it moves freely with the hand (a cup); a held link of an
    articulated body (a drawer handle) is not carried, its body is simply not an obstacle."""
    if scene.attached is None:
        return None
    body, link = scene.attached
    return body if link == -1 else None


def _at_pose(pose, goal) -> bool:
    """Whether two (7,) xyz + quat xyzw poses agree within IK's tolerances."""
    return bool(np.linalg.norm(pose[:3] - goal[:3]) < planning.IK_POS_TOL
                and quat_angle(pose[3:], goal[3:]) < planning.IK_ROT_TOL)


class PlannerPolicy:
    """The "Planner" baseline: straight line if collision free, else RRT-Connect, to the NBP
    (RLBench's EndEffectorPoseViaPlanning); ``straight_first`` False: RRT-Connect only, as the
    paper describes its Planner row ('planner_rrt')."""

    training_seeds = None       # nothing learned: any evaluation seed is fair

    def __init__(self, rrt_timeout: float = 5.0, seed: int = 0, straight_first: bool = True):
        self.rrt_timeout = rrt_timeout
        self.seed = seed        # OMPL's: the same request plans the same path
        self.straight_first = straight_first
        self.name = 'planner' if straight_first else 'planner_rrt'

    def plan(self, request: SegmentRequest, scene: Scene | None = None) -> PlanResult:
        if _at_pose(request.start_pose, request.goal_pose):
            # Nothing to plan. Checking the goal would reject it whenever the arm is in
            # contact already, say with a grasped cup still standing on the table.
            return PlanResult(np.asarray(request.q, dtype=float)[None], extras={'kind': 'none'})
        scene = scene or standalone_scene()
        found = planning.plan_to_pose(scene.client, scene.robot, request.q, request.goal_pose[:3],
                                    request.goal_pose[3:], list(scene.obstacles),
                                    timeout=self.rrt_timeout, seed=self.seed,
                                    attached=_free_attached_body(scene), straight_first=self.straight_first)
        if found is None:
            return PlanResult(None, failure='no_path', ik_error=False)
        path, kind = found
        return PlanResult(path, extras={'kind': kind})


class PoseIKPolicy:
    """Pose diffusion + IK: ``pose_sampler(request)`` -> (HORIZON, 7) xyz + quat xyzw,
    each waypoint solved by IK seeded with the previous solution (the first with request.q)."""

    def __init__(self, pose_sampler, name: str = 'pose_ik', training_seeds: dict | None = None):
        self.pose_sampler = pose_sampler
        self.name = name
        self.training_seeds = training_seeds

    def reseed(self, episode_seed: int) -> None:
        start_episode(self.pose_sampler, episode_seed)      # a sampler without noise has nothing to reseed

    def plan(self, request: SegmentRequest, scene: Scene | None = None) -> PlanResult:
        scene = scene or standalone_scene()
        poses = np.asarray(self.pose_sampler(request), dtype=float)
        q, joints = np.asarray(request.q, dtype=float), [np.asarray(request.q, dtype=float)]
        for pose in poses:
            q = planning.solve_ik(scene.client, scene.robot, pose[:3], pose[3:], q)
            if q is None or not panda.within_limits(q):
                return PlanResult(None, failure='ik_error', ik_error=True, poses=poses)
            joints.append(q)
        return PlanResult(np.array(joints), poses=poses)
