"""One instruction's episode as seen from outside the graph.

Per segment the time splits into observe + predict (the previous result, or the instruction,
-> the NBP), controller (NBP -> JointTrajectory) and execution (trajectory -> segment result),
all on the demo's wall clock, so every stage includes the hops between processes a user sees.
"""

from __future__ import annotations

import dataclasses

import numpy as np

STAGES = ('observe_predict_s', 'controller_s', 'execution_s')


@dataclasses.dataclass
class Segment:
    """One NBP and what became of it; times are seconds since the instruction."""
    index: int
    key: int                                   # the NBP's stamp, ns
    xyz: tuple
    gripper: str | None                        # 'open' | 'close'; None: no gripper goal with its stamp
    nbp_s: float
    observe_predict_s: float
    trajectory_s: float | None = None
    trajectory_points: int = 0
    trajectory_duration_s: float | None = None  # its time_from_start: sim time
    result_s: float | None = None
    result: str | None = None

    @property
    def controller_s(self) -> float | None:
        """NBP -> trajectory; NBP -> result when the controller refused (no trajectory)."""
        end = self.trajectory_s if self.trajectory_s is not None else self.result_s
        return None if end is None else end - self.nbp_s

    @property
    def execution_s(self) -> float | None:
        if self.trajectory_s is None or self.result_s is None:
            return None
        return self.result_s - self.trajectory_s

    def to_dict(self) -> dict:
        out = {**dataclasses.asdict(self), 'controller_s': self.controller_s, 'execution_s': self.execution_s}
        out['xyz'] = [round(v, 4) for v in self.xyz]
        return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


class EpisodeLog:
    """One instruction's segments as seen from outside the graph, plus the front camera frames
    and arm joint positions for the GIF and plot. ``t`` arguments are the caller's clock
    (seconds); everything stored is relative to ``start``, the instruction's time."""

    def __init__(self, start: float):
        self.start = start
        self.segments: list[Segment] = []
        self.success_s: float | None = None
        self.frames: list[tuple[float, float, np.ndarray]] = []   # (t, sim stamp s, rgb)
        self.joints: list[tuple[float, float, np.ndarray]] = []   # (t, sim stamp s, (7,) rad)
        self.status: list[tuple[float, str]] = []             # (t, /hdp/status line)
        self.outcomes: list = []                                # hdp_msgs_py.outcome.Outcome heard since start
        self._goals: dict[int, bool] = {}      # gripper goals that came before their NBP
        self._mark = 0.0                       # when the planner's current observe + predict began

    def _t(self, t: float) -> float:
        return t - self.start

    @property
    def open_segment(self) -> Segment | None:
        last = self.segments[-1] if self.segments else None
        return last if last is not None and last.result is None else None

    def gripper_goal(self, key: int, is_open: bool) -> None:
        segment = next((s for s in self.segments if s.key == key), None)
        if segment is None:
            self._goals[key] = is_open
        else:
            segment.gripper = 'open' if is_open else 'close'

    def nbp(self, t: float, key: int, xyz) -> Segment:
        goal = self._goals.pop(key, None)
        segment = Segment(len(self.segments) + 1, key, tuple(float(v) for v in xyz),
                          None if goal is None else ('open' if goal else 'close'),
                          self._t(t), self._t(t) - self._mark)
        self.segments.append(segment)
        return segment

    def trajectory(self, t: float, points: int, duration_s: float) -> Segment | None:
        """The arm trajectory of the open segment (the controller plans one segment at a time)."""
        segment = self.open_segment
        if segment is not None and segment.trajectory_s is None:
            segment.trajectory_s, segment.trajectory_points = self._t(t), points
            segment.trajectory_duration_s = duration_s
        return segment

    def result(self, t: float, key: int, outcome: str) -> Segment | None:
        """The segment this result answers (by its stamp), now finished; None for another's."""
        segment = next((s for s in self.segments if s.key == key and s.result is None), None)
        if segment is not None:
            segment.result_s, segment.result = self._t(t), outcome
            self._mark = segment.result_s
        return segment

    def success(self, t: float) -> None:
        if self.success_s is None:
            self.success_s = self._t(t)


def segment_line(segment: Segment) -> str:
    """One line per finished segment, as `hdp demo` prints it."""
    x, y, z = segment.xyz

    def seconds(value):
        return '-' if value is None else f'{value:.2f} s'
    trajectory = ('' if segment.trajectory_s is None else
                  f', {segment.trajectory_points} points over {segment.trajectory_duration_s:.2f} s sim')
    return (f'segment {segment.index}: NBP ({x:.3f}, {y:.3f}, {z:.3f}) gripper {segment.gripper or "unchanged"} '
            f'-> {segment.result} at {segment.result_s:.1f} s | observe+predict {seconds(segment.observe_predict_s)}, '
            f'controller {seconds(segment.controller_s)}, execution {seconds(segment.execution_s)}{trajectory}')




def stall_report(log: EpisodeLog, t: float, status_lines: int = 5) -> list[str]:
    """Where an episode without an outcome stands at time ``t`` (the caller's clock): which node
    it waits on, the robot's last joint state and planner_node's last status lines."""
    now = log._t(t)
    segment = log.open_segment
    if not log.segments:
        lines = ['no NBP from planner_node since the instruction']
    elif segment is None:
        last = log.segments[-1]
        lines = [f'segment {last.index} ended ({last.result}) at {last.result_s:.1f} s; no NBP from planner_node since']
    elif segment.trajectory_s is None:
        lines = [f'segment {segment.index}: NBP at {segment.nbp_s:.1f} s, no trajectory from controller_node since']
    else:
        lines = [f'segment {segment.index}: trajectory at {segment.trajectory_s:.1f} s, '
                 f'no segment result since']
    lines.append(f'last /joint_states at {log.joints[-1][0]:.1f} s of {now:.1f} s' if log.joints
                 else 'no /joint_states since the instruction')
    lines += [f'/hdp/status {when:6.1f} s: {text}' for when, text in log.status[-status_lines:]]
    return lines
