"""The node API every HDP node imports: rclpy under ROS 2, our DDS runtime elsewhere.

    from hdp_msgs_py import ros

    class MyNode(ros.Node): ...
    ros.init(args=args); ros.spin(node)

Both runtimes log and survive an exception raised in a subscription or timer
callback (plain rclpy would propagate it out of spin and stop the node).
"""

import functools

from .runtime_select import USING_RCLPY

if USING_RCLPY:
    import rclpy
    import rclpy.node
    from rclpy import init, ok, shutdown, spin, spin_once, try_shutdown
    from rclpy.clock import Clock
    from rclpy.duration import Duration
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                           qos_profile_sensor_data, qos_profile_system_default)
    from rclpy.time import Time

    class Node(rclpy.node.Node):
        """rclpy's Node whose callbacks log exceptions instead of ending spin."""

        def _guard(self, what, callback):
            @functools.wraps(callback)
            def guarded(*args):
                try:
                    return callback(*args)
                except Exception:   # noqa: BLE001 (a node must survive a bad callback)
                    import traceback
                    self.get_logger().error(f'{what} raised:\n{traceback.format_exc().rstrip()}')
            return guarded

        def create_subscription(self, msg_type, topic, callback, qos_profile, **kwargs):
            return super().create_subscription(
                msg_type, topic, self._guard(f"subscription callback on '{topic}'", callback),
                qos_profile, **kwargs)

        def create_timer(self, timer_period_sec, callback, **kwargs):
            return super().create_timer(timer_period_sec, self._guard('timer callback', callback), **kwargs)
else:
    from .dds import (Clock, Duration, DurabilityPolicy, ExternalShutdownException, HistoryPolicy,
                      Node, Parameter, QoSProfile, ReliabilityPolicy, SingleThreadedExecutor, Time,
                      init, ok, qos_profile_sensor_data, qos_profile_system_default, shutdown, spin,
                      spin_once, try_shutdown)



def run(node_class, args=None) -> None:
    """A node executable's main(): init, construct, spin, shut down cleanly.

    Ctrl-C and SIGTERM end the spin; the node is destroyed either way.
    """
    init(args=args)
    node = node_class()
    try:
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        try_shutdown()


__all__ = ['USING_RCLPY', 'run', 'Clock', 'Duration', 'DurabilityPolicy', 'ExternalShutdownException',
           'HistoryPolicy', 'Node', 'Parameter', 'QoSProfile', 'ReliabilityPolicy',
           'SingleThreadedExecutor', 'Time', 'init', 'ok', 'qos_profile_sensor_data',
           'qos_profile_system_default', 'shutdown', 'spin', 'spin_once', 'try_shutdown']
