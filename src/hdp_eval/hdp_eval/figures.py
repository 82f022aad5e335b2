"""`hdp plot low-level`: the paper's Fig. 4 for one episode.

RK-Diffuser runs an oracle episode (low_level_eval.oracle_episode); at every
segment the planner baseline also plans from the same state (not executed).
The figure shows one segment (by default the last: the lid's arc in
open_box): the pose diffuser's
trajectory, the joint diffuser's trajectory through FK, the refined joint
trajectory through FK, and the planner's path through FK; and beside it
each waypoint's distance to the pose trajectory before and after refinement.
"""

from __future__ import annotations

import numpy as np
import torch

from hdp_controller.baselines import PlannerPolicy
from hdp_motion.kinematics import fk_pose
from hdp_sim_bridge import experts
from hdp_sim_bridge.world import PandaWorld

from .low_level_eval import oracle_episode, world_scene
from .observation import front_camera, front_points, segment_request


def segments_of_episode(policy, task_name: str, seed: int) -> list[dict]:
    """Per segment: 'poses', 'joint_fk', 'refined_fk', 'planner_fk' (K, 3) EE positions (m)."""
    oracle = oracle_episode(task_name, seed)
    if not oracle.expert_success:
        raise ValueError(f'the expert fails on {task_name} seed {seed}: no oracle next-best poses')
    planner, out = PlannerPolicy(), []
    with PandaWorld() as world:
        task, _, _ = experts.reachable_scene(world, task_name, seed)
        camera, rng = front_camera(), np.random.default_rng(seed)
        for goal_pose, goal_open in oracle.nbps:
            request = segment_request(world, goal_pose, goal_open, front_points(world, camera, rng=rng))
            scene = world_scene(world, task)
            plan, baseline = policy.plan(request, scene), planner.plan(request, scene)
            if not plan.ok:
                break

            def fk(joints):
                return fk_pose(torch.as_tensor(np.asarray(joints), dtype=torch.float32))[:, :3].numpy()
            out.append({'poses': plan.poses[:, :3], 'joint_fk': fk(plan.extras['unrefined_joints']),
                        'refined_fk': fk(plan.joints),
                        'planner_fk': fk(baseline.joints) if baseline.ok else None})
            experts.follow(world, task, np.vstack([world.joint_positions(), plan.joints]), experts.ExpertConfig(),
                           lambda: None, lambda: None, hold=0.0)
            if goal_open != request.gripper_open:
                experts.actuate(world, task, 'open' if goal_open else 'close', lambda *_: None, lambda *_: None)
    return out


def plot(segment: dict, title: str, path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(11, 4.8))
    ax = fig.add_subplot(1, 2, 1, projection='3d')
    styles = [('poses', 'pose diffuser', 'tab:blue', '-'), ('joint_fk', 'joint diffuser (FK)', 'tab:orange', '--'),
              ('refined_fk', 'refined joints (FK)', 'tab:green', '-'), ('planner_fk', 'planner (FK)', 'tab:red', ':')]
    for key, label, colour, line in styles:
        if segment.get(key) is not None:
            xyz = segment[key]
            wide = key == 'poses'        # drawn wide and pale: the refined path lies on it
            ax.plot(xyz[:, 0], xyz[:, 1], xyz[:, 2], line, color=colour, label=label,
                    linewidth=6 if wide else 2, alpha=0.35 if wide else 1.0)
    ax.scatter(*segment['poses'][-1], color='black', s=40, label='next-best pose')
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_zlabel('z (m)')
    ax.legend(loc='upper left', fontsize=8)
    ax.set_title(title, fontsize=10)
    err = fig.add_subplot(1, 2, 2)
    for key, label, colour in (('joint_fk', 'joint diffuser', 'tab:orange'), ('refined_fk', 'refined', 'tab:green')):
        err.plot(100 * np.linalg.norm(segment[key] - segment['poses'], axis=1), color=colour, label=label)
    err.set_xlabel('waypoint')
    err.set_ylabel('distance to the pose trajectory (cm)')
    err.legend()
    err.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
