"""`hdp eval samples`: how good RK-Diffuser's raw samples are, offline, on recorded segments.

Every keyframe segment of the episodes in DATA (validation or evaluation
episodes: the checkpoint's training seeds are refused) is given to the
model with the conditions controller_node builds (start state, the
segment's goal as the NBP, the front camera's points, rank 1), one sample
from each diffuser, and measured:

  joint goal error   FK of the joint sample's last waypoint against the goal,
                     translation (cm) and rotation (deg, the hand's half-turn
                     symmetry allowed), before any refinement
  jitter             mean |second difference| of the joint waypoints (rad);
                     the demonstrations' is also printed
  refinement moves   how far rkd's refinement moves the joint sample: the
                     largest end-effector displacement over the waypoints (cm)
                     and the largest joint change (rad)

No simulator: this separates the joint diffuser's accuracy from execution,
and takes a minute where Table 2 takes many.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

GOAL_TRANSLATION_M = 0.02      # the "within 2 cm and 10 deg of its NBP"
GOAL_ROTATION_DEG = 10.0


def configure(parser) -> None:
    """RK-Diffuser's raw samples on recorded segments: joint goal error, jitter, how far refinement moves them."""
    parser.add_argument('--data', required=True, help='directory of episodes (hdp collect), not trained on')
    parser.add_argument('--checkpoint', help='RK-Diffuser checkpoint (default: the released one)')
    parser.add_argument('--sampler', choices=('ddpm', 'ddim'), default='ddim',
                        help='ddim (5 steps, unguided; default, as controller_node) or ddpm (100, guided)')
    parser.add_argument('--steps', type=int, help='sampler steps (default: 5 for ddim, 100 for ddpm)')
    parser.add_argument('--guidance', type=float, help='guidance weight (default: 1.0 for ddim, the checkpoint\'s '
                        'for ddpm)')
    parser.add_argument('--refine-steps', type=int, default=50, help='refinement steps (default 50)')
    parser.add_argument('--batch', type=int, default=64, help='segments per sampling batch (default 64)')
    parser.add_argument('--seed', type=int, default=0, help='sampling seed (default 0)')
    parser.add_argument('--cache', help='preprocessing cache directory (default DATA/.cache)')
    parser.add_argument('--device', default='cpu', help='where the diffusers sample: cpu (default), cuda, cuda:N, auto')
    parser.add_argument('--json', type=Path, help='also write the per-segment figures here')
    parser.set_defaults(func=run)


def run(args) -> int:
    import torch

    from hdp_controller import checkpoint
    from hdp_controller.dataset import load_segments
    from hdp_controller.policy import FAST_GUIDANCE, FAST_STEPS, default_checkpoint
    from hdp_learning import distributed

    if args.batch < 1 or args.refine_steps < 0:
        raise SystemExit('--batch must be >= 1 and --refine-steps >= 0')
    try:
        device = distributed.torch_device(args.device)
    except ValueError as err:
        raise SystemExit(f'hdp eval samples: {err}') from None
    path = args.checkpoint or default_checkpoint()
    model, payload = checkpoint.load_model(path)
    model.to(device)
    try:
        segs = load_segments(args.data, model.config.n_points, args.cache).moving()
    except ValueError as err:
        raise SystemExit(f'hdp eval samples: {err}') from None
    trained = trained_on(segs.task, segs.seed, payload.get('training_seeds') or {})
    if trained:
        raise SystemExit(f'hdp eval samples: {path} was trained on episodes in {args.data} '
                         f'({", ".join(trained[:5])}...); measure on seeds it never saw')
    fast = args.sampler == 'ddim'
    steps = args.steps or (FAST_STEPS if fast else None)
    guidance = args.guidance if args.guidance is not None else (FAST_GUIDANCE if fast else None)
    torch.set_grad_enabled(False)
    rows = measure(model, segs, args.sampler, steps, guidance, args.refine_steps, args.batch, args.seed)
    print(markdown_table(rows, demo_jitter(segs)))
    if args.json:
        args.json.write_text(json.dumps({'checkpoint': str(path), 'data': str(args.data), 'sampler': args.sampler,
                                         'steps': steps, 'guidance': guidance, 'refine_steps': args.refine_steps,
                                         'segments': rows}, indent=1))
    return 0


