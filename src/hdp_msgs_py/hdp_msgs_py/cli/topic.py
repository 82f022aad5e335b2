"""Inspect and use topics without ROS: list, echo, pub."""

from __future__ import annotations

import sys
import time

from .. import dds
from ..dds.graph import wait_for_discovery
from ..message import get_message
from ..message_yaml import message_from_yaml, message_to_yaml
from .common import add_discovery_args, add_qos_args, cli_node, qos_from_args


def configure(parser) -> None:
    """List, echo and publish topics on the ROS 2 graph (DDS, no ROS install needed)."""
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
                   help='how long to wait for those subscribers')
    p.add_argument('--qos-reliability', choices=['reliable', 'best_effort'], default='reliable')
    p.add_argument('--qos-durability', choices=['volatile', 'transient_local'], default='volatile')
    p.add_argument('--qos-depth', type=int, default=10)
    p.set_defaults(func=run_pub)


def run_list(args) -> int:
    with cli_node() as (node, graph):
        wait_for_discovery(args.spin_time)
        for name, types in sorted(graph.topic_names_and_types().items()):
            print(f"{name} [{', '.join(sorted(types))}]" if args.show_types else name)
    return 0


def _resolve_type(graph, topic: str, wait: float) -> str | None:
    end = time.monotonic() + wait
    while True:
        types = graph.topic_names_and_types().get(topic)
        if types:
            if len(types) > 1:
                raise SystemExit(f'{topic} carries several types ({", ".join(sorted(types))}): name one')
            return next(iter(types))
        if time.monotonic() >= end:
            return None
        time.sleep(0.1)


def run_echo(args) -> int:
    topic = args.topic if args.topic.startswith('/') else '/' + args.topic
    with cli_node() as (node, graph):
        type_name = args.type or _resolve_type(graph, topic, max(args.spin_time, 2.0))
        if type_name is None:
            print(f'could not find {topic} on the graph; give its type, e.g. '
                  f'hdp topic echo {topic} std_msgs/msg/String', file=sys.stderr)
            return 1
        try:
            msg_type = get_message(type_name)
        except ValueError as err:
            print(err, file=sys.stderr)
            return 1
        wait_for_discovery(min(args.spin_time, 0.5))
        publishers = [e for e in graph._alive('publications') if e.topic_name == 'rt' + topic]
        qos = qos_from_args(args, publishers)
        received = []

        def on_message(msg):
            received.append(msg)
            print(message_to_yaml(msg, None if args.full_length else 32), end='')
            print('---', flush=True)

        node.create_subscription(msg_type, topic, on_message, qos)
        start = time.monotonic()
        while dds.ok() and not (args.once and received):
            dds.spin_once(node, timeout_sec=0.1)
            if args.timeout is not None and not received and time.monotonic() - start > args.timeout:
                print(f'no message on {topic} within {args.timeout} s', file=sys.stderr)
                return 1
    return 0


def run_pub(args) -> int:
    from ..dds.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    try:
        msg = message_from_yaml(args.type, args.values)
    except (ValueError, TypeError) as err:
        print(f'cannot build {args.type}: {err}', file=sys.stderr)
        return 1
    if args.rate <= 0:
        print('--rate must be > 0', file=sys.stderr)
        return 1
    times = 1 if args.once else args.times
    wait_for = args.wait_matching_subscriptions
    if wait_for is None:
        wait_for = 1 if times else 0
    qos = QoSProfile(depth=args.qos_depth, reliability=ReliabilityPolicy(args.qos_reliability),
                     durability=DurabilityPolicy(args.qos_durability))
    with cli_node() as (node, graph):
        pub = node.create_publisher(type(msg), args.topic, qos)
        deadline = time.monotonic() + args.max_wait
        while pub.get_subscription_count() < wait_for and time.monotonic() < deadline and dds.ok():
            time.sleep(0.05)
        if pub.get_subscription_count() < wait_for:
            print(f'warning: only {pub.get_subscription_count()} of {wait_for} subscribers matched '
                  f'within {args.max_wait} s; publishing anyway', file=sys.stderr)
        sent = 0
        while dds.ok() and (not times or sent < times):
            pub.publish(msg)
            sent += 1
            print(f'publishing #{sent}: {message_to_yaml(msg).strip()}'.replace('\n', ' '), flush=True)
            if times and sent >= times:
                break
            dds.spin_once(node, timeout_sec=1.0 / args.rate)
        # Reliable samples are resent until acknowledged: stay up long enough.
        end = time.monotonic() + 0.5
        while dds.ok() and time.monotonic() < end:
            time.sleep(0.05)
    return 0
