"""CPU per node: utime + stime from /proc of each node process and its children."""

from __future__ import annotations

import contextlib
from pathlib import Path


def parse_stat(text: str) -> tuple[int, int]:
    """(ppid, utime + stime + cutime + cstime in clock ticks) of a /proc/<pid>/stat line.

    The command name (field 2) may hold spaces and parentheses: fields are counted after the
    last ')'. cutime + cstime hold the children that have already exited and been waited for.
    """
    fields = text[text.rindex(')') + 2:].split()
    return int(fields[1]), sum(int(v) for v in fields[11:15])


def tree_ticks(root: int, stats: dict[int, str]) -> int | None:
    """CPU ticks of ``root`` and its live descendants, from pid -> /proc stat text; None if gone."""
    if root not in stats:
        return None
    parsed = {pid: parse_stat(text) for pid, text in stats.items()}
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in parsed.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += parsed[pid][1]
        todo += children.get(pid, [])
    return total


def read_stats(proc: Path = Path('/proc')) -> dict[int, str]:
    """pid -> the text of /proc/<pid>/stat, for every process still there."""
    stats = {}
    for entry in proc.iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):       # gone meanwhile
                stats[int(entry.name)] = (entry / 'stat').read_text()
    return stats


def cpu_seconds(pids: dict[str, int], stats: dict[int, str], ticks_per_s: float) -> dict[str, float]:
    """name -> CPU seconds so far of that process tree; names whose process is gone are left out."""
    ticks = {name: tree_ticks(pid, stats) for name, pid in pids.items()}
    return {name: t / ticks_per_s for name, t in ticks.items() if t is not None}


def cpu_usage(before: dict[str, float], after: dict[str, float], wall_s: float) -> dict[str, dict]:
    """name -> {'cpu_s', 'cpu_percent'} between two cpu_seconds samples (100% = one core)."""
    return {name: {'cpu_s': round(after[name] - before[name], 3),
                   'cpu_percent': round(100.0 * (after[name] - before[name]) / wall_s, 1) if wall_s > 0 else None}
            for name in before if name in after}


