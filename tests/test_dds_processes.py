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
        'param_node:\n  ros__parameters:\n    checkpoint: models/rkd.pt\n    step_budget: 4\n'
        '    cameras: [front, side]\n'
        'other_node:\n  ros__parameters:\n    step_budget: 99\n')
    proc = start(ros_domain, 'params', '--ros-args', '--params-file', str(params),
                 '-p', 'step_budget:=7', '-p', 'timeout_sec:=2', '-r', '/hdp/status:=/robot/status',
                 '-r', '__ns:=/lab')
    values, _ = finish(proc)
    assert values == {
        'name': '/lab/param_node', 'use_sim_time': True, 'checkpoint': 'models/rkd.pt',
        'step_budget': 7,            # the command line wins over the file
        'timeout_sec': 2.0,          # an integer given for a double is accepted as a double
        'cameras': ['front', 'side'], 'untouched': True, 'status_topic': '/robot/status'}


def test_bad_parameter_type_is_refused(ros_domain):
    proc = start(ros_domain, 'params', '--ros-args', '-p', 'step_budget:=lots')
    _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0
    assert "parameter 'step_budget' is INTEGER, got STRING" in err


def test_publishing_wrong_type_raises_type_error_naming_topic_and_types(ros_domain):
    result, _ = finish(start(ros_domain, 'wrong_type'))
    assert result['error'] == ("publisher on '/hdp/instruction' takes std_msgs/msg/String, "
                               'got sensor_msgs/msg/Image')


def test_malformed_samples_are_dropped_and_the_reader_keeps_going(ros_domain):
    sub = start(ros_domain, 'sub', 'string', '--expect', '1', '--timeout', '20')
    time.sleep(0.5)
    writer = start(ros_domain, 'raw_truncated')
    received, err = finish(sub)
    sent, _ = finish(writer)
    # Truncated CDR never leaves the writer: Cyclone checks every payload
    # against the type (DDS_RETCODE_BAD_PARAMETER = -3).
    assert sent == {'refused': [-3, -3], 'accepted': [0, 0]}
    # What does arrive but does not decode is logged and dropped.
    assert received['got'] == [{'data': 'after the broken ones'}]
    assert err.count('dropped a malformed std_msgs/msg/String') == 1


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
    assert all(0.9 <= b - a <= 1.3 for a, b in zip(ticks, ticks[1:]))   # 1 s timer in sim seconds


def test_domains_do_not_cross(ros_domain):
    other = ros_domain % 199 + 1
    sub = start(other, 'sub', 'string', '--timeout', '4')
    pub = start(ros_domain, 'pub', 'string', '--count', '60', '--rate', '10')
    assert finish(sub)[0]['got'] == []
    pub.kill()
    pub.communicate()
