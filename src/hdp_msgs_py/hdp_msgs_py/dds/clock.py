"""Time, Duration and a Clock that follows /clock when use_sim_time is set."""

from __future__ import annotations

import dataclasses
import threading
import time

from ..message import get_message

_NS = 1_000_000_000


@dataclasses.dataclass(frozen=True, order=True)
class Duration:
    nanoseconds: int = 0

    def __init__(self, *, seconds: float = 0, nanoseconds: int = 0):
        object.__setattr__(self, 'nanoseconds', int(round(seconds * _NS)) + int(nanoseconds))

    def to_msg(self):
        sec, nanosec = divmod(self.nanoseconds, _NS)
        return get_message('builtin_interfaces/msg/Duration')(sec=sec, nanosec=nanosec)

    @classmethod
    def from_msg(cls, msg) -> Duration:
        return cls(nanoseconds=msg.sec * _NS + msg.nanosec)


@dataclasses.dataclass(frozen=True, order=True)
class Time:
    nanoseconds: int = 0

    def __init__(self, *, seconds: float = 0, nanoseconds: int = 0):
        object.__setattr__(self, 'nanoseconds', int(round(seconds * _NS)) + int(nanoseconds))

    def seconds_nanoseconds(self) -> tuple[int, int]:
        return divmod(self.nanoseconds, _NS)

    def to_msg(self):
        sec, nanosec = self.seconds_nanoseconds()
        return get_message('builtin_interfaces/msg/Time')(sec=sec, nanosec=nanosec)

    @classmethod
    def from_msg(cls, msg) -> Time:
        return cls(nanoseconds=msg.sec * _NS + msg.nanosec)

    def __sub__(self, other):
        if isinstance(other, Time):
            return Duration(nanoseconds=self.nanoseconds - other.nanoseconds)
        return Time(nanoseconds=self.nanoseconds - other.nanoseconds)

    def __add__(self, other: Duration) -> Time:
        return Time(nanoseconds=self.nanoseconds + other.nanoseconds)


class Clock:
    """ROS time: the system clock, or the last /clock message under sim time."""

    def __init__(self):
        self._lock = threading.Lock()
        self._sim_ns: int | None = None   # None: sim time off
        # Bumped when time jumps (sim time switched on or off, /clock going
        # back): timers restart from the new time, as rcl timers do.
        self.jumps = 0

    @property
    def ros_time_is_active(self) -> bool:
        return self._sim_ns is not None

    def set_sim_time(self, active: bool) -> None:
        with self._lock:
            if active != (self._sim_ns is not None):
                self.jumps += 1
            self._sim_ns = (self._sim_ns or 0) if active else None

    def set_sim_now(self, nanoseconds: int) -> None:
        with self._lock:
            if self._sim_ns is not None:
                if nanoseconds < self._sim_ns or self._sim_ns == 0:
                    self.jumps += 1
                self._sim_ns = nanoseconds

    def now(self) -> Time:
        with self._lock:
            return Time(nanoseconds=self._sim_ns if self._sim_ns is not None else time.time_ns())
