"""Small ROS programs the cross-process tests start as separate processes.

Each prints one JSON line on stdout with what it saw, so tests assert on facts
from another process, never on shared memory.

    python dds_procs.py pub string|trajectory|image [--qos ...] [--count N]
    python dds_procs.py sub string|trajectory|image [--qos ...] [--expect N]
    python dds_procs.py raising_sub        # callback raises on the first message
    python dds_procs.py params --ros-args ...
    python dds_procs.py set_params NODE --params '[[name, value], ...]'   # as `ros2 param set`, one by one
    python dds_procs.py foreign_writer     # plain cyclonedds writer, a string that is not UTF-8
    python dds_procs.py foreign_reader [--stop-on-receipt]   # plain cyclonedds reader: UDP only
    python dds_procs.py gripper_goals --goals '[[position, max_effort], ...]'   # GripperCommand goals
"""

import argparse
import hashlib
import json
import os
import signal
import sys
import threading
import time

import numpy as np
import rclpy

from hdp_msgs_py import conversions
from hdp_ros import ros
from hdp_msgs_py.msg import String, TFMessage, TransformStamped
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

QOS = {
    'reliable': QoSProfile(depth=10),
    'best_effort': QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT),
    'transient_local': QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL),
}
JOINTS = [f'panda_joint{i}' for i in range(1, 8)]


def make(kind: str, i: int):
    if kind == 'string':
        return String(data=f'open the drawer #{i}')
    if kind == 'trajectory':
        positions = np.linspace(0, 1, 64)[:, None] * np.arange(1, 8)[None, :] * 0.1 + i
        return conversions.build_joint_trajectory(JOINTS, positions, np.arange(1, 65) * 0.05)
    if kind == 'image':
        pixels = np.random.default_rng(i).integers(0, 255, (480, 640, 3), dtype=np.uint8)
        return conversions.numpy_to_image(pixels, 'rgb8')
    if kind == 'tf':
        return TFMessage(transforms=[TransformStamped(child_frame_id=f'camera_{i}')])
    raise ValueError(kind)


def summary(kind: str, msg) -> dict:
    if kind == 'string':
        return {'data': msg.data}
    if kind == 'trajectory':
        names, positions, times, _ = conversions.parse_joint_trajectory(msg)
        return {'joints': names, 'shape': list(positions.shape), 'sum': round(float(positions.sum()), 6),
                'last_time': round(float(times[-1]), 6)}
    if kind == 'image':
        pixels = conversions.image_to_numpy(msg)
        return {'shape': list(pixels.shape), 'sha1': hashlib.sha1(pixels.tobytes()).hexdigest()}
    if kind == 'tf':
        return {'child': msg.transforms[0].child_frame_id}
    raise ValueError(kind)


def topic_of(kind: str) -> str:
    return {'string': '/hdp/instruction', 'trajectory': '/panda_arm_controller/joint_trajectory',
            'image': '/camera/front/color/image_raw', 'tf': '/tf_static'}[kind]


_nodes = []


def make_node(name: str, **kwargs) -> ros.Node:
    """A node that main() destroys before it exits: its participant then leaves the graph at
    once (its peers stop waiting on it) and takes its shared memory with it."""
    _nodes.append(ros.Node(name, **kwargs))
    return _nodes[-1]


def spin_until(node, done, timeout: float) -> None:
    """Spin until done() or timeout; a shutdown (SIGINT/SIGTERM) just ends the wait."""
    end = time.monotonic() + timeout
    try:
        while rclpy.ok() and time.monotonic() < end and not done():
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        return      # shut down from outside: the caller reports what it saw
    except RuntimeError:
        if not ros.shutting_down():     # the signal landed while the wait set was built
            raise


def emit(**facts):
    print(json.dumps(facts), flush=True)


def run_pub(args):
    node = make_node('test_publisher')
    msg_type = type(make(args.kind, 0))
    pub = node.create_publisher(msg_type, topic_of(args.kind), QOS[args.qos])
    sent = []
    for i in range(args.count):
        msg = make(args.kind, i)
        pub.publish(msg)
        sent.append(summary(args.kind, msg))
        rclpy.spin_once(node, timeout_sec=1.0 / args.rate)
    emit(sent=sent)
    spin_until(node, lambda: False, args.linger)


