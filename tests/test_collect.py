"""Scripted demonstrations: recorded as rosbag2 episodes a ROS tool reads, keyframes at the expert's rests."""

import subprocess
import sys

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from hdp_data.episodes import list_episodes, read_episode
from hdp_sim_bridge.collect import record_episode
from hdp_sim_bridge.tasks import TASKS, make_task
from hdp_sim_bridge.world import PandaWorld

pytestmark = pytest.mark.dds

HDP = [sys.executable, '-m', 'hdp_tools.cli.main']


@pytest.fixture(scope='module')
def episodes(tmp_path_factory):
    out = tmp_path_factory.mktemp('episodes')
    result = subprocess.run([*HDP, 'collect', '--tasks', 'all', '--episodes', '1',
                             '--seed-start', '7', '--out', str(out), '--width', '64', '--height', '48'],
                            text=True, capture_output=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert '| open_drawer |' in result.stdout and 'episodes/min' in result.stdout
    return out


def test_every_bag_reads_back_with_rosbags(episodes):
    paths = list_episodes(episodes, successful_only=False)
    assert sorted(p.name for p in paths) == sorted(f'{task}_000007' for task in TASKS)
    for path in paths:
        with AnyReader([path]) as reader:
            topics = {c.topic for c in reader.connections}
            assert {'/joint_states', '/hdp/instruction', '/tf_static', '/camera/front/color/image_raw',
                    '/camera/side/aligned_depth_to_color/image_raw', '/camera/front/color/camera_info'} <= topics
            for connection, _, raw in reader.messages():
                reader.deserialize(raw, connection.msgtype)


def test_episode_content_and_metadata(episodes):
    for path in list_episodes(episodes):
        episode = read_episode(path)
        meta = episode.metadata
        task = make_task(meta['task'])
        assert meta['seed'] == 7 and meta['success'] is True
        assert any(episode.instruction == p.format(*[task.variations[meta['variation']]] * p.count('{}'))
                   for p in task.phrasings)
        t = episode.joint_states.t
        assert 1 / np.median(np.diff(t)) >= 100          # joint states at >= 100 Hz of sim time
        assert set(episode.tf_static) == {'front_color_optical_frame', 'side_color_optical_frame'}


def test_keyframes_are_the_experts_rests(episodes):
    """Camera frames are taken where the expert rests: the keyframe rule finds those moments."""
    assert len(list_episodes(episodes)) >= len(TASKS) - 1      # every task's expert but at most one succeeded
    for path in list_episodes(episodes):
        episode = read_episode(path)
        times = episode.joint_states.t
        keyframe_times = times[episode.keyframes()]
        frames = episode.image_stamps['/camera/front/color/image_raw'][1:] / 1e9   # after the first frame
        for frame in frames:
            assert np.min(np.abs(keyframe_times - frame)) < 0.02, (path.name, keyframe_times, frames)


@pytest.mark.sim
def test_same_seed_same_episode():
    runs = []
    for _ in range(2):
        with PandaWorld() as world:
            joints = []
            task = make_task('pick_up_cup')
            world.reset(3)
            rng = np.random.default_rng(3)
            task.reset(world, rng, 1)
            from hdp_sim_bridge.experts import run_expert
            run_expert(world, task, rng, on_step=lambda: joints.append(world.joint_positions()))
            runs.append(np.array(joints))
    assert runs[0].shape == runs[1].shape and np.array_equal(runs[0], runs[1])


def test_collect_refuses_to_overwrite(episodes):
    result = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '7',
                             '--out', str(episodes), '--width', '64', '--height', '48'],
                            text=True, capture_output=True, timeout=120)
    assert result.returncode == 1 and 'already exist' in result.stderr
    result = subprocess.run([*HDP, 'collect', '--tasks', 'make_tea', '--episodes', '1', '--out', str(episodes)],
                            text=True, capture_output=True, timeout=120)
    assert result.returncode != 0 and 'unknown task' in result.stderr


@pytest.mark.sim
def test_failed_demos_are_marked(tmp_path):
    with PandaWorld() as world:
        summary = record_episode(world, 'reach_target', 0, tmp_path, 64, 48)
    assert summary.success
    # A demo whose expert fails is kept, marked, and left out of training lists.
    with PandaWorld() as world:
        task = TASKS['reach_target']
        original = task.waypoints
        task.waypoints = lambda self, world, flip=False: []          # an expert that does nothing
        try:
            failed = record_episode(world, 'reach_target', 1, tmp_path, 64, 48)
        finally:
            task.waypoints = original
    assert not failed.success
    assert [p.name for p in list_episodes(tmp_path)] == ['reach_target_000000']
    assert read_episode(tmp_path / 'reach_target_000001').metadata['success'] is False


def test_camera_rate_adds_frames_between_rests(tmp_path):
    """--camera-rate 10: a frame every 0.1 s of sim time besides the rests, the same demonstration
    (joint states identical to a rests-only recording of the seed), and the keyframes unchanged."""
    result = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '4',
                             '--out', str(tmp_path / 'dense'), '--width', '32', '--height', '24',
                             '--camera-rate', '10'], text=True, capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr
    with PandaWorld() as world:
        record_episode(world, 'reach_target', 4, tmp_path / 'sparse', 32, 24)
    dense = read_episode(tmp_path / 'dense' / 'reach_target_000004')
    sparse = read_episode(tmp_path / 'sparse' / 'reach_target_000004')
    assert dense.metadata['camera_rate_hz'] == 10 and sparse.metadata['camera_rate_hz'] == 0
    assert np.array_equal(dense.joint_states.position, sparse.joint_states.position)
    assert dense.keyframes() == sparse.keyframes()
    frames = dense.image_stamps['/camera/front/color/image_raw'] / 1e9
    rests = sparse.image_stamps['/camera/front/color/image_raw'] / 1e9
    assert all(np.min(np.abs(frames - t)) < 1e-6 for t in rests)              # every rest frame is kept
    steady = np.arange(0.1, dense.joint_states.t[-1] - 0.05, 0.1)
    assert all(np.min(np.abs(frames - t)) < 1 / 240 + 1e-6 for t in steady)  # and one every 0.1 s
    assert len(frames) >= len(steady) + len(rests) - 2
    bad = subprocess.run([*HDP, 'collect', '--tasks', 'reach_target', '--episodes', '1', '--out',
                          str(tmp_path / 'bad'), '--camera-rate', '-1'], text=True, capture_output=True, timeout=120)
    assert bad.returncode != 0 and '--camera-rate' in bad.stderr


def test_render_writes_pngs(tmp_path):
    result = subprocess.run([*HDP, 'render', '--task', 'open_box', '--seed', '2', '--out', str(tmp_path),
                             '--width', '80', '--height', '60'], text=True, capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr
    import cv2
    for camera in ('front', 'side'):
        for kind in ('color', 'depth'):
            image = cv2.imread(str(tmp_path / f'open_box_2_{camera}_{kind}.png'))
            assert image.shape == (60, 80, 3) and image.std() > 5     # not blank
