"""What every HDP node adds to rclpy: a middleware set up for camera frames, callbacks that
cannot stop the node, a status line for users, and a main().

    from hdp_ros import ros

    class PlannerNode(ros.Node): ...          # an rclpy.node.Node
        self.status = ros.Status(self)

    def main(args=None):
        ros.run(PlannerNode, args)

Any process that talks to the graph calls ``ros.init()`` instead of ``rclpy.init()``.

Plain rclpy propagates an exception raised in a subscription or timer callback
out of spin, which ends the node; a robot's nodes should log it and keep
serving the next message instead. A node that cannot start (a bad parameter, a
damaged checkpoint) exits 1 with one line saying why, not a traceback.
"""

import functools
import os
import signal
import sys
import threading
import time
import traceback
from pathlib import Path

import rclpy
import rclpy.node
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.utilities import remove_ros_args

from hdp_msgs_py import topics
from hdp_msgs_py.msg import String

from . import shm


FASTDDS_LOCALHOST_PROFILE = Path(__file__).with_name('config') / 'fastdds_localhost.xml'


def use_localhost_profile(environ=os.environ) -> bool:
    """Give Fast DDS the project's localhost profile (config/fastdds_localhost.xml says why)
    unless the user chose a profile, another middleware, static peers or a wider discovery
    range. True when it did. Children started from here inherit the choice."""
    if environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') != 'rmw_fastrtps_cpp':
        return False
    if any(environ.get(name) for name in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE',
                                          'ROS_STATIC_PEERS')):
        return False
    if environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST') != 'LOCALHOST':
        return False
    environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(FASTDDS_LOCALHOST_PROFILE)
    environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SYSTEM_DEFAULT'    # rmw_fastrtps then takes the profile as is
    return True


_interrupted = threading.Event()


def _interrupt(signum, frame):
    """Python's own SIGINT behaviour, remembered: see shutting_down()."""
    _interrupted.set()
    raise KeyboardInterrupt


def init(args=None, **kwargs) -> None:
    """rclpy.init() with the middleware set up for the graph (use_localhost_profile), once the
    shared memory of Fast DDS processes that died without cleaning up is gone (shm)."""
    shm.remove_dead_segments()
    use_localhost_profile()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _interrupt)        # rclpy's handler chains to this one
    rclpy.init(args=args, **kwargs)


def shutting_down(wait_s: float = 2.0) -> bool:
    """Whether the process is being shut down: Ctrl-C arrived, or the context stops within wait_s.

    rclpy shuts its context down from a thread of its own after SIGINT/SIGTERM, so
    an error raised by that signal can reach the node before rclpy.ok() turns False.
    """
    end = time.monotonic() + wait_s
    while not _interrupted.is_set() and rclpy.ok():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


class StartupError(Exception):
    """A parameter or checkpoint the node cannot run with."""


