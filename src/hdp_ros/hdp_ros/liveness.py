"""Is the robot still there? Judged on the wall clock, which keeps running when the robot does not.

A node on sim time whose simulator dies sees its clock stop with it: its own timeouts never
fire. planner_node and controller_node therefore also run a steady (wall-clock) timer that asks
Liveness whether /joint_states still arrive and whether the node's clock still moves.
"""

from __future__ import annotations

from hdp_msgs_py import topics

ROBOT_HINT = 'is sim_bridge_node (or the robot driver) running?'   # what to check when it is silent


class Liveness:
    """Last /joint_states arrival and last clock movement, both in wall-clock seconds.

    timeout_s: how long either may stay silent before problem() names it.
    """

    def __init__(self, timeout_s: float):
        self.set_timeout(timeout_s)
        self.heard_s: float | None = None        # wall time of the last /joint_states
        self._clock: float | None = None         # the node's clock when last seen to change
        self._clock_moved_s: float | None = None
        self._checked_s: float | None = None     # wall time of the last stalled() call

    def set_timeout(self, timeout_s: float) -> None:
        """Change timeout_s; the next problem() and stalled() judge by it."""
        if not timeout_s > 0:
            raise ValueError(f'a liveness timeout must be > 0 s, got {timeout_s}')
        self.timeout_s = timeout_s

    def heard(self, wall_s: float) -> None:
        """A /joint_states message arrived."""
        self.heard_s = wall_s

    def excuse(self, wall_s: float) -> None:
        """The node was busy (planning) until ``wall_s`` and could not listen: silence before that
        does not count. Messages that queued meanwhile arrive after it."""
        if self.heard_s is not None:
            self.heard_s = max(self.heard_s, wall_s)
        if self._clock_moved_s is not None:
            self._clock_moved_s = max(self._clock_moved_s, wall_s)

    def stalled(self, wall_s: float) -> str | None:
        """Why the node itself was silent, when it did not run for longer than timeout_s since the
        last call (it was stopped, or starved of CPU), else None. That silence is the node's own,
        not the robot's: it is excused, and messages queued meanwhile arrive next. Call it from the
        same periodic timer as problem(), first."""
        gap = None if self._checked_s is None else wall_s - self._checked_s
        self._checked_s = wall_s
        if gap is None or gap <= self.timeout_s:
            return None
        self.excuse(wall_s)
        return (f'this node itself did not run for {gap:.1f} s (stopped or starved of CPU); '
                'not blaming the robot for that silence')

    def problem(self, wall_s: float, clock_s: float) -> str | None:
        """Why the robot looks gone (for the node's status and results), or None.

        clock_s: the node's clock now (sim time under use_sim_time). Call it periodically even
        when idle, so that the clock's movement is tracked.
        """
        if clock_s != self._clock or self._clock_moved_s is None:
            self._clock, self._clock_moved_s = clock_s, wall_s
        if self.heard_s is not None and wall_s - self.heard_s > self.timeout_s:
            return f'no {topics.JOINT_STATES} for {wall_s - self.heard_s:.1f} s (wall clock): ' + ROBOT_HINT
        if wall_s - self._clock_moved_s > self.timeout_s:
            return (f'the node\'s clock has not moved for {wall_s - self._clock_moved_s:.1f} s (wall clock): '
                    f'under use_sim_time, is {topics.CLOCK} published?')
        return None
