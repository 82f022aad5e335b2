"""`hdp demo`: segment timing bookkeeping, CPU accounting from /proc, statistics, the GIF and plot
writers, and the command itself (bad arguments, Ctrl-C, one whole episode of the real graph)."""

import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hdp_bringup.demo import cli, cpu, episode_log, figures, media
from hdp_bringup.launch_cli import NODES, default_params_file, node_commands

pytestmark = pytest.mark.unit


def _hdp(*args) -> list[str]:
    return [sys.executable, '-m', 'hdp_tools.cli.main', *args]


def _env(ros_domain) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), OMP_NUM_THREADS='1', PYTHONUNBUFFERED='1')


# --- domain -------------------------------------------------------------------------------------

def test_domain_comes_from_the_environment_else_is_picked_in_the_safe_range():
    assert cli.pick_domain({'ROS_DOMAIN_ID': '42'}, random.Random(0)) == (42, False)
    assert cli.pick_domain({'ROS_DOMAIN_ID': '0'}, random.Random(0)) == (0, False)
    picked = {cli.pick_domain({'ROS_DOMAIN_ID': ' '}, random.Random(seed)) for seed in range(50)}
    assert all(p and d in cli.SAFE_DOMAINS for d, p in picked) and len(picked) > 10
    with pytest.raises(ValueError, match='0..232'):
        cli.pick_domain({'ROS_DOMAIN_ID': '300'}, random.Random(0))


# --- segment bookkeeping --------------------------------------------------------------------------

def test_segment_times_split_into_observe_predict_controller_execution():
    log = episode_log.EpisodeLog(start=100.0)
    log.gripper_goal(key=7, is_open=False)                 # the planner sends the goal first
    first = log.nbp(101.5, key=7, xyz=(0.5, 0.1, 0.9))
    assert log.trajectory(102.25, points=40, duration_s=1.6) is first
    assert log.result(105.0, key=99, outcome='done') is None       # another segment's result
    assert log.result(105.25, key=7, outcome='done') is first
    second = log.nbp(106.0, key=8, xyz=(0.4, 0.0, 1.0))
    log.gripper_goal(key=8, is_open=True)                  # or just after its NBP
    log.success(108.0)
    log.trajectory(106.5, points=30, duration_s=1.0)
    log.result(110.0, key=8, outcome='done')
    log.success(109.0)                                     # the first report counts

    assert (first.observe_predict_s, first.controller_s, first.execution_s) == (1.5, 0.75, 3.0)
    assert first.gripper == 'close' and first.trajectory_points == 40 and first.trajectory_duration_s == 1.6
    assert (second.observe_predict_s, second.controller_s, second.execution_s) == (0.75, 0.5, 3.5)
    assert second.gripper == 'open' and second.index == 2 and log.success_s == 8.0
    assert second.to_dict()['observe_predict_s'] == 0.75 and second.to_dict()['xyz'] == [0.4, 0.0, 1.0]


def test_a_refused_segment_has_controller_time_and_no_execution():
    log = episode_log.EpisodeLog(start=0.0)
    segment = log.nbp(2.0, key=1, xyz=(0.0, 0.0, 0.0))
    assert log.open_segment is segment
    log.result(2.5, key=1, outcome='failed: outside the workspace')
    assert (segment.controller_s, segment.execution_s, segment.gripper) == (0.5, None, None)
    assert log.open_segment is None and log.trajectory(3.0, 10, 1.0) is None
    line = episode_log.segment_line(segment)
    assert line.startswith('segment 1: NBP (0.000, 0.000, 0.000) gripper unchanged -> failed: outside')
    assert 'controller 0.50 s, execution -' in line



