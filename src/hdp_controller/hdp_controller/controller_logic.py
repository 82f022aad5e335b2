"""What controller_node does between messages, without ROS: NBP in, trajectory out, result back.

One segment at a time (the protocol is in the package README):

1. An NBP (geometry_msgs/PoseStamped) arrives; its gripper goal (sensor_msgs/JointState)
   carries the same stamp and may come just before or after it.
2. ``validate_nbp`` refuses NaN/inf, a non-unit quaternion, a frame other than 'world' and a
   position outside ``workspace.WORKSPACE``, with a reason.
3. The latest /joint_states (and, for learned methods, the front camera's points) make the
   SegmentRequest; the policy plans; ``trajectory.joint_trajectory`` times the joints inside
   the Panda's position and velocity limits, or refuses; so does ``check_reach`` when the
   plan's last waypoint (by forward kinematics) ends farther from the NBP than the tolerance.
4. ``SegmentExecution`` follows the published trajectory: the arm at its last waypoint and
   still, then the gripper command and the fingers settling, then 'done' (or a timeout).

``SegmentController`` holds that state; every method returns the messages to publish as
``Out(kind, msg)``, kinds 'arm', 'gripper', 'result' (a message) and 'info', 'error'
(a status line). A refusal is a status line and a 'failed: ...' result, never a trajectory.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import torch

from hdp_motion import kinematics, panda
from hdp_msgs_py import conversions, topics, workspace
from hdp_msgs_py.msg import Header

from .low_level import SegmentRequest, nearest_of_draws
from .observation import points_from_messages
from .refine import goal_error
from .trajectory import TrajectoryError, joint_trajectory

GOAL_TOLERANCE = 0.02          # rad: max joint error at the last waypoint that counts as arrived
STILL_VELOCITY = 0.02          # rad/s: max joint speed that counts as still (the sim settles < 0.01)
BLOCKED_STILL_S = 0.5          # s without progress short of the last waypoint after the trajectory's end: blocked
BLOCKED_BAND = 0.005           # rad every joint stays within meanwhile (pressed on a contact, the arm jitters)
GRIPPER_TOLERANCE = 0.002      # m of width from the target that counts as reached
GRIPPER_MOVED = 0.001          # m of width change that shows the fingers responded
GRIPPER_STILL_S = 0.2          # s without width change after moving: closed on an object
GRIPPER_TIMEOUT_S = 3.0        # s for the fingers to reach the target or stop
PAIRING_WAIT_S = 0.5           # s an NBP waits for its gripper goal before keeping the gripper as is
# s an NBP waits for the first /joint_states and, for a learned method (it needs the points), the
# first front depth image: right after start-up the first NBP can beat the cameras' first frame
# (2 Hz of sim time by default) and DDS discovery of the joint-state publisher (up to ~2.5 s
# measured with Fast DDS on loopback).
STARTUP_WAIT_S = 3.0
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
FRAME_LEAD_NS = 1_000_000_000  # how far a depth image's stamp may run ahead of the latest joint state
_KEPT_GRIPPER_GOALS = 16       # gripper goals remembered by stamp, for NBPs still to come


class SegmentRefused(ValueError):
    """Why a segment cannot run; goes back to the planner as 'failed: <reason>'."""


class Out(NamedTuple):
    kind: str                  # 'arm' | 'gripper' | 'result' (msg is a message) | 'info' | 'error' (a str)
    msg: object


class ArmState(NamedTuple):
    q: np.ndarray              # (7,) rad, arm joint order
    qd: np.ndarray             # (7,) rad/s
    gripper_width: float       # m between the fingers


def stamp_ns(stamp) -> int:
    """A builtin_interfaces/Time as integer nanoseconds: the segment's key, compared exactly."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_label(stamp) -> str:
    """How status lines name a segment: its NBP's stamp in seconds."""
    return f'{stamp_ns(stamp) / 1e9:.3f}'


