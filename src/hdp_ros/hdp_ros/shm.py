"""Fast DDS shared-memory segments whose process is gone, found and removed.

Each Fast DDS participant creates a segment of its own, ``/dev/shm/fastrtps_<16 hex digits>``
(with the project's profile 16 MiB for samples plus Fast DDS's bookkeeping: 17.5 MB), and holds
an exclusive flock on its lock file ``<segment>_el`` as long as it lives. A process that ends
without deleting its participant (SIGKILL, a crash, ``os._exit``) leaves both files behind, and
Fast DDS 2.14 removes them only from a live peer that had mapped the segment (its watchdog
notices the lock is free); otherwise they stay until reboot. A lock nobody holds proves the
owner is gone: ``fastdds shm clean`` removes such segments by the same test, and so does
remove_dead_segments(), which ros.init() runs before every start.

Port queues (``fastrtps_port<N>``, 52 kB, and their ``_el`` and ``sem.*_mutex`` files) are left
alone: they are named by port number, so they do not pile up, and Fast DDS resets a dead
listener's port itself when a participant takes that number again, under the port's mutex,
which a removal from here would race with.
"""

import contextlib
import fcntl
import os
import re
import time
from pathlib import Path

SHM_DIR = Path('/dev/shm')
_SEGMENT_LOCK = re.compile(r'fastrtps_[0-9a-z]{16}_el')
# Fast DDS creates a lock file, then locks it: a younger file may be one not locked yet.
MIN_AGE_S = 2.0


def _dead_locks(shm_dir: Path, min_age_s: float):
    """Each segment lock file that no process holds, held by us until the next one is yielded."""
    if not shm_dir.is_dir():
        return
    now = time.time()
    for entry in os.scandir(shm_dir):
        if not _SEGMENT_LOCK.fullmatch(entry.name):
            continue
        try:
            if now - entry.stat().st_mtime < min_age_s:
                continue
            fd = os.open(entry.path, os.O_RDONLY)
        except OSError:             # removed meanwhile, or not ours to read
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:             # held: its owner is alive
            os.close(fd)
            continue
        try:
            yield Path(entry.path)
        finally:
            os.close(fd)            # releases the lock


def _segment(lock: Path) -> Path:
    return lock.with_name(lock.name[:-len('_el')])


def dead_segments(shm_dir: Path = SHM_DIR, min_age_s: float = MIN_AGE_S) -> list[Path]:
    """The segments (their paths) whose owner is gone."""
    return [_segment(lock) for lock in _dead_locks(shm_dir, min_age_s)]


def remove_dead_segments(shm_dir: Path = SHM_DIR, min_age_s: float = MIN_AGE_S) -> int:
    """Remove each segment whose owner is gone, with its lock file; how many segments went.

    Never one of a live process: the lock is held while the files go. Another user's files
    (/dev/shm is sticky) stay.
    """
    removed = 0
    for lock in _dead_locks(shm_dir, min_age_s):
        with contextlib.suppress(FileNotFoundError, PermissionError):
            _segment(lock).unlink()
            removed += 1
        with contextlib.suppress(FileNotFoundError, PermissionError):
            lock.unlink()
    return removed
