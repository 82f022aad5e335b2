"""The real-robot path, checked without a robot or ROS 2 launch: what hdp_real_fr3.launch.py
starts and with which parameters, against Jazzy franka_ros2's and realsense-ros's names."""

from pathlib import Path

import launch_stubs
import numpy as np
import pytest
import yaml

from hdp_motion import panda

pytestmark = pytest.mark.unit

BRINGUP = Path(__file__).resolve().parents[1] / 'src' / 'hdp_bringup'
LAUNCH = BRINGUP / 'launch' / 'hdp_real_fr3.launch.py'


def _launch(monkeypatch, tmp_path, **given):
    shares = {'hdp_bringup': BRINGUP, 'franka_bringup': tmp_path / 'franka_bringup'}
    launch_stubs.install(monkeypatch, shares)
    actions, declared = launch_stubs.run(LAUNCH, {'front_extrinsics': '1 0 1.3 0 0 0 1',
                                                  'side_extrinsics': '0 -1 1.2 0 0 0 1', **given})
    nodes = [a for a in actions if 'package' in a.kwargs]
    (franka,) = [a for a in actions if a not in nodes]
    return nodes, franka, declared


def test_franka_ros2_is_included_with_the_fr3_and_our_controllers(monkeypatch, tmp_path):
    nodes, franka, declared = _launch(monkeypatch, tmp_path, robot_ip='172.16.0.9')
    assert 'robot_type' not in declared               # fixed: a FER cannot run on Jazzy franka_ros2
    source, = franka.args
    assert source.args[0] == str(tmp_path / 'franka_bringup' / 'launch' / 'franka.launch.py')
    arguments = dict(franka.kwargs['launch_arguments'])
    assert arguments['robot_type'] == 'fr3' and arguments['robot_ip'] == '172.16.0.9'
    assert arguments['controllers_yaml'] == str(BRINGUP / 'config' / 'hdp_fr3_controllers.yaml')
    spawned = [n.kwargs['arguments'][0] for n in nodes if n.kwargs.get('executable') == 'spawner']
    assert spawned == ['hdp_arm_controller']

    controllers = yaml.safe_load(Path(arguments['controllers_yaml']).read_text())['/**']
    manager = controllers['controller_manager']['ros__parameters']
    # every controller franka.launch.py spawns, and ours, is defined (ours replaces its YAML)
    assert {'joint_state_broadcaster', 'franka_robot_state_broadcaster', 'hdp_arm_controller'} <= set(manager)
    assert manager['hdp_arm_controller']['type'] == 'joint_trajectory_controller/JointTrajectoryController'
    arm = controllers['hdp_arm_controller']['ros__parameters']
    assert arm['joints'] == list(panda.joint_names('fr3')) and set(arm['gains']) == set(arm['joints'])

    controller, = [n for n in nodes if n.kwargs.get('executable') == 'controller_node']
    assert controller.kwargs['remappings'] == [('/panda_arm_controller/joint_trajectory',
                                                '/hdp_arm_controller/joint_trajectory')]
    assert controller.kwargs['parameters'][1] == {'joint_prefix': 'fr3', 'robot_type': 'fr3'}
    panda.limits_for(controller.kwargs['parameters'][1]['robot_type'])
    manager, = [n for n in nodes if n.kwargs.get('executable') == 'lifecycle_manager']
    assert manager.kwargs['parameters'][1] == {'node_names': ['controller_node', 'planner_node']}
    assert 'lifecycle_manager' in yaml.safe_load((BRINGUP / 'config' / 'hdp_real_fr3.yaml').read_text())


def test_the_arm_is_mounted_on_base_never_on_link0_and_cameras_named_as_the_nodes_expect(monkeypatch, tmp_path):
    nodes, _, declared = _launch(monkeypatch, tmp_path)
    transforms = {}
    for node in nodes:
        if node.kwargs.get('executable') == 'static_transform_publisher':
            a = node.kwargs['arguments']
            transforms[a[a.index('--child-frame-id') + 1]] = (a[a.index('--frame-id') + 1],
                                                             [float(a[a.index(k) + 1]) for k in ('--x', '--y', '--z')])
    # franka_description's URDF: base -> fr3_link0; a second parent for link0 would break TF
    assert transforms['base'] == ('world', list(panda.ROBOT_BASE))
    assert not any(child.endswith('link0') for child in transforms)
    assert transforms['front_color_optical_frame'][0] == 'world' == transforms['side_color_optical_frame'][0]
    cameras = {n.kwargs['name']: n for n in nodes if n.kwargs.get('package') == 'realsense2_camera'}
    assert set(cameras) == {'front', 'side'}
    for name, node in cameras.items():
        assert node.kwargs['namespace'] == 'camera'         # -> /camera/<name>/color/image_raw, as topics.py
        parameters = node.kwargs['parameters'][0]
        assert parameters['align_depth.enable'] and not parameters['publish_tf']
        assert parameters['camera_name'] == name
    assert np.allclose([float(v) for v in declared['base_pose'].split()], [*panda.ROBOT_BASE, 0, 0, 0, 1])