def validate_nbp(msg) -> np.ndarray:
    """(7,) xyz (m) + unit quaternion xyzw of a PoseStamped NBP, or SegmentRefused saying why."""
    if msg.header.frame_id != topics.NBP_FRAME:
        raise SegmentRefused(f"frame_id {msg.header.frame_id!r} is not {topics.NBP_FRAME!r} "
                             '(the controller takes NBPs in the world frame only)')
    try:
        xyz, quat = conversions.pose_to_xyz_quat(msg)
    except ValueError as err:          # NaN/inf, zero or non-unit quaternion
        raise SegmentRefused(f'invalid pose: {err}') from None
    if not workspace.in_workspace(xyz[None])[0]:
        low, high = workspace.WORKSPACE
        raise SegmentRefused(
            f'position ({xyz[0]:.3f}, {xyz[1]:.3f}, {xyz[2]:.3f}) m is outside the workspace '
            f'x [{low[0]}, {high[0]}], y [{low[1]}, {high[1]}], '
            f'z [{low[2] + workspace.ABOVE_TABLE:.3f}, {high[2]}]')
    return np.concatenate([xyz, quat])


def gripper_goal(msg) -> bool:
    """Whether a gripper goal (JointState, name [GRIPPER_GOAL_JOINT], position [width m]) opens."""
    if list(msg.name) != [topics.GRIPPER_GOAL_JOINT] or len(msg.position) != 1:
        raise ValueError(f'a gripper goal names [{topics.GRIPPER_GOAL_JOINT!r}] with one position, '
                         f'got names {list(msg.name)} and {len(msg.position)} positions')
    width = float(msg.position[0])
    if not 0.0 <= width <= panda.GRIPPER_OPEN_WIDTH + 1e-6:      # also refuses NaN
        raise ValueError(f'gripper goal width must be within [0, {panda.GRIPPER_OPEN_WIDTH}] m, got {width}')
    return width >= panda.GRIPPER_OPEN_WIDTH / 2


def arm_state(msg, arm_joints, finger_joints) -> ArmState:
    """The arm (by name, any order) and gripper width of a sensor_msgs/JointState."""
    names = list(msg.name)
    missing = [n for n in (*arm_joints, *finger_joints) if n not in names]
    if missing:
        raise ValueError(f'joint state lacks {missing}')
    position = np.asarray(msg.position, dtype=float)
    velocity = np.asarray(msg.velocity, dtype=float)
    arm = [names.index(n) for n in arm_joints]
    qd = velocity[arm] if len(velocity) == len(names) else np.zeros(len(arm))
    return ArmState(position[arm], qd, float(sum(position[names.index(n)] for n in finger_joints)))


def measured_open(width: float) -> bool:
    """The gripper's state from its fingers: open when (nearly) fully open. Measured at every
    segment, not remembered, so a simulator reset or a hand on the gripper cannot mislead it
    (a grasped object is narrower than the open width)."""
    return width >= panda.GRIPPER_OPEN_WIDTH - 0.005


def gripper_command(is_open: bool, finger_joints=panda.FINGER_JOINTS):
    """The finger JointTrajectory (m per finger, start now) for the gripper controller."""
    finger = panda.FINGER_MAX if is_open else 0.0
    return conversions.build_joint_trajectory(list(finger_joints), [[finger, finger]], [0.5])


def world_transform(transforms: dict, frame: str):
    """The TransformStamped world -> ``frame`` among /tf_static's (child frame -> transform)."""
    transform = transforms.get(frame)
    if transform is None:
        raise SegmentRefused(f"no /tf_static transform to the camera frame {frame!r} yet")
    if transform.header.frame_id != topics.NBP_FRAME:
        raise SegmentRefused(f"/tf_static gives {frame!r} in {transform.header.frame_id!r}, "
                             f"not {topics.NBP_FRAME!r}")
    return transform


def segment_request(state: ArmState, gripper_open: bool, goal_pose, goal_open: bool, points) -> SegmentRequest:
    """A SegmentRequest from the arm state towards ``goal_pose`` (7,); start pose by FK."""
    start = kinematics.fk_pose(torch.as_tensor(state.q, dtype=torch.float64)).numpy()
    return SegmentRequest(q=state.q, qd=state.qd, gripper_width=state.gripper_width,
                          gripper_open=gripper_open, start_pose=start,
                          goal_pose=np.asarray(goal_pose, dtype=float), points=points,
                          goal_gripper_open=goal_open)


