"""The episode's pictures: a GIF of the front camera and a plot of joints and end-effector path."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .episode_log import EpisodeLog, Segment

GIF_WIDTH = 320                # px; the front camera is scaled down to keep the GIF small
GIF_SPEEDUP = 2.0              # the GIF plays sim time this many times faster


def gif_durations_ms(stamps_s, speedup: float = GIF_SPEEDUP, last_ms: int = 1000) -> list[int]:
    """Per-frame display times that replay the frames' sim-time spacing ``speedup`` times faster."""
    gaps = np.diff(np.asarray(stamps_s, dtype=float)) * 1000.0 / speedup
    return [max(20, int(round(g))) for g in gaps] + [last_ms]


def write_gif(frames: list[np.ndarray], durations_ms: list[int], path: Path) -> None:
    """An animated GIF (looping) of RGB frames (H, W, 3) uint8."""
    from PIL import Image
    if not frames:
        raise ValueError('no frames to write')
    images = [Image.fromarray(np.ascontiguousarray(f)) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=durations_ms, loop=0)


def caption(frame: np.ndarray, text: str) -> np.ndarray:
    """A copy of an RGB frame with ``text`` on a dark band along its top."""
    import cv2
    out = np.array(frame, copy=True)
    out[:18] = (out[:18] * 0.35).astype(np.uint8)
    cv2.putText(out, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def ee_positions(q: np.ndarray) -> np.ndarray:
    """World positions (N, 3) of panda_grasptarget for arm joint positions (N, 7)."""
    import torch

    from hdp_motion import kinematics
    pose = kinematics.fk_pose(torch.as_tensor(np.asarray(q, dtype=np.float64).reshape(-1, 7)))
    return pose[:, :3].numpy()


def wall_to_sim(events_s, wall_s, sim_s) -> np.ndarray:
    """Times on the demo's clock -> sim time, through samples (wall_s, sim_s) taken together
    (joint states: stamped in sim time, received on the wall clock); clamped at the ends."""
    return np.interp(np.asarray(events_s, dtype=float), np.asarray(wall_s, dtype=float),
                     np.asarray(sim_s, dtype=float))


def write_plot(wall_s, sim_s, q, segments: list[Segment], success_s: float | None, title: str,
               path: Path) -> None:
    """Joint positions over sim time with each segment's execution shaded, and the end-effector
    path in 3D with the NBPs numbered (green: gripper open, red: close).

    Sim time, not the wall clock: the bridge steps physics in bursts between camera renders, so
    on the wall clock the joints would move in stairs. ``wall_s`` (s since the instruction, when
    each joint state arrived) maps the segment events onto sim time.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    q = np.asarray(q, dtype=float).reshape(-1, 7)
    sim0 = float(wall_to_sim(0.0, wall_s, sim_s))

    def at(event_s):
        return float(wall_to_sim(event_s, wall_s, sim_s)) - sim0
    fig = plt.figure(figsize=(12, 4.8))
    ax = fig.add_subplot(1, 2, 1)
    for j in range(7):
        ax.plot(np.asarray(sim_s, dtype=float) - sim0, q[:, j], lw=1.2, label=f'joint {j + 1}')
    for s in segments:
        ax.axvline(at(s.nbp_s), color='0.4', ls=':', lw=0.8)
        if s.trajectory_s is not None and s.result_s is not None:
            ax.axvspan(at(s.trajectory_s), at(s.result_s), color='C0' if s.result == 'done' else 'C3', alpha=0.08)
        ax.text(at(s.nbp_s), 1.0, f' {s.index}', transform=ax.get_xaxis_transform(), va='top', fontsize=8)
    if success_s is not None:
        ax.axvline(at(success_s), color='green', lw=1.5, label='success')
    ax.set_xlabel('sim time since the instruction, s (dotted: NBP received; shaded: execution)')
    ax.set_ylabel('joint position (rad)')
    ax.legend(fontsize=7, ncol=2, loc='lower left')
    ax3 = fig.add_subplot(1, 2, 2, projection='3d')
    if len(q):
        ee = ee_positions(q)
        ax3.plot(ee[:, 0], ee[:, 1], ee[:, 2], color='C0', lw=1.5, label='end effector')
        ax3.scatter(*ee[0], color='k', s=20, label='start')
    for s in segments:
        ax3.scatter(*s.xyz, color='green' if s.gripper == 'open' else 'red' if s.gripper == 'close' else 'gray',
                    s=40, marker='^')
        ax3.text(*s.xyz, f' {s.index}', fontsize=8)
    ax3.set_xlabel('x (m)')
    ax3.set_ylabel('y (m)')
    ax3.set_zlabel('z (m)')
    ax3.set_title('end-effector path and NBPs (^)', fontsize=9)
    ax3.legend(fontsize=7, loc='upper left')
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_episode_files(log: EpisodeLog, record: dict, out: Path, title: str) -> None:
    """The episode's GIF and trajectory plot, named in ``record`` (relative to ``out``)."""
    stem = f"{record['task']}_seed{record['seed']}"
    if log.frames:
        def label(t):
            index = sum(s.nbp_s <= t for s in log.segments)
            return f"{record['task']} seed {record['seed']}  t={max(t, 0.0):4.1f}s  " + (
                f'segment {index}' if index else 'observing')
        frames = [caption(rgb, label(t)) for t, _, rgb in log.frames]
        write_gif(frames, gif_durations_ms([stamp for _, stamp, _ in log.frames]), out / f'{stem}.gif')
        record['gif'] = f'{stem}.gif'
    if log.joints:
        wall, sim, q = zip(*log.joints)
        write_plot(wall, sim, np.array(q), log.segments, log.success_s, title, out / f'{stem}_trajectory.png')
        record['plot'] = f'{stem}_trajectory.png'


