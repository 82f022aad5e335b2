"""Parameters at run time: each node changes the ones in its RUNTIME set live, judged by the rules
it starts with, and refuses the others (read-only) and invalid values with a reason, keeping the
value it had. The probe's finding: every set_parameters succeeded and changed nothing."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from hdp_controller.controller_node import ControllerNode
from hdp_planner.planner_node import PlannerNode
from hdp_ros import ros
from hdp_ros.liveness import Liveness
from hdp_sim_bridge.sim_bridge_node import SimBridgeNode
from test_planner_node import tiny_checkpoint  # noqa: F401 (a fixture)

pytestmark = pytest.mark.unit

TESTS = Path(__file__).parent
NODES = (PlannerNode, ControllerNode, SimBridgeNode)


def _defaults(node_class, **changes) -> dict:
    return {**{name: default for name, (default, _) in node_class.PARAMETERS.items()}, **changes}


@pytest.mark.parametrize('node_class', NODES)
def test_every_node_starts_on_its_defaults_and_changes_only_its_own_parameters_live(node_class):
    node_class.check_parameters(_defaults(node_class))
    assert node_class.RUNTIME and node_class.RUNTIME < set(node_class.PARAMETERS)


@pytest.mark.parametrize('node_class, changes, reason', [
    (PlannerNode, {'max_segments': -3}, "parameter 'max_segments' must be >= 1, got -3"),
    (PlannerNode, {'min_confidence': 7.0}, "parameter 'min_confidence' must be in [0, 1), got 7.0"),
    (PlannerNode, {'result_timeout_s': -1.0}, "parameter 'result_timeout_s' must be > 0, got -1.0"),
    (PlannerNode, {'queue_policy': 'lifo'}, "parameter 'queue_policy' must be one of replace, queue, refuse, "
                                            "got 'lifo'"),
    (PlannerNode, {'camera_size': [4, 4]}, "parameter 'camera_size' must be [width, height] in 8..4096, or "
                                           "[0, 0], got [4, 4]"),
    (PlannerNode, {'depth_filter': 'median'}, "parameter 'depth_filter' must be one of none, realsense, got 'median'"),
    (ControllerNode, {'method': 'no_such_method'}, "parameter 'method' must be one of"),
    (ControllerNode, {'depth_filter': 'bilateral'}, "parameter 'depth_filter' must be one of none, realsense, "
                                                    "got 'bilateral'"),
    (ControllerNode, {'velocity_scale': 1.5}, "parameter 'velocity_scale' must be in (0, 1], got 1.5"),
    (ControllerNode, {'state_timeout_s': -2.0}, "parameter 'state_timeout_s' must be > 0, got -2.0"),
    (ControllerNode, {'unsettled': 'wait'}, "parameter 'unsettled' must be fail or carry_on, got 'wait'"),
    (ControllerNode, {'plan_attempts': 0}, "parameter 'plan_attempts' must be >= 1, got 0"),
    (SimBridgeNode, {'real_time_factor': -1.0}, "parameter 'real_time_factor' must be >= 0, got -1.0"),
    (SimBridgeNode, {'camera_rate_hz': -2.0}, "parameter 'camera_rate_hz' must be >= 0, got -2.0"),
    (SimBridgeNode, {'joint_state_rate_hz': 0.0}, "parameter 'joint_state_rate_hz' must be > 0, got 0.0"),
    (SimBridgeNode, {'task': 'no_such_task'}, 'bad first episode: '),
    (SimBridgeNode, {'sensor_profile': 'no_such_profile'}, 'bad sensor parameters: '),
])
def test_each_nodes_rules_name_the_parameter_and_the_value(node_class, changes, reason):
    with pytest.raises(ros.StartupError) as refused:
        node_class.check_parameters(_defaults(node_class, **changes))
    assert str(refused.value).startswith(reason)


def test_the_planner_loop_and_liveness_take_new_limits():
    from test_planner_node import _loop
    loop = _loop(max_segments=8, camera_timeout_s=5.0)
    loop.configure(2, 1.0, 9.0, 0.0, 'replace', 3)
    assert loop.on_instruction('open the drawer', 0.0)[0].text == "instruction 'open the drawer': up to 2 segments"
    assert loop.step(0.0, 0) == []
    assert loop.step(1.5, 1_500_000_000)[-1].reason.startswith('camera front, side timed out after 1.0 s')
    with pytest.raises(ValueError, match='queue_policy must be one of'):
        loop.configure(2, 1.0, 9.0, 0.0, 'lifo', 3)
    live = Liveness(5.0)
    live.heard(0.0)
    assert live.problem(3.0, 3.0) is None
    live.set_timeout(2.0)
    assert live.problem(3.0, 3.0).startswith('no /joint_states for 3.0 s')
    with pytest.raises(ValueError):
        live.set_timeout(-1.0)


# --- processes ---------------------------------------------------------------------------------

def _set(env, node: str, params: list) -> dict:
    """dds_procs.py set_params: each answer and the values read back afterwards."""
    proc = subprocess.run([sys.executable, str(TESTS / 'dds_procs.py'), 'set_params', node, '--timeout', '60',
                           '--params', json.dumps(params)], env=env, text=True, capture_output=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _stop(proc) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    return proc.communicate(timeout=30)[1]


READ_ONLY = 'Trying to set a read-only parameter: {}.'


@pytest.mark.dds
def test_planner_node_applies_runtime_changes_and_refuses_the_probes_values(ros_domain, tiny_checkpoint):
    """The probe's values are refused with the reason `ros2 param set` prints and change nothing;
    max_segments and camera_timeout_s changed while the node runs rule the next instruction."""
    checkpoint = tiny_checkpoint
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true',
                                '-p', f'checkpoint:={checkpoint}', '-p', 'camera_timeout_s:=30.0'],
                               env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        facts = _set(env, 'planner_node', [
            ['max_segments', -3], ['min_confidence', 7.0], ['result_timeout_s', -1.0],
            ['checkpoint', '/etc/passwd'], ['queue_policy', 'no_such_policy'],
            ['max_segments', 2], ['camera_timeout_s', 1.0], ['use_sim_time', False]])
        listener = subprocess.run([sys.executable, str(TESTS / 'test_planner_node.py'), 'listen', '1', '30',
                                   'open the middle drawer'], env=env, text=True, capture_output=True, timeout=90)
    finally:
        planner_err = _stop(planner)
    assert facts['answers'] == [
        ['max_segments', False, "parameter 'max_segments' must be >= 1, got -3"],
        ['min_confidence', False, "parameter 'min_confidence' must be in [0, 1), got 7.0"],
        ['result_timeout_s', False, "parameter 'result_timeout_s' must be > 0, got -1.0"],
        ['checkpoint', False, READ_ONLY.format('checkpoint')],
        ['queue_policy', False, "parameter 'queue_policy' must be one of replace, queue, refuse, "
                                "got 'no_such_policy'"],
        ['max_segments', True, ''], ['camera_timeout_s', True, ''], ['use_sim_time', True, '']]
    assert facts['values'] == {'max_segments': 2, 'min_confidence': PlannerNode.PARAMETERS['min_confidence'][0],
                               'result_timeout_s': 60.0, 'checkpoint': str(checkpoint), 'queue_policy': 'replace',
                               'camera_timeout_s': 1.0, 'use_sim_time': False}
    assert listener.returncode == 0, listener.stderr + planner_err
    seen = json.loads(listener.stdout.strip().splitlines()[-1])
    assert "planner_node: instruction 'open the middle drawer': up to 2 segments" in seen['status']
    assert seen['outcomes'][0]['reason'].startswith('camera front, side timed out after 1.0 s')
    assert 'applied max_segments := 2' in planner_err


@pytest.mark.dds
def test_controller_node_applies_runtime_changes_and_refuses_the_probes_values(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    controller = subprocess.Popen([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                                   '-p', 'autostart:=true',
                                   '-p', 'method:=planner'],
                                  env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        facts = _set(env, 'controller_node', [
            ['method', 'no_such_method'], ['checkpoint', '/etc/passwd'], ['velocity_scale', 1.5],
            ['segment_timeout_s', -1.0], ['plan_attempts', 0], ['velocity_scale', 0.5], ['unsettled', 'carry_on']])
    finally:
        controller_err = _stop(controller)
    assert facts['answers'] == [
        ['method', False, READ_ONLY.format('method')], ['checkpoint', False, READ_ONLY.format('checkpoint')],
        ['velocity_scale', False, "parameter 'velocity_scale' must be in (0, 1], got 1.5"],
        ['segment_timeout_s', False, "parameter 'segment_timeout_s' must be > 0, got -1.0"],
        ['plan_attempts', False, "parameter 'plan_attempts' must be >= 1, got 0"],
        ['velocity_scale', True, ''], ['unsettled', True, '']]
    assert facts['values'] == {'method': 'planner', 'checkpoint': '', 'velocity_scale': 0.5, 'segment_timeout_s': 10.0,
                               'plan_attempts': ControllerNode.PARAMETERS['plan_attempts'][0], 'unsettled': 'carry_on'}
    assert 'applied velocity_scale := 0.5' in controller_err and "applied unsettled := 'carry_on'" in controller_err


@pytest.mark.dds
def test_sim_bridge_node_applies_rates_live_and_refuses_episode_parameters(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_width:=64', '-p', 'camera_height:=48'],
                              env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        facts = _set(env, 'sim_bridge_node', [
            ['task', 'open_drawer'], ['seed', 3], ['real_time_factor', -1.0], ['camera_rate_hz', -2.0],
            ['real_time_factor', 2.0], ['camera_rate_hz', 0.0]])
    finally:
        bridge_err = _stop(bridge)
    assert facts['answers'] == [
        ['task', False, READ_ONLY.format('task')], ['seed', False, READ_ONLY.format('seed')],
        ['real_time_factor', False, "parameter 'real_time_factor' must be >= 0, got -1.0"],
        ['camera_rate_hz', False, "parameter 'camera_rate_hz' must be >= 0, got -2.0"],
        ['real_time_factor', True, ''], ['camera_rate_hz', True, '']]
    assert facts['values'] == {'task': 'reach_target', 'seed': 0, 'real_time_factor': 2.0, 'camera_rate_hz': 0.0}
    assert 'applied real_time_factor := 2.0' in bridge_err