def plan_within_reach(policy, request: SegmentRequest, reach_tolerance: tuple[float, float] | None,
                      attempts: int = 1, scene=None):
    """(plan, draws): ``policy.plan`` drawn up to ``attempts`` times until a plan ends within
    ``reach_tolerance`` (m, deg) of the NBP, else the draw that ended nearest (nearest_of_draws).
    Each draw of a diffusion policy uses fresh noise."""
    return nearest_of_draws(lambda: policy.plan(request, scene),
                            lambda plan: reach_error(plan.joints[-1], request.goal_pose), reach_tolerance, attempts)


def plan_segment(policy, request: SegmentRequest, joint_names, velocity_scale: float,
                 reach_tolerance: tuple[float, float] | None = None,
                 limits: panda.JointLimits = panda.ROBOT_LIMITS['panda'], attempts: int = 1):
    """The policy's joints as a JointTrajectory from request.q, or SegmentRefused.

    reach_tolerance: (m, deg) for check_reach, after up to ``attempts`` draws (plan_within_reach);
    None leaves the plan's end unchecked.
    limits: the robot's joint limits, which the trajectory is checked and timed against.
    """
    plan, _ = plan_within_reach(policy, request, reach_tolerance, attempts)
    if not plan.ok:
        raise SegmentRefused(f'{policy.name} found no trajectory ({plan.failure or "no plan"})')
    try:
        msg = joint_trajectory(request.q, plan.joints, joint_names, velocity_scale, limits=limits)
    except TrajectoryError as err:
        raise SegmentRefused(f'{policy.name} trajectory refused: {err}') from None
    if reach_tolerance is not None:
        check_reach(policy.name, plan.joints[-1], request.goal_pose, *reach_tolerance)
    return msg, plan


def reach_error(q_end, goal_pose) -> tuple[float, float]:
    """(m, deg) from the hand at joints ``q_end`` (7,) to ``goal_pose`` (7,) (rotation: to the
    grasp or the same grasp turned half a turn, whichever is nearer)."""
    translation, rotation = goal_error(torch.as_tensor(np.asarray(q_end, dtype=float))[None, None],
                                       torch.as_tensor(np.asarray(goal_pose, dtype=float))[None])
    return float(translation[0]), float(np.degrees(float(rotation[0])))


def check_reach(name: str, q_end, goal_pose, tolerance_m: float, tolerance_deg: float) -> None:
    """SegmentRefused, with the distance, when joints ``q_end`` put the hand farther than the
    tolerance from ``goal_pose`` (reach_error)."""
    metres, degrees = reach_error(q_end, goal_pose)
    if metres > tolerance_m or degrees > tolerance_deg:
        raise SegmentRefused(f'{name} plan ends {metres:.3f} m and {degrees:.1f} deg from the NBP (tolerance '
                             f'{tolerance_m:.3f} m, {tolerance_deg:.1f} deg): the NBP is not reachable as given')


class Update(NamedTuple):
    send_gripper: bool = False
    result: str | None = None


