"""Execute JointTrajectory goals the way ros2_controllers' joint_trajectory_controller does.

- header.stamp 0 means "start now"; a stamp in the future waits for it.
- time_from_start strictly increasing; the first segment starts from where
  the arm is when the trajectory arrives.
- a new trajectory replaces the one running.
- one point at time_from_start 0 holds that position: JTC's own hold command (set_hold_position),
  which a client sends to stop the arm on the topic interface. An empty trajectory (no points)
  is refused, as JTC refuses it since ros2_controllers#902 (2024; Humble and Jazzy).
- positions are interpolated linearly, or with cubic Hermite splines when
  every point carries velocities.

Anything the Panda cannot do (unknown or missing joints, NaN, times not
increasing, positions outside the joint limits, speeds over the velocity
limits) is refused with a ValueError that says why, before anything moves.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from hdp_motion import panda
from hdp_msgs_py import conversions

VELOCITY_TOLERANCE = 1.02   # allow 2 % over the limit for rounding in time stamps


@dataclasses.dataclass
class ActiveTrajectory:
    start_time: float          # s, on the follower's clock
    times: np.ndarray          # (T+1,) s from start; index 0 is the arm's state on arrival
    positions: np.ndarray      # (T+1, 7) in panda.ARM_JOINTS order
    velocities: np.ndarray | None

    @property
    def end_time(self) -> float:
        return self.start_time + self.times[-1]

    def sample(self, now: float) -> np.ndarray:
        """Commanded joint positions (7,) at ``now``; holds the last point after the end."""
        if len(self.times) == 1:                     # one point at time 0: hold it
            return self.positions[0].copy()
        t = np.clip(now - self.start_time, 0.0, self.times[-1])
        i = int(np.clip(np.searchsorted(self.times, t, side='right') - 1, 0, len(self.times) - 2))
        t0, t1 = self.times[i], self.times[i + 1]
        s = (t - t0) / (t1 - t0)
        p0, p1 = self.positions[i], self.positions[i + 1]
        if self.velocities is None:
            return p0 + s * (p1 - p0)
        h = t1 - t0
        v0, v1 = self.velocities[i] * h, self.velocities[i + 1] * h
        return ((2 * s**3 - 3 * s**2 + 1) * p0 + (s**3 - 2 * s**2 + s) * v0
                + (-2 * s**3 + 3 * s**2) * p1 + (s**3 - s**2) * v1)


def accept(msg, now: float, current: np.ndarray, joint_names=panda.ARM_JOINTS) -> ActiveTrajectory:
    """Validate a trajectory_msgs/JointTrajectory and plan its execution from ``current`` (7,)."""
    if not msg.points:
        raise ValueError('trajectory has no points')
    names, positions, times, velocities = conversions.parse_joint_trajectory(msg)
    unknown = sorted(set(names) - set(joint_names))
    missing = sorted(set(joint_names) - set(names))
    if unknown or missing:
        raise ValueError(f'joints must be exactly {list(joint_names)}; '
                         f'unknown: {unknown}, missing: {missing}')
    order = [names.index(n) for n in joint_names]
    positions = positions[:, order]
    velocities = velocities[:, order] if velocities is not None else None
    low = np.nonzero(positions < panda.LOWER - 1e-9)
    high = np.nonzero(positions > panda.UPPER + 1e-9)
    for rows, cols, side in ((*low, 'below'), (*high, 'above')):
        if len(rows):
            i, j = int(rows[0]), int(cols[0])
            raise ValueError(f'point {i}: {joint_names[j]} = {positions[i, j]:.4f} rad is {side} its limit '
                             f'[{panda.LOWER[j]:.4f}, {panda.UPPER[j]:.4f}]')
    if velocities is not None and np.any(np.abs(velocities) > panda.VELOCITY_LIMITS * VELOCITY_TOLERANCE):
        i, j = np.argwhere(np.abs(velocities) > panda.VELOCITY_LIMITS * VELOCITY_TOLERANCE)[0]
        raise ValueError(f'point {i}: {joint_names[j]} velocity {velocities[i, j]:.3f} rad/s exceeds '
                         f'{panda.VELOCITY_LIMITS[j]} rad/s')

    stamp = conversions.time_to_seconds(msg.header.stamp)
    start = now if stamp == 0.0 else stamp
    # The first segment runs from the arm's position on arrival to point 0.
    full_times = np.concatenate([[0.0], times]) if times[0] > 0 else times.copy()
    full_positions = np.vstack([current, positions]) if times[0] > 0 else positions.copy()
    if times[0] == 0 and np.max(np.abs(positions[0] - current)) > 0.05:
        raise ValueError('point 0 has time_from_start 0 but is '
                         f'{np.max(np.abs(positions[0] - current)):.3f} rad from the current position')
    full_velocities = None
    if velocities is not None:
        full_velocities = np.vstack([np.zeros(7), velocities]) if times[0] > 0 else velocities.copy()
    implied = np.abs(np.diff(full_positions, axis=0)) / np.diff(full_times)[:, None]
    too_fast = implied > panda.VELOCITY_LIMITS * VELOCITY_TOLERANCE
    if np.any(too_fast):
        i, j = np.argwhere(too_fast)[0]
        raise ValueError(f'segment {i}->{i + 1}: {joint_names[j]} would move at {implied[i, j]:.3f} rad/s, '
                         f'over its {panda.VELOCITY_LIMITS[j]} rad/s limit')
    return ActiveTrajectory(start, full_times, full_positions, full_velocities)
