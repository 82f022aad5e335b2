"""One segment's plan, as controller_node makes it and the evaluations score it.

    ArmState + NBP -> SegmentRequest -> policy.plan (up to plan_attempts draws, the one ending
    nearest the NBP) -> a timed JointTrajectory inside the robot's limits -> check_reach

Any step may refuse (SegmentRefused, carrying the PlanReport); nothing else decides whether a
plan runs, so `hdp eval hierarchy` and `hdp eval low-level` refuse exactly what the node refuses.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch

from hdp_data import workspace
from hdp_motion import kinematics, panda

from .inputs import ArmState, SegmentRefused
from .low_level import SegmentRequest, nearest_of_draws
from .observation import workspace_points
from .refine import goal_error
from .trajectory import VELOCITY_SCALE, TrajectoryError, joint_trajectory

# How far a plan's last waypoint may end from its NBP. On the validation seeds 900-909 (all six
# tasks, oracle NBPs, rkd with the graph's DDIM sampler) 165 of 168 segments ended within 0.1 mm
# and 0.05 deg; the other three, pressing on a hinge the expert's own NBP lies beyond, ended
# 5.5-6.1 cm and 1.5-3.6 deg away and their episodes still succeeded. Closed loop (agent NBPs,
# same seeds, `hdp eval hierarchy --reach-tolerance off`) every plan of a successful episode ended
# within 2.5 cm and 1.2 deg, and any tolerance from 5 cm/10 deg to 20 cm/45 deg refuses none of them.
# An NBP the arm cannot reach (the hand pointing up at the table) ends 13 cm away: refused.
REACH_TOLERANCE_M = 0.10
REACH_TOLERANCE_DEG = 15.0
# Plans a learned policy draws (fresh noise each) before a plan ending beyond the tolerance is
# refused: with the fast sampler one draw in a few for the same NBP can end 9-11 cm off (open_box,
# seed 1000's first NBP: 2 of 6 draws), and the next draw costs ~0.1 s.
PLAN_ATTEMPTS = 3


@dataclasses.dataclass(frozen=True)
class PlanReport:
    """How one segment was planned, for status lines, diagnostics and the evaluations.

    draws: plans drawn (plan_within_reach). seconds: NBP to a publishable trajectory (or to the
    refusal): every draw, the timing and the checks, what controller_node spends. reach_error: (m, deg)
    from the kept plan's last waypoint to the NBP, None when no plan came back. failure: the
    policy's reason when it found none ('ik_error', 'no_path', ...). stats: the plan's scalar
    extras (rkd: from_start, timings)."""
    method: str
    draws: int
    seconds: float
    reach_error: tuple[float, float] | None = None
    failure: str | None = None
    ik_error: bool = False
    stats: dict = dataclasses.field(default_factory=dict)


def segment_request(state: ArmState, gripper_open: bool, goal_pose, goal_open: bool, points) -> SegmentRequest:
    """A SegmentRequest from the arm state towards ``goal_pose`` (7,); start pose by FK.

    gripper_open: the gripper's state now (the node reads it from the fingers, panda.reads_open)."""
    start = kinematics.fk_pose(torch.as_tensor(state.q, dtype=torch.float64)).numpy()
    return SegmentRequest(q=state.q, qd=state.qd, gripper_width=state.gripper_width,
                          gripper_open=gripper_open, start_pose=start,
                          goal_pose=np.asarray(goal_pose, dtype=float), points=points,
                          goal_gripper_open=goal_open)


def reach_error(q_end, goal_pose) -> tuple[float, float]:
    """(m, deg) from the hand at joints ``q_end`` (7,) to ``goal_pose`` (7,) (rotation: to the
    grasp or the same grasp turned half a turn, whichever is nearer)."""
    translation, rotation = goal_error(torch.as_tensor(np.asarray(q_end, dtype=float))[None, None],
                                       torch.as_tensor(np.asarray(goal_pose, dtype=float))[None])
    return float(translation[0]), float(np.degrees(float(rotation[0])))


