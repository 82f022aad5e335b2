"""Managed nodes' states, like `ros2 lifecycle nodes/get/set`."""

from __future__ import annotations

import contextlib
import threading

from rclpy.executors import SingleThreadedExecutor

from hdp_ros.lifecycle import LifecycleClient

from .common import add_discovery_args, cli_node, spin_until

TRANSITIONS = ('configure', 'activate', 'deactivate', 'cleanup', 'shutdown')


def configure(parser) -> None:
    """Read and change the state of managed (lifecycle) nodes."""
    sub = parser.add_subparsers(title='commands', metavar='COMMAND')
    parser.set_defaults(func=lambda args: parser.print_help() or 2)
    p = sub.add_parser('nodes', help='the managed nodes found (those serving <node>/get_state)')
    add_discovery_args(p)
    p.set_defaults(func=run_nodes)
    p = sub.add_parser('get', help="a node's state")
    p.add_argument('node', help='node name, e.g. /planner_node')
    p.add_argument('--timeout', type=float, default=10.0, metavar='S', help='seconds to wait for the node')
    p.set_defaults(func=run_get)
    p = sub.add_parser('set', help='trigger a transition')
    p.add_argument('node', help='node name, e.g. /planner_node')
    p.add_argument('transition', choices=TRANSITIONS)
    p.add_argument('--timeout', type=float, default=120.0, metavar='S',
                   help='seconds to wait for the node and the transition (configure loads models)')
    p.set_defaults(func=run_set)


def run_nodes(args) -> int:
    with cli_node() as node:
        spin_until(node, lambda: False, args.spin_time)
        names = sorted(name.removesuffix('/get_state') for name, types in node.get_service_names_and_types()
                       if name.endswith('/get_state') and 'lifecycle_msgs/srv/GetState' in types)
    for name in names:
        print(name)
    return 0


@contextlib.contextmanager
def _client(name: str, timeout_s: float):
    """A LifecycleClient of ``name`` whose answers a spin thread takes in; None when its services
    do not appear within timeout_s."""
    with cli_node() as node:
        client = LifecycleClient(node, name)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        try:
            yield client if client.wait_for_services(timeout_s) else None
        finally:
            executor.shutdown()
            spinner.join(timeout=2.0)


def run_get(args) -> int:
    with _client(args.node, args.timeout) as client:
        state = None if client is None else client.get_state(args.timeout)
    if state is None:
        print(f'hdp lifecycle: {args.node} does not answer (is it running, and a managed node?)')
        return 1
    print(state)
    return 0


def run_set(args) -> int:
    with _client(args.node, args.timeout) as client:
        ok = None if client is None else client.change_state(args.transition, args.timeout)
    if ok is None:
        print(f'hdp lifecycle: {args.node} does not answer (is it running, and a managed node?)')
        return 1
    print('Transitioning successful' if ok else 'Transitioning failed')
    return 0 if ok else 1
