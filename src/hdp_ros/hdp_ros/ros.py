"""What every HDP node adds to rclpy: a middleware set up for camera frames, callbacks that
cannot stop the node, a status line for users, managed (lifecycle) states, and a main().

    from hdp_ros import ros

    class PlannerNode(ros.LifecycleNode): ...   # an rclpy.lifecycle.LifecycleNode
        self.status = ros.Status(self)

    def main(args=None):
        ros.run(PlannerNode, args)

Any process that talks to the graph calls ``ros.init()`` instead of ``rclpy.init()``.

Plain rclpy propagates an exception raised in a subscription, timer or service
callback out of spin, which ends the node; a robot's nodes should log it and
keep serving the next message instead. A node that cannot start (a bad
parameter, a damaged checkpoint) exits 1 with one line saying why, not a
traceback. At Ctrl-C or SIGTERM a managed node goes through its shutdown
transition (ending its work, and saying so) while the middleware still runs.
"""

import functools
import gc
import os
import signal
import sys
import threading
import time
import traceback
from pathlib import Path

import rclpy
import rclpy.lifecycle
import rclpy.node
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.client import Client
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from rclpy.utilities import remove_ros_args

from hdp_msgs_py import topics
from hdp_msgs_py.msg import String

from . import fastdds, shm


# What a node that waits for its transitions tells the user.
MANAGER_HINT = 'hdp launch starts a lifecycle manager; alone: -p autostart:=true, or hdp lifecycle set'

FASTDDS_LOCALHOST_PROFILE = Path(__file__).with_name('config') / 'fastdds_localhost.xml'
# Set, each of these says the user has set up Fast DDS themselves.
_OWN_FASTDDS_SETUP = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE', 'ROS_DISCOVERY_SERVER')


def use_project_profile(environ=os.environ) -> str | None:
    """Give Fast DDS the project's profile for the discovery the environment asks for, and say which:

    'tls'        HDP_DDS_TLS_DIR and HDP_DDS_DISCOVERY_SERVER set (opt-in): fastdds.tls_profile
    'localhost'  the default, ROS_AUTOMATIC_DISCOVERY_RANGE unset or LOCALHOST:
                 config/fastdds_localhost.xml
    'network'    SUBNET, or static peers (ROS_STATIC_PEERS) with LOCALHOST: fastdds.network_profile
    None         the user's own choice stands: a profile file, ROS_DISCOVERY_SERVER, another
                 RMW_IMPLEMENTATION, a discovery range OFF or SYSTEM_DEFAULT

    The profile reaches rmw_fastrtps_cpp with the range SYSTEM_DEFAULT, the one range for which it
    keeps the profile's transports and peers as they are. Children started from here inherit the
    choice (their profile file is set). ValueError: a setting the profile cannot be made from.
    """
    tls = fastdds.tls_settings(environ)
    if tls:
        return _use_tls_profile(environ, tls)
    if environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') != 'rmw_fastrtps_cpp':
        return None
    if any(environ.get(name) for name in _OWN_FASTDDS_SETUP):
        return None
    discovery_range = environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if discovery_range not in ('LOCALHOST', 'SUBNET'):
        return None
    peers = fastdds.static_peers(environ)
    if discovery_range == 'LOCALHOST' and not peers:
        name, profile = 'localhost', FASTDDS_LOCALHOST_PROFILE
    else:
        name, profile = 'network', fastdds.write_profile(
            environ, 'network', fastdds.network_profile(peers, subnet=discovery_range == 'SUBNET'))
    _give_rmw(environ, profile)
    return name


def _use_tls_profile(environ, tls: fastdds.TlsSettings) -> str:
    """The TLS profile, or refusal: asked for, it must be what the process runs with."""
    if environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') != 'rmw_fastrtps_cpp':
        raise ValueError('HDP_DDS_TLS_DIR: the TLS profile is for rmw_fastrtps_cpp; unset RMW_IMPLEMENTATION')
    profile = environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
    if not fastdds.is_tls_profile(profile, environ):        # not one this process inherited
        if any(environ.get(name) for name in _OWN_FASTDDS_SETUP):
            raise ValueError('HDP_DDS_TLS_DIR asks for the TLS profile, but ' + ' and '.join(
                name for name in _OWN_FASTDDS_SETUP if environ.get(name)) + ' set up Fast DDS otherwise')
        profile = fastdds.write_profile(environ, 'tls', fastdds.tls_profile(tls))
    environ['OPENSSL_CONF'] = str(fastdds.REQUIRE_PEER_CERTIFICATE)
    _give_rmw(environ, profile)
    return 'tls'


