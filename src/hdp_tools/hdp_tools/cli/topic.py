"""Inspect and use topics like `ros2 topic`: list, echo, pub."""

from __future__ import annotations

import math
import sys
import time

from rclpy.duration import Duration
from rclpy.exceptions import InvalidTopicNameException
from rclpy.qos import ReliabilityPolicy
from rclpy.validate_topic_name import validate_topic_name

from hdp_msgs_py.message_yaml import get_message, message_from_yaml, message_to_yaml
from .common import (DISCOVERY_WAIT, add_discovery_args, add_qos_args, cli_node, interrupted, qos_from_args,
                     qos_profile, spin_until)

# A volatile reader of another vendor's DDS (Cyclone DDS, ...) takes a writer's samples only from
# the first heartbeat it hears after it discovered the writer: a sample published before is
# acknowledged and never delivered (a Fast DDS reader still gets it from the writer's history).
# It discovers our writer up to one of Fast DDS's discovery heartbeats (1 s) and a resend after we
# discovered it, so the first message waits this long for such a reader.
FOREIGN_READER_SETTLE_S = 1.5
FAST_DDS_VENDOR_ID = bytes((0x01, 0x0f))      # the first two bytes of an RTPS GUID name its vendor


def configure(parser) -> None:
    """List, echo and publish topics on the ROS 2 graph."""
    sub = parser.add_subparsers(title='commands', metavar='COMMAND')
    parser.set_defaults(func=lambda args: parser.print_help() or 2)

    p = sub.add_parser('list', help='topics seen on the graph')
    p.add_argument('-t', '--show-types', action='store_true', help='print each topic\'s type')
    add_discovery_args(p)
    p.set_defaults(func=run_list)

    p = sub.add_parser('echo', help='print messages on a topic as YAML')
    p.add_argument('topic')
    p.add_argument('type', nargs='?', help="e.g. std_msgs/msg/String (found on the graph if left out)")
    p.add_argument('--once', action='store_true', help='exit after the first message')
    p.add_argument('--full-length', action='store_true', help='print arrays in full')
    p.add_argument('--timeout', type=float, default=None, metavar='SEC',
                   help='give up (exit 1) after this long without a message')
    add_qos_args(p)
    add_discovery_args(p)
    p.set_defaults(func=run_echo)

    p = sub.add_parser('pub', help='publish a message given as YAML',
                       description="e.g. hdp topic pub --once /hdp/instruction std_msgs/msg/String "
                                   "\"{data: 'open the drawer'}\"")
    p.add_argument('topic')
    p.add_argument('type')
    p.add_argument('values', nargs='?', default='{}', help='field values as YAML')
    p.add_argument('--once', action='store_true', help='publish one message and exit')
    p.add_argument('-t', '--times', type=int, default=0, help='publish this many messages, then exit')
    p.add_argument('-r', '--rate', type=float, default=1.0, help='publishing rate in Hz (default 1)')
    p.add_argument('-w', '--wait-matching-subscriptions', type=int, default=None, metavar='N',
                   help='wait for N subscribers before publishing (default 1 with --once/--times)')
    p.add_argument('--max-wait', type=float, default=5.0, metavar='SEC',
                   help='how long to wait for those subscribers, and (if reliable) for their acknowledgements '
                        'before exiting (exit 1 without them)')
    p.add_argument('--qos-reliability', choices=['reliable', 'best_effort'], default='reliable')
    p.add_argument('--qos-durability', choices=['volatile', 'transient_local'], default='volatile')
    p.add_argument('--qos-depth', type=int, default=10)
    p.set_defaults(func=run_pub)


def run_list(args) -> int:
    with cli_node() as node:
        spin_until(node, lambda: False, args.spin_time)
        for name, types in sorted(node.get_topic_names_and_types()):
            print(f"{name} [{', '.join(sorted(types))}]" if args.show_types else name)
    return 0


def _graph_types(node, topic: str, seconds: float) -> list[str]:
    """The types `topic` carries on the graph, given up to `seconds` to show up."""
    def types() -> list[str]:
        return dict(node.get_topic_names_and_types()).get(topic, [])
    spin_until(node, lambda: bool(types()), seconds)
    return sorted(types())


def _invalid_topic(name: str) -> str | None:
    """One line saying why rclpy would refuse `name`, or None if it is valid."""
    try:
        validate_topic_name(name)
    except InvalidTopicNameException as err:
        return f"{str(err).splitlines()[0].rstrip(':')}: {name!r}"
    return None


