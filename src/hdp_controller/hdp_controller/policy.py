"""RK-Diffuser and its learned ablations as LowLevelPolicy objects.

  rkd      sample both diffusers, refine the joints onto the poses (the paper's method)
  planner, planner_rrt  (baselines.PlannerPolicy: straight line else RRT-Connect; RRT-Connect only)
  joint    the joint diffuser alone: no distillation at inference, no refinement, no smoothing
  joint_guided  the same, each denoising step's estimate pulled onto the NBP (RKDiffuser.sample's goal_guidance)
  pose_ik  the pose diffuser (smoothed), then IK per waypoint (baselines.PoseIKPolicy)

All three come from one checkpoint, so they see the same conditions.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from hdp_motion import panda
from hdp_learning import checkpoints, distributed

from . import checkpoint
from .low_level import PlanResult, Scene, SegmentRequest, nearest_of_draws, within
from .methods import METHODS, RKD_VARIANTS
from .refine import SMOOTHING_PASSES, goal_error, refine, smooth_poses, track
from .rk_diffuser import RKDiffuser, as_batch

DEFAULT_CHECKPOINT_NAME = 'rk_diffuser_11tasks.pt'      # the eleven-task RK-Diffuser
# The fast sampler: DDIM over FAST_STEPS of the 100 training steps, without
# classifier-free guidance (half the network evaluations). The refinement is the
# same for both samplers: success hangs on it, not on the sampler (validation
# seeds 900-909, oracle NBPs, the earlier Adam refinement: DDIM-10 with 10
# refinement steps 78%, with 50 88%; DDIM-5 unguided 92%; DDPM-100 85%).
FAST_STEPS = 5
FAST_GUIDANCE = 1.0
REFINE_STEPS = 50
# rkd draws again (up to DRAWS samples, keeping the one that ends nearest) when refinement has
# not brought the end onto the NBP: on validation seeds 900-919 it stalled 5 and 22 cm short on
# two open_box segments, a new draw converged, while the refined end of almost every other
# segment is exact (p95 0.0 cm / 0.02 deg). Some NBPs stall in every draw (models/rk_diffuser.md).
DRAWS = 3
# joint_guided's Gauss-Newton steps on the last waypoint at each denoising step.
GOAL_GUIDANCE_STEPS = 10
CONVERGED_M, CONVERGED_DEG = 0.01, 5.0


def default_checkpoint() -> Path:
    """$HDP_MODELS_DIR/rk_diffuser_11tasks.pt, else the repository's models/rk_diffuser_11tasks.pt."""
    return checkpoints.default_path(DEFAULT_CHECKPOINT_NAME)


def conditions(request: SegmentRequest) -> dict:
    """A SegmentRequest -> a batch of one, with quaternion signs as in training:
    the start's w >= 0 and the goal on the start's side (rank 1, as the paper infers)."""
    start, goal = np.array(request.start_pose, dtype=float), np.array(request.goal_pose, dtype=float)
    start[3:] /= np.linalg.norm(start[3:])
    goal[3:] /= np.linalg.norm(goal[3:])
    if start[6] < 0:
        start[3:] *= -1
    if np.dot(start[3:], goal[3:]) < 0:
        goal[3:] *= -1
    return as_batch(dict(q=request.q, qd=request.qd, gripper=[request.gripper_width, float(request.gripper_open)],
                         start_pose=start, goal_pose=goal, rank=[1.0], points=request.points))


