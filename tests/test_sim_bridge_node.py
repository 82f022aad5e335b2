"""sim_bridge_node as a process: topics of a real Panda + two D415s, JTC-like execution, resets."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hdp_sim_bridge.bridge import gripper_target, parse_cameras, parse_reset

pytestmark = pytest.mark.unit


@pytest.mark.dds
def test_bridge_node_end_to_end(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                             '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=4.0',
                             '-p', 'task:=reach_target', '-p', 'seed:=3'],
                            env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        probe = subprocess.run([sys.executable, str(Path(__file__).with_name('bridge_probe.py'))], env=env,
                               text=True, capture_output=True, timeout=120)
    finally:
        node.send_signal(signal.SIGINT)
        _, node_err = node.communicate(timeout=20)
    assert probe.returncode == 0, probe.stderr + node_err
    facts = json.loads(probe.stdout.strip().splitlines()[-1])
    assert facts['first_episode']['task'] == 'reach_target' and facts['first_episode']['seed'] == 3
    assert facts['moved_after_bad'] < 1e-3                       # refused: nothing moved
    assert facts['error_after_good'] < 0.01                       # executed
    assert facts['last_episode'] == {**facts['last_episode'], 'task': 'open_drawer', 'seed': 5, 'variation': 2}
    assert facts['joint_state_hz'] >= 100
    assert facts['clock_advances']
    assert facts['images'] == {'/camera/front/color/image_raw': ['rgb8', 64, 48],
                               '/camera/side/aligned_depth_to_color/image_raw': ['16UC1', 64, 48],
                               '/camera/front/color/camera_info': ['info', 64, 48]}
    # Both latched /tf_static messages (the cameras' extrinsics, then the arm's fixed joints)
    # reach a subscriber that joined later; movable joints come on /tf, parent -> child.
    assert facts['tf'] == ['front_color_optical_frame', 'panda_grasptarget', 'panda_hand', 'panda_link0',
                           'panda_link8', 'side_color_optical_frame']
    assert facts['tf_moving'] == {'panda_link1': 'panda_link0', 'panda_link2': 'panda_link1',
                                  'panda_link3': 'panda_link2', 'panda_link4': 'panda_link3',
                                  'panda_link5': 'panda_link4', 'panda_link6': 'panda_link5',
                                  'panda_link7': 'panda_link6', 'panda_leftfinger': 'panda_hand',
                                  'panda_rightfinger': 'panda_hand'}
    assert '<robot name="panda"' in facts['robot_description'] and 'package://' not in facts['robot_description']
    status = '\n'.join(facts['status'])
    assert 'rejected arm trajectory' in status and 'above its limit' in status
    assert "unknown: ['elbow']" in status
    assert "rejected reset: unknown task 'make_tea'" in status
    assert 'rejected reset: open_drawer has variations 0..2, got 999' in status, status
    assert facts['success_reports_after_bad_variation'] >= 3            # 2 Hz, still running
    assert facts['last_episode']['seed'] == 5                           # the old episode stands
    assert facts['success_reports'] > 0
    assert node.returncode == 0, node_err


def test_reset_requests_are_validated():
    assert parse_reset('{"task": "open_box", "seed": 4}') == {'task': 'open_box', 'seed': 4}
    assert parse_reset('{"task": "open_drawer", "seed": 4, "variation": 2}')['variation'] == 2
    for bad in ('open_box', '{"task": "open_box", "seed": -1}', '{"task": "open_box", "colour": 1}', '[]',
                '{"task": "open_drawer", "seed": 4, "variation": 3}', '{"task": "open_box", "variation": 1}'):
        with pytest.raises(ValueError):
            parse_reset(bad)


def test_gripper_commands_are_validated():
    from hdp_motion import panda
    from hdp_msgs_py import conversions
    names = list(panda.FINGER_JOINTS)
    assert gripper_target(conversions.build_joint_trajectory(names, [[0.04, 0.04]], [0.5])) is True
    assert gripper_target(conversions.build_joint_trajectory(names, [[0.0, 0.0]], [0.5])) is False
    with pytest.raises(ValueError, match='within'):
        gripper_target(conversions.build_joint_trajectory(names, [[0.09, 0.09]], [0.5]))
    with pytest.raises(ValueError, match='must name'):
        gripper_target(conversions.build_joint_trajectory(['a', 'b'], [[0.0, 0.0]], [0.5]))


def test_camera_selections_are_validated_and_keep_the_cameras_order():
    known = ('front', 'side')
    assert parse_cameras('front,side', known) == ('front', 'side')
    assert parse_cameras(' side , front ', known) == ('front', 'side')
    assert parse_cameras('side', known) == ('side',)
    assert parse_cameras('', known) == parse_cameras('  ', known) == ()
    for bad in ('top', 'front,top', 'front,,side', 'front side', 'FRONT'):
        with pytest.raises(ValueError, match='unknown camera'):
            parse_cameras(bad, known)


@pytest.mark.dds
def test_a_bad_first_episode_stops_the_node_at_start_with_one_line(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    proc = subprocess.run([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                           '-p', 'task:=open_drawer', '-p', 'variation:=7'],
                          env=env, text=True, capture_output=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert 'bad first episode: open_drawer has variations 0..2, got 7' in proc.stderr
    assert 'Traceback' not in proc.stderr


def test_link_transforms_chain_to_the_simulators_hand_pose_and_the_urdf_loads():
    """world -> panda_link0 -> ... -> panda_hand composed from the TF messages is where PyBullet
    has the hand, with the arm away from its home; the description's meshes exist."""
    import xml.etree.ElementTree as ET
    from urllib.parse import urlparse

    import numpy as np

    from hdp_motion import panda
    from hdp_msgs_py.conversions import quat_to_matrix
    from hdp_sim_bridge.bridge import SimBridge
    from hdp_sim_bridge.robot_state import robot_description

    def matrix(t):
        m = np.eye(4)
        r, q = t.transform.translation, t.transform.rotation
        m[:3, :3], m[:3, 3] = quat_to_matrix([q.x, q.y, q.z, q.w]), [r.x, r.y, r.z]
        return m
    bridge = SimBridge(32, 24)
    try:
        bridge.reset('reach_target', 0)
        bridge.world.reset_arm(panda.HOME + np.array([0.3, -0.2, 0.1, 0.2, -0.3, 0.2, 0.4]))
        transforms = {t.child_frame_id: t for t in bridge.robot_tf_static().transforms + bridge.robot_tf().transforms}
        frame, pose = 'panda_hand', np.eye(4)
        while frame != 'world':
            pose = matrix(transforms[frame]) @ pose
            frame = transforms[frame].header.frame_id
        state = bridge.world.client.getLinkState(bridge.world.robot, 8, computeForwardKinematics=True)
        assert np.allclose(pose[:3, 3], state[4], atol=1e-6)
        assert np.allclose(pose[:3, :3], quat_to_matrix(state[5]), atol=1e-6)
    finally:
        bridge.close()
    urdf = ET.fromstring(robot_description())
    links = {link.get('name') for link in urdf.iter('link')}
    assert set(transforms) <= links | {'panda_link0'}
    meshes = [urlparse(m.get('filename')) for m in urdf.iter('mesh')]
    assert meshes and all(m.scheme == 'file' and Path(m.path).is_file() for m in meshes)