def run_sub(args):
    node = make_node('test_subscriber')
    got = []
    msg_type = type(make(args.kind, 0))
    node.create_subscription(msg_type, topic_of(args.kind), lambda m: got.append(summary(args.kind, m)),
                             QOS[args.qos])
    spin_until(node, lambda: len(got) >= args.expect, args.timeout)
    emit(got=got)


def run_raising_sub(args):
    node = make_node('raising_subscriber')
    got = []

    def callback(msg):
        got.append(msg.data)
        if len(got) == 1:
            raise RuntimeError('deliberate failure in a callback')

    node.create_subscription(String, '/hdp/instruction', callback, 10)
    spin_until(node, lambda: len(got) >= args.expect, args.timeout)
    emit(got=got)


def run_params(args):
    node = make_node('param_node')
    node.declare_parameter('checkpoint', 'models/default.pt')
    node.declare_parameter('step_budget', 10)
    node.declare_parameter('timeout_sec', 5.0)
    node.declare_parameter('cameras', ['front'])
    node.declare_parameter('untouched', True)
    emit(name=node.get_fully_qualified_name(), use_sim_time=node.get_parameter('use_sim_time').value,
         **{n: node.get_parameter(n).value
            for n in ('checkpoint', 'step_budget', 'timeout_sec', 'cameras', 'untouched')},
         status_topic=node.resolve_topic_name('/hdp/status'))


def run_set_params(args):
    """Set each parameter of node ``args.kind`` on its own, as `ros2 param set` does, then read them all
    back: each answer (successful, reason) and the values the node holds afterwards."""
    from rclpy.parameter_client import AsyncParameterClient
    node = make_node('param_setter')
    client = AsyncParameterClient(node, args.kind)
    if not client.wait_for_services(timeout_sec=args.timeout):
        raise SystemExit(f'no parameter services of {args.kind} within {args.timeout} s')
    answers = []
    for name, value in json.loads(args.params):
        future = client.set_parameters([Parameter(name, value=value)])
        spin_until(node, future.done, args.timeout)
        result, = future.result().results
        answers.append([name, result.successful, result.reason])
    names = sorted({name for name, _ in json.loads(args.params)})
    future = client.get_parameters(names)
    spin_until(node, future.done, args.timeout)
    values = {name: parameter_value_to_python(value) for name, value in zip(names, future.result().values)}
    emit(answers=answers, values=values)