def trained_on(tasks, seeds, training_seeds: dict) -> list[str]:
    """'task seed' of every segment whose episode the checkpoint was trained on."""
    return sorted({f'{t} {s}' for t, s in zip(tasks, seeds) if int(s) in set(training_seeds.get(str(t), ()))})


def measure(model, segs, sampler: str, steps, guidance, refine_steps: int, batch_size: int, seed: int) -> list[dict]:
    """One record per segment (see the module docstring)."""
    import torch
    from tqdm import tqdm

    from hdp_controller.refine import goal_error, refine
    from hdp_motion.kinematics import forward_kinematics

    generator = torch.Generator().manual_seed(seed)
    rows = []
    for start in tqdm(range(0, len(segs), batch_size), desc='sampling segments', unit='batch'):
        part = segs.select(np.arange(start, min(start + batch_size, len(segs))))
        batch = conditions(part)
        device = next(model.parameters()).device
        out = model.sample({k: v.to(device) for k, v in batch.items()}, sampler, steps, guidance, generator)
        out = {k: v.cpu() for k, v in out.items()}
        joints = out['joints']
        translation, rotation = goal_error(joints, batch['goal_pose'])
        refined = refine(joints, out['poses'], steps=refine_steps)
        moved = torch.linalg.norm(forward_kinematics(refined)[0] - forward_kinematics(joints)[0], dim=-1).amax(1)
        jitter = torch.diff(joints, n=2, dim=1).abs().mean((1, 2))
        for i in range(len(part)):
            rows.append({'task': str(part.task[i]), 'seed': int(part.seed[i]),
                         'goal_cm': 100 * float(translation[i]), 'goal_deg': float(np.degrees(rotation[i].item())),
                         'jitter_rad': float(jitter[i]), 'refine_moves_cm': 100 * float(moved[i]),
                         'refine_moves_rad': float((refined[i] - joints[i]).abs().max())})
    return rows


def conditions(segs) -> dict:
    """Segments -> a batch as policy.conditions builds one per request (rank 1, as at inference)."""
    import torch
    n = len(segs)
    arrays = dict(q=segs.joints[:, 0], qd=segs.qd0, gripper=segs.gripper, start_pose=segs.poses[:, 0],
                  goal_pose=segs.poses[:, -1], rank=np.ones((n, 1)), points=segs.points)
    return {k: torch.as_tensor(np.asarray(v, dtype=np.float32)) for k, v in arrays.items()}


def demo_jitter(segs) -> float:
    return float(np.abs(np.diff(segs.joints, n=2, axis=1)).mean())


def summary(rows: list[dict]) -> dict:
    """Medians (and the share within the goal tolerance) of a list of segment records."""
    goal_cm = np.array([r['goal_cm'] for r in rows])
    goal_deg = np.array([r['goal_deg'] for r in rows])
    within = (goal_cm <= 100 * GOAL_TRANSLATION_M) & (goal_deg <= GOAL_ROTATION_DEG)
    return {'segments': len(rows), 'goal_cm': float(np.median(goal_cm)), 'goal_deg': float(np.median(goal_deg)),
            'within': 100 * float(within.mean()),
            'jitter_rad': float(np.median([r['jitter_rad'] for r in rows])),
            'refine_moves_cm': float(np.median([r['refine_moves_cm'] for r in rows])),
            'refine_moves_rad': float(np.median([r['refine_moves_rad'] for r in rows]))}


def markdown_table(rows: list[dict], demonstrations_jitter: float) -> str:
    tasks = sorted({r['task'] for r in rows})
    lines = ['| task | segments | joint goal error, median cm / deg | within 2 cm and 10 deg | jitter, median rad '
             '| refinement moves it, median of max cm / rad |', '|---|---|---|---|---|---|']
    for name, subset in [(t, [r for r in rows if r['task'] == t]) for t in tasks] + [('**all**', rows)]:
        s = summary(subset)
        lines.append(f"| {name} | {s['segments']} | {s['goal_cm']:.1f} / {s['goal_deg']:.1f} | {s['within']:.0f}% "
                     f"| {s['jitter_rad']:.4f} | {s['refine_moves_cm']:.1f} / {s['refine_moves_rad']:.2f} |")
    lines.append(f'\nThe demonstrations\' jitter: {demonstrations_jitter:.4f} rad.')
    return '\n'.join(lines)