def run_echo(args) -> int:
    topic = args.topic if args.topic.startswith('/') else '/' + args.topic
    if error := _invalid_topic(topic):
        print(error, file=sys.stderr)
        return 1
    with cli_node() as node:
        return _echo(node, topic, args)     # Ctrl-C (interrupted()) is how an endless echo ends: 0


def _echo(node, topic: str, args) -> int:
    type_name = args.type
    if type_name is None:
        types = _graph_types(node, topic, max(args.spin_time, DISCOVERY_WAIT))
        if len(types) != 1:
            print(f'{topic} carries several types ({", ".join(types)}): name one' if types else
                  f'could not find {topic} on the graph; give its type, e.g. '
                  f'hdp topic echo {topic} std_msgs/msg/String', file=sys.stderr)
            return 1
        type_name = types[0]
    try:
        msg_type = get_message(type_name)
    except ValueError as err:
        print(err, file=sys.stderr)
        return 1
    # 'auto' QoS needs the publishers' offers: give them the discovery time to show up
    spin_until(node, lambda: node.get_publishers_info_by_topic(topic), args.spin_time)
    qos = qos_from_args(args, node.get_publishers_info_by_topic(topic))
    received = 0

    def on_message(msg):
        nonlocal received
        received += 1
        print(message_to_yaml(msg, None if args.full_length else 32), end='')
        print('---', flush=True)

    node.create_subscription(msg_type, topic, on_message, qos)
    if args.timeout is not None and not spin_until(node, lambda: received > 0, args.timeout) \
            and not interrupted():
        print(f'no message on {topic} within {args.timeout} s', file=sys.stderr)
        return 1
    spin_until(node, lambda: args.once and received > 0, math.inf)
    return 0


def run_pub(args) -> int:
    error = _invalid_topic(args.topic) or ('--rate must be > 0' if args.rate <= 0 else None)
    if error:
        print(error, file=sys.stderr)
        return 1
    try:
        msg = message_from_yaml(args.type, args.values)
    except ValueError as err:
        print(f'cannot build {args.type}: {err}', file=sys.stderr)
        return 1
    times = 1 if args.once else args.times
    wait_for = args.wait_matching_subscriptions
    if wait_for is None:
        wait_for = 1 if times else 0
    qos = qos_profile(args.qos_reliability, args.qos_durability, args.qos_depth)
    with cli_node() as node:
        pub = node.create_publisher(type(msg), args.topic, qos)
        if not spin_until(node, lambda: pub.get_subscription_count() >= wait_for, args.max_wait):
            print(f'warning: only {pub.get_subscription_count()} of {wait_for} subscribers matched '
                  f'within {args.max_wait} s; publishing anyway', file=sys.stderr)
        elif wait_for and not all(bytes(info.endpoint_gid[:2]) == FAST_DDS_VENDOR_ID
                                  for info in node.get_subscriptions_info_by_topic(args.topic)):
            spin_until(node, lambda: False, FOREIGN_READER_SETTLE_S)     # until they know us too
        text = message_to_yaml(msg).strip().replace('\n', ' ')
        sent = 0
        while not interrupted():         # Ctrl-C ends an endless pub
            pub.publish(msg)
            sent += 1
            print(f'publishing #{sent}: {text}', flush=True)
            if times and sent >= times:
                break
            spin_until(node, lambda: False, 1.0 / args.rate)
        # A reliable sample is resent until acknowledged: stay up until it is (ros2 topic pub's
        # fixed keep-alive can end the process first, and the sample with it).
        if qos.reliability == ReliabilityPolicy.RELIABLE and not _all_acknowledged(pub, args.max_wait) \
                and not interrupted():
            print(f'error: not every subscriber ({pub.get_subscription_count()} matched) acknowledged '
                  f'what was published within {args.max_wait} s; it may not have arrived', file=sys.stderr)
            return 1
    return 0


def _all_acknowledged(pub, seconds: float) -> bool:
    """Whether every matched reliable subscriber acknowledged all that `pub` sent within `seconds`
    (waited in short slices, so that Ctrl-C ends the wait)."""
    end = time.monotonic() + seconds
    while not pub.wait_for_all_acked(Duration(seconds=min(0.1, max(0.0, end - time.monotonic())))):
        if interrupted() or time.monotonic() >= end:
            return False
    return True
