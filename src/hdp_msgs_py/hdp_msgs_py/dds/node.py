"""Node, Publisher, Subscription and Timer with rclpy's API, over Cyclone DDS."""

from __future__ import annotations

import traceback

from cyclonedds._clayer import ddspy_take
from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from .. import cdr
from ..message import Message, type_name_of
from .arguments import parse_ros_args
from .clock import Clock
from .context import default_context, write_raw
from .logging import Logger
from .names import (apply_remaps, expand_topic_name, fully_qualified, normalize_namespace,
                    validate_node_name)
from .parameters import (InvalidParameterTypeException, Parameter,
                         ParameterAlreadyDeclaredException, ParameterNotDeclaredException,
                         ParameterType, coerce)
from .qos import QoSProfile, ReliabilityPolicy, as_profile, to_dds

_ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
_TAKE_BATCH = 64


class Publisher:
    def __init__(self, node: Node, msg_type, topic_name: str, qos: QoSProfile):
        self.msg_type, self.topic_name, self.qos_profile = msg_type, topic_name, qos
        topic = node.context.dds_topic('rt' + topic_name, msg_type)
        self._writer = DataWriter(node.context.participant, topic, qos=to_dds(qos))

    def publish(self, msg) -> None:
        if type(msg) is not self.msg_type:
            raise TypeError(f"publisher on '{self.topic_name}' takes {type_name_of(self.msg_type)}, "
                            f'got {type_name_of(type(msg))}')
        write_raw(self._writer, cdr.serialize(msg, pad_to=4))

    def get_subscription_count(self) -> int:
        return len(self._writer.get_matched_subscriptions())

    @property
    def gid(self) -> bytes:
        return self._writer.guid.bytes

    def destroy(self):
        self._writer = None


class Subscription:
    def __init__(self, node: Node, msg_type, topic_name: str, callback, qos: QoSProfile, raw: bool):
        self.msg_type, self.topic_name, self.callback, self.qos_profile = msg_type, topic_name, callback, qos
        self.raw = raw
        self._logger = node.get_logger()
        topic = node.context.dds_topic('rt' + topic_name, msg_type)
        self._reader = DataReader(node.context.participant, topic, qos=to_dds(qos))
        self.condition = ReadCondition(self._reader, _ANY_SAMPLE)

    def take(self) -> list:
        """Decoded samples waiting in the reader; malformed ones are logged and dropped."""
        ret = ddspy_take(self._reader._ref, _ANY_SAMPLE, _TAKE_BATCH)
        if isinstance(ret, int):
            self._logger.error(f"DDS take on '{self.topic_name}' failed with code {ret}")
            return []
        samples = []
        for data, info in ret:
            if not info.valid_data:
                continue
            if self.raw:
                samples.append(data)
                continue
            try:
                samples.append(cdr.deserialize(self.msg_type, data))
            except cdr.CdrError as err:
                self._logger.warning(f"dropped a malformed {type_name_of(self.msg_type)} on "
                                     f"'{self.topic_name}' ({len(data)} bytes): {err}")
        return samples

    def get_publisher_count(self) -> int:
        return len(self._reader.get_matched_publications())

    @property
    def gid(self) -> bytes:
        return self._reader.guid.bytes

    def destroy(self):
        self.condition = None
        self._reader = None


