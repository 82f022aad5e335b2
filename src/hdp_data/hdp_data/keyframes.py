"""Keyframe discovery: the one implementation both HDP levels use.

HDP's maintainers found that the high-level agent and RK-Diffuser must be
trained on the same keyframes or the hierarchy fails, so every consumer calls
``discover_keyframes`` with the same ``DEFAULT_STOPPING_DELTA``.

The heuristic is ARM/PerAct's. Frame i (> 0) is a keyframe when
  * the gripper open state changes at i (differs from frame i-1), or
  * it is the last frame, or
  * the arm has stopped: every |joint velocity| <= stopping_delta, the gripper
    state is the same over frames i-2..i+1, and the arm has moved since the
    previous keyframe, counting only frames after a refractory buffer of
    ``stopped_buffer`` frames that follows every keyframe;
and the second-to-last frame is never a keyframe.

Two departures from PerAct's code, both because our joint states come at
>= 100 Hz instead of RLBench's 20 Hz:
  * "moved since the previous keyframe": PerAct re-arms its 4-frame buffer
    after every stop, so a rest of 50 frames at 100 Hz would give ten
    keyframes at one pose. Here a rest gives one keyframe, at its first
    frame, however long it lasts; the buffer keeps velocity noise around
    the threshold just after a keyframe from counting as motion. The rest
    the demo starts in belongs to frame 0.
  * The gripper window i-2..i+1 starts at i = 2 (PerAct's indices -1 and -2
    wrap around to the end of the demo).
"""

from __future__ import annotations

import operator

import numpy as np

# HDP's value (PerAct uses 0.1 rad/s, which misses slow approach motions).
DEFAULT_STOPPING_DELTA = 0.01     # rad/s
# PerAct's refractory period after a keyframe, in frames.
DEFAULT_STOPPED_BUFFER = 4


def discover_keyframes(joint_velocities, gripper_open, stopping_delta: float = DEFAULT_STOPPING_DELTA,
                       stopped_buffer: int = DEFAULT_STOPPED_BUFFER) -> list[int]:
    """Keyframe indices of one demo, sorted, without index 0.

    joint_velocities: (T, J) rad/s, one row per frame (J = 7 for the Panda arm).
    gripper_open: (T,) truthy where the gripper is open (commanded state).
    Returns [] for T <= 1; otherwise the last index T-1 is always included.
    Raises ValueError on mismatched lengths, wrong shapes or non-finite velocities.
    """
    velocities = np.asarray(joint_velocities, dtype=np.float64)
    gripper = np.asarray(gripper_open).astype(bool)
    if velocities.ndim != 2 or gripper.ndim != 1:
        raise ValueError(f'need joint_velocities (T, J) and gripper_open (T,), got shapes '
                         f'{velocities.shape} and {gripper.shape}')
    if len(velocities) != len(gripper):
        raise ValueError(f'joint_velocities has {len(velocities)} frames, gripper_open {len(gripper)}')
    if not np.all(np.isfinite(velocities)):
        raise ValueError('joint_velocities contains NaN or infinity')
    if stopping_delta < 0 or stopped_buffer < 0:
        raise ValueError(f'stopping_delta and stopped_buffer must be >= 0, '
                         f'got {stopping_delta} and {stopped_buffer}')
    n = len(gripper)
    if n <= 1:
        return []

    still = np.all(np.abs(velocities) <= stopping_delta, axis=1)   # PerAct: np.allclose(v, 0, atol=delta)
    changed = np.zeros(n, dtype=bool)
    changed[1:] = gripper[1:] != gripper[:-1]
    # gripper unchanged over i-2..i+1 <=> no change at i-1, i, i+1
    steady = np.zeros(n, dtype=bool)
    steady[2:n - 1] = ~(changed[1:n - 2] | changed[2:n - 1] | changed[3:n])

    keyframes, previous, moved = [], 0, False
    for i in range(1, n):
        if i - previous > stopped_buffer:
            moved |= not still[i]
        stopped = moved and still[i] and steady[i]
        if changed[i] or stopped or i == n - 1:
            keyframes.append(i)
            previous, moved = i, False
    # The second-to-last frame is too close to the last one to be a goal of its own.
    return [k for k in keyframes if k != n - 2]


def segments(keyframes, include_start: bool = True) -> list[tuple[int, int]]:
    """Consecutive (start, end) index pairs between keyframes.

    With include_start, index 0 is prepended (unless already there), so the
    first segment runs from the demo's first frame to its first keyframe:
    segments([100, 250, 299]) == [(0, 100), (100, 250), (250, 299)].
    Raises ValueError unless keyframes are strictly increasing indices >= 0
    (TypeError for non-integers).
    """
    points = [operator.index(k) for k in keyframes]
    if any(k < 0 for k in points) or any(b <= a for a, b in zip(points, points[1:])):
        raise ValueError(f'keyframes must be strictly increasing indices >= 0, got {points}')
    if include_start and (not points or points[0] != 0):
        points.insert(0, 0)
    return list(zip(points, points[1:]))