def test_a_stalled_episode_names_the_node_it_waits_on():
    log = episode_log.EpisodeLog(start=10.0)
    assert episode_log.stall_report(log, 40.0)[:2] == ['no NBP from planner_node since the instruction',
                                                        'no /joint_states since the instruction']
    log.status += [(0.1, 'instruction accepted'), (1.5, 'segment 1 sent')]
    log.joints.append((2.0, 5.0, np.zeros(7)))
    segment = log.nbp(11.5, key=1, xyz=(0.5, 0.0, 1.0))
    report = episode_log.stall_report(log, 40.0)
    assert report == ['segment 1: NBP at 1.5 s, no trajectory from controller_node since',
                      'last /joint_states at 2.0 s of 30.0 s',
                      '/hdp/status    0.1 s: instruction accepted', '/hdp/status    1.5 s: segment 1 sent']
    log.trajectory(12.0, points=10, duration_s=1.0)
    assert episode_log.stall_report(log, 40.0)[0] == 'segment 1: trajectory at 2.0 s, no segment result since'
    log.result(14.0, key=segment.key, outcome='done')
    assert episode_log.stall_report(log, 40.0, status_lines=1)[::2] == [
        'segment 1 ended (done) at 4.0 s; no NBP from planner_node since', '/hdp/status    1.5 s: segment 1 sent']


# --- CPU --------------------------------------------------------------------------------------------

def _stat(pid, ppid, utime, stime, cutime=0, cstime=0, comm='python3'):
    return f'{pid} ({comm}) S {ppid} {pid} {pid} 0 -1 4194560 100 0 0 0 {utime} {stime} {cutime} {cstime} 20 0 4 0'


def test_parse_stat_counts_fields_after_the_last_parenthesis():
    assert cpu.parse_stat(_stat(9, 3, 250, 50, 7, 3, comm='odd) name (x')) == (3, 310)


def test_parse_stat_agrees_with_os_times():
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    ticks = os.sysconf('SC_CLK_TCK')
    ppid, total = cpu.parse_stat(Path(f'/proc/{os.getpid()}/stat').read_text())
    times = os.times()
    assert ppid == os.getppid()
    assert abs(total - (times.user + times.system + times.children_user + times.children_system) * ticks) <= 3


def test_cpu_of_a_node_includes_its_live_descendants():
    before = {10: _stat(10, 1, 100, 20), 11: _stat(11, 10, 30, 0), 12: _stat(12, 11, 5, 5), 13: _stat(13, 1, 999, 0),
              20: _stat(20, 1, 50, 0)}
    # 11 exited and was waited for: its 40 ticks are in 10's cutime now; its child 12 went to init.
    after = {10: _stat(10, 1, 200, 40, 40, 0), 12: _stat(12, 1, 5, 5), 13: _stat(13, 1, 999, 0),
             20: _stat(20, 1, 150, 0)}
    assert cpu.tree_ticks(10, before) == 100 + 20 + 30 + 10 and cpu.tree_ticks(10, after) == 280
    assert cpu.tree_ticks(30, before) is None
    pids = {'planner_node': 10, 'controller_node': 20, 'gone': 30}
    a, b = (cpu.cpu_seconds(pids, stats, ticks_per_s=100) for stats in (before, after))
    assert a == {'planner_node': 1.6, 'controller_node': 0.5}
    usage = cpu.cpu_usage(a, b, wall_s=2.0)
    assert usage == {'planner_node': {'cpu_s': 1.2, 'cpu_percent': 60.0},
                     'controller_node': {'cpu_s': 1.0, 'cpu_percent': 50.0}}


def test_read_stats_skips_what_is_not_a_process(tmp_path):
    (tmp_path / '17').mkdir()
    (tmp_path / '17' / 'stat').write_text(_stat(17, 1, 1, 1))
    (tmp_path / '18').mkdir()                          # exited between listing and reading
    (tmp_path / 'self').mkdir()
    assert cpu.read_stats(tmp_path) == {17: _stat(17, 1, 1, 1)}


# --- figures ----------------------------------------------------------------------------------------

