"""Scripted demonstrations recorded as rosbag2 episodes of the graph's own topics.

One episode = one (task, seed): the seed fixes the scene, the variation and
the phrasing, so the same seed always gives the same demonstration. Joint
states go in at 120 Hz of sim time; both cameras (colour, depth, camera
info) at the first frame and whenever the expert rests at a waypoint, which
is where keyframes are found, and with ``camera_rate`` also at that rate of
sim time in between (what a flat policy sees: it acts between keyframes);
/tf_static and the instruction at the start.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from hdp_motion import panda
from hdp_msgs_py import conversions, topics
from hdp_data.episodes import EpisodeWriter
from hdp_msgs_py.msg import Header, JointState, String, TFMessage

from .cameras import CameraRig, default_cameras
from .experts import reachable_scene, run_expert
from .sensor_model import SensorSettings, profile_named
from .tasks import make_task
from .world import TIME_STEP, PandaWorld

JOINT_STATE_EVERY = 2          # physics steps: 240 Hz / 2 = 120 Hz of sim time


@dataclasses.dataclass
class EpisodeSummary:
    task: str
    seed: int
    variation: int
    instruction: str
    success: bool
    reason: str
    sim_seconds: float
    wall_seconds: float
    path: str


def episode_name(task: str, seed: int) -> str:
    return f'{task}_{seed:06d}'


def stamp(sim_seconds: float):
    return conversions.seconds_to_time(sim_seconds)


def joint_state(world, sim_seconds: float) -> JointState:
    fingers = world.finger_positions()
    return JointState(header=Header(stamp=stamp(sim_seconds)),
                      name=list(panda.ARM_JOINTS + panda.FINGER_JOINTS),
                      position=np.concatenate([world.joint_positions(), fingers]),
                      velocity=np.concatenate([world.joint_velocities(), np.zeros(2)]))


def write_cameras(writer: EpisodeWriter, world, rig: CameraRig, sim_seconds: float) -> None:
    ns = int(round(sim_seconds * 1e9))
    for name, camera in rig.cameras.items():
        rgb, depth = rig.render(world.client, name, round(sim_seconds / TIME_STEP))
        header = Header(stamp=stamp(sim_seconds), frame_id=camera.frame_id)
        writer.write(topics.color_image(name), conversions.numpy_to_image(rgb, 'rgb8', header), ns)
        writer.write(topics.depth_image(name), conversions.numpy_to_image(depth, '16UC1', header), ns)
        writer.write(topics.camera_info(name), camera.camera_info(stamp(sim_seconds)), ns)


def record_episode(world: PandaWorld, task_name: str, seed: int, out_dir: Path,
                   width: int = 640, height: int = 480, camera_rate: float = 0.0,
                   sensor_profile: str = 'ideal') -> EpisodeSummary:
    """Reset the world to (task, seed), run the expert, write the bag; never raises on task failure.

    camera_rate: Hz of sim time at which both cameras are also recorded between rests (0: rests only).
    sensor_profile: the cameras' sensor model (sensor_model.PROFILES), its draws seeded by the episode.
    """
    start = time.monotonic()
    task, rng, variation = reachable_scene(world, task_name, seed)
    instruction = task.instruction(rng)
    cameras = default_cameras(width, height)
    rig = CameraRig(cameras, SensorSettings(profile_named(sensor_profile)))
    rig.start_episode(seed)
    path = out_dir / episode_name(task_name, seed)
    metadata = {'task': task_name, 'variation': variation, 'seed': seed, 'instruction': instruction,
                'camera_resolution': [width, height], 'camera_rate_hz': camera_rate,
                'sensor_profile': sensor_profile, 'source': 'hdp_sim_bridge scripted expert'}
    with EpisodeWriter(path, metadata) as writer:
        t0 = world.sim_time
        writer.write(topics.TF_STATIC, TFMessage(transforms=[c.transform_stamped() for c in cameras.values()]), 0)
        writer.write(topics.INSTRUCTION, String(data=instruction), 0)
        writer.write(topics.JOINT_STATES, joint_state(world, 0.0), 0)
        write_cameras(writer, world, rig, 0.0)
        steps = [0]
        next_frame = [1.0 / camera_rate if camera_rate > 0 else float('inf')]

        def on_step():
            steps[0] += 1
            t = world.sim_time - t0
            if steps[0] % JOINT_STATE_EVERY == 0:
                writer.write(topics.JOINT_STATES, joint_state(world, t), int(round(t * 1e9)))
            if t >= next_frame[0] - 1e-9:
                write_cameras(writer, world, rig, t)
                next_frame[0] += 1.0 / camera_rate

        def on_rest():
            write_cameras(writer, world, rig, world.sim_time - t0)

        def on_gripper(is_open):
            t = world.sim_time - t0
            writer.write(topics.GRIPPER_TRAJECTORY, conversions.finger_trajectory(is_open, stamp=stamp(t)), int(round(t * 1e9)))

        result = run_expert(world, task, rng, on_step, on_rest, on_gripper)
        writer.set_metadata('failure_reason', result.reason)
        writer.set_success(result.success)
    return EpisodeSummary(task_name, seed, variation, instruction, result.success, result.reason,
                          world.sim_time - t0, time.monotonic() - start, str(path))


# -- worker processes --------------------------------------------------------------------
_world: PandaWorld | None = None


def _work(job) -> EpisodeSummary:
    """One episode in a worker process, which keeps its world between episodes."""
    global _world
    task_name, seed, out_dir, width, height, camera_rate, sensor_profile = job
    if _world is None:
        _world = PandaWorld()
    return record_episode(_world, task_name, seed, Path(out_dir), width, height, camera_rate, sensor_profile)


def collect(tasks: list[str], episodes: int, seed_start: int, out_dir: Path, workers: int = 1,
            width: int = 640, height: int = 480, camera_rate: float = 0.0, sensor_profile: str = 'ideal'):
    """Record ``episodes`` per task with seeds seed_start.. ; yields summaries as they finish."""
    if camera_rate < 0:
        raise ValueError(f'camera_rate must be >= 0 Hz, got {camera_rate}')
    profile_named(sensor_profile)         # an unknown profile fails before any work starts
    for name in tasks:
        make_task(name)           # unknown names fail before any work starts
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(name, seed, str(out_dir), width, height, camera_rate, sensor_profile)
            for name in tasks for seed in range(seed_start, seed_start + episodes)]
    clashes = [j for j in jobs if (out_dir / episode_name(j[0], j[1])).exists()]
    if clashes:
        raise FileExistsError(f'{len(clashes)} episodes already exist in {out_dir} '
                              f'(e.g. {episode_name(*clashes[0][:2])}): choose another --out or --seed-start')
    if workers <= 1:
        for job in jobs:
            yield _work(job)
        return
    import multiprocessing
    with multiprocessing.get_context('spawn').Pool(workers) as pool:
        yield from pool.imap_unordered(_work, jobs)


def summary_table(summaries: list[EpisodeSummary]) -> str:
    """Markdown: per task, success rate, mean sim/wall seconds, the commonest failure."""
    rows = ['| task | success | episodes | sim s / episode | wall s / episode | commonest failure |',
            '|---|---|---|---|---|---|']
    for name in sorted({s.task for s in summaries}):
        mine = [s for s in summaries if s.task == name]
        ok = sum(s.success for s in mine)
        reasons = [s.reason for s in mine if not s.success]
        common = max(set(reasons), key=reasons.count) if reasons else ''
        rows.append(f'| {name} | {100 * ok / len(mine):.0f}% | {len(mine)} | '
                    f'{np.mean([s.sim_seconds for s in mine]):.1f} | '
                    f'{np.mean([s.wall_seconds for s in mine]):.2f} | {common} |')
    return '\n'.join(rows)
