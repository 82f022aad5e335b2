"""A single-threaded executor: one Cyclone WaitSet over every subscription."""

from __future__ import annotations

import time

from cyclonedds.core import WaitSet

from .context import ExternalShutdownException, default_context

# Cap on one blocking wait so SIGINT/SIGTERM are handled promptly: Python runs
# signal handlers only between bytecodes, not inside a C wait.
_MAX_WAIT_NS = 100_000_000


class SingleThreadedExecutor:
    def __init__(self, *, context=None):
        self.context = context or default_context
        self._nodes: list = []
        self._waitset: WaitSet | None = None
        self._attached: dict[int, object] = {}

    def add_node(self, node) -> bool:
        if node in self._nodes:
            return False
        self._nodes.append(node)
        return True

    def remove_node(self, node) -> None:
        if node in self._nodes:
            self._nodes.remove(node)

    def get_nodes(self) -> list:
        return list(self._nodes)

    def _sync_waitset(self, subscriptions) -> None:
        if self._waitset is None:
            self._waitset = WaitSet(self.context.participant)
            self._waitset.attach(self.context.guard)
        wanted = {id(s.condition): s.condition for s in subscriptions if s.condition is not None}
        for key in set(self._attached) - set(wanted):
            try:
                self._waitset.detach(self._attached.pop(key))
            except Exception:   # noqa: BLE001 (the reader may already be gone)
                pass
        for key in set(wanted) - set(self._attached):
            self._waitset.attach(wanted[key])
            self._attached[key] = wanted[key]

    def spin_once(self, timeout_sec: float | None = None) -> None:
        if not self.context.ok():
            raise ExternalShutdownException()
        subscriptions = [(n, s) for n in self._nodes for s in list(n.subscriptions)]
        timers = [(n, t) for n in self._nodes for t in list(n.timers)]
        self._sync_waitset([s for _, s in subscriptions])

        # Block until a sample or the guard arrives, a timer is due, or the timeout ends.
        deadline = None if timeout_sec is None else time.monotonic_ns() + int(max(timeout_sec, 0) * 1e9)
        while True:
            wait_ns = _MAX_WAIT_NS
            if deadline is not None:
                wait_ns = min(wait_ns, deadline - time.monotonic_ns())
            for _, timer in timers:
                due = timer.time_until_next_call()
                if due is not None:
                    wait_ns = min(wait_ns, due)
            if wait_ns <= 0 or self._waitset.wait(wait_ns) > 0 or not self.context.ok():
                break
            if deadline is not None and time.monotonic_ns() >= deadline:
                break
        self.context.guard.set(False)
        if not self.context.ok():
            raise ExternalShutdownException()

        for node, timer in timers:
            due = timer.time_until_next_call()
            if due is not None and due <= 0:
                node.run_callback('timer callback', timer.call)
        for node, sub in subscriptions:
            if sub.condition is None:
                continue
            for msg in sub.take():
                node.run_callback(f"subscription callback on '{sub.topic_name}'", sub.callback, msg)

    def spin(self) -> None:
        while self.context.ok():
            self.spin_once()
        raise ExternalShutdownException()
