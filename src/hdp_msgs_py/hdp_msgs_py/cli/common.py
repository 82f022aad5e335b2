"""Shared pieces of the ROS-like CLI: a hidden node on our DDS runtime, QoS options."""

from __future__ import annotations

import contextlib
import os

from cyclonedds.core import Policy

from .. import dds
from ..dds.graph import Graph
from ..dds.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


def add_discovery_args(parser, default_wait: float = 1.0) -> None:
    parser.add_argument('--spin-time', type=float, default=default_wait, metavar='SEC',
                        help=f'seconds to wait for discovery (default {default_wait})')


def add_qos_args(parser) -> None:
    parser.add_argument('--qos-reliability', choices=['auto', 'reliable', 'best_effort'], default='auto',
                        help="'auto' matches the publishers found")
    parser.add_argument('--qos-durability', choices=['auto', 'volatile', 'transient_local'], default='auto',
                        help="'auto' matches the publishers found")
    parser.add_argument('--qos-depth', type=int, default=10)


def qos_from_args(args, publishers: list) -> QoSProfile:
    """Explicit choices win; 'auto' takes what every discovered publisher offers."""
    def all_offer(policy, wanted) -> bool:
        def offers(endpoint) -> bool:
            got = endpoint.qos[policy] if endpoint.qos is not None else None
            return isinstance(got, wanted) if isinstance(wanted, type) else got == wanted
        return bool(publishers) and all(offers(e) for e in publishers)

    reliability = args.qos_reliability
    if reliability == 'auto':
        reliable = all_offer(Policy.Reliability, Policy.Reliability.Reliable)
        reliability = 'reliable' if reliable else 'best_effort'
    durability = args.qos_durability
    if durability == 'auto':
        latched = all_offer(Policy.Durability, Policy.Durability.TransientLocal)
        durability = 'transient_local' if latched else 'volatile'
    return QoSProfile(depth=args.qos_depth, reliability=ReliabilityPolicy(reliability),
                      durability=DurabilityPolicy(durability))


@contextlib.contextmanager
def cli_node(wait: float = 0.0):
    """A hidden node (leading underscore, as ros2cli's) living for one command."""
    dds.init(args=[])
    node = dds.Node(f'_hdp_cli_{os.getpid()}')
    try:
        graph = Graph.of(node.context)
        if wait > 0:
            _spin_for(node, wait)
        yield node, graph
    finally:
        node.destroy_node()
        dds.try_shutdown()


def _spin_for(node, seconds: float) -> None:
    import time
    end = time.monotonic() + seconds
    while dds.ok() and time.monotonic() < end:
        dds.spin_once(node, timeout_sec=max(0.0, end - time.monotonic()))
