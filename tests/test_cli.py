"""`hdp topic` / `hdp node` against real nodes in other processes, and the YAML they read and write.

The discovery checks read `ros_discovery_info` with rosbags' deserialiser, an
implementation that knows nothing of rclpy's, the way `ros2 node list` does.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from hdp_msgs_py.message_yaml import message_from_yaml, message_to_yaml
from test_dds_processes import finish, start

pytestmark = pytest.mark.dds

HDP = [sys.executable, '-m', 'hdp_tools.cli.main']


def hdp(domain: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    return subprocess.run([*HDP, *args], env=env, text=True, capture_output=True, timeout=timeout)


def hdp_popen(domain: int, *args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    return subprocess.Popen([*HDP, *args], env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def echo_until(echo: subprocess.Popen, done, timeout: float) -> list[dict]:
    """The documents a running `hdp topic echo` prints, until done(documents so far)."""
    watchdog = threading.Timer(timeout, echo.kill)   # a silent echo then ends the read with EOF
    watchdog.start()
    docs, lines = [], []
    try:
        for line in echo.stdout:
            if line != '---\n':
                lines.append(line)
                continue
            docs.append(yaml.safe_load(''.join(lines)))
            lines = []
            if done(docs):
                break
    finally:
        watchdog.cancel()
    return docs


def interrupt(proc: subprocess.Popen) -> str:
    """Ctrl-C a CLI process; its stderr."""
    proc.send_signal(signal.SIGINT)
    return proc.communicate(timeout=20)[1]


def test_help_lists_every_command():
    out = subprocess.run([*HDP, '--help'], text=True, capture_output=True, check=True).stdout
    for command in ('topic', 'node', 'bench'):
        assert command in out
    out = subprocess.run([*HDP, 'topic', 'pub', '--help'], text=True, capture_output=True, check=True).stdout
    assert '--once' in out


def test_topic_pub_once_reaches_a_subscriber(ros_domain):
    sub = start(ros_domain, 'sub', 'string', '--expect', '1', '--timeout', '20')
    result = hdp(ros_domain, 'topic', 'pub', '--once', '/hdp/instruction', 'std_msgs/msg/String',
                 "{data: 'open the drawer'}")
    assert result.returncode == 0, result.stderr
    received, _ = finish(sub)
    assert received['got'] == [{'data': 'open the drawer'}]


def test_topic_pub_once_reaches_a_reader_that_is_not_on_shared_memory(ros_domain):
    """A reliable reader over UDP, of another DDS vendor (plain Cyclone DDS): it takes a writer's
    samples only from the first heartbeat after it discovered the writer, so a message published
    as soon as pub had matched it was acknowledged and lost (every time, with the reader joining
    after pub started, before pub waited for the reader to match it too)."""
    pub = hdp_popen(ros_domain, 'topic', 'pub', '--once', '/hdp/instruction', 'std_msgs/msg/String',
                    "{data: 'open the drawer'}")
    time.sleep(1.0)                              # pub is waiting for a subscriber
    reader = start(ros_domain, 'foreign_reader', '--timeout', '10')
    out, err = pub.communicate(timeout=60)
    received, _ = finish(reader)
    assert pub.returncode == 0 and out.startswith('publishing #1'), err
    assert received['got'] == ['open the drawer']


def test_topic_pub_exits_1_when_a_reader_never_acknowledges(ros_domain):
    reader = start(ros_domain, 'foreign_reader', '--stop-on-receipt', '--timeout', '60')
    try:
        result = hdp(ros_domain, 'topic', 'pub', '--once', '--max-wait', '3', '/hdp/instruction',
                     'std_msgs/msg/String', "{data: 'open the drawer'}")
    finally:
        reader.kill()
        reader.communicate()
    assert result.returncode == 1 and result.stdout.startswith('publishing #1'), result.stderr
    assert 'error: not every subscriber (1 matched) acknowledged what was published within 3.0 s' in result.stderr


def test_topic_pub_refuses_bad_input(ros_domain):
    result = hdp(ros_domain, 'topic', 'pub', '--once', '/x', 'std_msgs/msg/String', '{colour: red}')
    assert result.returncode == 1 and "has no field 'colour'" in result.stderr
    result = hdp(ros_domain, 'topic', 'pub', '--once', '/x', 'std_msgs/msg/Nope', '{}')
    assert result.returncode == 1 and 'unknown message type' in result.stderr
    assert 'Traceback' not in result.stderr


@pytest.mark.unit
def test_pub_values_fill_nested_messages_and_arrays_of_messages():
    msg = message_from_yaml('trajectory_msgs/msg/JointTrajectory',
                            '{header: {frame_id: world}, joint_names: [j1, j2], '
                            'points: [{positions: [1, 2.5], time_from_start: {sec: 2}}, {positions: [3, 4]}]}')
    assert msg.header.frame_id == 'world'
    assert [list(p.positions) for p in msg.points] == [[1.0, 2.5], [3.0, 4.0]]
    assert msg.points[0].time_from_start.sec == 2
    doc = yaml.safe_load(message_to_yaml(msg))
    assert doc['joint_names'] == ['j1', 'j2'] and doc['points'][1]['positions'] == [3.0, 4.0]
    # YAML writes 1 for 1.0; rclpy's float fields take only floats
    assert message_from_yaml('geometry_msgs/msg/PoseStamped', '{pose: {position: {x: 1}}}').pose.position.x == 1.0


@pytest.mark.unit
@pytest.mark.parametrize('type_name, values, error', [
    ('std_msgs/msg/String', '{data: [1, 2]}', "String.data: The 'data' field must be of type 'str'"),
    ('trajectory_msgs/msg/JointTrajectory', '{points: [{colour: red}]}', "has no field 'colour'"),
    ('trajectory_msgs/msg/JointTrajectory', '{points: {positions: [1]}}', 'expected a list'),
    ('sensor_msgs/msg/Image', '{height: -1}', 'Image.height'),
    ('std_msgs/msg/String', "{data: 'unclosed", 'not valid YAML'),
    ('std_msgs/msg/String', 'just text', 'needs a mapping'),
    ('std_msgs/msg/Nope', '{}', 'unknown message type'),
    ('nopkg/msg/String', '{}', 'unknown message type'),
    ('std_msgs/srv/String', '{}', 'unknown message type'),
])
def test_pub_values_are_checked(type_name, values, error):
    with pytest.raises(ValueError) as err:
        message_from_yaml(type_name, values)
    assert error in str(err.value)


@pytest.mark.unit
def test_echo_yaml_truncates_long_arrays_unless_full_length():
    msg = message_from_yaml('sensor_msgs/msg/Image', '{height: 1, width: 40, data: [%s]}' % ', '.join(['7'] * 40))
    data = yaml.safe_load(message_to_yaml(msg))['data']
    assert data[:32] == [7] * 32 and data[32:] == ['... (40 items)']
    assert yaml.safe_load(message_to_yaml(msg, None))['data'] == [7] * 40


def test_topic_echo_once_finds_the_type_and_prints_yaml(ros_domain):
    pub = start(ros_domain, 'pub', 'trajectory', '--count', '200', '--rate', '10')
    result = hdp(ros_domain, 'topic', 'echo', '--once', '--full-length',
                 '/panda_arm_controller/joint_trajectory')
    pub.kill()
    pub.communicate()
    assert result.returncode == 0, result.stderr
    doc = yaml.safe_load(result.stdout.split('---')[0])
    assert doc['joint_names'][0] == 'panda_joint1'
    assert len(doc['points']) == 64


def test_topic_echo_latched_tf_static_and_timeout(ros_domain):
    pub = start(ros_domain, 'pub', 'tf', '--qos', 'transient_local', '--count', '1', '--linger', '30')
    pub.stdout.readline()
    result = hdp(ros_domain, 'topic', 'echo', '--once', '--timeout', '10', '/tf_static')
    assert result.returncode == 0, result.stderr
    assert yaml.safe_load(result.stdout.split('---')[0])['transforms'][0]['child_frame_id'] == 'camera_0'
    result = hdp(ros_domain, 'topic', 'echo', '--timeout', '1', '/nothing', 'std_msgs/msg/String')
    assert result.returncode == 1 and 'no message on /nothing' in result.stderr
    pub.kill()
    pub.communicate()


def test_topic_echo_streams_until_ctrl_c(ros_domain):
    pub = start(ros_domain, 'pub', 'string', '--count', '300', '--rate', '10')
    echo = hdp_popen(ros_domain, 'topic', 'echo', '/hdp/instruction')
    docs = echo_until(echo, lambda docs: len(docs) >= 3, 40)
    err = interrupt(echo)
    pub.kill()
    pub.communicate()
    assert len(docs) == 3 and all(d['data'].startswith('open the drawer #') for d in docs), err
    assert echo.returncode == 0 and 'Traceback' not in err, err


def test_topic_list_and_node_list_see_other_processes(ros_domain):
    pub = start(ros_domain, 'pub', 'image', '--count', '400', '--rate', '10')
    sub = start(ros_domain, 'sub', 'string', '--timeout', '60', '--expect', '1000')
    time.sleep(2.0)
    running = [hdp_popen(ros_domain, *args) for args in (('topic', 'list', '-t'), ('node', 'list'),
                                                          ('node', 'list', '-a'))]
    topics, nodes, every_node = [p.communicate(timeout=60)[0].split('\n') for p in running]
    pub.kill()
    sub.kill()
    pub.communicate()
    sub.communicate()
    assert '/camera/front/color/image_raw [sensor_msgs/msg/Image]' in topics
    assert '/hdp/instruction [std_msgs/msg/String]' in topics
    assert {'/test_publisher', '/test_subscriber'} <= set(nodes)
    assert not any(n.startswith('/_hdp_cli') for n in nodes)   # hidden
    assert {'/test_publisher', '/test_subscriber'} <= set(every_node)
    assert any(n.startswith('/_hdp_cli_') for n in every_node)  # -a: hidden ones too


def test_ros_discovery_info_decodes_with_rosbags(ros_domain):
    """What `ros2 node list` reads, decoded by an independent implementation."""
    sub = start(ros_domain, 'sub', 'string', '--timeout', '60', '--expect', '1000')
    # the reader discovers by unicast only: it finds the participants already up when it starts
    time.sleep(2.0)
    reader = subprocess.run([sys.executable, str(Path(__file__).with_name('discovery_reader.py'))],
                            env=dict(os.environ, ROS_DOMAIN_ID=str(ros_domain)), text=True,
                            capture_output=True, timeout=60)
    sub.kill()
    sub.communicate()
    assert reader.returncode == 0, reader.stderr
    nodes = json.loads(reader.stdout)
    entry = next(n for n in nodes if n['name'] == 'test_subscriber')
    assert entry['namespace'] == '/'
    assert len(entry['readers']) >= 1 and all(len(g) == 32 for g in entry['readers'])


def test_planner_node_executable_acknowledges_an_instruction(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args', '-p', 'autostart:=true',
                             '-p', 'use_sim_time:=false'], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    # /hdp/status keeps its history (transient local): the acknowledgement follows 'ready'
    # Generous waits: with both cores busy the node has taken over 30 s to load and answer.
    echo = hdp_popen(ros_domain, 'topic', 'echo', '--timeout', '60', '/hdp/status', 'std_msgs/msg/String')
    time.sleep(2.0)
    result = hdp(ros_domain, 'topic', 'pub', '--once', '-w', '1', '--max-wait', '50', '/hdp/instruction',
                 'std_msgs/msg/String', "{data: 'open the drawer'}")
    docs = echo_until(echo, lambda docs: "'open the drawer'" in docs[-1]['data'], 60)
    err = interrupt(echo)
    node.send_signal(signal.SIGINT)
    node.communicate(timeout=10)
    assert result.returncode == 0, result.stderr
    assert echo.returncode == 0, err
    assert docs and "'open the drawer'" in docs[-1]['data'], (docs, err)
    assert node.returncode == 0


# --- damaged checkpoints: one line naming the file, never torch's traceback or advice ----------------

def _damaged_checkpoint(tmp_path) -> Path:
    """The released RK-Diffuser cut after 5 kB: a zip whose header is whole (torch's reader fails
    with an OSError, not an unpickling error)."""
    from hdp_learning import checkpoints
    path = tmp_path / 'cut.pt'
    path.write_bytes(checkpoints.default_path('rk_diffuser.pt').read_bytes()[:5000])
    return path


@pytest.mark.parametrize('command', [
    ('eval', 'low-level', '--methods', 'rkd', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '1000',
     '--checkpoint', '{bad}'),
    ('eval', 'hierarchy', '--agents', 'hdp', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '1000',
     '--low-level-checkpoint', '{bad}'),
    ('eval', 'hierarchy', '--agents', 'hdp', '--tasks', 'reach_target', '--episodes', '1', '--seed-start', '1000',
     '--agent-checkpoint', '{bad}'),
    ('plot', 'low-level', '--checkpoint', '{bad}', '--out', '{tmp}/fig.png'),
    ('bench', 'controller', '--checkpoint', '{bad}', '--tasks', 'reach_target', '--episodes', '1'),
    ('eval', 'high-level-offline', '--checkpoint', '{bad}', '--data', '{tmp}'),
], ids=lambda c: ' '.join(c[:2]) + (' ' + c[-2] if 'hierarchy' in c else ''))
def test_a_damaged_checkpoint_is_one_line_naming_the_file(tmp_path, command):
    bad = _damaged_checkpoint(tmp_path)
    argv = [a.format(bad=bad, tmp=tmp_path) for a in command]
    proc = subprocess.run([*HDP, *argv], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, OMP_NUM_THREADS='1'))
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if str(bad) in line]
    assert len(errors) == 1 and 'is not a readable checkpoint' in errors[0], proc.stderr
    assert 'Traceback' not in proc.stderr and 'weights_only' not in proc.stderr + proc.stdout