def _record(success, segment_times, cpu_s, wall_s=10.0, success_s=8.0):
    return {'success': success, 'success_s': success_s if success else None, 'wall_s': wall_s,
            'segments': [{**dict(zip(episode_log.STAGES, t)), 'trajectory_s': t[0] + t[1]} for t in segment_times],
            'cpu': {name: {'cpu_s': c} for name, c in zip(cli.NODES, cpu_s)}}


def test_stats_and_figures_over_episodes():
    assert figures.stats([3.0, 1.0, 2.0, None]) == {'n': 3, 'p50': 2.0, 'p95': 2.9, 'mean': 2.0, 'max': 3.0}
    assert figures.stats([])['p50'] is None
    episodes = [_record(True, [(1.0, 0.5, 3.0), (2.0, 0.7, None)], (5.0, 1.0, 2.0)),
                _record(False, [(3.0, 0.9, 4.0)], (5.0, 1.0, 2.0), wall_s=30.0)]
    figs = figures.figures(episodes)
    assert figs['observe_predict_s']['n'] == 3 and figs['observe_predict_s']['p50'] == 2.0
    assert figs['execution_s']['n'] == 2 and figs['execution_s']['max'] == 4.0
    assert figs['episode_s'] == figures.stats([8.0])                  # successful episodes only
    assert figs['first_trajectory_s'] == figures.stats([1.5, 3.9])    # each episode's first segment
    assert figs['cpu']['sim_bridge_node'] == {'cpu_s': 10.0, 'cpu_percent': 25.0}
    assert (figs['episodes'], figs['succeeded']) == (2, 1)
    table = figures.format_figures(figs)
    assert '1 of 2 episodes succeeded, 3 segments' in table
    assert '| observe + predict (result -> NBP) | 3 | 2.00 | 2.90 | 2.00 | 3.00 |' in table
    assert '| sim_bridge_node | 10.0 | 25 |' in table


# --- writers ----------------------------------------------------------------------------------------

def test_gif_replays_sim_time_faster_and_is_a_valid_animation(tmp_path):
    assert media.gif_durations_ms([10.0, 10.5, 11.0], speedup=2.0, last_ms=900) == [250, 250, 900]
    frames = [np.full((48, 64, 3), 40 * i, np.uint8) for i in range(4)]
    captioned = media.caption(frames[3], 'reach_target t=1.0s')
    band = captioned[:18]
    assert np.median(band) < 120 / 2 and band.max() > 200 and np.all(captioned[18:] == 120)   # dark band, white text
    assert np.all(frames[3] == 120)                                                        # the frame is not changed
    media.write_gif(frames, [100, 100, 100, 500], tmp_path / 'a.gif')
    with Image.open(tmp_path / 'a.gif') as gif:
        assert gif.format == 'GIF' and gif.n_frames == 4 and gif.size == (64, 48)
        gif.seek(3)
        assert np.asarray(gif.convert('RGB'))[40, 10].mean() == pytest.approx(120, abs=3)
    with pytest.raises(ValueError, match='no frames'):
        media.write_gif([], [], tmp_path / 'b.gif')


def test_ee_positions_are_the_sims_own_forward_kinematics():
    from hdp_motion import panda
    from hdp_sim_bridge.world import PandaWorld
    q = np.array([panda.HOME, panda.HOME + np.array([0.3, 0.2, -0.1, 0.2, 0.1, -0.2, 0.4])])
    with PandaWorld() as world:
        expected = []
        for row in q:
            world.reset_arm(row)
            expected.append(world.ee_pose()[0])
    np.testing.assert_allclose(media.ee_positions(q), expected, atol=1e-6)


def test_wall_to_sim_maps_events_through_joint_state_samples():
    np.testing.assert_allclose(media.wall_to_sim([0.5, 1.5, 9.0], [0.0, 1.0, 2.0], [5.0, 5.0, 6.0]), [5.0, 5.5, 6.0])


