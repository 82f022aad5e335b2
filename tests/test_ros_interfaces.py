"""The interface packages built at setup (tf2_msgs, control_msgs) are ROS 2 Jazzy's on the wire.

An instance goes through Fast DDS and its payload is taken as received; rosbags, which knows
these types from its own Jazzy store or from the upstream definitions, must read it and write
back the same bytes; and the RIHS01 type hashes rosidl generated must be the ones rosbags
computes.
"""

import json
import re
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.dds

pytest.importorskip('control_msgs.action', reason='the interface packages are built by `make setup`')

from builtin_interfaces.msg import Duration  # noqa: E402
from control_msgs.action import FollowJointTrajectory, GripperCommand  # noqa: E402
from control_msgs.msg import GripperCommand as GripperCommandMsg  # noqa: E402
from control_msgs.msg import JointComponentTolerance, JointTolerance  # noqa: E402
from geometry_msgs.msg import Transform, TransformStamped, Vector3  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

UPSTREAM = Path(__file__).parents[1] / 'src/hdp_msgs_py/ros_interfaces'
SHARE = Path(sys.prefix) / 'share'


@pytest.fixture(scope='module')
def typestore():
    return jazzy_typestore()


@pytest.fixture(scope='module')
def wire():
    """wire(msg) -> the CDR payload a subscriber receives for ``msg``. (Not rclpy's
    serialize_message: with Fast DDS it returns bytes past the CDR, uninitialised memory.)"""
    import os

    import rclpy
    from hdp_ros import ros
    ros.init(args=[], domain_id=int(os.environ.get('ROS_DOMAIN_ID', 0)) or 230)
    node = rclpy.create_node('wire_check')

    def payload(msg) -> bytes:
        topic = f'/wire_check/{type(msg).__name__}'
        received = []
        node.create_subscription(type(msg), topic, received.append, 10, raw=True)
        publisher = node.create_publisher(type(msg), topic, 10)
        for _ in range(100):
            if publisher.get_subscription_count():
                publisher.publish(msg)
                break
            rclpy.spin_once(node, timeout_sec=0.05)
        for _ in range(100):
            if received:
                return received[0]
            rclpy.spin_once(node, timeout_sec=0.05)
        raise AssertionError(f'{topic}: nothing received')
    yield payload
    node.destroy_node()
    rclpy.try_shutdown()


def jazzy_typestore():
    """Jazzy's store plus control_msgs from the upstream files (rosbags ships no control_msgs)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in ('JointTolerance', 'JointComponentTolerance', 'GripperCommand'):
        types.update(get_types_from_msg((UPSTREAM / f'control_msgs/msg/{name}.msg').read_text(),
                                        f'control_msgs/msg/{name}'))
    # An action names its package's messages without the package; rosbags would look for
    # them beside the action, rosidl looks in control_msgs/msg.
    local = re.compile(r'^(JointTolerance|JointComponentTolerance|GripperCommand)\b', re.MULTILINE)
    for action in ('FollowJointTrajectory', 'GripperCommand'):
        text = local.sub(r'control_msgs/msg/\1', (UPSTREAM / f'control_msgs/action/{action}.action').read_text())
        parts = text.split('\n---\n')
        for part, text in zip(('Goal', 'Result', 'Feedback'), parts):
            types.update(get_types_from_msg(text, f'control_msgs/action/{action}_{part}'))
    store.register(types)
    return store


def _transforms():
    return TFMessage(transforms=[TransformStamped(
        child_frame_id=f'camera_{i}', transform=Transform(translation=Vector3(x=0.1 * i, y=-2.5, z=1e-3)))
        for i in range(3)])


def _trajectory_goal():
    points = [JointTrajectoryPoint(positions=[0.1 * i] * 7, velocities=[0.0] * 7,
                                   time_from_start=Duration(sec=i, nanosec=5)) for i in range(4)]
    return FollowJointTrajectory.Goal(
        trajectory=JointTrajectory(joint_names=[f'fr3_joint{i}' for i in range(1, 8)], points=points),
        path_tolerance=[JointTolerance(name='fr3_joint1', position=0.05, velocity=-1.0)],
        component_goal_tolerance=[JointComponentTolerance(joint_name='x', component=4, position=0.01)],
        goal_time_tolerance=Duration(sec=0, nanosec=500_000_000))


CASES = [
    ('tf2_msgs/msg/TFMessage', _transforms),
    ('control_msgs/action/FollowJointTrajectory_Goal', _trajectory_goal),
    ('control_msgs/action/FollowJointTrajectory_Result',
     lambda: FollowJointTrajectory.Result(error_code=-5, error_string='goal tolerance violated')),
    ('control_msgs/action/GripperCommand_Goal',
     lambda: GripperCommand.Goal(command=GripperCommandMsg(position=0.04, max_effort=70.0))),
    ('control_msgs/action/GripperCommand_Result',
     lambda: GripperCommand.Result(position=0.02, effort=31.5, stalled=True, reached_goal=False)),
]


@pytest.mark.parametrize('type_name, make', CASES, ids=[c[0].rsplit('/', 1)[1] for c in CASES])
def test_wire_bytes_read_and_rewrite_identically_with_rosbags(typestore, wire, type_name, make):
    """Fast DDS payload -> rosbags -> bytes: the same CDR, and rclpy reads it back as sent.
    (Fast CDR leaves alignment padding uninitialised and pads the end to 4 bytes: both ignored.)"""
    original = make()
    payload = wire(original)
    rewritten = bytes(typestore.serialize_cdr(typestore.deserialize_cdr(payload, type_name), type_name))
    assert 0 <= len(payload) - len(rewritten) < 4
    assert deserialize_message(rewritten, type(original)) == original


def test_decoded_values_are_the_ones_sent(typestore, wire):
    goal = typestore.deserialize_cdr(wire(_trajectory_goal()), 'control_msgs/action/FollowJointTrajectory_Goal')
    assert goal.trajectory.joint_names[6] == 'fr3_joint7'
    assert goal.trajectory.points[3].positions[0] == pytest.approx(0.3)
    assert goal.path_tolerance[0].velocity == -1.0 and goal.component_goal_tolerance[0].component == 4
    assert goal.goal_time_tolerance.nanosec == 500_000_000


@pytest.mark.unit
@pytest.mark.parametrize('package, kind, name', [
    ('tf2_msgs', 'msg', 'TFMessage'), ('control_msgs', 'msg', 'JointTolerance'),
    ('control_msgs', 'msg', 'GripperCommand'), ('control_msgs', 'action', 'FollowJointTrajectory'),
    ('control_msgs', 'action', 'GripperCommand')])
def test_type_hashes_match_rosbags(typestore, package, kind, name):
    """rosidl's RIHS01 hashes of the built types (an action's Goal/Result/Feedback and the
    package's messages they nest included) against rosbags' own computation."""
    described = json.loads((SHARE / package / kind / f'{name}.json').read_text())['type_hashes']
    checked = 0
    for entry in described:
        if entry['type_name'].startswith(f'{package}/') and entry['type_name'] in typestore.types:
            assert typestore.hash_rihs01(entry['type_name']) == entry['hash_string'], entry['type_name']
            checked += 1
    assert checked >= 1