def plan_within_reach(policy, request: SegmentRequest, reach_tolerance: tuple[float, float] | None,
                      attempts: int = 1, scene=None):
    """(plan, draws): ``policy.plan`` drawn up to ``attempts`` times until a plan ends within
    ``reach_tolerance`` (m, deg) of the NBP, else the draw that ended nearest (nearest_of_draws).
    Each draw of a diffusion policy uses fresh noise."""
    return nearest_of_draws(lambda: policy.plan(request, scene),
                            lambda plan: reach_error(plan.joints[-1], request.goal_pose), reach_tolerance, attempts)


def check_reach(name: str, miss: tuple[float, float], tolerance: tuple[float, float] | None) -> None:
    """SegmentRefused, with the distance, when a plan's end misses its NBP by more than the
    tolerance (m, deg); None checks nothing."""
    if tolerance is None:
        return
    (metres, degrees), (tolerance_m, tolerance_deg) = miss, tolerance
    if metres > tolerance_m or degrees > tolerance_deg:
        raise SegmentRefused(f'{name} plan ends {metres:.3f} m and {degrees:.1f} deg from the NBP (tolerance '
                             f'{tolerance_m:.3f} m, {tolerance_deg:.1f} deg): the NBP is not reachable as given')


def plan_segment(policy, request: SegmentRequest, joint_names, velocity_scale: float,
                 reach_tolerance: tuple[float, float] | None = None,
                 limits: panda.JointLimits = panda.ROBOT_LIMITS['panda'], attempts: int = 1, scene=None):
    """(JointTrajectory from request.q, PlanReport), or SegmentRefused carrying the PlanReport.

    reach_tolerance: (m, deg) for check_reach, after up to ``attempts`` draws (plan_within_reach);
    None leaves the plan's end unchecked. limits: the robot's joint limits, which the trajectory
    is checked and timed against. scene: collision geometry for the planning baselines (None:
    their own kinematic scene, as on a robot).
    """
    started = time.perf_counter()
    plan, draws = plan_within_reach(policy, request, reach_tolerance, attempts, scene)
    if not plan.ok:
        report = PlanReport(policy.name, draws, time.perf_counter() - started, failure=plan.failure or 'no plan',
                            ik_error=bool(plan.ik_error))
        raise SegmentRefused(f'{policy.name} found no trajectory ({report.failure})', report)
    miss = reach_error(plan.joints[-1], request.goal_pose)
    stats = {k: v for k, v in plan.extras.items() if isinstance(v, (bool, int, float))}
    try:
        msg = joint_trajectory(request.q, plan.joints, joint_names, velocity_scale, limits=limits)
        check_reach(policy.name, miss, reach_tolerance)
    except (TrajectoryError, SegmentRefused) as err:
        why = f'{policy.name} trajectory refused: {err}' if isinstance(err, TrajectoryError) else str(err)
        raise SegmentRefused(why, PlanReport(policy.name, draws, time.perf_counter() - started, miss,
                                             stats=stats)) from None
    return msg, PlanReport(policy.name, draws, time.perf_counter() - started, miss, stats=stats)


def warm_up(policy, joint_names=panda.ARM_JOINTS, limits: panda.JointLimits = panda.ROBOT_LIMITS['panda']) -> float:
    """One plan_segment from the home posture to a pose 5 cm ahead, on a flat table's points, so
    that the first real segment does not pay for torch's first calls; returns its seconds (a
    refusal is as good a warm-up as a plan)."""
    q = panda.HOME
    goal = kinematics.fk_pose(torch.as_tensor(q, dtype=torch.float64)).numpy()
    goal[0] += 0.05
    points = workspace_points(np.array([[*workspace.TABLE_CENTER_XY, workspace.TABLE_TOP_Z + 0.01]]))
    request = segment_request(ArmState(q, np.zeros(7), panda.GRIPPER_OPEN_WIDTH), True, goal, True, points)
    started = time.perf_counter()
    try:
        plan_segment(policy, request, joint_names, VELOCITY_SCALE, limits=limits)
    except SegmentRefused:
        pass
    return time.perf_counter() - started
