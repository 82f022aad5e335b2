"""Launch arguments: task, seed, method and params_file on hdp_graph.launch.py and `hdp launch`."""

import argparse
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import launch_stubs
import pytest
import yaml

from hdp_bringup.launch_cli import NODES, launch_overrides

pytestmark = pytest.mark.unit

LAUNCH_FILE = Path(__file__).resolve().parents[1] / 'src' / 'hdp_bringup' / 'launch' / 'hdp_graph.launch.py'


def test_launch_arguments_set_the_parameters_of_the_nodes_they_concern():
    assert launch_overrides() == {}
    assert launch_overrides('open_drawer', '3', 'planner') == {
        'sim_bridge_node': {'task': 'open_drawer', 'seed': 3}, 'controller_node': {'method': 'planner'}}
    for bad, match in ((('make_tea', None, None), 'unknown task'), ((None, '-1', None), 'whole number'),
                       ((None, 'x', None), 'whole number'), ((None, None, 'magic'), 'unknown method')):
        with pytest.raises(ValueError, match=match):
            launch_overrides(*bad)


def test_hdp_launch_and_hdp_demo_take_every_method_controller_node_takes():
    """One list of low-level methods (hdp_controller.methods): `--method planner_rrt` was refused
    by `hdp launch` and `hdp demo` while controller_node ran it."""
    from hdp_bringup.demo import cli as demo_cli
    from hdp_controller import controller_node
    assert 'planner_rrt' in controller_node.METHODS
    for method in controller_node.METHODS:
        assert launch_overrides(method=method) == {'controller_node': {'method': method}}
        parser = argparse.ArgumentParser()
        demo_cli.configure(parser)
        assert parser.parse_args(['--task', 'reach_target', '--method', method]).method == method


def _launch_file_nodes(monkeypatch, tmp_path, given: dict) -> tuple[list, dict]:
    launch_stubs.install(monkeypatch, {'hdp_bringup': tmp_path})
    return launch_stubs.run(LAUNCH_FILE, given)


def test_the_launch_file_declares_its_arguments_and_passes_them_on(monkeypatch, tmp_path):
    nodes, declared = _launch_file_nodes(monkeypatch, tmp_path, {})
    assert set(declared) == {'task', 'seed', 'method', 'params_file'}
    assert declared['params_file'] == str(tmp_path / 'config' / 'hdp_graph.yaml')
    assert [n.kwargs['name'] for n in nodes] == [*NODES, 'lifecycle_manager']
    graph_nodes, manager = nodes[:-1], nodes[-1]
    assert all(n.kwargs['parameters'] == [declared['params_file'], {}] for n in graph_nodes)    # the YAML alone
    # The managed nodes go up controller first: it is active before the planner sends it work.
    assert manager.kwargs['parameters'] == [declared['params_file'], {'node_names': ['controller_node',
                                                                                    'planner_node']}]

    nodes, _ = _launch_file_nodes(monkeypatch, tmp_path, {'task': 'open_oven', 'seed': '7', 'method': 'planner',
                                                         'params_file': '/robot/params.yaml'})
    parameters = {n.kwargs['name']: n.kwargs['parameters'] for n in nodes if n.kwargs['name'] in NODES}
    assert parameters == {'sim_bridge_node': ['/robot/params.yaml', {'task': 'open_oven', 'seed': 7}],
                          'planner_node': ['/robot/params.yaml', {}],
                          'controller_node': ['/robot/params.yaml', {'method': 'planner'}]}


@pytest.mark.dds
def test_hdp_launch_takes_the_same_arguments(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1')
    graph = subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'launch', '--nodes', 'sim_bridge_node',
                              '--task', 'open_oven', '--seed', '7', '-p', 'sim_bridge_node:camera_rate_hz:=0.0'],
                             env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        echo = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'topic', 'echo', '--once',
                               '--timeout', '60', '/hdp/sim/episode', 'std_msgs/msg/String'],
                              env=env, text=True, capture_output=True, timeout=90)
    finally:
        graph.send_signal(signal.SIGINT)
        output, _ = graph.communicate(timeout=30)
    assert echo.returncode == 0, echo.stderr + output
    episode = json.loads(yaml.safe_load(echo.stdout.split('\n---')[0])['data'])     # echo prints YAML
    assert (episode['task'], episode['seed']) == ('open_oven', 7)
    bad = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'launch', '--method', 'magic'],
                         env=env, text=True, capture_output=True, timeout=60)
    assert bad.returncode == 2 and "unknown method 'magic'" in bad.stderr


def test_the_viewer_configs_name_topics_the_graph_publishes():
    """hdp.rviz and the Foxglove layout show only topics hdp demo --record records."""
    import re

    from hdp_bringup.demo.recording import RECORDED
    config = LAUNCH_FILE.parents[1] / 'config'
    rviz = yaml.safe_load((config / 'hdp.rviz').read_text())
    displays = rviz['Visualization Manager']['Displays']
    rviz_topics = {d['Topic']['Value'] for d in displays if 'Topic' in d}
    rviz_topics |= {d['Description Topic']['Value'] for d in displays if 'Description Topic' in d}
    assert rviz['Visualization Manager']['Global Options']['Fixed Frame'] == 'world'
    layout = json.loads((config / 'hdp_foxglove_layout.json').read_text())
    foxglove_topics = set(layout['configById']['3D!hdp']['topics'])
    foxglove_topics |= {panel['imageMode']['imageTopic'] for panel in layout['configById'].values()
                        if 'imageMode' in panel}
    foxglove_topics |= {re.match(r'(/[^.]+)', p['value']).group(1)
                        for p in layout['configById']['Plot!joints']['paths']}
    for topics in (rviz_topics, foxglove_topics):
        assert topics and topics <= set(RECORDED), topics - set(RECORDED)
    assert '/robot_description' in rviz_topics & foxglove_topics
