"""controller_node's state machine, without ROS: NBP in, trajectory out, result back.

One segment at a time (the protocol is in the package README):

1. An NBP (geometry_msgs/PoseStamped) arrives; its gripper goal (sensor_msgs/JointState)
   carries the same stamp and may come just before or after it. Both are validated (inputs).
2. The latest /joint_states (and, for learned methods, the front camera's points) make the
   SegmentRequest, which segment_planning turns into a timed JointTrajectory, or refuses.
3. ``SegmentExecution`` (execution) follows the published trajectory: the arm at its last
   waypoint and still, then the gripper command and the fingers settling, then 'done'. Another
   command to the arm meanwhile (the node watches the arm's topic and action) ends it
   'failed: preempted by another command (...)'.

``SegmentController`` holds that state. Every method returns what to publish, as records:
ArmCommand, FingerCommand, HoldArm, SegmentResult and StatusLine. A refusal is a status line and a
'failed: ...' result, never a trajectory.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.conversions import time_to_ns
from hdp_msgs_py.msg import Header, JointTrajectory, Time
from hdp_msgs_py.outcome import StatusLine

from .execution import PREEMPTED, SegmentExecution
from .inputs import ArmState, SegmentRefused, arm_state, gripper_goal, validate_nbp, world_transform
from .observation import points_from_messages
from .segment_planning import (PLAN_ATTEMPTS, REACH_TOLERANCE_DEG, REACH_TOLERANCE_M, PlanReport, plan_segment,
                               segment_request)

PAIRING_WAIT_S = 0.5           # s an NBP waits for its gripper goal before keeping the gripper as is
# s an NBP waits for the first /joint_states and, for a learned method (it needs the points), the
# first front depth image: right after start-up the first NBP can beat the cameras' first frame
# (2 Hz of sim time by default) and DDS discovery of the joint-state publisher (up to ~2.5 s
# measured with Fast DDS on loopback).
STARTUP_WAIT_S = 3.0
FRAME_LEAD_NS = 1_000_000_000  # how far a depth image's stamp may run ahead of the latest joint state
_KEPT_GRIPPER_GOALS = 16       # gripper goals remembered by stamp, for NBPs still to come


@dataclasses.dataclass(frozen=True)
class ArmCommand:
    """Send the arm segment ``stamp``'s trajectory (on the topic, or as one FollowJointTrajectory goal)."""
    stamp: Time                # the segment's key: its NBP's header.stamp
    trajectory: JointTrajectory
    plan: PlanReport


@dataclasses.dataclass(frozen=True)
class FingerCommand:
    """Send the gripper this finger JointTrajectory (or the GripperCommand goal of its width)."""
    trajectory: JointTrajectory


@dataclasses.dataclass(frozen=True)
class HoldArm:
    """Stop the arm where it is: cancel the active FollowJointTrajectory goal, or on the topic send
    ``trajectory``, joint_trajectory_controller's own hold command (one point, the arm's latest
    position, time_from_start 0); JTC refuses an empty trajectory. None: no joint state yet."""
    trajectory: JointTrajectory | None


@dataclasses.dataclass(frozen=True)
class SegmentResult:
    """Publish on /hdp/segment_result: stamp the NBP's, frame_id 'done' or 'failed: <why>'.
    plan: how the segment was planned, when planning refused it."""
    header: Header
    plan: PlanReport | None = None

    @property
    def done(self) -> bool:
        return self.header.frame_id == topics.SEGMENT_DONE


def stamp_label(stamp) -> str:
    """How status lines name a segment: its NBP's stamp in seconds."""
    return f'{time_to_ns(stamp) / 1e9:.3f}'


@dataclasses.dataclass
class _Pending:
    nbp: object                # the PoseStamped
    goal: np.ndarray           # (7,) validated pose
    received_s: float