def _give_rmw(environ, profile) -> None:
    environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile)
    environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SYSTEM_DEFAULT'    # rmw_fastrtps then takes it as it is


_interrupted = threading.Event()


def _interrupt(signum, frame):
    """Python's own SIGINT behaviour, remembered: see shutting_down()."""
    _interrupted.set()
    raise KeyboardInterrupt


def init(args=None, **kwargs) -> None:
    """rclpy.init() with the middleware set up for the graph (use_project_profile), once the
    shared memory of Fast DDS processes that died without cleaning up is gone (shm)."""
    shm.remove_dead_segments()
    use_project_profile()
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


class _NodeRules:
    """What Node and LifecycleNode add to rclpy's: callbacks that log exceptions instead of
    ending spin, and parameters declared, checked and applied from one table.

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

    def create_service(self, srv_type, srv_name, callback, **kwargs):
        return super().create_service(srv_type, srv_name,
                                      self._guard(f"service callback of '{srv_name}'", callback), **kwargs)


class Node(_NodeRules, rclpy.node.Node):
    """rclpy's Node with _NodeRules: for nodes that need no managed states (the simulator, tools)."""


def _logged(transition):
    """rclpy turns an exception in a transition callback into ERROR without a word: log it first."""
    @functools.wraps(transition)
    def logged(node, state):
        try:
            return transition(node, state)
        except Exception:   # noqa: BLE001 (logged, re-raised for rclpy)
            node.get_logger().error(f'{transition.__name__} raised:\n{traceback.format_exc().rstrip()}')
            raise
    return logged


class LifecycleNode(_NodeRules, rclpy.lifecycle.LifecycleNode):
    """A managed node (rclpy.lifecycle), its transitions as nav2's nodes keep them:

    configure   configure(parameters): load and warm up, create what the work needs;
                StartupError fails it with a status line saying why
    activate    accept work (``active``; activate() for anything more)
    deactivate  deactivate(why, shutting_down=False): end the running work, hold the arm
    cleanup     release() what configure created, back to unconfigured
    shutdown    deactivate(why, shutting_down=True) if active, then release()

    Construction makes the status line (``status``); a node's constructor declares the
    parameters (PARAMETERS includes LIFECYCLE_PARAMETERS) and creates what every state
    needs (/diagnostics, the topics that answer work it refuses); the standard
    services /<node>/get_state and /<node>/change_state come from rclpy. Work that comes
    while the node is not active is refused by the node, which says so. A transition that
    raises is logged with its traceback and ends in error processing, which releases
    everything (unconfigured).
    """

    LIFECYCLE_PARAMETERS = {
        'autostart': (False, 'configure and activate at start, without a lifecycle manager '
                             '(hdp launch starts one: hdp_bringup lifecycle_manager)'),
    }

    def __init__(self, node_name: str, **kwargs):
        super().__init__(node_name, **kwargs)
        # rclpy creates the lifecycle services itself, unguarded: a bad transition id would end spin.
        for service in self.services:
            service.callback = self._guard(f"service '{service.srv_name}'", service.callback)
        self.status = Status(self)
        self.active = False
        self.failure = ''                  # why the last configure failed
        self._kept: set[int] = set()       # the entities construction made, which cleanup keeps

    @property
    def state_label(self) -> str:
        """The primary state: unconfigured, inactive, active or finalized (or a transition's)."""
        return self._state_machine.current_state[1]

    # -- what a node defines ------------------------------------------------------------------
    def configure(self, parameters: dict) -> None:
        """Load, warm up, create the publishers, subscriptions and timers of the work."""

    def activate(self) -> None:
        """Anything beyond accepting work (``active`` is already True)."""

    def deactivate(self, why: str, shutting_down: bool) -> None:
        """End the running work and hold the arm (``active`` is already False)."""

    def forget(self) -> None:
        """Drop what configure() loaded (models), after its entities are gone."""

    # -- rclpy's transition callbacks -----------------------------------------------------------
    @_logged
    def on_configure(self, state) -> TransitionCallbackReturn:
        self._kept = {id(e) for e in self._entities()}
        try:
            self.configure(self.parameter_values())
        except StartupError as err:
            self.failure = str(err)
            self.release()
            self.status.error(f'cannot configure: {err}')
            return TransitionCallbackReturn.FAILURE
        self.failure = ''
        return TransitionCallbackReturn.SUCCESS

    @_logged
    def on_activate(self, state) -> TransitionCallbackReturn:
        self.active = True
        self.activate()
        return TransitionCallbackReturn.SUCCESS

    @_logged
    def on_deactivate(self, state) -> TransitionCallbackReturn:
        self.active = False
        self.deactivate(f'{self.get_name()} was deactivated', shutting_down=False)
        return TransitionCallbackReturn.SUCCESS

    @_logged
    def on_cleanup(self, state) -> TransitionCallbackReturn:
        self.release()
        return TransitionCallbackReturn.SUCCESS

    @_logged
    def on_shutdown(self, state) -> TransitionCallbackReturn:
        if self.active:
            self.active = False
            self.deactivate(f'{self.get_name()} shut down', shutting_down=True)
        self.release()
        return TransitionCallbackReturn.SUCCESS

    @_logged
    def on_error(self, state) -> TransitionCallbackReturn:
        self.active = False
        self.release()
        return TransitionCallbackReturn.SUCCESS

    # -- releasing ---------------------------------------------------------------------------------
    def _entities(self) -> list:
        return [*self.publishers, *self.subscriptions, *self.clients, *self.services, *self.timers,
                *self.waitables]

    def release(self) -> None:
        """Destroy every entity made since construction (after what its publishers sent is
        acknowledged, within a second), then forget() the models."""
        made = [e for e in self._entities() if id(e) not in self._kept]
        flush([e for e in made if isinstance(e, Publisher)])
        for entity in made:
            match entity:
                case Publisher():
                    self.destroy_publisher(entity)
                case Subscription():
                    self.destroy_subscription(entity)
                case Client():
                    self.destroy_client(entity)
                case Service():
                    self.destroy_service(entity)
                case Timer():
                    self.destroy_timer(entity)
                case _:                    # an action client or server
                    entity.destroy()
        self.forget()
        gc.collect()                       # models hold tens of MB: return them now, not at some later gc

    def finish(self) -> None:
        """Go through shutdown unless already finalized (the process is ending)."""
        if self.state_label != 'finalized':
            self.trigger_shutdown()