class _Sampling:
    """Shared by the learned policies: the model, the sampler, and seeded noise (call n of a
    policy built with seed s draws from seed s + n, so runs repeat; picklable for workers)."""

    def __init__(self, model: RKDiffuser, sampler: str = 'ddpm', steps: int | None = None, seed: int = 0,
                 training_seeds: dict | None = None, guidance: float | None = None, device: str = 'cpu'):
        self.model, self.sampler, self.steps, self.guidance = model.to(device), sampler, steps, guidance
        self.base_seed, self.seed, self.calls, self.device = seed, seed, 0, device
        self.training_seeds = training_seeds

    def reseed(self, episode_seed: int) -> None:
        """Draw from (the policy's seed, ``episode_seed``) on, call 0 first: an evaluation episode
        then plans the same whatever ran before it in the process (low_level.start_episode)."""
        self.seed = int(np.random.SeedSequence([self.base_seed, episode_seed]).generate_state(1)[0])
        self.calls = 0

    def _sample(self, request: SegmentRequest, which, goal_guidance: int = 0) -> dict:
        """The samples on the CPU, wherever the model runs (refinement and IK run there)."""
        generator = torch.Generator().manual_seed(self.seed + self.calls)
        self.calls += 1
        batch = {k: v.to(self.device) for k, v in conditions(request).items()}
        out = self.model.sample(batch, self.sampler, self.steps, self.guidance, generator, which, goal_guidance)
        return {k: v.cpu() for k, v in out.items()}


class PoseSampler(_Sampling):
    """The pose diffuser alone, as PoseIKPolicy's pose_sampler, smoothed as RK-Diffuser's
    refinement smooths it (the two then differ only in IK against refinement)."""

    def __call__(self, request: SegmentRequest) -> np.ndarray:
        return smooth_poses(self._sample(request, ('pose',))['poses'], SMOOTHING_PASSES)[0].numpy()


class RKDPolicy(_Sampling):
    name = 'rkd'

    def __init__(self, *args, refine_steps: int = REFINE_STEPS, limits: panda.JointLimits = panda.ROBOT_LIMITS['panda'],
                 draws: int = DRAWS, track_fallback: bool = True, name: str = 'rkd', **kwargs):
        super().__init__(*args, **kwargs)
        self.refine_steps, self.limits = refine_steps, limits      # the robot's: refinement stays inside
        self.draws, self.track_fallback, self.name = draws, track_fallback, name

    def plan(self, request: SegmentRequest, scene: Scene | None = None) -> PlanResult:
        """Sample, refine; again (up to ``draws`` in all) while the refined end misses the NBP by
        more than CONVERGED_M / CONVERGED_DEG. If none converges and ``track_fallback``, the nearest
        draw's poses are tracked from where the arm is (``_from_start``), kept if that ends nearer.
        extras['draws'] says how many draws it took, extras['from_start'] whether the plan was tracked."""
        goal, tolerance = torch.as_tensor(conditions(request)['goal_pose']), (CONVERGED_M, CONVERGED_DEG)
        plan, draws = nearest_of_draws(lambda: self._plan_once(request, goal), _goal_miss, tolerance, self.draws)
        from_start = False
        if self.track_fallback and not within(_goal_miss(plan), tolerance):
            again = self._from_start(request, plan, goal)
            from_start = _goal_miss(again) < _goal_miss(plan)
            plan = again if from_start else plan
        plan.extras.update(draws=draws, from_start=from_start)
        return plan

    def _plan_once(self, request: SegmentRequest, goal: torch.Tensor) -> PlanResult:
        started = time.perf_counter()
        out = self._sample(request, ('pose', 'joint'))
        sampled = time.perf_counter()
        joints = refine(out['joints'], out['poses'], steps=self.refine_steps, limits=self.limits)
        return _refined_plan(joints, out['poses'], goal, {
            'unrefined_joints': out['joints'][0].numpy(), 'sample_s': sampled - started,
            'refine_s': time.perf_counter() - sampled})

    def _from_start(self, request: SegmentRequest, nearest: PlanResult, goal: torch.Tensor) -> PlanResult:
        """The nearest draw's poses tracked from the start configuration (refine.track). A joint
        sample that stalls in every draw lies in an arm configuration that cannot reach its NBP
        (open_box validation seed 936: every draw ends 6 cm off with joint 6 at its limit), while
        the arm's own configuration, carried along the pose path, reaches it exactly."""
        started = time.perf_counter()
        poses = torch.as_tensor(nearest.poses)[None]
        joints = track(torch.as_tensor(request.q, dtype=torch.float32)[None], poses, limits=self.limits)
        return _refined_plan(joints, poses, goal, dict(nearest.extras, refine_s=time.perf_counter() - started))


