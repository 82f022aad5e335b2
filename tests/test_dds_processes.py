"""Messages cross real process boundaries over DDS, with ROS 2 semantics.

Every test runs its processes on a DDS domain of its own.
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.dds

PROCS = Path(__file__).with_name('dds_procs.py')


def start(domain: int, *args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    return subprocess.Popen([sys.executable, str(PROCS), *args], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(proc: subprocess.Popen, timeout: float = 60) -> tuple[dict, str]:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f'process timed out; stderr:\n{err}')
    assert proc.returncode == 0, f'exit {proc.returncode}; stderr:\n{err}'
    return json.loads(out.strip().splitlines()[-1]), err


@pytest.mark.parametrize('kind', ['string', 'trajectory', 'image'])
def test_message_crosses_processes(ros_domain, kind):
    sub = start(ros_domain, 'sub', kind, '--expect', '3', '--timeout', '20')
    pub = start(ros_domain, 'pub', kind, '--count', '60', '--rate', '10')
    received, _ = finish(sub)
    pub.kill()
    pub.communicate()
    got = received['got']
    assert len(got) == 3
    # each received message is one the publisher made, bit for bit
    import dds_procs
    expected = [dds_procs.summary(kind, dds_procs.make(kind, i)) for i in range(60)]
    assert all(g in expected for g in got)
    if kind == 'image':
        assert got[0]['shape'] == [480, 640, 3]


def test_best_effort_writer_does_not_match_reliable_reader(ros_domain):
    reliable = start(ros_domain, 'sub', 'string', '--qos', 'reliable', '--timeout', '4')
    best_effort = start(ros_domain, 'sub', 'string', '--qos', 'best_effort', '--timeout', '10')
    pub = start(ros_domain, 'pub', 'string', '--qos', 'best_effort', '--count', '80', '--rate', '10')
    assert finish(reliable)[0]['got'] == []
    assert len(finish(best_effort)[0]['got']) == 1        # control: the writer is there
    pub.kill()
    pub.communicate()


def test_late_transient_local_subscriber_gets_last_tf_static(ros_domain):
    pub = start(ros_domain, 'pub', 'tf', '--qos', 'transient_local', '--count', '3', '--linger', '20')
    line = pub.stdout.readline()        # the publisher is done publishing when it reports
    assert json.loads(line)['sent'][-1] == {'child': 'camera_2'}
    time.sleep(0.5)
    late = start(ros_domain, 'sub', 'tf', '--qos', 'transient_local', '--expect', '1', '--timeout', '10')
    received, _ = finish(late)
    pub.kill()
    pub.communicate()
    assert received['got'] == [{'child': 'camera_2'}]


def test_raising_callback_is_logged_and_node_keeps_serving(ros_domain):
    sub = start(ros_domain, 'raising_sub', '--expect', '3', '--timeout', '20')
    pub = start(ros_domain, 'pub', 'string', '--count', '60', '--rate', '10')
    received, err = finish(sub)
    pub.kill()
    pub.communicate()
    assert len(received['got']) == 3
    assert 'deliberate failure in a callback' in err and '[ERROR]' in err


def test_parameters_from_yaml_and_command_line(ros_domain, tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text(
        '/**:\n  ros__parameters:\n    use_sim_time: true\n'
        '/lab/param_node:\n  ros__parameters:\n    checkpoint: models/rkd.pt\n    step_budget: 4\n'
        '    cameras: [front, side]\n'
        'other_node:\n  ros__parameters:\n    step_budget: 99\n')
    proc = start(ros_domain, 'params', '--ros-args', '--params-file', str(params),
                 '-p', 'timeout_sec:=2.5', '-r', '/hdp/status:=/robot/status',
                 '-r', '__ns:=/lab')
    values, _ = finish(proc)
    assert values == {
        'name': '/lab/param_node', 'use_sim_time': True, 'checkpoint': 'models/rkd.pt',
        'step_budget': 4,            # the node's own section, not other_node's
        'timeout_sec': 2.5,
        'cameras': ['front', 'side'], 'untouched': True, 'status_topic': '/robot/status'}


@pytest.mark.parametrize('value, expected', [
    ('lots', "[ERROR] [planner_node]: Trying to set parameter 'max_segments' to 'lots' of type 'STRING', "
             "expecting type 'INTEGER'"),
    ('0', "[ERROR] [planner_node]: parameter 'max_segments' must be >= 1, got 0"),
    ('camera_size:=[640]', "[ERROR] [planner_node]: parameter 'camera_size' must be [width, height] in 8..4096"),
    ('camera_size:=[128, 4]', "[ERROR] [planner_node]: parameter 'camera_size' must be [width, height] in 8..4096")])
def test_a_node_refuses_a_bad_parameter_in_one_line(ros_domain, value, expected):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    parameter = value if ':=' in value else f'max_segments:={value}'
    proc = subprocess.run([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args', '-p', parameter],
                          env=env, text=True, capture_output=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1].startswith(expected)
    assert 'Traceback' not in proc.stderr


def test_a_foreign_peers_bad_string_does_not_stop_the_reader(ros_domain):
    """Fast DDS (rclpy) and Cyclone (a plain cyclonedds peer) on one topic: a string that
    is not UTF-8 arrives with its bad bytes replaced, and the next one arrives intact."""
    sub = start(ros_domain, 'sub', 'string', '--expect', '2', '--timeout', '20')
    time.sleep(0.5)
    writer = start(ros_domain, 'foreign_writer')
    received, _ = finish(sub)
    sent, _ = finish(writer)
    assert sent == {'accepted': [0]}
    assert received['got'] == [{'data': '\ufffd\ufffd'}, {'data': 'after the broken one'}]


def test_sigterm_and_sigint_exit_cleanly(ros_domain):
    import signal
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc = start(ros_domain, 'sub', 'string', '--timeout', '60')
        time.sleep(2.0)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert json.loads(out)['got'] == []


def test_use_sim_time_follows_clock(ros_domain):
    clock = start(ros_domain, 'clock', '--timeout', '30')
    node = start(ros_domain, 'sim_time', '--timeout', '20')
    result, _ = finish(node)
    clock.kill()
    clock.communicate()
    ticks = result['ticks']
    assert len(ticks) == 5
    assert all(1000 <= t < 2000 for t in ticks)                 # sim time, not the wall clock
    # A 1 s timer in sim seconds (sim time runs 10x the wall). The first tick is the one
    # that fell due when sim time jumped from 0 to the first /clock: it keeps no period.
    assert all(0.9 <= b - a <= 1.3 for a, b in zip(ticks[1:], ticks[2:]))


def test_domains_do_not_cross(ros_domain):
    other = ros_domain % 199 + 1
    sub = start(other, 'sub', 'string', '--timeout', '4')
    pub = start(ros_domain, 'pub', 'string', '--count', '60', '--rate', '10')
    assert finish(sub)[0]['got'] == []
    pub.kill()
    pub.communicate()
