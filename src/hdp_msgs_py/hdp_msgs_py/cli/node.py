"""List ROS nodes on the graph (ours and any ROS 2 peer's)."""

from __future__ import annotations

from ..dds.graph import wait_for_discovery
from .common import add_discovery_args, cli_node


def configure(parser) -> None:
    """List the ROS 2 nodes on the graph, read from ros_discovery_info."""
    sub = parser.add_subparsers(title='commands', metavar='COMMAND')
    parser.set_defaults(func=lambda args: parser.print_help() or 2)
    p = sub.add_parser('list', help='fully qualified names of the nodes found')
    p.add_argument('-a', '--all', action='store_true', help='include hidden nodes (names starting with _)')
    add_discovery_args(p)
    p.set_defaults(func=run_list)


def run_list(args) -> int:
    with cli_node() as (node, graph):
        wait_for_discovery(args.spin_time)
        for name in graph.node_names():
            if args.all or not name.rsplit('/', 1)[-1].startswith('_'):
                print(name)
    return 0