class SegmentExecution:
    """Follows one published segment: arm arrival, then the gripper action, then the result.

    goal_q: (7,) the trajectory's last waypoint. duration_s: its time_from_start.
    timeout_s: time after the trajectory's end for the arm to settle.
    gripper_open: the action after arriving, or None to leave the gripper as it is.
    Times are seconds on the node's clock (sim time under use_sim_time).

    The arm has arrived when, after the trajectory's end, it is still at the last waypoint,
    or has stayed within BLOCKED_BAND of one position for BLOCKED_STILL_S anywhere: in
    contact tasks a drawer's end stop or a hinge holds it short (``short_by`` then says how
    far, in rad), as it held the experts. Pressed against such a stop the joint velocities
    jitter above STILL_VELOCITY, so "blocked" looks at progress, not at speed.

    An arm neither there nor blocked ``timeout_s`` after the trajectory's end (sliding along a
    lid it presses on, say) fails the segment, unless ``carry_on``: then it counts as arrived
    where it is (``unsettled`` says how far off and how fast), as the experts carried on after
    their rest timeout, and the planner re-observes from there.
    """

    def __init__(self, goal_q, duration_s: float, start_s: float, timeout_s: float, gripper_open: bool | None,
                 carry_on: bool = False):
        self.goal_q = np.asarray(goal_q, dtype=float)
        self.duration_s, self.start_s, self.timeout_s = duration_s, start_s, timeout_s
        self.carry_on = carry_on
        self.unsettled: tuple[float, float] | None = None           # (joint error rad, speed rad/s) on carrying on
        self.gripper_open = gripper_open
        self._gripper_start: tuple[float, float] | None = None      # (time, width) when commanded
        self._last_change: tuple[float, float] | None = None        # (time, width) of the last motion
        self._held: tuple[float, np.ndarray] | None = None       # (since, q) while making no progress
        self.arrived_s: float | None = None
        self.short_by: float | None = None

    def update(self, now_s: float, state: ArmState) -> Update:
        if self.arrived_s is None:
            return self._update_arm(now_s, state)
        return self._update_gripper(now_s, state.gripper_width)

    def _update_arm(self, now_s: float, state: ArmState) -> Update:
        error = float(np.max(np.abs(state.q - self.goal_q)))
        speed = float(np.max(np.abs(state.qd)))
        elapsed = now_s - self.start_s
        ended = elapsed >= self.duration_s
        if not ended or self._held is None or np.max(np.abs(state.q - self._held[1])) > BLOCKED_BAND:
            self._held = (now_s, state.q.copy()) if ended else None
        at_goal = ended and speed <= STILL_VELOCITY and error <= GOAL_TOLERANCE
        blocked = self._held is not None and now_s - self._held[0] >= BLOCKED_STILL_S
        timed_out = elapsed > self.duration_s + self.timeout_s
        if timed_out and self.carry_on and not (at_goal or blocked):
            self.unsettled = (error, speed)
        if at_goal or blocked or self.unsettled:
            self.arrived_s = now_s
            self.short_by = error if error > GOAL_TOLERANCE and not self.unsettled else None
            if self.gripper_open is None:
                return Update(result=topics.SEGMENT_DONE)
            self._gripper_start = self._last_change = (now_s, state.gripper_width)
            return Update(send_gripper=True)
        if timed_out:
            return Update(result=f'{topics.SEGMENT_FAILED}the arm did not come to rest within '
                                 f'{self.timeout_s:.1f} s of the trajectory\'s end (max joint error '
                                 f'{error:.3f} rad, speed {speed:.3f} rad/s)')
        return Update()

    def _update_gripper(self, now_s: float, width: float) -> Update:
        target = panda.GRIPPER_OPEN_WIDTH if self.gripper_open else 0.0
        start_s, start_width = self._gripper_start
        if abs(width - self._last_change[1]) > GRIPPER_MOVED:
            self._last_change = (now_s, width)
        moved = abs(width - start_width) > GRIPPER_MOVED
        if abs(width - target) <= GRIPPER_TOLERANCE or (moved and now_s - self._last_change[0] >= GRIPPER_STILL_S):
            return Update(result=topics.SEGMENT_DONE)
        if now_s - start_s > GRIPPER_TIMEOUT_S:
            action = 'open' if self.gripper_open else 'close'
            return Update(result=f'{topics.SEGMENT_FAILED}the gripper did not {action} within '
                                 f'{GRIPPER_TIMEOUT_S:.0f} s (width {width:.3f} m)')
        return Update()


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
    """

    def __init__(self, policy, needs_points: bool, velocity_scale: float, segment_timeout_s: float,
                 arm_joints=panda.ARM_JOINTS, finger_joints=panda.FINGER_JOINTS,
                 reach_tolerance: tuple[float, float] = (REACH_TOLERANCE_M, REACH_TOLERANCE_DEG),
                 limits: panda.JointLimits = panda.ROBOT_LIMITS['panda'], carry_on_unsettled: bool = False,
                 plan_attempts: int = PLAN_ATTEMPTS):
        self.policy, self.needs_points, self.limits = policy, needs_points, limits
        self.plan_attempts = plan_attempts              # plan_within_reach
        self.carry_on_unsettled = carry_on_unsettled    # SegmentExecution.carry_on
        self.reach_tolerance = reach_tolerance
        self.velocity_scale, self.segment_timeout_s = velocity_scale, segment_timeout_s
        self.arm_joints, self.finger_joints = tuple(arm_joints), tuple(finger_joints)
        self.state: ArmState | None = None
        self.state_stamp_ns = 0
        self.joint_state_problem = ''                # why the last /joint_states was unusable
        self.depth = self.info = None
        self.transforms: dict = {}                   # child frame -> TransformStamped, from /tf_static
        self.gripper_goals: dict[int, bool] = {}     # NBP stamp (ns) -> open
        self.pending: _Pending | None = None
        self.running: tuple[object, SegmentExecution] | None = None    # (NBP stamp, execution)

    # -- observations --------------------------------------------------------------------
    def on_joint_state(self, msg) -> None:
        try:
            state = arm_state(msg, self.arm_joints, self.finger_joints)
        except ValueError as err:    # a partial or another robot's joint state: keep the last good one
            self.joint_state_problem = str(err)
            return
        if self.state is not None and stamp_ns(msg.header.stamp) < self.state_stamp_ns:
            self.depth = None        # the clock restarted (a simulator reset): that frame shows the old scene
        self.state, self.state_stamp_ns = state, stamp_ns(msg.header.stamp)

    def on_depth(self, msg) -> None:
        """Keep the front depth image, unless stamped far ahead of the joint states: a frame of the
        clock before a simulator reset, arriving late."""
        if self.state is None or stamp_ns(msg.header.stamp) <= self.state_stamp_ns + FRAME_LEAD_NS:
            self.depth = msg

    def on_tf_static(self, msg) -> None:
        self.transforms.update({t.child_frame_id: t for t in msg.transforms})

    def on_gripper_goal(self, msg) -> list[Out]:
        try:
            is_open = gripper_goal(msg)
        except ValueError as err:
            return [Out('error', f'ignored a gripper goal: {err}')]
        self.gripper_goals[stamp_ns(msg.header.stamp)] = is_open
        while len(self.gripper_goals) > _KEPT_GRIPPER_GOALS:
            self.gripper_goals.pop(next(iter(self.gripper_goals)))
        return []

    # -- segments -------------------------------------------------------------------------
    def on_nbp(self, msg, now_s: float) -> list[Out]:
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

    def _supersede(self, stamp) -> list[Out]:
        """End the pending or running segment for a newer NBP (``stamp``); one with the same stamp
        is a repeat and ignored. The arm takes the new segment's trajectory from where it is."""
        current = self.pending.nbp.header.stamp if self.pending is not None else (
            self.running[0] if self.running is not None else None)
        if current is None:
            return []
        if stamp_ns(current) == stamp_ns(stamp):
            return [Out('error', f'ignored a repeated NBP for segment {stamp_label(stamp)}')]
        self.pending = self.running = None
        return self._refuse(current, f'superseded by segment {stamp_label(stamp)}')

    def step(self, now_s: float) -> list[Out]:
        """Advance the pending or running segment; call it often (the node's timer)."""
        if self.running is not None:
            return self._follow(now_s)
        if self.pending is None:
            return []
        key = stamp_ns(self.pending.nbp.header.stamp)
        waited = now_s - self.pending.received_s
        unpaired = key not in self.gripper_goals and waited < PAIRING_WAIT_S
        blind = self.needs_points and (self.depth is None or self.info is None)
        starting = (blind or self.state is None) and waited < STARTUP_WAIT_S
        if unpaired or starting:
            return []
        pending, self.pending = self.pending, None
        return self._start(pending, self.gripper_goals.pop(key, None), now_s)

    def _start(self, pending: _Pending, goal_open: bool | None, now_s: float) -> list[Out]:
        stamp = pending.nbp.header.stamp
        if self.state is None:
            problem = f' ({self.joint_state_problem})' if self.joint_state_problem else ''
            return self._refuse(stamp, f'no usable /joint_states received yet{problem}')
        is_open = measured_open(self.state.gripper_width)
        out = []
        if goal_open is None:
            out.append(Out('info', f'segment {stamp_label(stamp)}: no gripper goal with its stamp; '
                                   f'the gripper stays {"open" if is_open else "closed"}'))
        try:
            points = self._points() if self.needs_points else np.zeros((0, 3), np.float32)
            request = segment_request(self.state, is_open, pending.goal, is_open if goal_open is None else goal_open,
                                      points)
            trajectory, plan = plan_segment(self.policy, request, self.arm_joints, self.velocity_scale,
                                            self.reach_tolerance, self.limits, self.plan_attempts)
        except SegmentRefused as err:
            return out + self._refuse(stamp, str(err))
        duration = conversions.duration_to_seconds(trajectory.points[-1].time_from_start)
        act = goal_open if goal_open is not None and goal_open != is_open else None
        self.running = (stamp, SegmentExecution(np.asarray(trajectory.points[-1].positions), duration, now_s,
                                                self.segment_timeout_s, act, self.carry_on_unsettled))
        x, y, z = pending.goal[:3]
        gripper = '' if act is None else f', then {"open" if act else "close"} the gripper'
        return out + [Out('arm', trajectory), Out('info', (
            f'segment {stamp_label(stamp)}: {self.policy.name} to ({x:.3f}, {y:.3f}, {z:.3f}): '
            f'{len(trajectory.points)} points over {duration:.2f} s{gripper}'))]

    def arm_failed(self, stamp, why: str) -> list[Out]:
        """The arm controller refused or aborted segment ``stamp``'s trajectory (the action
        interface): that segment fails with the controller's reason, if it is still running."""
        if self.running is None or stamp_ns(self.running[0]) != stamp_ns(stamp):
            return []
        self.running = None
        return self._refuse(stamp, why, 'segment {} failed')

    def robot_gone(self, why: str) -> list[Out]:
        """The robot stopped answering (Liveness.problem): the pending or running segment fails."""
        current = self.pending.nbp.header.stamp if self.pending is not None else (
            self.running[0] if self.running is not None else None)
        if current is None:
            return []
        self.pending = self.running = None
        return self._refuse(current, why, 'segment {} failed')

    def _follow(self, now_s: float) -> list[Out]:
        stamp, execution = self.running
        update = execution.update(now_s, self.state)
        out = []
        if update.send_gripper:
            out.append(Out('gripper', gripper_command(execution.gripper_open, self.finger_joints)))
        if update.result is not None:
            self.running = None
            kind = 'info' if update.result == topics.SEGMENT_DONE else 'error'
            short = (f' (the arm stopped {execution.short_by:.3f} rad short of the last waypoint: blocked)'
                     if execution.short_by is not None else '')
            if execution.unsettled:
                error, speed = execution.unsettled
                short = (f' (the arm had not come to rest {execution.timeout_s:.1f} s after the trajectory\'s end: '
                         f'carried on {error:.3f} rad from the last waypoint, moving at {speed:.3f} rad/s)')
            out += [Out(kind, f'segment {stamp_label(stamp)}: {update.result}{short}'),
                    Out('result', Header(stamp=stamp, frame_id=update.result))]
        return out

    def _points(self) -> np.ndarray:
        if self.depth is None or self.info is None:
            raise SegmentRefused('no front camera depth and camera_info received yet')
        transform = world_transform(self.transforms, self.depth.header.frame_id)
        try:
            return points_from_messages(self.depth, self.info, transform)
        except ValueError as err:
            raise SegmentRefused(f'front camera unusable: {err}') from None

    def _refuse(self, stamp, reason: str, what: str = 'refused segment {}') -> list[Out]:
        self.gripper_goals.pop(stamp_ns(stamp), None)
        return [Out('error', f'{what.format(stamp_label(stamp))}: {reason}'),
                Out('result', Header(stamp=stamp, frame_id=topics.SEGMENT_FAILED + reason))]
