"""Offline metrics of the next-best-pose network on recorded episodes (no simulation).

For every sample, the full coarse-to-fine prediction against the demo's next
keyframe: translation error (cm), rotation error (deg, geodesic; also up to
the parallel gripper's 180 deg symmetry), gripper accuracy. Per task and
overall (the mean over samples). Instructions are drawn from the training phrasings ('seen'),
the held-out one ('heldout') or the paraphrase set ('paraphrase', never trained on).
"""

from __future__ import annotations

import numpy as np
import torch

from . import language, rotations
from .dataset import Item, KeyframeDataset
from .model import NextBestPoseNet
from .voxels import collate_clouds

PHRASING_LABELS = {'seen': 'training phrasings', 'heldout': 'held-out phrasings', 'paraphrase': 'paraphrases'}


def evaluation_item(dataset: KeyframeDataset, i: int, rng: np.random.Generator, phrasing: str) -> Item:
    """Sample ``i`` of ``dataset`` with an instruction in ``phrasing`` (a key of PHRASING_LABELS)."""
    if phrasing not in PHRASING_LABELS:
        raise ValueError(f'unknown phrasing {phrasing!r}; phrasings: {", ".join(PHRASING_LABELS)}')
    item = dataset.item(i, rng, heldout=phrasing == 'heldout')
    if phrasing == 'paraphrase':            # the dataset draws only training and held-out phrasings
        variation = int(dataset.episodes[dataset.index[i][0]]['variation'])
        item.instruction = language.instruction(item.task, variation, language.paraphrase_phrasings(item.task), rng)
    return item


def sample_errors(model: NextBestPoseNet, dataset: KeyframeDataset, phrasing: str = 'seen',
                  batch: int = 32, seed: int = 0) -> dict[str, np.ndarray]:
    """{'translation_cm' | 'rotation_deg' | 'rotation_symmetric_deg' | 'gripper_accuracy': (N,)}
    of every sample of ``dataset``, instructions in ``phrasing`` (seen, heldout, paraphrase)."""
    rng = np.random.default_rng(seed)
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    errors = {'translation_cm': [], 'rotation_deg': [], 'rotation_symmetric_deg': [], 'gripper_accuracy': []}
    for start in range(0, len(dataset), batch):
        items = [evaluation_item(dataset, i, rng, phrasing) for i in range(start, min(start + batch, len(dataset)))]
        xyz, rgb, cloud = collate_clouds([(i.xyz, i.rgb) for i in items], device)
        proprio = torch.as_tensor(np.stack([i.proprio for i in items]), device=device)
        predicted = model.predict(xyz, rgb, cloud, [i.instruction for i in items], proprio)
        target_quat = np.stack([i.target_quat for i in items])
        errors['translation_cm'].append(
            100 * np.linalg.norm(predicted.xyz.cpu().numpy() - np.stack([i.target_xyz for i in items]), axis=1))
        angle = rotations.angle_between(predicted.quat, target_quat)
        flipped = rotations.angle_between(rotations.flip_about_approach(predicted.quat), target_quat)
        errors['rotation_deg'].append(np.degrees(angle))
        errors['rotation_symmetric_deg'].append(np.degrees(np.minimum(angle, flipped)))
        errors['gripper_accuracy'].append(predicted.gripper_open.cpu().numpy() == [i.target_open for i in items])
    model.train(was_training)
    return {name: np.concatenate(parts) for name, parts in errors.items()}


def offline_metrics(model: NextBestPoseNet, dataset: KeyframeDataset, phrasing: str = 'seen',
                    batch: int = 32, seed: int = 0) -> dict:
    """{'overall' | task: {'translation_cm', 'rotation_deg', 'rotation_symmetric_deg',
    'gripper_accuracy', 'samples'}}, instructions in ``phrasing`` (seen, heldout, paraphrase)."""
    return task_metrics(dataset, sample_errors(model, dataset, phrasing, batch, seed))


def task_metrics(dataset: KeyframeDataset, errors: dict) -> dict:
    """offline_metrics' summaries (means) of sample_errors' ``errors``."""
    metrics = {'overall': _summary(errors, np.ones(len(dataset), dtype=bool))}
    for task in np.unique(dataset.tasks):
        metrics[str(task)] = _summary(errors, dataset.tasks == task)
    return metrics


def keyframe_metrics(dataset: KeyframeDataset, errors: dict) -> dict:
    """{'task keyframe k': summary} of sample_errors' ``errors``: where in an episode a task's
    predictions go wrong (k = 0 predicts the first keyframe from the episode's start)."""
    keyframe = dataset.index[:, 1]
    return {f'{task} keyframe {k}': _summary(errors, (dataset.tasks == task) & (keyframe == k))
            for task in np.unique(dataset.tasks) for k in np.unique(keyframe[dataset.tasks == task])}


def _summary(values: dict, chosen: np.ndarray) -> dict:
    summary = {name: round(float(v[chosen].mean()), 4) for name, v in values.items()}
    summary['samples'] = int(chosen.sum())
    return summary


def format_metrics(metrics: dict) -> str:
    """A markdown table of offline_metrics' result, one row per task and overall."""
    lines = ['| task | samples | translation (cm) | rotation (deg) | rotation, up to flip (deg) | gripper acc. |',
             '|---|---|---|---|---|---|']
    for task, m in sorted(metrics.items(), key=lambda kv: (kv[0] == 'overall', kv[0])):
        lines.append(f"| {task} | {m['samples']} | {m['translation_cm']:.2f} | {m['rotation_deg']:.1f} | "
                     f"{m['rotation_symmetric_deg']:.1f} | {m['gripper_accuracy']:.3f} |")
    return '\n'.join(lines)
