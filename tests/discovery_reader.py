"""Read `ros_discovery_info` the way a ROS 2 tool does, with no HDP code at all.

Plain cyclonedds for the transport (its own IDL of the rmw_dds_common types),
rosbags for decoding. Prints the nodes found as JSON.
"""

import json
import os
import time
from dataclasses import dataclass

from cyclonedds.core import InstanceState, Policy, Qos, SampleState, ViewState
from cyclonedds.idl import IdlStruct, types
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds._clayer import ddspy_take
from rosbags.typesys import Stores, get_typestore

import cyclone_loopback


@dataclass
class Gid_(IdlStruct, typename='rmw_dds_common::msg::dds_::Gid_'):
    data: types.array[types.uint8, 16]


@dataclass
class NodeEntitiesInfo_(IdlStruct, typename='rmw_dds_common::msg::dds_::NodeEntitiesInfo_'):
    node_namespace: types.bounded_str[256]
    node_name: types.bounded_str[256]
    reader_gid_seq: types.sequence[Gid_]
    writer_gid_seq: types.sequence[Gid_]


@dataclass
class ParticipantEntitiesInfo_(IdlStruct, typename='rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_'):
    gid: Gid_
    node_entities_info_seq: types.sequence[NodeEntitiesInfo_]


domain_id = int(os.environ['ROS_DOMAIN_ID'])
domain, participant = cyclone_loopback.participant(domain_id)
topic = Topic(participant, 'ros_discovery_info', ParticipantEntitiesInfo_)
reader = DataReader(participant, topic, qos=Qos(Policy.Reliability.Reliable(0), Policy.History.KeepAll,
                                                Policy.Durability.TransientLocal))
typestore = get_typestore(Stores.ROS2_JAZZY)
latest = {}   # participant gid -> its newest ParticipantEntitiesInfo
end = time.monotonic() + 3.0
while time.monotonic() < end:
    time.sleep(0.2)
    for data, info in ddspy_take(reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, 100):
        msg = typestore.deserialize_cdr(data, 'rmw_dds_common/msg/ParticipantEntitiesInfo')
        latest[bytes(msg.gid.data)] = msg
print(json.dumps([{'namespace': n.node_namespace, 'name': n.node_name,
                   'readers': [bytes(g.data).hex() for g in n.reader_gid_seq],
                   'writers': [bytes(g.data).hex() for g in n.writer_gid_seq]}
                  for msg in latest.values() for n in msg.node_entities_info_seq]))
