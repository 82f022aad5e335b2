"""`hdp demo --record`: the run as an MCAP bag that Foxglove opens, or `ros2 bag play` replays
for RViz: the robot (description and TF), both cameras, what the planner chose and what the
controller sent. A one-episode recording is also a training episode, written the way
`ros2 bag record` writes a real demonstration (the hdp_bringup README's recipe).

Messages are written as they come off the wire (rclpy's raw subscriptions: the CDR bytes, no
decoding), stamped with the wall clock on arrival as `ros2 bag record` stamps them.
"""

from __future__ import annotations

import time
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from hdp_msgs_py import topics
from hdp_data.episodes import offered_qos
from hdp_msgs_py.message import type_name_of
from hdp_msgs_py.msg import (CameraInfo, Image, JointState, JointTrajectory, Marker, PointCloud2, PoseStamped,
                             String, TFMessage)

# topic -> (type, QoS the recorder subscribes with)
RECORDED = {
    topics.ROBOT_DESCRIPTION: (String, topics.LATCHED_QOS),
    topics.TF_STATIC: (TFMessage, topics.TF_STATIC_QOS),
    topics.TF: (TFMessage, topics.TF_QOS),
    topics.JOINT_STATES: (JointState, topics.COMMAND_QOS),
    **{topic: (kind, topics.SENSOR_QOS) for camera in topics.CAMERAS
       for topic, kind in ((topics.color_image(camera), Image), (topics.depth_image(camera), Image),
                           (topics.camera_info(camera), CameraInfo))},
    topics.INSTRUCTION: (String, topics.COMMAND_QOS),
    topics.NEXT_BEST_POSE: (PoseStamped, topics.COMMAND_QOS),
    topics.NEXT_BEST_POSE_MARKER: (Marker, topics.COMMAND_QOS),
    topics.PLANNER_CLOUD: (PointCloud2, topics.SENSOR_QOS),
    topics.ARM_TRAJECTORY: (JointTrajectory, topics.COMMAND_QOS),
    topics.STATUS: (String, topics.STATUS_QOS),
    topics.OUTCOME: (String, topics.COMMAND_QOS),
}


class BagRecorder:
    """Records RECORDED into ``path`` (a new rosbag2 directory, MCAP) from ``node``'s executor."""

    def __init__(self, node, path: Path):
        self.path = Path(path)
        self._writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self.counts = dict.fromkeys(RECORDED, 0)
        for topic, (kind, qos) in RECORDED.items():
            connection = self._writer.add_connection(topic, type_name_of(kind), typestore=self._typestore,
                                                     offered_qos_profiles=[offered_qos(topic)])
            node.create_subscription(kind, topic, lambda raw, c=connection, t=topic: self._write(c, t, raw),
                                     qos, raw=True)

    def _write(self, connection, topic: str, raw: bytes) -> None:
        if self._writer is not None:
            self._writer.write(connection, time.time_ns(), raw)
            self.counts[topic] += 1

    def close(self, custom_data: dict | None = None) -> None:
        """Finish the bag; ``custom_data`` goes in its metadata as plain strings, as
        `ros2 bag record --custom-data key=value` writes them."""
        if self._writer is not None:
            for key, value in (custom_data or {}).items():
                self._writer.set_custom_data(key, str(value))
            self._writer.close()
            self._writer = None
