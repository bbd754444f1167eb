"""Small filesystem helpers shared by the store and checkpoints: directory fsync and pid liveness."""

from __future__ import annotations

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
