"""rclpy-style node loggers: `[INFO] [1712345678.123456789] [node]: message` on stderr."""

from __future__ import annotations

import enum
import sys
import threading
import time


class LoggingSeverity(enum.IntEnum):
    DEBUG = 10
    INFO = 20
    WARN = 30
    ERROR = 40
    FATAL = 50


_default_level = LoggingSeverity.INFO
_lock = threading.Lock()


def set_default_level(level: str | LoggingSeverity) -> None:
    global _default_level
    _default_level = parse_level(level)


def parse_level(level) -> LoggingSeverity:
    if isinstance(level, LoggingSeverity):
        return level
    name = str(level).upper()
    name = 'WARN' if name == 'WARNING' else name
    if name not in LoggingSeverity.__members__:
        raise ValueError(f'unknown log level {level!r}; use debug, info, warn, error or fatal')
    return LoggingSeverity[name]


class Logger:
    def __init__(self, name: str):
        self.name = name
        self._level: LoggingSeverity | None = None
        self._once: set[str] = set()
        self._last: dict[str, float] = {}

    def get_effective_level(self) -> LoggingSeverity:
        return self._level if self._level is not None else _default_level

    def set_level(self, level) -> None:
        self._level = parse_level(level)

    def get_child(self, name: str) -> Logger:
        return Logger(f'{self.name}.{name}')

    def log(self, message, severity: LoggingSeverity, *, once: bool = False,
            throttle_duration_sec: float | None = None, skip_first: bool = False) -> bool:
        if severity < self.get_effective_level():
            return False
        key = str(message)
        if once:
            if key in self._once:
                return False
            self._once.add(key)
        if throttle_duration_sec or skip_first:
            now = time.monotonic()
            last = self._last.get(key)
            if last is None:
                self._last[key] = now
                if skip_first:
                    return False
            elif throttle_duration_sec and now - last < throttle_duration_sec:
                return False
            self._last[key] = now
        sec, nsec = divmod(time.time_ns(), 1_000_000_000)
        with _lock:
            print(f'[{severity.name}] [{sec}.{nsec:09d}] [{self.name}]: {message}', file=sys.stderr, flush=True)
        return True

    def debug(self, message, **kwargs):
        return self.log(message, LoggingSeverity.DEBUG, **kwargs)

    def info(self, message, **kwargs):
        return self.log(message, LoggingSeverity.INFO, **kwargs)

    def warning(self, message, **kwargs):
        return self.log(message, LoggingSeverity.WARN, **kwargs)

    warn = warning

    def error(self, message, **kwargs):
        return self.log(message, LoggingSeverity.ERROR, **kwargs)

    def fatal(self, message, **kwargs):
        return self.log(message, LoggingSeverity.FATAL, **kwargs)


def get_logger(name: str) -> Logger:
    return Logger(name)