@pytest.mark.dds
def test_the_actions_have_ros_2s_names_and_types_on_the_wire(ros_domain):
    """Seen from a process with no HDP code (plain Cyclone DDS): the sim serves
    FollowJointTrajectory and GripperCommand under the names and DDS types ROS 2 gives them."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                             '-p', 'camera_rate_hz:=0.0'], env=env, text=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        time.sleep(3.0)
        reader = subprocess.run([sys.executable, str(Path(__file__).with_name('endpoints_reader.py'))], env=env,
                                text=True, capture_output=True, timeout=60)
    finally:
        node.send_signal(signal.SIGINT)
        node.communicate(timeout=20)
    assert reader.returncode == 0, reader.stderr
    wire = json.loads(reader.stdout)
    subscriptions = {tuple(p) for p in wire['subscriptions']}
    publications = {tuple(p) for p in wire['publications']}
    for action, kind in (('panda_arm_controller/follow_joint_trajectory', 'FollowJointTrajectory'),
                         ('franka_gripper/gripper_action', 'GripperCommand')):
        assert (f'rq/{action}/_action/send_goalRequest',
                f'control_msgs::action::dds_::{kind}_SendGoal_Request_') in subscriptions, subscriptions
        assert (f'rr/{action}/_action/get_resultReply',
                f'control_msgs::action::dds_::{kind}_GetResult_Response_') in publications
        assert (f'rt/{action}/_action/feedback',
                f'control_msgs::action::dds_::{kind}_FeedbackMessage_') in publications
        assert (f'rt/{action}/_action/status', 'action_msgs::msg::dds_::GoalStatusArray_') in publications


@pytest.mark.dds
def test_gripper_goals_are_refused_with_a_status_line_and_answered_in_franka_gripper_units(ros_domain):
    """franka_gripper's gripper_action: position is half the width, in the goal and the result
    alike; a goal it cannot act on is refused (not accepted and then aborted) with a status line."""
    from test_dds_processes import finish, start
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                             '-p', 'camera_rate_hz:=0.0'], env=env, text=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    nan, inf = float('nan'), float('inf')
    bad = [(nan, 20), (inf, 20), (-0.02, 20), (1e9, 20), (0.04, nan), (0.04, -5), (0.04, inf)]
    try:
        probe = start(ros_domain, 'gripper_goals', '--timeout', '60',
                      '--goals', json.dumps([*bad, (0.0, 20), (0.04, 20)]))     # NaN, Infinity: Python's JSON
        facts, _ = finish(probe, timeout=120)
    finally:
        node.send_signal(signal.SIGINT)
        _, node_err = node.communicate(timeout=20)
    answers = facts['answers']
    assert answers[:len(bad)] == [{'accepted': False}] * len(bad), (answers, node_err)
    refusals = [s for s in facts['status'] if s.startswith('sim_bridge_node: rejected gripper goal: ')]
    assert [r.split(', got ')[-1] for r in refusals] == ['nan', 'inf', '-0.02', '1000000000.0', 'nan', '-5.0', 'inf']
    assert refusals[0].endswith('position (half the width) must be within [0, 0.04] m, got nan')
    assert refusals[-1].endswith('max_effort must be a finite force >= 0 N, got inf')
    closed, opened = answers[len(bad):]
    assert closed['accepted'] and closed['succeeded'] and closed['reached_goal'] and closed['position'] < 0.0025
    assert opened['accepted'] and opened['succeeded'] and opened['reached_goal']
    assert opened['position'] == pytest.approx(0.04, abs=0.0025)        # half the 0.08 m width, as asked
    assert node.returncode == 0, node_err
