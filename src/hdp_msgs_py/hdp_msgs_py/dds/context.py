"""The process-wide DDS context: one participant, shutdown, signals, discovery info.

Discovery defaults to this machine only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
semantics: no multicast, unicast to localhost). SUBNET restores multicast, OFF
keeps the process to itself; ROS_STATIC_PEERS adds peers; a user's own
CYCLONEDDS_URI replaces all of this. ROS_DOMAIN_ID picks the domain.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading

from cyclonedds._clayer import ddspy_write
from cyclonedds.core import GuardCondition, Policy
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.qos import Qos
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic

from .. import cdr
from ..message import get_message
from . import logging as ros_logging
from .arguments import RosArguments, parse_ros_args
from .idl_types import idl_struct

_UDP_MAX = '65500B'


class ExternalShutdownException(Exception):
    """Raised out of spin when the context is shut down (SIGINT, SIGTERM, shutdown())."""


def domain_id_from_env() -> int:
    text = os.environ.get('ROS_DOMAIN_ID', '').strip() or '0'
    if not text.isdigit() or int(text) > 232:
        raise ValueError(f'ROS_DOMAIN_ID must be an integer 0..232, got {text!r}')
    return int(text)


def cyclone_config() -> str | None:
    """Cyclone XML for the discovery range; None to let CYCLONEDDS_URI decide."""
    if os.environ.get('CYCLONEDDS_URI'):
        return None
    scope = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST').upper() or 'LOCALHOST'
    if scope not in ('LOCALHOST', 'SUBNET', 'OFF', 'SYSTEM_DEFAULT'):
        raise ValueError(f'ROS_AUTOMATIC_DISCOVERY_RANGE must be LOCALHOST, SUBNET, OFF or '
                         f'SYSTEM_DEFAULT, got {scope!r}')
    peers = [p for p in os.environ.get('ROS_STATIC_PEERS', '').replace(',', ';').split(';') if p.strip()]
    general = f'<MaxMessageSize>{_UDP_MAX}</MaxMessageSize>'
    discovery = '<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>64</MaxAutoParticipantIndex>'
    if scope in ('LOCALHOST', 'OFF'):
        general = ('<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
                   '<AllowMulticast>false</AllowMulticast>' + general)
        if scope == 'LOCALHOST':
            peers.insert(0, 'localhost')
    if peers:
        discovery += '<Peers>' + ''.join(f'<Peer Address="{p.strip()}"/>' for p in peers) + '</Peers>'
    # Large camera frames: bigger socket buffers and fragments keep best-effort
    # images from being dropped piecemeal on loopback.
    internal = ('<Internal><SocketReceiveBufferSize min="default" max="8MB"/>'
                '<SocketSendBufferSize min="default" max="8MB"/></Internal>')
    return (f'<CycloneDDS><Domain Id="any"><General>{general}</General>'
            f'<Discovery>{discovery}</Discovery>{internal}</Domain></CycloneDDS>')


def tune_malloc() -> None:
    """Keep freed camera-sized buffers in the heap instead of returning them to the OS.

    glibc serves allocations over ~128 KiB with fresh mmap()s and unmaps them on
    free, so every received 640x480 frame page-faults its way into new memory:
    measured here, that alone costs two thirds of image throughput. A 32 MiB mmap
    threshold and a 256 MiB trim threshold make frames reuse heap memory. A user's
    own MALLOC_MMAP_THRESHOLD_ wins; other C libraries are left alone.
    """
    if os.environ.get('MALLOC_MMAP_THRESHOLD_') or not sys.platform.startswith('linux'):
        return
    try:
        libc = ctypes.CDLL('libc.so.6')
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    libc.mallopt(m_mmap_threshold, 32 * 1024 * 1024)
    libc.mallopt(m_trim_threshold, 256 * 1024 * 1024)


class Context:
    def __init__(self):
        self._lock = threading.RLock()
        self._ok = False
        self.ros_args = RosArguments()
        self.argv: list[str] = []
        self.domain_id = 0
        self._domain = None
        self._participant = None
        self._guard = None
        self._topics: dict[str, Topic] = {}
        self._nodes: list = []
        self._discovery_writer = None
        self._previous_handlers: dict = {}

    # -- lifecycle -----------------------------------------------------------
    def init(self, args=None, domain_id: int | None = None, install_signal_handlers: bool = True):
        with self._lock:
            if self._ok:
                raise RuntimeError('init() called twice without shutdown()')
            # like rclpy, args=None means this process's command line
            self.ros_args, self.argv = parse_ros_args(sys.argv if args is None else args)
            if self.ros_args.log_level:
                ros_logging.set_default_level(self.ros_args.log_level)
            domain_id = domain_id if domain_id is not None else domain_id_from_env()
            if self._participant is not None and domain_id != self.domain_id:
                raise RuntimeError(f'this process already joined DDS domain {self.domain_id}; '
                                   f'one process, one domain')
            self.domain_id = domain_id
            tune_malloc()
            self._ok = True
        if install_signal_handlers and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous_handlers[sig] = signal.signal(sig, self._on_signal)

    def ok(self) -> bool:
        return self._ok

    def _on_signal(self, signum, frame):
        self.shutdown()

    def shutdown(self):
        with self._lock:
            if not self._ok:
                raise RuntimeError('shutdown() called on a context that is not initialised')
            self._ok = False
            if self._guard is not None:
                self._guard.set(True)
        for sig, handler in self._previous_handlers.items():
            if threading.current_thread() is threading.main_thread():
                signal.signal(sig, handler)
        self._previous_handlers.clear()

    def try_shutdown(self):
        if self._ok:
            self.shutdown()

    # -- DDS entities --------------------------------------------------------
    @property
    def participant(self) -> DomainParticipant:
        with self._lock:
            if self._participant is None:
                self._domain = Domain(self.domain_id, cyclone_config())
                self._participant = DomainParticipant(
                    self.domain_id, qos=Qos(Policy.Userdata(b'enclave=/;')))
                self._guard = GuardCondition(self._participant)
            return self._participant

    @property
    def guard(self) -> GuardCondition:
        self.participant  # noqa: B018 (creates the guard with the participant)
        return self._guard

    def dds_topic(self, dds_name: str, msg_type) -> Topic:
        """One Topic entity per name; a second type on the same name is refused."""
        with self._lock:
            topic = self._topics.get(dds_name)
            if topic is None:
                topic = Topic(self.participant, dds_name, idl_struct(msg_type._type))
                self._topics[dds_name] = topic
            elif topic.data_type is not idl_struct(msg_type._type):
                raise TypeError(f"topic '{dds_name}' already carries "
                                f'{topic.data_type.__idl_typename__} in this process, not {msg_type._type}')
            return topic

    # -- ros_discovery_info: makes `ros2 node list` show our nodes -----------
    def add_node(self, node):
        with self._lock:
            self._nodes.append(node)
        self.publish_discovery_info()

    def remove_node(self, node):
        with self._lock:
            if node in self._nodes:
                self._nodes.remove(node)
        self.publish_discovery_info()

    def publish_discovery_info(self):
        if not self._ok:
            return
        from .qos import DurabilityPolicy, QoSProfile, to_dds
        Gid = get_message('rmw_dds_common/msg/Gid')
        NodeInfo = get_message('rmw_dds_common/msg/NodeEntitiesInfo')
        Info = get_message('rmw_dds_common/msg/ParticipantEntitiesInfo')
        with self._lock:
            if self._discovery_writer is None:
                topic = self.dds_topic('ros_discovery_info', Info)
                self._discovery_writer = DataWriter(self.participant, topic, qos=to_dds(
                    QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)))
            nodes = [NodeInfo(node_namespace=node.get_namespace(), node_name=node.get_name(),
                              reader_gid_seq=[Gid(data=g) for g in node.reader_gids()],
                              writer_gid_seq=[Gid(data=g) for g in node.writer_gids()])
                     for node in self._nodes]
            info = Info(gid=Gid(data=self.participant.guid.bytes), node_entities_info_seq=nodes)
            write_raw(self._discovery_writer, cdr.serialize(info, pad_to=4))


def write_raw(writer: DataWriter, payload: bytes) -> None:
    """Hand serialised CDR straight to Cyclone (padded to 4 bytes, as rmw sends it)."""
    ret = ddspy_write(writer._ref, payload)
    if ret < 0:
        raise RuntimeError(f'DDS write failed with code {ret}')


default_context = Context()
