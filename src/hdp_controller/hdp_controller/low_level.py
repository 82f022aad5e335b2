"""What every low-level method takes and returns: one segment, current state to NBP.

RK-Diffuser and the baselines (planner, pose diffusion + IK, joint
diffusion) all implement ``LowLevelPolicy``, so the evaluation harness and
controller_node run them through one execution path.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np

HORIZON = 64                 # waypoints per generated trajectory (the paper's T)


@dataclasses.dataclass(frozen=True)
class SegmentRequest:
    """The state at the start of a segment and its goal (the next-best pose).

    q, qd: (7,) joint positions (rad) and velocities (rad/s), ARM_JOINTS order.
    gripper_width: m between the fingers. gripper_open: the commanded state.
    start_pose, goal_pose: (7,) world-frame xyz (m) + quaternion xyzw of
    panda_grasptarget. points: (N, 3) float32 world-frame front-camera
    points cropped to the workspace (see observation.workspace_points).
    goal_gripper_open: the gripper action applied after the segment.
    """
    q: np.ndarray
    qd: np.ndarray
    gripper_width: float
    gripper_open: bool
    start_pose: np.ndarray
    goal_pose: np.ndarray
    points: np.ndarray
    goal_gripper_open: bool = True


@dataclasses.dataclass
class Scene:
    """Collision geometry a planner may check against: a PyBullet client id,
    the robot body, obstacle bodies, and (body, link) held in the gripper."""
    client: int
    robot: int
    obstacles: tuple = ()
    attached: tuple | None = None


@dataclasses.dataclass
class PlanResult:
    """joints: (K, 7) joint waypoints from q to the goal, or None on failure.

    failure: why there is no trajectory ('ik_error', 'no_path', ...).
    ik_error: True when the method found no joint solution within tolerance
    or limits (the paper's IK-error column). poses: (HORIZON, 7) the pose
    trajectory the method generated, when it has one (for plots).
    """
    joints: np.ndarray | None
    failure: str | None = None
    ik_error: bool = False
    poses: np.ndarray | None = None
    extras: dict = dataclasses.field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.joints is not None


class LowLevelPolicy(Protocol):
    name: str

    def plan(self, request: SegmentRequest, scene: Scene | None = None) -> PlanResult:
        ...


def start_episode(policy: LowLevelPolicy, seed: int) -> None:
    """Before an evaluation episode: a policy that draws noise (one with ``reseed``) draws this
    episode's from its seed. Otherwise its noise would run on from whatever episodes the process
    planned before, and an episode's result would change with the episodes run beside it (the
    other rows and phrasings of a table, or how torchrun shards them)."""
    reseed = getattr(policy, 'reseed', None)
    if reseed is not None:
        reseed(seed)


def within(miss: tuple[float, float], tolerance: tuple[float, float]) -> bool:
    """(m, deg) miss inside (m, deg) tolerance, both parts."""
    return miss[0] <= tolerance[0] and miss[1] <= tolerance[1]


def nearest_of_draws(draw, error, tolerance: tuple[float, float] | None, attempts: int):
    """(plan, draws): ``draw()`` up to ``attempts`` times until ``error(plan)`` (m, deg) is within
    ``tolerance``, else the draw that ended nearest. A plan that failed outright comes back at
    once, as does any plan when the tolerance is None."""
    best = None
    for draws in range(1, max(1, attempts) + 1):
        plan = draw()
        if not plan.ok or tolerance is None:
            return plan, draws
        miss = error(plan)
        if best is None or miss < best[1]:
            best = (plan, miss)
        if within(miss, tolerance):
            break
    return best[0], draws