def run_clock(args):
    """Publish /clock: sim time starts at 1000 s and runs 10x faster than the wall."""
    from hdp_msgs_py.msg import Clock, Time
    node = make_node('fake_sim')
    pub = node.create_publisher(Clock, '/clock', 10)
    start = time.monotonic()
    while rclpy.ok() and time.monotonic() - start < args.timeout:
        sim_ns = 1000 * 10**9 + int((time.monotonic() - start) * 10 * 1e9)
        pub.publish(Clock(clock=Time(sec=sim_ns // 10**9, nanosec=sim_ns % 10**9)))
        time.sleep(0.01)


def run_sim_time(args):
    """With use_sim_time, now() and timers follow /clock."""
    node = make_node('sim_time_node', parameter_overrides=[Parameter('use_sim_time', value=True)])
    ticks = []
    node.create_timer(1.0, lambda: ticks.append(node.get_clock().now().nanoseconds / 1e9))
    spin_until(node, lambda: len(ticks) >= 5, args.timeout)
    emit(ticks=ticks)


def run_foreign_writer(args):
    """A peer on another middleware (plain cyclonedds, no ROS) sends a string that is
    not UTF-8, then a good one."""
    from dataclasses import dataclass

    from cyclonedds._clayer import ddspy_write
    from cyclonedds.core import Policy, Qos
    from cyclonedds.idl import IdlStruct
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic

    @dataclass
    class String_(IdlStruct, typename='std_msgs::msg::dds_::String_'):
        data: str

    import cyclone_loopback
    _domain, participant = cyclone_loopback.participant(int(os.environ['ROS_DOMAIN_ID']))
    writer = DataWriter(participant, Topic(participant, 'rt/hdp/instruction', String_),
                        qos=Qos(Policy.Reliability.Reliable(0), Policy.History.KeepLast(10)))
    deadline = time.monotonic() + 10
    while not writer.get_matched_subscriptions() and time.monotonic() < deadline:
        time.sleep(0.05)
    not_utf8 = b'\x00\x01\x00\x00\x03\x00\x00\x00\xff\xfe\x00\x00'
    accepted = [ddspy_write(writer._ref, not_utf8)]
    writer.write(String_(data='after the broken one'))
    time.sleep(1.0)
    emit(accepted=accepted)


def run_foreign_reader(args):
    """A reliable, volatile reader of /hdp/instruction on another middleware (plain cyclonedds,
    which never uses Fast DDS's shared memory): prints what it got after --timeout (it stays up,
    and so acknowledges, as a subscriber that lives on does). --stop-on-receipt: SIGSTOPs itself
    once a message arrives, before it acknowledges (it does on the writer's next heartbeat): a
    reader that never acknowledges."""
    from dataclasses import dataclass

    from cyclonedds.core import Policy, Qos
    from cyclonedds.idl import IdlStruct
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    @dataclass
    class String_(IdlStruct, typename='std_msgs::msg::dds_::String_'):
        data: str

    import cyclone_loopback
    _domain, participant = cyclone_loopback.participant(int(os.environ['ROS_DOMAIN_ID']))
    reader = DataReader(participant, Topic(participant, 'rt/hdp/instruction', String_),
                        qos=Qos(Policy.Reliability.Reliable(0), Policy.History.KeepLast(10)))
    got = []
    end = time.monotonic() + args.timeout
    while time.monotonic() < end:
        got += [s.data for s in reader.take(10) if isinstance(s, String_)]     # not the writer's end
        if got and args.stop_on_receipt:
            os.kill(os.getpid(), signal.SIGSTOP)
        time.sleep(0.01)
    emit(got=got)


def run_gripper_goals(args):
    """Send each (position, max_effort) of --goals to the GripperCommand server in turn; print
    whether each was accepted, its result, and the /hdp/status lines seen."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import GripperCommand
    from rclpy.action import ActionClient

    from hdp_msgs_py import topics
    node = make_node('gripper_probe')
    status = []
    node.create_subscription(String, topics.STATUS, lambda m: status.append(m.data), topics.STATUS_QOS)
    client = ActionClient(node, GripperCommand, topics.GRIPPER_ACTION)
    spin_until(node, client.server_is_ready, args.timeout)
    answers = []
    for position, max_effort in json.loads(args.goals):
        goal = GripperCommand.Goal()
        goal.command.position, goal.command.max_effort = float(position), float(max_effort)
        sent = client.send_goal_async(goal)
        spin_until(node, sent.done, args.timeout)
        if not sent.result().accepted:
            answers.append({'accepted': False})
            continue
        result = sent.result().get_result_async()
        spin_until(node, result.done, args.timeout)
        answers.append({'accepted': True, 'succeeded': result.result().status == GoalStatus.STATUS_SUCCEEDED,
                        'position': result.result().result.position,
                        'reached_goal': result.result().result.reached_goal})
    spin_until(node, lambda: False, 0.5)       # the last status lines
    emit(answers=answers, status=status)


def main():
    ros.init(args=sys.argv)
    argv = [a for a in sys.argv[1:]]
    if '--ros-args' in argv:
        argv = argv[:argv.index('--ros-args')]
    parser = argparse.ArgumentParser()
    parser.add_argument('role')
    parser.add_argument('kind', nargs='?', default='string')
    parser.add_argument('--qos', default='reliable', choices=sorted(QOS))
    parser.add_argument('--count', type=int, default=20)
    parser.add_argument('--rate', type=float, default=10.0)
    parser.add_argument('--linger', type=float, default=0.0)
    parser.add_argument('--expect', type=int, default=1)
    parser.add_argument('--timeout', type=float, default=15.0)
    parser.add_argument('--stop-on-receipt', action='store_true')
    parser.add_argument('--goals', default='[]')
    parser.add_argument('--params', default='[]')
    args = parser.parse_args(argv)
    try:
        globals()[f'run_{args.role}'](args)
    finally:
        # What these programs saw is printed by now; the tests judge that, not the middleware's
        # teardown, which under load has hung past the test's timeout once (CI, 2026-12-03: the
        # subscriber had printed what it got): end the process anyway.
        # Interpreter finalisation (leftover middleware handles) is skipped for the same reason.
        threading.Thread(target=_exit_if_hung, daemon=True).start()
        for node in _nodes:
            node.destroy_node()
        rclpy.try_shutdown()


def _exit_if_hung():
    time.sleep(10.0)
    print('dds_procs: middleware teardown hung for 10 s; exiting', file=sys.stderr, flush=True)
    os._exit(0)


if __name__ == '__main__':
    main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
