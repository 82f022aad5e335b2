"""`hdp topic` / `hdp node` against real nodes in other processes.

The discovery checks read `ros_discovery_info` with rosbags' deserialiser, an
implementation that knows nothing of ours, the way `ros2 node list` does.
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

from test_dds_processes import finish, start

HDP = [sys.executable, '-m', 'hdp_msgs_py.cli.main']


def hdp(domain: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    return subprocess.run([*HDP, *args], env=env, text=True, capture_output=True, timeout=timeout)


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


def test_topic_pub_refuses_bad_input(ros_domain):
    result = hdp(ros_domain, 'topic', 'pub', '--once', '/x', 'std_msgs/msg/String', '{colour: red}')
    assert result.returncode == 1 and "has no field 'colour'" in result.stderr
    result = hdp(ros_domain, 'topic', 'pub', '--once', '/x', 'std_msgs/msg/Nope', '{}')
    assert result.returncode == 1 and 'unknown message type' in result.stderr


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


def test_topic_list_and_node_list_see_other_processes(ros_domain):
    pub = start(ros_domain, 'pub', 'image', '--count', '400', '--rate', '10')
    sub = start(ros_domain, 'sub', 'string', '--timeout', '60', '--expect', '1000')
    time.sleep(2.0)
    topics = hdp(ros_domain, 'topic', 'list', '-t')
    nodes = hdp(ros_domain, 'node', 'list')
    pub.kill()
    sub.kill()
    pub.communicate()
    sub.communicate()
    assert '/camera/front/color/image_raw [sensor_msgs/msg/Image]' in topics.stdout.splitlines()
    assert '/hdp/instruction [std_msgs/msg/String]' in topics.stdout.splitlines()
    assert {'/test_publisher', '/test_subscriber'} <= set(nodes.stdout.split())
    assert not any(n.startswith('/_hdp_cli') for n in nodes.stdout.split())   # hidden


def test_ros_discovery_info_decodes_with_rosbags(ros_domain):
    """What `ros2 node list` reads, decoded by an independent implementation."""
    sub = start(ros_domain, 'sub', 'string', '--timeout', '60', '--expect', '1000')
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
    import signal
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                             '-p', 'use_sim_time:=false'], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    echo = subprocess.Popen([*HDP, 'topic', 'echo', '--once', '--timeout', '20', '/hdp/status',
                             'std_msgs/msg/String'], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    time.sleep(2.0)
    result = hdp(ros_domain, 'topic', 'pub', '--once', '-w', '2', '/hdp/instruction',
                 'std_msgs/msg/String', "{data: 'open the drawer'}")
    out, err = echo.communicate(timeout=30)
    node.send_signal(signal.SIGINT)
    node.communicate(timeout=10)
    assert result.returncode == 0, result.stderr
    assert echo.returncode == 0, err
    assert "'open the drawer'" in yaml.safe_load(out.split('---')[0])['data']
    assert node.returncode == 0
