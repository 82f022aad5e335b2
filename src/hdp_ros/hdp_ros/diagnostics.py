"""What every node says on /diagnostics once a second, as diagnostic_updater would say it.

Plain code (no rclpy): a RateMeter per subscribed topic, the one rule that turns a topic's
age and rate into OK/WARN/ERROR with a message a person can act on, and DiagnosticStatus
building. The nodes' 1 Hz steady-clock timers put the statuses into one DiagnosticArray.
Everything is judged on the wall clock, which keeps running when a simulator stops.
"""

from __future__ import annotations

import collections
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from hdp_msgs_py import topics

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
PERIOD_S = 1.0          # diagnostic_updater's default period
STALE_PERIODS = 3       # a topic silent for this many of its periods is late (WARN)
SLOW_FRACTION = 0.5     # a topic below this fraction of its expected rate is slow (WARN)

class RateMeter:
    """Arrivals of one topic on the wall clock: their rate over the last window_s, and the age of
    the last one (or of the meter, before any came, so a topic that never arrives ages too)."""

    def __init__(self, started_s: float, window_s: float = 5.0):
        self.started_s, self.window_s = started_s, window_s
        self.last_s: float | None = None
        self._arrivals: collections.deque[float] = collections.deque()

    def tick(self, wall_s: float) -> None:
        """One message arrived."""
        self.last_s = wall_s
        self._arrivals.append(wall_s)
        self._forget(wall_s)

    def rate_hz(self, wall_s: float) -> float:
        """Arrivals per second over the last window_s (or since the meter started, if less)."""
        self._forget(wall_s)
        span = min(self.window_s, wall_s - self.started_s)
        return len(self._arrivals) / span if span > 0 else 0.0

    def age_s(self, wall_s: float) -> float:
        return wall_s - (self.started_s if self.last_s is None else self.last_s)

    def _forget(self, wall_s: float) -> None:
        while self._arrivals and self._arrivals[0] <= wall_s - self.window_s:
            self._arrivals.popleft()


def topic_level(what: str, heard: bool, age_s: float, rate_hz: float, expected_hz: float, timeout_s: float,
                hint: str) -> tuple[bytes, str]:
    """The level and message for a topic: ERROR silent beyond timeout_s (the node's own limit, after
    which it fails its work), WARN silent for STALE_PERIODS of its expected periods or slower than
    SLOW_FRACTION of expected_hz, else OK. hint: what to check, for the messages that are not OK."""
    silent = f'no {what} for {age_s:.1f} s' if heard else f'no {what} yet ({age_s:.1f} s)'
    if age_s > timeout_s:
        return ERROR, f'{silent}: {hint}'
    if age_s > STALE_PERIODS / expected_hz:
        return WARN, f'{silent}, expected {expected_hz:g} Hz: {hint}'
    if rate_hz < SLOW_FRACTION * expected_hz:
        return WARN, f'{what} {rate_hz:.1f} Hz, expected {expected_hz:g} Hz: {hint}'
    return OK, f'{rate_hz:.1f} Hz'


def status(node: str, what: str, level: bytes, message: str, values: dict | None = None) -> DiagnosticStatus:
    """A status named as diagnostic_updater names them ('<node>: <what>'), hardware_id the node."""
    return DiagnosticStatus(level=level, name=f'{node}: {what}', message=message, hardware_id=node,
                            values=[KeyValue(key=key, value=_text(value)) for key, value in (values or {}).items()])


def topic_status(node: str, what: str, topic: str, meter: RateMeter, wall_s: float, expected_hz: float,
                 timeout_s: float, hint: str) -> DiagnosticStatus:
    """A subscribed topic's status: its rate and age judged by topic_level."""
    rate, age = meter.rate_hz(wall_s), meter.age_s(wall_s)
    level, message = topic_level(topic, meter.last_s is not None, age, rate, expected_hz, timeout_s, hint)
    return status(node, what, level, message, {'topic': topic, 'rate_hz': rate, 'age_s': age,
                                               'expected_hz': expected_hz, 'timeout_s': timeout_s})


def lifecycle_status(node: str, state: str, failure: str = '') -> DiagnosticStatus:
    """The managed node's state: OK when active, WARN otherwise (ERROR when configure failed)."""
    if state == 'active':
        return status(node, 'lifecycle', OK, 'active', {'state': state})
    if failure:
        return status(node, 'lifecycle', ERROR, f'{state}: configure failed: {failure}', {'state': state})
    return status(node, 'lifecycle', WARN, f'{state}: takes no work until activated (by the lifecycle manager)',
                  {'state': state})


def liveness_status(node: str, liveness, wall_s: float, clock_s: float) -> DiagnosticStatus:
    """The node's hdp_ros.liveness.Liveness: ERROR with its problem (the one its watchdog fails work
    for), else OK. clock_s: the node's clock now."""
    problem = liveness.problem(wall_s, clock_s)
    return status(node, 'liveness', OK if problem is None else ERROR,
                  problem or 'joint states arriving and the clock moving', {'state_timeout_s': liveness.timeout_s})


def advertise(node, collect) -> None:
    """Publish ``collect(wall_s)``'s statuses on /diagnostics from a 1 Hz steady-clock timer: under
    use_sim_time a node's own timers stop with the simulator, and that is when it matters most."""
    from rclpy.clock import Clock, ClockType      # here, so that the rules above load without rclpy
    publisher = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, topics.DIAGNOSTICS_QOS)

    def publish():
        array = DiagnosticArray(status=collect(time.monotonic()))
        array.header.stamp = node.get_clock().now().to_msg()
        publisher.publish(array)

    node.create_timer(PERIOD_S, publish, clock=Clock(clock_type=ClockType.STEADY_TIME))


def _text(value) -> str:
    if isinstance(value, float):
        return f'{value:.3f}'
    return str(value)