def _refined_plan(joints: torch.Tensor, poses: torch.Tensor, goal: torch.Tensor, extras: dict) -> PlanResult:
    """joints, poses (1, T, 7) -> a PlanResult with how far the end lands from ``goal``."""
    translation, rotation = goal_error(joints, goal)
    return PlanResult(joints[0].numpy(), poses=poses[0].numpy(), extras=dict(
        extras, goal_error_m=float(translation[0]), goal_error_deg=float(np.degrees(rotation[0].item()))))


def _goal_miss(plan: PlanResult) -> tuple[float, float]:
    return plan.extras['goal_error_m'], plan.extras['goal_error_deg']



class JointDiffusionPolicy(_Sampling):
    def __init__(self, *args, goal_guidance: int = 0, **kwargs):
        super().__init__(*args, **kwargs)
        self.goal_guidance = goal_guidance
        self.name = 'joint_guided' if goal_guidance else 'joint'

    def plan(self, request: SegmentRequest, scene: Scene | None = None) -> PlanResult:
        joints = self._sample(request, ('joint',), self.goal_guidance)['joints']
        translation, rotation = goal_error(joints, torch.as_tensor(conditions(request)['goal_pose']))
        return PlanResult(joints[0].numpy(), extras={'goal_error_m': float(translation[0]),
                                                     'goal_error_deg': float(np.degrees(rotation[0].item()))})


def load_policy(method: str, checkpoint_path=None, sampler: str = 'ddpm', steps: int | None = None,
                seed: int = 0, guidance: float | None = None, refine_steps: int = REFINE_STEPS,
                limits: panda.JointLimits = panda.ROBOT_LIMITS['panda'], device: str = 'cpu', draws: int = DRAWS):
    """A LowLevelPolicy by name; learned ones from ``checkpoint_path`` (default: the released one).
    ``limits``: the robot's joint limits, which rkd's refinement keeps to. ``device``: where the
    diffusers sample (distributed.torch_device checks it); refinement stays on the CPU.

    sampler 'ddpm' runs all 100 steps with the checkpoint's guidance; 'ddim' defaults to
    FAST_STEPS with FAST_GUIDANCE. ``steps`` and ``guidance`` override those defaults. ``draws``:
    the samples per segment at most of rkd and rkd_redraw (RKDPolicy.plan); rkd_single draws once
    (methods.RKD_VARIANTS).
    """
    if method not in METHODS:
        raise ValueError(f'unknown low-level method {method!r}; choose from {", ".join(METHODS)}')
    if method in ('planner', 'planner_rrt', 'pose_ik'):
        from .baselines import PlannerPolicy, PoseIKPolicy   # they plan: PyBullet and OMPL, loaded only here
    if method in ('planner', 'planner_rrt'):
        return PlannerPolicy(straight_first=method == 'planner')
    model, payload = checkpoint.load_model(checkpoint_path or default_checkpoint())
    fast = sampler == 'ddim'
    if guidance is None and fast:
        guidance = FAST_GUIDANCE
    common = dict(sampler=sampler, steps=steps or (FAST_STEPS if fast else None), seed=seed,
                  guidance=guidance, training_seeds=payload.get('training_seeds'), device=distributed.torch_device(device))
    if method in RKD_VARIANTS:
        return RKDPolicy(model, refine_steps=refine_steps, limits=limits, draws=1 if method == 'rkd_single' else draws,
                         track_fallback=method == 'rkd', name=method, **common)
    if method in ('joint', 'joint_guided'):
        return JointDiffusionPolicy(model, goal_guidance=GOAL_GUIDANCE_STEPS if method == 'joint_guided' else 0, **common)
    return PoseIKPolicy(PoseSampler(model, **common), training_seeds=common['training_seeds'])
