"""List ROS 2 nodes on the graph, like `ros2 node list`."""

from __future__ import annotations

from .common import add_discovery_args, cli_node, spin_until


def configure(parser) -> None:
    """List the ROS 2 nodes on the graph."""
    sub = parser.add_subparsers(title='commands', metavar='COMMAND')
    parser.set_defaults(func=lambda args: parser.print_help() or 2)
    p = sub.add_parser('list', help='fully qualified names of the nodes found')
    p.add_argument('-a', '--all', action='store_true', help='include hidden nodes (names starting with _)')
    add_discovery_args(p)
    p.set_defaults(func=run_list)


def run_list(args) -> int:
    with cli_node() as node:
        spin_until(node, lambda: False, args.spin_time)
        names = sorted(namespace.rstrip('/') + '/' + name
                       for name, namespace in node.get_node_names_and_namespaces()
                       if args.all or not name.startswith('_'))
    for name in names:
        print(name)
    return 0
