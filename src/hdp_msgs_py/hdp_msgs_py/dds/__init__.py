"""Our rclpy-compatible runtime over Cyclone DDS, for machines without ROS 2.

Node code does not import this package: it imports `hdp_msgs_py.ros`, which
picks rclpy when available and this runtime otherwise.
"""

from .clock import Clock, Duration, Time
from .context import ExternalShutdownException, default_context
from .executor import SingleThreadedExecutor
from .node import Node, Publisher, Subscription, Timer
from .parameters import Parameter
from .qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                  qos_profile_sensor_data, qos_profile_system_default)

_executor: SingleThreadedExecutor | None = None


def init(*, args=None, context=None, domain_id=None) -> None:
    (context or default_context).init(args=args, domain_id=domain_id)


def ok(*, context=None) -> bool:
    return (context or default_context).ok()


def shutdown(*, context=None) -> None:
    (context or default_context).shutdown()


def try_shutdown(*, context=None) -> None:
    (context or default_context).try_shutdown()


def get_global_executor() -> SingleThreadedExecutor:
    global _executor
    if _executor is None:
        _executor = SingleThreadedExecutor()
    return _executor


def spin_once(node, *, executor=None, timeout_sec=None) -> None:
    executor = executor or get_global_executor()
    executor.add_node(node)
    try:
        executor.spin_once(timeout_sec=timeout_sec)
    finally:
        executor.remove_node(node)


def spin(node, executor=None) -> None:
    executor = executor or get_global_executor()
    executor.add_node(node)
    try:
        executor.spin()
    finally:
        executor.remove_node(node)


__all__ = ['Clock', 'Duration', 'Time', 'ExternalShutdownException', 'SingleThreadedExecutor',
           'Node', 'Publisher', 'Subscription', 'Timer', 'Parameter', 'DurabilityPolicy',
           'HistoryPolicy', 'QoSProfile', 'ReliabilityPolicy', 'qos_profile_sensor_data',
           'qos_profile_system_default', 'init', 'ok', 'shutdown', 'try_shutdown', 'spin',
           'spin_once', 'get_global_executor']