class Timer:
    def __init__(self, period_sec: float, callback, clock: Clock):
        if not period_sec > 0:
            raise ValueError(f'timer period must be > 0 s, got {period_sec}')
        self.timer_period_ns = int(period_sec * 1e9)
        self.callback, self._clock = callback, clock
        self.is_canceled = False
        self.reset()

    def reset(self):
        self.is_canceled = False
        self._epoch = self._clock.jumps
        self._next_ns = self._clock.now().nanoseconds + self.timer_period_ns

    def cancel(self):
        self.is_canceled = True

    def time_until_next_call(self) -> int | None:
        """Nanoseconds until due (<= 0: due now); None when cancelled."""
        if self.is_canceled:
            return None
        if self._epoch != self._clock.jumps:
            self.reset()
        return self._next_ns - self._clock.now().nanoseconds

    def call(self):
        now = self._clock.now().nanoseconds
        # skip missed periods instead of bursting, like rcl timers
        missed = max(0, (now - self._next_ns) // self.timer_period_ns)
        self._next_ns += (missed + 1) * self.timer_period_ns
        self.callback()


class Node:
    """rclpy.node.Node's API for the parts our nodes use."""

    def __init__(self, node_name: str, *, context=None, cli_args=None, namespace: str | None = None,
                 use_global_arguments: bool = True, parameter_overrides=None,
                 allow_undeclared_parameters: bool = False,
                 automatically_declare_parameters_from_overrides: bool = False, **_ignored):
        self.context = context or default_context
        if not self.context.ok():
            raise RuntimeError('call init() before creating a node')
        local_args, _ = parse_ros_args(['--ros-args', *cli_args] if cli_args and '--ros-args' not in cli_args
                                       else cli_args)
        self._remaps = local_args.remaps + (self.context.ros_args.remaps if use_global_arguments else [])
        overrides_from = [self.context.ros_args, local_args] if use_global_arguments else [local_args]
        self._name = validate_node_name(
            local_args.node_name_override(node_name)
            or (self.context.ros_args.node_name_override(node_name) if use_global_arguments else None)
            or node_name)
        self._namespace = normalize_namespace(
            local_args.namespace_override(node_name)
            or (self.context.ros_args.namespace_override(node_name) if use_global_arguments else None)
            or namespace)
        fqn = self.get_fully_qualified_name()
        self._logger = Logger(fqn.lstrip('/').replace('/', '.'))
        self._clock = Clock()
        self._overrides = {}
        for args in overrides_from:
            self._overrides.update(args.parameters_for(fqn))
        for param in parameter_overrides or []:
            self._overrides[param.name] = param.value
        self._allow_undeclared = allow_undeclared_parameters
        self._parameters: dict[str, Parameter] = {}
        self.publishers: list[Publisher] = []
        self.subscriptions: list[Subscription] = []
        self.timers: list[Timer] = []
        self._clock_sub = None
        if automatically_declare_parameters_from_overrides:
            for name, value in self._overrides.items():
                self.declare_parameter(name, value)
        if not self.has_parameter('use_sim_time'):
            self.declare_parameter('use_sim_time', False)
        self._apply_use_sim_time(self.get_parameter('use_sim_time').value)
        self.context.add_node(self)

    # -- identity ------------------------------------------------------------
    def get_name(self) -> str:
        return self._name

    def get_namespace(self) -> str:
        return self._namespace

    def get_fully_qualified_name(self) -> str:
        return fully_qualified(self._namespace, self._name)

    def get_logger(self) -> Logger:
        return self._logger

    def get_clock(self) -> Clock:
        return self._clock

    def resolve_topic_name(self, topic: str) -> str:
        expanded = expand_topic_name(topic, self._name, self._namespace)
        return apply_remaps(expanded, self._remaps, self._name, self._namespace)

    # -- entities --------------------------------------------------------------
    def create_publisher(self, msg_type, topic: str, qos_profile, **_ignored) -> Publisher:
        _check_msg_type(msg_type)
        pub = Publisher(self, msg_type, self.resolve_topic_name(topic), as_profile(qos_profile))
        self.publishers.append(pub)
        self.context.publish_discovery_info()
        return pub

    def create_subscription(self, msg_type, topic: str, callback, qos_profile, *, raw: bool = False,
                            **_ignored) -> Subscription:
        _check_msg_type(msg_type)
        sub = Subscription(self, msg_type, self.resolve_topic_name(topic), callback,
                           as_profile(qos_profile), raw)
        self.subscriptions.append(sub)
        self.context.publish_discovery_info()
        self.context.guard.set(True)   # let a running executor pick it up
        return sub

    def create_timer(self, timer_period_sec: float, callback, **_ignored) -> Timer:
        timer = Timer(timer_period_sec, callback, self._clock)
        self.timers.append(timer)
        self.context.guard.set(True)
        return timer

    def destroy_publisher(self, pub: Publisher) -> bool:
        return self._destroy(self.publishers, pub)

    def destroy_subscription(self, sub: Subscription) -> bool:
        return self._destroy(self.subscriptions, sub)

    def destroy_timer(self, timer: Timer) -> bool:
        timer.cancel()
        if timer in self.timers:
            self.timers.remove(timer)
            return True
        return False

    def _destroy(self, entities: list, entity) -> bool:
        if entity not in entities:
            return False
        entities.remove(entity)
        entity.destroy()
        self.context.publish_discovery_info()
        return True

    def destroy_node(self):
        for timer in list(self.timers):
            self.destroy_timer(timer)
        for entity in self.publishers + self.subscriptions:
            entity.destroy()
        self.publishers.clear()
        self.subscriptions.clear()
        self.context.remove_node(self)

    def reader_gids(self) -> list[bytes]:
        return [s.gid for s in self.subscriptions if s.condition is not None]

    def writer_gids(self) -> list[bytes]:
        return [p.gid for p in self.publishers]

    def count_publishers(self, topic: str) -> int:
        from .graph import Graph
        return Graph.of(self.context).count('publications', 'rt' + self.resolve_topic_name(topic))

    def count_subscribers(self, topic: str) -> int:
        from .graph import Graph
        return Graph.of(self.context).count('subscriptions', 'rt' + self.resolve_topic_name(topic))

    # -- parameters ----------------------------------------------------------
    def declare_parameter(self, name: str, value=None, descriptor=None, ignore_override: bool = False):
        if name in self._parameters:
            raise ParameterAlreadyDeclaredException(f"parameter '{name}' is already declared")
        if isinstance(value, ParameterType):      # declare_parameter('x', Parameter.Type.DOUBLE)
            declared_type, value = value, None
        else:
            declared_type = Parameter(name, value=value).type_
        if not ignore_override and name in self._overrides:
            value = self._overrides[name]
            if declared_type is not ParameterType.NOT_SET:
                value = coerce(name, value, declared_type)
        param = Parameter(name, value=value)
        if value is not None and declared_type is not ParameterType.NOT_SET:
            param.type_ = declared_type
        self._parameters[name] = param
        return param

    def declare_parameters(self, namespace: str, parameters) -> list:
        prefix = f'{namespace}.' if namespace else ''
        return [self.declare_parameter(prefix + entry[0], *entry[1:]) for entry in parameters]

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def get_parameter(self, name: str) -> Parameter:
        if name in self._parameters:
            return self._parameters[name]
        if self._allow_undeclared:
            return Parameter(name, value=self._overrides.get(name))
        raise ParameterNotDeclaredException(f"parameter '{name}' has not been declared")

    def get_parameters(self, names) -> list:
        return [self.get_parameter(n) for n in names]

    def get_parameter_or(self, name: str, alternative_value=None) -> Parameter:
        return self._parameters.get(name) or Parameter(name, value=alternative_value)

    def set_parameters(self, parameters) -> list:
        results = []
        for param in parameters:
            current = self._parameters.get(param.name)
            if current is None and not self._allow_undeclared:
                raise ParameterNotDeclaredException(f"parameter '{param.name}' has not been declared")
            if current is not None and current.type_ is not ParameterType.NOT_SET:
                try:
                    param = Parameter(param.name, current.type_, coerce(param.name, param.value, current.type_))
                except InvalidParameterTypeException as err:
                    results.append(_SetResult(False, str(err)))
                    continue
            self._parameters[param.name] = param
            if param.name == 'use_sim_time':
                self._apply_use_sim_time(param.value)
            results.append(_SetResult(True, ''))
        return results

    # -- sim time ----------------------------------------------------------------
    def _apply_use_sim_time(self, enabled: bool):
        from ..message import get_message
        self._clock.set_sim_time(bool(enabled))
        if enabled and self._clock_sub is None:
            self._clock_sub = self.create_subscription(
                get_message('rosgraph_msgs/msg/Clock'), '/clock',
                lambda msg: self._clock.set_sim_now(msg.clock.sec * 1_000_000_000 + msg.clock.nanosec),
                QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        elif not enabled and self._clock_sub is not None:
            self.destroy_subscription(self._clock_sub)
            self._clock_sub = None

    # -- used by the executor ------------------------------------------------------
    def run_callback(self, what: str, callback, *args):
        """Run one callback; an exception is logged and the node keeps serving."""
        try:
            callback(*args)
        except Exception:   # noqa: BLE001 (a node must survive a bad callback)
            self._logger.error(f'{what} raised:\n{traceback.format_exc().rstrip()}')


class _SetResult:
    def __init__(self, successful: bool, reason: str):
        self.successful, self.reason = successful, reason


def _check_msg_type(msg_type):
    if not (isinstance(msg_type, type) and issubclass(msg_type, Message)):
        raise TypeError(f'{msg_type!r} is not a message class from hdp_msgs_py.msg')

