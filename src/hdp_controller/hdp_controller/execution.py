"""Following one published segment, as controller_node watches it: the arm's arrival, then the
gripper action, then the result ('done' or 'failed: <why>'). Only the joint states decide; the
arm controller's own word (an action's result) is advisory.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hdp_motion import panda
from hdp_msgs_py import topics

from .inputs import ArmState

GOAL_TOLERANCE = 0.02          # rad: max joint error at the last waypoint that counts as arrived
STILL_VELOCITY = 0.02          # rad/s: max joint speed that counts as still (the sim settles < 0.01)
BLOCKED_STILL_S = 0.5          # s without progress short of the last waypoint after the trajectory's end: blocked
BLOCKED_BAND = 0.005           # rad every joint stays within meanwhile (pressed on a contact, the arm jitters)
GRIPPER_TOLERANCE = 0.002      # m of width from the target that counts as reached
GRIPPER_MOVED = 0.001          # m of width change that shows the fingers responded
GRIPPER_STILL_S = 0.2          # s without width change after moving: closed on an object
GRIPPER_TIMEOUT_S = 3.0        # s for the fingers to reach the target or stop
PREEMPTED = 'preempted by another command'      # a segment's failure reason (after 'failed: ')


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
