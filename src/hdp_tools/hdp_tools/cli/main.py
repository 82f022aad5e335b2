"""`hdp`: subcommands come from the `hdp.commands` entry-point group.

An entry point named `topic` adds `hdp topic`; `bench.transport` adds
`hdp bench transport`. Each points at `configure(parser)`, which adds its
arguments and sets `func(args) -> exit code`.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

from hdp_learning.checkpoints import CheckpointError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='hdp', description='Hierarchical Diffusion Policy on ROS 2.')
    groups = {(): parser.add_subparsers(title='commands', metavar='COMMAND')}
    parsers = {}
    for entry in sorted(entry_points(group='hdp.commands'), key=lambda e: e.name):
        path = tuple(entry.name.split('.'))
        for depth in range(1, len(path)):
            prefix = path[:depth]
            if prefix not in parsers:
                parsers[prefix] = groups[prefix[:-1]].add_parser(prefix[-1], help=f'{prefix[-1]} commands')
                groups[prefix] = parsers[prefix].add_subparsers(title='commands', metavar='COMMAND')
                parsers[prefix].set_defaults(func=lambda args, p=parsers[prefix]: p.print_help() or 2)
        configure = entry.load()
        doc = (configure.__doc__ or '').strip().replace('%', '%%')     # argparse formats help with %
        sub = groups[path[:-1]].add_parser(path[-1], help=doc.split('\n')[0], description=doc)
        sub.set_defaults(command=' '.join(path))
        configure(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, 'func'):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except CheckpointError as err:      # a damaged or foreign checkpoint/resume file: one line naming it
        print(f'hdp {getattr(args, "command", "")}: {err}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