class Node(rclpy.node.Node):
    """rclpy's Node whose subscription and timer callbacks log exceptions instead of ending spin.

    A node lists its parameters once, in PARAMETERS (name -> (default, description)):
    ``declare_parameter_table()`` declares them and returns their values, and
    ``--help`` prints them. The names in RUNTIME may change while the node runs; the
    others are declared read-only, so rclpy refuses a change to them. A node's one
    set of rules, ``check_parameters()``, judges the values at start (StartupError
    ends the node) and every change at run time (refused with the rule's words); a
    change it accepts reaches the node through ``apply_parameters()``.
    """

    PARAMETERS: dict = {}
    RUNTIME: frozenset = frozenset()

    def declare_parameter_table(self) -> dict:
        """Declare every entry of PARAMETERS (with its description); their values by name, checked
        by check_parameters()."""
        for name, (default, description) in self.PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(
                description=description, read_only=name not in self.RUNTIME))
        values = self.parameter_values()
        self.check_parameters(values)
        # Registered after the declarations, so that these judge changes at run time only.
        self.add_on_set_parameters_callback(self._judge_parameters)
        self.add_post_set_parameters_callback(self._changed_parameters)
        return values

    def parameter_values(self) -> dict:
        """The values of PARAMETERS by name."""
        return {name: self.get_parameter(name).value for name in self.PARAMETERS}

    def check_parameters(self, values: dict) -> None:
        """Raise StartupError naming the first of ``values`` (all of PARAMETERS) the node cannot run with."""

    def apply_parameters(self, values: dict) -> None:
        """Hand ``values`` (all of PARAMETERS, some RUNTIME ones just changed) to the node's logic."""

    def _judge_parameters(self, parameters) -> SetParametersResult:
        # Parameters not in PARAMETERS (use_sim_time) are rclpy's to judge.
        proposed = {p.name: p.value for p in parameters if p.name in self.PARAMETERS}
        if proposed:
            try:
                self.check_parameters({**self.parameter_values(), **proposed})
            except StartupError as err:
                return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def _changed_parameters(self, parameters) -> None:
        changed = [p for p in parameters if p.name in self.RUNTIME]
        if changed:
            self.apply_parameters(self.parameter_values())
            self.get_logger().info('applied ' + ', '.join(f'{p.name} := {p.value!r}' for p in changed))

    def _guard(self, what, callback):
        @functools.wraps(callback)
        def guarded(*args):
            try:
                return callback(*args)
            except Exception:   # noqa: BLE001 (a node must survive a bad callback)
                self.get_logger().error(f'{what} raised:\n{traceback.format_exc().rstrip()}')
        return guarded

    def create_subscription(self, msg_type, topic, callback, qos_profile, **kwargs):
        return super().create_subscription(
            msg_type, topic, self._guard(f"subscription callback on '{topic}'", callback),
            qos_profile, **kwargs)

    def create_timer(self, timer_period_sec, callback, **kwargs):
        return super().create_timer(timer_period_sec, self._guard('timer callback', callback), **kwargs)


class Status:
    """Log a line and publish it on /hdp/status as '<node name>: <line>', where users watch the graph."""

    def __init__(self, node: rclpy.node.Node):
        self._node = node
        self._publisher = node.create_publisher(String, topics.STATUS, topics.STATUS_QOS)

    def info(self, text: str) -> None:
        self._node.get_logger().info(text)
        self._publisher.publish(String(data=f'{self._node.get_name()}: {text}'))

    def error(self, text: str) -> None:
        # rclpy ties a severity to each logging call site, so each level has its own.
        self._node.get_logger().error(text)
        self._publisher.publish(String(data=f'{self._node.get_name()}: {text}'))

    def line(self, line) -> None:
        """A StatusLine (hdp_msgs_py.outcome) as the node logic hands it out."""
        (self.error if line.error else self.info)(line.text)


def usage(node_class, name: str) -> str:
    """The --help text of a node executable: its module's summary and its parameters."""
    summary = (sys.modules[node_class.__module__].__doc__ or '').strip()
    lines = [f'usage: {name} [--ros-args -p NAME:=VALUE ... --params-file FILE -r FROM:=TO ...]', '',
             summary, '', 'parameters:']
    for parameter, (default, description) in node_class.PARAMETERS.items():
        runtime = ', changes at run time' if parameter in node_class.RUNTIME else ''
        lines.append(f'  {parameter} (default {default!r}{runtime}): {description}')
    return '\n'.join(lines)


def run(node_class, args=None, name: str = '') -> None:
    """A node executable's main(): init, construct, spin, shut down cleanly.

    Ctrl-C and SIGTERM end the spin; the node is destroyed either way. A
    StartupError or a parameter of the wrong type or value ends the process
    with exit status 1 and one line on stderr. ``-h``/``--help`` prints usage().
    """
    if {'-h', '--help'} & set(remove_ros_args(sys.argv if args is None else args)[1:]):
        print(usage(node_class, name))
        return
    init(args=args)
    try:
        node = node_class()
    except (StartupError, InvalidParameterTypeException, InvalidParameterValueException) as err:
        rclpy.try_shutdown()
        print(f'[ERROR] [{name or node_class.__name__}]: {err}', file=sys.stderr)
        sys.exit(1)
    except BaseException:
        rclpy.try_shutdown()
        raise
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # A signal can land while the executor builds its wait set (RCLError 'the given
        # context is not valid') or while a subscription converts a message (pybind11 turns
        # the KeyboardInterrupt into 'Unable to convert call argument'): a shutdown, not a failure.
        if not shutting_down():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