def flush(publishers, timeout_s: float = 1.0) -> None:
    """Wait, at most timeout_s in all, until each reliable reader has acknowledged what
    ``publishers`` sent: a process that ends or destroys a publisher right after its last
    message would otherwise lose it."""
    end = time.monotonic() + timeout_s
    for publisher in publishers:
        left = end - time.monotonic()
        if left <= 0:
            return
        publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))


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


def run(node_class, args=None, name: str = '', threads: int = 1) -> None:
    """A node executable's main(): init, construct, spin, shut down cleanly.

    Ctrl-C and SIGTERM end the spin; a managed node then goes through its shutdown
    transition, what it published is flushed, and the node is destroyed. (rclpy's own
    handler would shut the middleware down first, and the node's last words with it; a
    second Ctrl-C ends the process at once.) A StartupError or a parameter of the wrong
    type or value ends the process with exit status 1 and one line on stderr, and so does
    a failed configure under autostart. ``-h``/``--help`` prints usage(). ``threads`` > 1 spins
    the node with a MultiThreadedExecutor (for callbacks that wait on a service's answer).
    """
    if {'-h', '--help'} & set(remove_ros_args(sys.argv if args is None else args)[1:]):
        print(usage(node_class, name))
        return
    init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def request_stop(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, request_stop)
    label = name or node_class.__name__
    try:
        node = node_class()
    except (StartupError, InvalidParameterTypeException, InvalidParameterValueException) as err:
        _exit_failed(label, str(err))
    except BaseException:
        rclpy.try_shutdown()
        raise
    executor = SingleThreadedExecutor() if threads == 1 else MultiThreadedExecutor(num_threads=threads)
    executor.add_node(node)
    failed = ''
    try:
        if isinstance(node, LifecycleNode) and node.get_parameter('autostart').value:
            if node.trigger_configure() == TransitionCallbackReturn.SUCCESS:
                node.trigger_activate()
            else:
                failed = node.failure or 'configure failed (see the log above)'
        while not failed and not stop.is_set():
            executor.spin_once(timeout_sec=0.1)     # a stop request is seen within 0.1 s
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # The context can go down under the executor as it builds its wait set (RCLError 'the
        # given context is not valid'), and a second signal can land while a subscription converts
        # a message (pybind11 turns the KeyboardInterrupt into 'Unable to convert call argument'):
        # a shutdown, not a failure.
        if not stop.is_set() and rclpy.ok():
            raise
    finally:
        if rclpy.ok():
            if isinstance(node, LifecycleNode):
                node.finish()
            flush(node.publishers)
        node.destroy_node()
    if failed:
        _exit_failed(label, failed)
    rclpy.try_shutdown()


def _exit_failed(label: str, why: str):
    rclpy.try_shutdown()
    print(f'[ERROR] [{label}]: {why}', file=sys.stderr)
    sys.exit(1)
