"""Shared pieces of the ROS 2-like CLI: a hidden rclpy node per command, QoS options."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from hdp_ros import ros

# A peer usually shows up in well under a second, but when the first exchange with a new
# participant is lost (about one start in five here) only at the peer's next announcement:
# every 0.5 s with the project's Fast DDS profile (ros.init), every 3 s with Fast DDS's
# default (a node started some other way).
DISCOVERY_WAIT = 1.5


def add_discovery_args(parser, default_wait: float = DISCOVERY_WAIT) -> None:
    parser.add_argument('--spin-time', type=float, default=default_wait, metavar='SEC',
                        help=f'seconds to wait for discovery (default {default_wait})')


def add_qos_args(parser) -> None:
    parser.add_argument('--qos-reliability', choices=['auto', 'reliable', 'best_effort'], default='auto',
                        help="'auto' matches the publishers found")
    parser.add_argument('--qos-durability', choices=['auto', 'volatile', 'transient_local'], default='auto',
                        help="'auto' matches the publishers found")
    parser.add_argument('--qos-depth', type=int, default=10)


def qos_profile(reliability: str, durability: str, depth: int) -> QoSProfile:
    """A profile from the options' short names ('best_effort', 'transient_local', ...)."""
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.get_from_short_key(reliability),
                      durability=DurabilityPolicy.get_from_short_key(durability))


def qos_from_args(args, publishers: list) -> QoSProfile:
    """Explicit choices win; 'auto' takes what every discovered publisher offers, as `ros2 topic echo`.

    `publishers` are rclpy TopicEndpointInfo; a subscription asking for more than
    one of them offers (reliable, transient_local) would not match it.
    """
    def all_offer(policy: str, wanted) -> bool:
        return bool(publishers) and all(getattr(p.qos_profile, policy) == wanted for p in publishers)

    reliability = args.qos_reliability
    if reliability == 'auto':
        reliability = 'reliable' if all_offer('reliability', ReliabilityPolicy.RELIABLE) else 'best_effort'
    durability = args.qos_durability
    if durability == 'auto':
        latched = all_offer('durability', DurabilityPolicy.TRANSIENT_LOCAL)
        durability = 'transient_local' if latched else 'volatile'
    return qos_profile(reliability, durability, args.qos_depth)


_interrupted = threading.Event()


def interrupted() -> bool:
    """Whether Ctrl-C (SIGINT) came while a cli_node was up."""
    return _interrupted.is_set()


@contextlib.contextmanager
def cli_node():
    """A hidden node (leading underscore, as ros2cli's) living for one command.

    Ctrl-C sets a flag that ends the current wait (spin_until) instead of raising
    KeyboardInterrupt wherever the main thread is: raised inside rclpy's executor, it
    could leave the node unable to shut down (seen as an `hdp topic echo` that outlived
    Ctrl-C by 20 s). rclpy's own handlers are off for the same reason.
    """
    ros.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    try:
        # no parameter services or /rosout publisher: nothing on the graph that a tool has no use for
        node = rclpy.create_node(f'_hdp_cli_{os.getpid()}', start_parameter_services=False,
                                 enable_rosout=False)
    except BaseException:
        rclpy.try_shutdown()
        raise
    previous = signal.signal(signal.SIGINT, lambda signum, frame: _interrupted.set())
    try:
        yield node
    finally:
        signal.signal(signal.SIGINT, previous)
        node.destroy_node()
        rclpy.try_shutdown()


def spin_until(node, done, seconds: float) -> bool:
    """Spin until done() or `seconds` pass; returns done().

    Short slices: graph changes (discovery) run no callback to end a spin, and
    Ctrl-C waits for the slice to end.
    """
    end = time.monotonic() + seconds
    while not done() and not interrupted():
        left = end - time.monotonic()
        if left <= 0:
            break
        rclpy.spin_once(node, timeout_sec=min(left, 0.1))
    return done()
