"""What is on the DDS network: topics with their types, and ROS nodes.

Endpoints come from DDS built-in discovery topics; nodes from
`ros_discovery_info`, which every ROS 2 participant (and ours) publishes.
"""

from __future__ import annotations

import time

from cyclonedds.builtin import (BuiltinDataReader, BuiltinTopicDcpsParticipant,
                                BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription)
from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState
from cyclonedds.sub import DataReader

from .. import cdr
from ..message import get_message
from .qos import DurabilityPolicy, HistoryPolicy, QoSProfile, to_dds

_ALIVE = SampleState.Any | ViewState.Any | InstanceState.Alive


def ros_type_name(dds_type: str) -> str:
    """'std_msgs::msg::dds_::String_' -> 'std_msgs/msg/String'."""
    parts = dds_type.split('::')
    if len(parts) == 4 and parts[2] == 'dds_' and parts[3].endswith('_'):
        return f'{parts[0]}/{parts[1]}/{parts[3][:-1]}'
    return dds_type


class Graph:
    _instances: dict[int, Graph] = {}

    def __init__(self, context):
        participant = context.participant
        self._readers = {
            'publications': BuiltinDataReader(participant, BuiltinTopicDcpsPublication),
            'subscriptions': BuiltinDataReader(participant, BuiltinTopicDcpsSubscription),
            'participants': BuiltinDataReader(participant, BuiltinTopicDcpsParticipant),
        }
        info_type = get_message('rmw_dds_common/msg/ParticipantEntitiesInfo')
        self._info_type = info_type
        self._info_reader = DataReader(participant, context.dds_topic('ros_discovery_info', info_type),
                                       qos=to_dds(QoSProfile(history=HistoryPolicy.KEEP_ALL,
                                                             durability=DurabilityPolicy.TRANSIENT_LOCAL)))
        self._node_info: dict[bytes, object] = {}

    @classmethod
    def of(cls, context) -> Graph:
        key = id(context.participant)
        if key not in cls._instances:
            cls._instances[key] = cls(context)
        return cls._instances[key]

    def _alive(self, kind: str) -> list:
        reader = self._readers[kind]
        return reader.read(N=10_000, condition=ReadCondition(reader, _ALIVE))

    def count(self, kind: str, dds_topic: str) -> int:
        return sum(1 for e in self._alive(kind) if e.topic_name == dds_topic)

    def topic_names_and_types(self) -> dict[str, set[str]]:
        """ROS topic name -> ROS type names, for every 'rt/' topic seen."""
        topics: dict[str, set[str]] = {}
        for kind in ('publications', 'subscriptions'):
            for endpoint in self._alive(kind):
                if endpoint.topic_name.startswith('rt/'):
                    topics.setdefault(endpoint.topic_name[2:], set()).add(ros_type_name(endpoint.type_name))
        return topics

    def node_names(self) -> list[str]:
        """Fully qualified names of the ROS nodes of live participants."""
        from cyclonedds._clayer import ddspy_take
        ret = ddspy_take(self._info_reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, 10_000)
        for data, info in ([] if isinstance(ret, int) else ret):
            if info.valid_data:
                try:
                    msg = cdr.deserialize(self._info_type, data)
                except cdr.CdrError:
                    continue
                self._node_info[bytes(msg.gid.data)] = msg
        alive = {p.key.bytes for p in self._alive('participants')}
        names = []
        for gid, msg in self._node_info.items():
            if gid in alive:
                names += [n.node_namespace.rstrip('/') + '/' + n.node_name for n in msg.node_entities_info_seq]
        return sorted(names)


def wait_for_discovery(seconds: float) -> None:
    """Discovery is asynchronous: CLI queries give peers this long to show up."""
    time.sleep(seconds)