class SegmentController:
    """controller_node's state: the latest observations, the segment waiting or running.

    policy: a LowLevelPolicy. needs_points: whether it looks at the front camera (all but
    'planner'). One segment at a time. The planner sends the next NBP only after the last one's
    result, so an NBP that arrives while a segment is pending or running means the planner has
    moved on (it stopped waiting, or the simulator was reset for a new episode, restarting sim
    time): the new NBP supersedes that segment, which ends 'failed: superseded by ...'.

    scene: a callable giving the planning baselines' collision scene for each segment (a
    simulator's, in the evaluations); None lets them build their own, as on a robot.
    """

    def __init__(self, policy, needs_points: bool, velocity_scale: float, segment_timeout_s: float,
                 arm_joints=panda.ARM_JOINTS, finger_joints=panda.FINGER_JOINTS,
                 reach_tolerance: tuple[float, float] | None = (REACH_TOLERANCE_M, REACH_TOLERANCE_DEG),
                 limits: panda.JointLimits = panda.ROBOT_LIMITS['panda'], carry_on_unsettled: bool = False,
                 plan_attempts: int = PLAN_ATTEMPTS, scene: Callable | None = None):
        self.policy, self.needs_points, self.limits, self.scene = policy, needs_points, limits, scene
        self.configure(velocity_scale, segment_timeout_s, reach_tolerance, plan_attempts, carry_on_unsettled)
        self.arm_joints, self.finger_joints = tuple(arm_joints), tuple(finger_joints)
        self.state: ArmState | None = None
        self.state_stamp_ns = 0
        self.joint_state_problem = ''                # why the last /joint_states was unusable
        self.depth = self.info = None
        self.transforms: dict = {}                   # child frame -> TransformStamped, from /tf_static
        self.gripper_goals: dict[int, bool] = {}     # NBP stamp (ns) -> open
        self.pending: _Pending | None = None
        self.running: tuple[object, SegmentExecution] | None = None    # (NBP stamp, execution)

    def configure(self, velocity_scale: float, segment_timeout_s: float, reach_tolerance: tuple[float, float] | None,
                  plan_attempts: int, carry_on_unsettled: bool) -> None:
        """How segments are planned and judged; a change reaches the next segment to start."""
        self.plan_attempts = plan_attempts              # plan_within_reach
        self.carry_on_unsettled = carry_on_unsettled    # SegmentExecution.carry_on
        self.reach_tolerance = reach_tolerance
        self.velocity_scale, self.segment_timeout_s = velocity_scale, segment_timeout_s

    # -- observations --------------------------------------------------------------------
    def on_joint_state(self, msg) -> None:
        try:
            state = arm_state(msg, self.arm_joints, self.finger_joints)
        except ValueError as err:    # a partial or another robot's joint state: keep the last good one
            self.joint_state_problem = str(err)
            return
        if self.state is not None and time_to_ns(msg.header.stamp) < self.state_stamp_ns:
            self.depth = None        # the clock restarted (a simulator reset): that frame shows the old scene
        self.state, self.state_stamp_ns = state, time_to_ns(msg.header.stamp)

    def on_depth(self, msg) -> None:
        """Keep the front depth image, unless stamped far ahead of the joint states: a frame of the
        clock before a simulator reset, arriving late."""
        if self.state is None or time_to_ns(msg.header.stamp) <= self.state_stamp_ns + FRAME_LEAD_NS:
            self.depth = msg

    def on_camera_info(self, msg) -> None:
        self.info = msg

    def on_tf_static(self, msg) -> None:
        self.transforms.update({t.child_frame_id: t for t in msg.transforms})

    def on_gripper_goal(self, msg) -> list:
        try:
            is_open = gripper_goal(msg)
        except ValueError as err:
            return [StatusLine(f'ignored a gripper goal: {err}', error=True)]
        self.gripper_goals[time_to_ns(msg.header.stamp)] = is_open
        while len(self.gripper_goals) > _KEPT_GRIPPER_GOALS:
            self.gripper_goals.pop(next(iter(self.gripper_goals)))
        return []

    # -- segments -------------------------------------------------------------------------
    def on_nbp(self, msg, now_s: float) -> list:
        """Validate an NBP and keep it until step() starts it (after its gripper goal)."""
        out = self._supersede(msg.header.stamp)
        if self.pending is not None or self.running is not None:       # the same NBP again
            return out
        try:
            goal = validate_nbp(msg)
        except SegmentRefused as err:
            return out + self._refuse(msg.header.stamp, str(err))
        self.pending = _Pending(msg, goal, now_s)
        return out

    def _supersede(self, stamp) -> list:
        """End the pending or running segment for a newer NBP (``stamp``); one with the same stamp
        is a repeat and ignored. The arm takes the new segment's trajectory from where it is."""
        current = self.pending.nbp.header.stamp if self.pending is not None else (
            self.running[0] if self.running is not None else None)
        if current is None:
            return []
        if time_to_ns(current) == time_to_ns(stamp):
            return [StatusLine(f'ignored a repeated NBP for segment {stamp_label(stamp)}', error=True)]
        self.pending = self.running = None
        return self._refuse(current, f'superseded by segment {stamp_label(stamp)}')

    def step(self, now_s: float) -> list:
        """Advance the pending or running segment; call it often (the node's timer)."""
        if self.running is not None:
            return self._follow(now_s)
        if self.pending is None:
            return []
        key = time_to_ns(self.pending.nbp.header.stamp)
        waited = now_s - self.pending.received_s
        unpaired = key not in self.gripper_goals and waited < PAIRING_WAIT_S
        blind = self.needs_points and (self.depth is None or self.info is None)
        starting = (blind or self.state is None) and waited < STARTUP_WAIT_S
        if unpaired or starting:
            return []
        pending, self.pending = self.pending, None
        return self._start(pending, self.gripper_goals.pop(key, None), now_s)

    def _start(self, pending: _Pending, goal_open: bool | None, now_s: float) -> list:
        stamp = pending.nbp.header.stamp
        if self.state is None:
            problem = f' ({self.joint_state_problem})' if self.joint_state_problem else ''
            return self._refuse(stamp, f'no usable /joint_states received yet{problem}')
        is_open = panda.reads_open(self.state.gripper_width)
        out = []
        if goal_open is None:
            out.append(StatusLine(f'segment {stamp_label(stamp)}: no gripper goal with its stamp; '
                                  f'the gripper stays {"open" if is_open else "closed"}'))
        try:
            points = self._points() if self.needs_points else np.zeros((0, 3), np.float32)
            request = segment_request(self.state, is_open, pending.goal, is_open if goal_open is None else goal_open,
                                      points)
            trajectory, report = plan_segment(self.policy, request, self.arm_joints, self.velocity_scale,
                                              self.reach_tolerance, self.limits, self.plan_attempts,
                                              self.scene() if self.scene is not None else None)
        except SegmentRefused as err:
            return out + self._refuse(stamp, str(err), plan=err.report)
        duration = conversions.duration_to_seconds(trajectory.points[-1].time_from_start)
        act = goal_open if goal_open is not None and goal_open != is_open else None
        self.running = (stamp, SegmentExecution(np.asarray(trajectory.points[-1].positions), duration, now_s,
                                                self.segment_timeout_s, act, self.carry_on_unsettled))
        x, y, z = pending.goal[:3]
        gripper = '' if act is None else f', then {"open" if act else "close"} the gripper'
        return out + [ArmCommand(stamp, trajectory, report), StatusLine(
            f'segment {stamp_label(stamp)}: {self.policy.name} to ({x:.3f}, {y:.3f}, {z:.3f}): '
            f'{len(trajectory.points)} points over {duration:.2f} s{gripper} (planned in {report.seconds:.2f} s, '
            f'{report.draws} draw{"s" if report.draws > 1 else ""})')]

    def preempted(self, command: str) -> list:
        """Another command (``command`` says what and from whom) took the arm: the running segment
        fails as preempted; nothing is held, the arm is the other command's now."""
        if self.running is None:
            return []
        stamp, self.running = self.running[0], None
        return self._refuse(stamp, f'{PREEMPTED} ({command})', 'segment {} failed')

    def arm_failed(self, stamp, why: str) -> list:
        """The arm controller refused or aborted segment ``stamp``'s trajectory (the action
        interface): that segment fails with the controller's reason, if it is still running."""
        if self.running is None or time_to_ns(self.running[0]) != time_to_ns(stamp):
            return []
        self.running = None
        return self._refuse(stamp, why, 'segment {} failed')

    def robot_gone(self, why: str) -> list:
        """The robot stopped answering (Liveness.problem): the pending or running segment fails."""
        current = self.pending.nbp.header.stamp if self.pending is not None else (
            self.running[0] if self.running is not None else None)
        if current is None:
            return []
        self.pending = self.running = None
        return self._refuse(current, why, 'segment {} failed')

    def hold(self, why: str) -> list:
        """An operator's stop: hold the arm where it is, whatever it was doing, and end the pending
        or running segment 'failed: <why>'."""
        trajectory = None if self.state is None else conversions.build_joint_trajectory(
            self.arm_joints, self.state.q[None], [0.0])
        return [HoldArm(trajectory), StatusLine(f'holding the arm: {why}')] + self.robot_gone(why)

    def _follow(self, now_s: float) -> list:
        stamp, execution = self.running
        update = execution.update(now_s, self.state)
        out = []
        if update.send_gripper:
            out.append(FingerCommand(conversions.finger_trajectory(execution.gripper_open, self.finger_joints)))
        if update.result is not None:
            self.running = None
            short = (f' (the arm stopped {execution.short_by:.3f} rad short of the last waypoint: blocked)'
                     if execution.short_by is not None else '')
            if execution.unsettled:
                error, speed = execution.unsettled
                short = (f' (the arm had not come to rest {execution.timeout_s:.1f} s after the trajectory\'s end: '
                         f'carried on {error:.3f} rad from the last waypoint, moving at {speed:.3f} rad/s)')
            out += [StatusLine(f'segment {stamp_label(stamp)}: {update.result}{short}',
                               error=update.result != topics.SEGMENT_DONE),
                    SegmentResult(Header(stamp=stamp, frame_id=update.result))]
        return out

    def _points(self) -> np.ndarray:
        if self.depth is None or self.info is None:
            raise SegmentRefused('no front camera depth and camera_info received yet')
        transform = world_transform(self.transforms, self.depth.header.frame_id)
        try:
            return points_from_messages(self.depth, self.info, transform)
        except ValueError as err:
            raise SegmentRefused(f'front camera unusable: {err}') from None

    def _refuse(self, stamp, reason: str, what: str = 'refused segment {}', plan: PlanReport | None = None) -> list:
        self.gripper_goals.pop(time_to_ns(stamp), None)
        return [StatusLine(f'{what.format(stamp_label(stamp))}: {reason}', error=True),
                SegmentResult(Header(stamp=stamp, frame_id=topics.SEGMENT_FAILED + reason), plan)]
