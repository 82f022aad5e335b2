"""Trajectory timing: when to be at each waypoint of a joint path, within the Panda's limits.

Plain numpy, so robot-side code (controller_node) times its paths without the
planner's PyBullet and OMPL. Paths are (N, 7) arrays in radians, times (N,) seconds.
"""

import math

import numpy as np

from .panda import ACCELERATION_LIMITS, VELOCITY_LIMITS

# rad/s^2 per joint: 60% of what the simulated arm can follow (world.ACCELERATION_LIMITS), as
# the spline through the waypoints accelerates more than the profile it samples.
DEFAULT_ACCELERATION = 0.3 * ACCELERATION_LIMITS
_MIN_DT = 1e-3            # s: the time given to a zero-length segment
# Round a turn the spline through the waypoints accelerates up to about four times speed^2 x
# curvature (its velocities there are central differences across the turn).
_TURN_MARGIN = 4.0


def time_parameterize(path, velocity_scale=1.0, acceleration=DEFAULT_ACCELERATION,
                      velocity_limits=VELOCITY_LIMITS):
    """time_from_start (N,) for a joint path (N, 7): 0 first, strictly increasing.

    Along the path the speed follows a trapezoidal profile that starts and
    ends at rest, with no joint exceeding velocity_limits * velocity_scale
    between consecutive waypoints nor `acceleration` (rad/s^2, scalar or (7,))
    along a segment. Where the path turns, the speed is also capped so that
    no joint's acceleration round the turn (speed^2 x curvature) exceeds
    `acceleration`, the curvature spread over the two segments either side:
    a dense path turns gently at speed, and a planner's sharp corner is taken
    slowly. Streamed as a cubic spline through the waypoints at the
    velocities of `path_velocities`, a planner's timed path is followed by
    the simulated arm to within a few mrad. A path that zig-zags between
    waypoints is slowed at every reversal but followed less closely, as the
    spline stops the joint at each one.
    """
    path = np.asarray(path, dtype=float)
    acceleration = np.broadcast_to(np.asarray(acceleration, dtype=float), (7,))
    step = np.diff(path, axis=0)                             # (N-1, 7)
    dq = np.abs(step)
    length = np.linalg.norm(dq, axis=1)                      # (N-1,)
    moving = length > 0
    # Path speed and acceleration at which the most loaded joint hits its
    # limit, and the change of speed^2 a segment allows (none when empty).
    v_cap = np.full(len(dq), np.inf)
    a_cap = np.full(len(dq), np.inf)
    v_cap[moving] = length[moving] / np.max(dq[moving] / (np.asarray(velocity_limits) * velocity_scale), axis=1)
    a_cap[moving] = length[moving] / np.max(dq[moving] / acceleration, axis=1)
    reach = np.zeros(len(dq))
    reach[moving] = 2 * a_cap[moving] * length[moving]
    # Speeds at the waypoints: at rest at both ends, capped by both adjacent
    # segments and by the turn between the moving segments either side, and
    # reachable under the acceleration cap (forward, then back).
    speed = np.zeros(len(path))
    speed[1:-1] = np.minimum(v_cap[:-1], v_cap[1:])
    moves = np.flatnonzero(moving)
    for before, after in zip(moves[:-1], moves[1:]):
        turn = np.abs(step[after] / length[after] - step[before] / length[before])    # (7,)
        curvature = turn / ((length[before] + length[after]) / 2)
        with np.errstate(divide='ignore'):
            speed[after] = min(speed[after], np.sqrt(np.min(acceleration / (_TURN_MARGIN * curvature))))
    for k in range(len(dq)):
        speed[k + 1] = min(speed[k + 1], math.sqrt(speed[k] ** 2 + reach[k]))
    for k in reversed(range(len(dq))):
        speed[k] = min(speed[k], math.sqrt(speed[k + 1] ** 2 + reach[k]))
    dt = np.full(len(dq), _MIN_DT)
    for k in moves:
        va, vb, a, L = speed[k], speed[k + 1], a_cap[k], length[k]
        peak = min(v_cap[k], math.sqrt(a * L + (va ** 2 + vb ** 2) / 2))
        ramps = (2 * peak ** 2 - va ** 2 - vb ** 2) / (2 * a)    # distance spent ramping
        dt[k] = max(_MIN_DT, (2 * peak - va - vb) / a + (L - ramps) / peak)
    return np.concatenate([[0.0], np.cumsum(dt)])


def path_velocities(path, times, velocity_scale=1.0, velocity_limits=VELOCITY_LIMITS):
    """Joint velocities (N, 7) at the waypoints of a timed path (N, 7), times (N,):
    central differences, zero at both ends, clipped to velocity_limits * velocity_scale."""
    velocities = np.gradient(np.asarray(path, dtype=float), times, axis=0)
    velocities[[0, -1]] = 0.0
    limit = np.asarray(velocity_limits) * velocity_scale
    return np.clip(velocities, -limit, limit)


def resample_path(path, n):
    """n (>= 2) waypoints (n, 7) evenly spaced by joint-space arc length."""
    path = np.asarray(path, dtype=float)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    if arc[-1] == 0:
        return np.repeat(path[:1], n, axis=0)
    targets = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(targets, arc, path[:, j]) for j in range(path.shape[1])], axis=1)
