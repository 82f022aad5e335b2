"""QoS profiles with rclpy's names, and their translation to Cyclone DDS."""

from __future__ import annotations

import dataclasses
import enum

from cyclonedds.core import Policy
from cyclonedds.qos import Qos
from cyclonedds.util import duration


class ReliabilityPolicy(enum.Enum):
    RELIABLE = 'reliable'
    BEST_EFFORT = 'best_effort'


class DurabilityPolicy(enum.Enum):
    VOLATILE = 'volatile'
    TRANSIENT_LOCAL = 'transient_local'


class HistoryPolicy(enum.Enum):
    KEEP_LAST = 'keep_last'
    KEEP_ALL = 'keep_all'


@dataclasses.dataclass(frozen=True)
class QoSProfile:
    """The subset of rclpy.qos.QoSProfile our nodes use (same defaults as ROS)."""
    depth: int = 10
    reliability: ReliabilityPolicy = ReliabilityPolicy.RELIABLE
    durability: DurabilityPolicy = DurabilityPolicy.VOLATILE
    history: HistoryPolicy = HistoryPolicy.KEEP_LAST

    def __post_init__(self):
        if self.history is HistoryPolicy.KEEP_LAST and self.depth < 1:
            raise ValueError(f'KEEP_LAST needs depth >= 1, got {self.depth}')


qos_profile_system_default = QoSProfile()
qos_profile_sensor_data = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
qos_profile_parameters = QoSProfile(depth=1000)


def as_profile(qos_or_depth) -> QoSProfile:
    """rclpy accepts a QoSProfile or a plain history depth."""
    if isinstance(qos_or_depth, QoSProfile):
        return qos_or_depth
    if isinstance(qos_or_depth, int) and not isinstance(qos_or_depth, bool):
        return QoSProfile(depth=qos_or_depth)
    raise TypeError(f'expected a QoSProfile or a history depth, got {qos_or_depth!r}')


def to_dds(profile: QoSProfile, user_data: bytes | None = None) -> Qos:
    reliability = (Policy.Reliability.Reliable(duration(milliseconds=100))
                   if profile.reliability is ReliabilityPolicy.RELIABLE else Policy.Reliability.BestEffort)
    durability = (Policy.Durability.TransientLocal if profile.durability is DurabilityPolicy.TRANSIENT_LOCAL
                  else Policy.Durability.Volatile)
    history = (Policy.History.KeepLast(profile.depth) if profile.history is HistoryPolicy.KEEP_LAST
               else Policy.History.KeepAll)
    policies = [reliability, durability, history]
    if user_data:
        policies.append(Policy.Userdata(user_data))
    return Qos(*policies)