def test_trajectory_plot_is_a_png(tmp_path):
    from hdp_motion import panda
    log = episode_log.EpisodeLog(start=0.0)
    wall = np.linspace(0.1, 6.0, 120)
    q = np.tile(panda.HOME, (120, 1))              # at home, then turning joint 1
    q[60:, 0] = np.linspace(0.0, 0.8, 60)
    segment = log.nbp(1.0, key=1, xyz=(0.5, 0.0, 1.0))
    log.gripper_goal(1, True)
    log.trajectory(1.5, 50, 2.0)
    log.result(4.0, 1, 'done')
    media.write_plot(wall, wall * 0.9 + 3.0, q, [segment], 3.5, 'test', tmp_path / 'p.png')
    with Image.open(tmp_path / 'p.png') as png:
        assert png.format == 'PNG' and png.size == (1200, 480)
        pixels = np.asarray(png.convert('RGB'))
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50     # lines and text, not an empty canvas


# --- the command --------------------------------------------------------------------------------------

@pytest.mark.dds
def test_unknown_task_exits_2_before_starting_anything(tmp_path, ros_domain):
    proc = subprocess.run(_hdp('demo', '--task', 'nonsense', '--out', str(tmp_path / 'out')),
                          env=_env(ros_domain), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "hdp demo: unknown task 'nonsense'; tasks: reach_target, pick_up_cup, open_drawer" in proc.stderr
    assert 'started' not in proc.stdout and not (tmp_path / 'out').exists()


def _parse(*args):
    import argparse
    parser = argparse.ArgumentParser()
    cli.configure(parser)
    return parser.parse_args(args)


def test_argument_problems_are_found_before_anything_starts(tmp_path):
    tasks = ('reach_target', 'open_drawer')
    assert cli.argument_problem(_parse('--task', 'open_drawer'), tasks) is None
    for args, problem in ((('--task', 'open_door'), "unknown task 'open_door'; tasks: reach_target, open_drawer"),
                          (('--episodes', '0'), '--episodes >= 1'), (('--seed', '-1'), '--seed must be >= 0'),
                          (('--timeout', '0'), '--timeout > 0'), (('--instruction', '  '), '--instruction is empty'),
                          (('--params-file', str(tmp_path / 'no.yaml')), 'no parameter file'),
                          (('--agent-checkpoint', str(tmp_path / 'no.pt')), '--agent-checkpoint: no file'),
                          (('--low-level-checkpoint', str(tmp_path / 'no.pt')), '--low-level-checkpoint: no file'),
                          (('--instruction', 'open it', '--phrasing', 'seen'), 'exclude each other')):
        assert problem in cli.argument_problem(_parse('--task', 'reach_target', *args), tasks), args
    with pytest.raises(SystemExit) as exit_:
        _parse('--task', 'reach_target', '--method', 'teleport')
    assert exit_.value.code == 2


def test_a_refused_episode_fails_and_the_next_seed_runs(monkeypatch):
    """A low-confidence refusal on one seed is that episode's failure (as the harness counts it);
    exit 2 only when the planner refused every episode."""
    outcomes = {1000: 'succeeded', 1001: 'refused', 1002: 'failed'}

    def fake_episode(session, seed, *args):
        outcome = outcomes[seed]
        return {'outcome': outcome, 'success': outcome == 'succeeded', 'reason': 'confidence 0.07',
                'segments': [], 'success_s': 3.0}, None
    monkeypatch.setattr(cli, 'wait_for_graph', lambda *args: None)
    monkeypatch.setattr(cli, 'run_episode', fake_episode)

    class Session:
        procs = {}

        class node:
            episode, reset = None, type('Publisher', (), {'publish': lambda self, msg: None})()

    def run(seed, episodes):
        records, said = [], []
        args = _parse('--task', 'open_drawer', '--seed', str(seed), '--episodes', str(episodes))
        code = cli._episodes(Session(), args, records, [], time.monotonic(), said.append)
        return code, [r['outcome'] for r in records], said
    code, ran, said = run(1000, 3)
    assert code == 1 and ran == ['succeeded', 'refused', 'failed']
    assert any('seed 1001: REFUSED by planner_node (confidence 0.07)' in line for line in said)
    assert run(1001, 1)[:2] == (2, ['refused'])
    assert run(1000, 1)[0] == 0 and run(1002, 1)[0] == 1


def test_checkpoint_flags_reach_the_nodes_that_load_them(tmp_path):
    agent, low_level = tmp_path / 'agent.pt', tmp_path / 'rkd.pt'
    plain = cli.parameter_overrides(_parse('--task', 'open_box', '--seed', '1003'))
    assert 'sim_bridge_node:seed:=1003' in plain and not any(':checkpoint:=' in o for o in plain)
    overrides = cli.parameter_overrides(_parse('--task', 'open_box', '--agent-checkpoint', str(agent),
                                               '--low-level-checkpoint', str(low_level)))
    assert f'planner_node:checkpoint:={agent}' in overrides
    assert f'controller_node:checkpoint:={low_level}' in overrides
    commands = node_commands(list(NODES), default_params_file(), overrides)
    assert f'checkpoint:={low_level}' in ' '.join(commands['controller_node'])


GRAPH_WAIT = r"""
import time
import rclpy
from hdp_msgs_py import topics
from hdp_ros import ros
from hdp_msgs_py.msg import String
from hdp_bringup.demo.watcher import DemoNode

def missing_after(seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for node in nodes:
            rclpy.spin_once(node, timeout_sec=0.05)
    return demo.not_connected()

ros.init()
demo = DemoNode(lambda segment: None)
# A recorder in the demo's process subscribes to the instruction too.
demo.create_subscription(String, topics.INSTRUCTION, lambda msg: None, topics.COMMAND_QOS)
nodes = [demo]
print('before:', missing_after(3.0))
planner = rclpy.create_node('planner_node')
planner.create_subscription(String, topics.INSTRUCTION, lambda msg: None, topics.COMMAND_QOS)
nodes.append(planner)
print('after:', missing_after(3.0))
"""


@pytest.mark.dds
def test_the_graph_is_not_up_until_planner_node_itself_hears_instructions(ros_domain):
    """The demo's own subscriptions (a recorder's) on /hdp/instruction once counted as the
    planner's, and the first instruction of a recorded demo could be lost."""
    proc = subprocess.run([sys.executable, '-c', GRAPH_WAIT], env=_env(ros_domain), capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    before, after = (line for line in proc.stdout.splitlines() if line.startswith(('before:', 'after:')))
    assert 'planner_node subscribed to /hdp/instruction' in before
    assert 'planner_node subscribed to /hdp/instruction' not in after and 'sim_bridge_node' in after


def _alive(pid: int) -> bool:
    try:
        state = Path(f'/proc/{pid}/stat').read_text()
    except FileNotFoundError:
        return False
    return state[state.rindex(')') + 2] != 'Z'


def _node_pids(text: str) -> list[int]:
    return [int(p) for p in re.findall(r'\[demo\] started \w+ \(pid (\d+)\)', text)]


@pytest.mark.dds
def test_ctrl_c_stops_every_node_and_exits_130(tmp_path, ros_domain):
    proc = subprocess.Popen(_hdp('demo', '--task', 'reach_target', '--out', str(tmp_path)), env=_env(ros_domain),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if 'waiting for the nodes' in line:
            break
    proc.send_signal(signal.SIGINT)
    lines += proc.stdout.readlines()
    proc.wait(timeout=60)
    text = ''.join(lines)
    assert proc.returncode == 130, text
    assert '[demo] SIGINT: stopped the nodes' in text
    pids = _node_pids(text)
    assert len(pids) == 4 and not any(_alive(p) for p in pids), text      # the three nodes and the manager


def _node_log_tails(logs: Path, lines: int = 20) -> str:
    """Each node's last lines, so a failure on a CI machine says what the nodes were doing."""
    return ''.join(f'\n--- {log.name} (last {lines} lines)\n' + '\n'.join(log.read_text().splitlines()[-lines:])
                   for log in sorted(logs.glob('*.log')))


@pytest.mark.dds
def test_demo_runs_a_reach_target_episode_end_to_end(tmp_path, ros_domain):
    out = tmp_path / 'demo'
    proc = subprocess.run(_hdp('demo', '--task', 'reach_target', '--seed', '1000', '--out', str(out), '--record'),
                          env=_env(ros_domain), capture_output=True, text=True, timeout=240)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text + _node_log_tails(out / 'logs')
    assert f'ROS_DOMAIN_ID={ros_domain} (from the environment)' in text
    assert re.search(r'segment 1: NBP \(.+\) gripper \w+ -> done at .+ observe\+predict [\d.]+ s', text), text
    pids = _node_pids(text)
    assert len(pids) == 4 and not any(_alive(p) for p in pids)

    summary = json.loads((out / 'summary.json').read_text())
    episode, = summary['episodes']
    assert episode['success'] and episode['seed'] == 1000 and episode['success_s'] > 0
    assert f"episode reach_target seed 1000 variation {episode['variation']}: {episode['instruction']!r}" in text
    for segment in episode['segments']:
        assert all(segment[stage] > 0 for stage in episode_log.STAGES), segment
    assert set(episode['cpu']) == {*cli.NODES, 'lifecycle_manager'}
    assert all(episode['cpu'][name]['cpu_s'] > 0 for name in cli.NODES)
    assert summary['figures']['episode_s']['n'] == 1
    with Image.open(out / episode['gif']) as gif:
        assert gif.n_frames >= 3 and gif.size == (media.GIF_WIDTH, 240)
    with Image.open(out / episode['plot']) as png:
        assert png.format == 'PNG'
    assert (out / episode['plot']).stat().st_size > 30_000
    assert all((out / 'logs' / f'{name}.log').is_file() for name in cli.NODES)

    # The recording: every topic a viewer needs, readable by plain rosbags, the robot moving.
    from rosbags.highlevel import AnyReader
    from hdp_bringup.demo.recording import RECORDED
    with AnyReader([out / 'bag']) as reader:
        assert {c.topic for c in reader.connections} == set(RECORDED)
        seen, joint1, nbp_frames = set(), [], 0
        for connection, _, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            seen.add(connection.topic)
            if connection.topic == '/tf':       # the sim's links and the planner's NBP frames
                joint1 += [t.transform.rotation.z for t in msg.transforms if t.child_frame_id == 'panda_link1']
                nbp_frames += sum(t.child_frame_id == 'hdp_next_best_pose' for t in msg.transforms)
    missing = set(RECORDED) - seen - {'/hdp/planner/cloud'}        # the cloud only with publish_cloud
    assert not missing, missing
    assert len(joint1) > 100 and max(joint1) - min(joint1) > 1e-3     # the arm turned
    assert nbp_frames == len(episode['segments'])

    # A one-episode recording is a demonstration as `ros2 bag record --custom-data` writes one
    # on a robot: it reads as an episode and the agent trains on it.
    from hdp_data.episodes import list_episodes, read_episode
    recorded = read_episode(out / 'bag')
    assert recorded.metadata == {'task': 'reach_target', 'seed': 1000, 'variation': episode['variation'],
                                 'instruction': episode['instruction'], 'success': True}
    assert recorded.instruction == episode['instruction'] and len(recorded.keyframes()) >= 2
    assert list_episodes(out) == [out / 'bag']
    train = subprocess.run(_hdp('train', 'high-level', '--data', str(out), '--out', str(tmp_path / 'agent.pt'),
                                '--steps', '2', '--batch', '2', '--cache', str(tmp_path / 'cache')),
                           env=_env(ros_domain), capture_output=True, text=True, timeout=300)
    assert train.returncode == 0, train.stdout[-2000:] + train.stderr[-2000:]
    assert (tmp_path / 'agent.pt').is_file()
