"""Subscribe to the HDP graph the way a ROS 2 node would see it, with no HDP code at all.

Plain cyclonedds for the transport, with the ROS 2 types written out from their .msg files
under their DDS names (rt/joint_states, sensor_msgs::msg::dds_::JointState_, ...); rosbags
(typestore ROS2_JAZZY) decodes the raw CDR. Prints `ready` once every topic has a matched
writer, then one JSON line with the first joint state, next-best pose and arm trajectory.

    ROS_DOMAIN_ID=N python interop_reader.py TIMEOUT_S
"""

import json
import math
import os
import sys
import time
from dataclasses import dataclass

from cyclonedds._clayer import ddspy_take
from cyclonedds.core import InstanceState, Policy, Qos, SampleState, ViewState
from cyclonedds.idl import IdlStruct, types
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from rosbags.typesys import Stores, get_typestore

import cyclone_loopback


@dataclass
class Time_(IdlStruct, typename='builtin_interfaces::msg::dds_::Time_'):
    sec: types.int32
    nanosec: types.uint32


@dataclass
class Duration_(IdlStruct, typename='builtin_interfaces::msg::dds_::Duration_'):
    sec: types.int32
    nanosec: types.uint32


@dataclass
class Header_(IdlStruct, typename='std_msgs::msg::dds_::Header_'):
    stamp: Time_
    frame_id: str


@dataclass
class JointState_(IdlStruct, typename='sensor_msgs::msg::dds_::JointState_'):
    header: Header_
    name: types.sequence[str]
    position: types.sequence[types.float64]
    velocity: types.sequence[types.float64]
    effort: types.sequence[types.float64]


@dataclass
class Point_(IdlStruct, typename='geometry_msgs::msg::dds_::Point_'):
    x: types.float64
    y: types.float64
    z: types.float64


@dataclass
class Quaternion_(IdlStruct, typename='geometry_msgs::msg::dds_::Quaternion_'):
    x: types.float64
    y: types.float64
    z: types.float64
    w: types.float64


@dataclass
class Pose_(IdlStruct, typename='geometry_msgs::msg::dds_::Pose_'):
    position: Point_
    orientation: Quaternion_


@dataclass
class PoseStamped_(IdlStruct, typename='geometry_msgs::msg::dds_::PoseStamped_'):
    header: Header_
    pose: Pose_


@dataclass
class JointTrajectoryPoint_(IdlStruct, typename='trajectory_msgs::msg::dds_::JointTrajectoryPoint_'):
    positions: types.sequence[types.float64]
    velocities: types.sequence[types.float64]
    accelerations: types.sequence[types.float64]
    effort: types.sequence[types.float64]
    time_from_start: Duration_


@dataclass
class JointTrajectory_(IdlStruct, typename='trajectory_msgs::msg::dds_::JointTrajectory_'):
    header: Header_
    joint_names: types.sequence[str]
    points: types.sequence[JointTrajectoryPoint_]


# DDS topic -> (IDL type, ROS 2 type rosbags decodes it as)
TOPICS = {
    'rt/joint_states': (JointState_, 'sensor_msgs/msg/JointState'),
    'rt/hdp/next_best_pose': (PoseStamped_, 'geometry_msgs/msg/PoseStamped'),
    'rt/panda_arm_controller/joint_trajectory': (JointTrajectory_, 'trajectory_msgs/msg/JointTrajectory'),
}


def summary(topic: str, msg) -> dict:
    if topic == 'rt/joint_states':
        return {'name': list(msg.name), 'position': [float(x) for x in msg.position]}
    if topic == 'rt/hdp/next_best_pose':
        p, q = msg.pose.position, msg.pose.orientation
        return {'frame_id': msg.header.frame_id, 'stamp': [msg.header.stamp.sec, msg.header.stamp.nanosec],
                'position': [p.x, p.y, p.z], 'orientation': [q.x, q.y, q.z, q.w]}
    times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in msg.points]
    return {'joint_names': list(msg.joint_names), 'points': len(msg.points),
            'finite': all(math.isfinite(x) for p in msg.points for x in p.positions),
            'times_increasing': all(b > a for a, b in zip(times, times[1:]))}


def main(timeout_s: float) -> int:
    domain_id = int(os.environ['ROS_DOMAIN_ID'])
    _domain, participant = cyclone_loopback.participant(domain_id)     # loopback only, like the graph
    qos = Qos(Policy.Reliability.Reliable(0), Policy.History.KeepLast(10))
    readers = {name: DataReader(participant, Topic(participant, name, idl), qos=qos)
               for name, (idl, _) in TOPICS.items()}
    deadline = time.monotonic() + timeout_s
    while not all(r.get_matched_publications() for r in readers.values()):
        if time.monotonic() > deadline:
            print(f'no writer matched on {[n for n, r in readers.items() if not r.get_matched_publications()]}',
                  file=sys.stderr)
            return 1
        time.sleep(0.05)
    print('ready', flush=True)

    typestore = get_typestore(Stores.ROS2_JAZZY)
    first = {}
    while len(first) < len(TOPICS) and time.monotonic() < deadline:
        time.sleep(0.05)
        for name, reader in readers.items():
            for data, _ in ddspy_take(reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, 10):
                if name not in first:
                    first[name] = summary(name, typestore.deserialize_cdr(data, TOPICS[name][1]))
    if len(first) < len(TOPICS):
        print(f'nothing received on {sorted(set(TOPICS) - set(first))} within {timeout_s} s', file=sys.stderr)
        return 1
    print(json.dumps({'joint_states': first['rt/joint_states'], 'next_best_pose': first['rt/hdp/next_best_pose'],
                      'joint_trajectory': first['rt/panda_arm_controller/joint_trajectory']}), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main(float(sys.argv[1])))
