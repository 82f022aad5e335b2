"""Small ROS programs the cross-process tests start as separate processes.

Each prints one JSON line on stdout with what it saw, so tests assert on facts
from another process, never on shared memory.

    python dds_procs.py pub string|trajectory|image [--qos ...] [--count N]
    python dds_procs.py sub string|trajectory|image [--qos ...] [--expect N]
    python dds_procs.py raising_sub        # callback raises on the first message
    python dds_procs.py params --ros-args ...
    python dds_procs.py wrong_type
    python dds_procs.py raw_truncated      # plain cyclonedds writer, broken payloads
"""

import argparse
import hashlib
import json
import sys
import time

import numpy as np

from hdp_msgs_py import conversions, ros
from hdp_msgs_py.msg import Image, String, TFMessage, TransformStamped
from hdp_msgs_py.ros import DurabilityPolicy, QoSProfile, ReliabilityPolicy

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


def spin_until(node, done, timeout: float) -> None:
    """Spin until done() or timeout; a shutdown (SIGINT/SIGTERM) just ends the wait."""
    end = time.monotonic() + timeout
    try:
        while ros.ok() and time.monotonic() < end and not done():
            ros.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, ros.ExternalShutdownException):
        return      # shut down from outside: the caller reports what it saw


def emit(**facts):
    print(json.dumps(facts), flush=True)


def run_pub(args):
    node = ros.Node('test_publisher')
    msg_type = type(make(args.kind, 0))
    pub = node.create_publisher(msg_type, topic_of(args.kind), QOS[args.qos])
    sent = []
    for i in range(args.count):
        msg = make(args.kind, i)
        pub.publish(msg)
        sent.append(summary(args.kind, msg))
        ros.spin_once(node, timeout_sec=1.0 / args.rate)
    emit(sent=sent)
    spin_until(node, lambda: False, args.linger)


def run_sub(args):
    node = ros.Node('test_subscriber')
    got = []
    msg_type = type(make(args.kind, 0))
    node.create_subscription(msg_type, topic_of(args.kind), lambda m: got.append(summary(args.kind, m)),
                             QOS[args.qos])
    spin_until(node, lambda: len(got) >= args.expect, args.timeout)
    emit(got=got)


def run_raising_sub(args):
    node = ros.Node('raising_subscriber')
    got = []

    def callback(msg):
        got.append(msg.data)
        if len(got) == 1:
            raise RuntimeError('deliberate failure in a callback')

    node.create_subscription(String, '/hdp/instruction', callback, 10)
    spin_until(node, lambda: len(got) >= args.expect, args.timeout)
    emit(got=got)


def run_params(args):
    node = ros.Node('param_node')
    node.declare_parameter('checkpoint', 'models/default.pt')
    node.declare_parameter('step_budget', 10)
    node.declare_parameter('timeout_sec', 5.0)
    node.declare_parameter('cameras', ['front'])
    node.declare_parameter('untouched', True)
    emit(name=node.get_fully_qualified_name(), use_sim_time=node.get_parameter('use_sim_time').value,
         **{n: node.get_parameter(n).value
            for n in ('checkpoint', 'step_budget', 'timeout_sec', 'cameras', 'untouched')},
         status_topic=node.resolve_topic_name('/hdp/status'))


def run_clock(args):
    """Publish /clock: sim time starts at 1000 s and runs 10x faster than the wall."""
    from hdp_msgs_py.msg import Clock, Time
    node = ros.Node('fake_sim')
    pub = node.create_publisher(Clock, '/clock', 10)
    start = time.monotonic()
    while ros.ok() and time.monotonic() - start < args.timeout:
        sim_ns = 1000 * 10**9 + int((time.monotonic() - start) * 10 * 1e9)
        pub.publish(Clock(clock=Time(sec=sim_ns // 10**9, nanosec=sim_ns % 10**9)))
        time.sleep(0.01)


def run_sim_time(args):
    """With use_sim_time, now() and timers follow /clock."""
    node = ros.Node('sim_time_node', parameter_overrides=[ros.Parameter('use_sim_time', value=True)])
    ticks = []
    node.create_timer(1.0, lambda: ticks.append(node.get_clock().now().nanoseconds / 1e9))
    spin_until(node, lambda: len(ticks) >= 5, args.timeout)
    emit(ticks=ticks)


def run_wrong_type(args):
    node = ros.Node('wrong_type_node')
    pub = node.create_publisher(String, '/hdp/instruction', 10)
    try:
        pub.publish(Image())
    except TypeError as err:
        emit(error=str(err))
    else:
        emit(error=None)


def run_raw_truncated(args):
    """Send broken payloads, then a good one, with cyclonedds' C calls."""
    from cyclonedds._clayer import ddspy_write
    from cyclonedds.pub import DataWriter

    from hdp_msgs_py import cdr
    from hdp_msgs_py.dds import default_context
    from hdp_msgs_py.dds.qos import to_dds
    node = ros.Node('raw_writer')
    writer = DataWriter(default_context.participant, default_context.dds_topic('rt/hdp/instruction', String),
                        qos=to_dds(QOS['reliable']))
    deadline = time.monotonic() + 10
    while not writer.get_matched_subscriptions() and time.monotonic() < deadline:
        time.sleep(0.05)
    good = cdr.serialize(String(data='after the broken ones'), pad_to=4)
    # Cyclone refuses structurally broken CDR itself (truncated, bad lengths):
    # record what it returns, then send what it lets through but ROS cannot
    # decode: a string that is not UTF-8.
    refused = [ddspy_write(writer._ref, payload)
               for payload in (good[:6] + bytes(2), b'\x00\x01\x00\x00\xff\xff\xff\x7f')]
    not_utf8 = b'\x00\x01\x00\x00\x03\x00\x00\x00\xff\xfe\x00\x00'
    accepted = [ddspy_write(writer._ref, payload) for payload in (not_utf8, good)]
    time.sleep(1.0)
    emit(refused=refused, accepted=accepted)
    node.destroy_node()


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
    args = parser.parse_args(argv)
    try:
        globals()[f'run_{args.role}'](args)
    finally:
        ros.try_shutdown()


if __name__ == '__main__':
    main()
