"""Atomic file writes: write a temporary sibling, fsync, then rename over the target.

The one implementation, used by the method (exports, adapter checkpoints) and the store alike.

A killed process leaves either the old file or the new one, never a half-written artifact;
temporaries are dot-files ending in ``.tmp`` so no reader mistakes them for outputs. Their names,
``.<name>.<host>.<pid>.tmp``, say which process wrote them: process ids repeat across the hosts (and
pods) sharing a store, so only a process on the same host may judge a temporary abandoned by its id.
"""

from __future__ import annotations

import os
import re
import socket
from collections.abc import Callable
from pathlib import Path

HOST = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname()) or "host"


def atomic_write(path: Path, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` and move the result to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{HOST}.{os.getpid()}.tmp")
    try:
        writer(tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def atomic_write_text(path: Path, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    return atomic_write(path, lambda p: p.write_bytes(data))
