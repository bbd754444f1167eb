"""Small filesystem helpers shared by the store, checkpoints and GPU leases: directory fsync, pid
liveness and advisory locks."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (renames, new files) durable, not just the files' contents."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists; used to tell leftovers of killed writers from live work.

    A process owned by another user counts as alive (we may not signal it, but it exists).
    """
    if pid <= 0:  # 0 and negatives address process groups, not one process
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:  # beyond the platform's pid_t: no such process
        return False
    return True


def try_lock(path: Path) -> int | None:
    """An exclusive ``flock`` on ``path`` (created if missing), or None when another process holds it.

    The kernel releases it when the holder's descriptor closes, including when the process dies. On
    NFS, Linux maps flock onto NFSv4 byte-range locks, which the server drops only after the dead
    client's lease expires (about 90 s); on NFSv3 without a lock manager, locks are local only.
    """
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def lock_held(path: Path) -> bool:
    """Whether some process holds the ``flock`` on ``path`` (False when the file is gone)."""
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False
