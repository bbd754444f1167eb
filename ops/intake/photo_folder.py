"""A watched folder of photos: which files are photos, their keys, and whether an upload is finished.

Built for folders of 100k files: ``scan`` reads names only (one ``os.scandir``, no ``stat``), so a
caller can diff keys first and look closely (``upload_state``) only at the few new files.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from assets_store.keys import assign_keys
from ops.intake.photo import EXTENSIONS

# Names that upload tools give files while they are still being written.
PARTIAL_SUFFIXES = (".part", ".partial", ".crdownload", ".download", ".tmp", ".temp", ".filepart", ".uploading")
_JPEG_END = b"\xff\xd9"
_PNG_END = b"IEND\xaeB`\x82"
_TAIL = 64  # JPEG writers may pad after the end-of-image marker
_LAST_SCAN: dict[str, tuple[int, dict[str, str]]] = {}  # resolved folder → (mtime_ns, key → name)


def is_photo_name(name: str) -> bool:
    """An image extension, not hidden (rsync and many uploaders write to ``.name.XXXX`` first)."""
    lower = name.lower()
    return not name.startswith(".") and not lower.endswith(PARTIAL_SUFFIXES) and Path(lower).suffix in EXTENSIONS


def list_photos(folder: Path) -> list[Path]:
    """The photos directly in ``folder`` (what ``scan`` finds), sorted by name."""
    return [Path(folder) / name for name in sorted(scan(folder).values())]


def scan(folder: Path) -> dict[str, str]:
    """Photo key → file name for every photo-named regular file directly in ``folder``."""
    folder = Path(folder)
    try:
        stamp = (str(folder.resolve()), folder.stat().st_mtime_ns)
    except OSError:
        stamp = None
    if stamp is None or not folder.is_dir():
        raise FileNotFoundError(f"photo folder {folder} does not exist; create it or point MORPHEUS_PHOTO_DIR at one")
    # Every stage of every photo resolves its key through this; a folder's listing only changes
    # when its mtime does (an entry added, removed or renamed), so reuse the last listing until then —
    # unless the mtime is recent: on filesystems with coarse timestamps a second change could share it.
    cached = _LAST_SCAN.get(stamp[0])
    if cached is not None and cached[0] == stamp[1] and time.time_ns() - stamp[1] > 2_000_000_000:
        return dict(cached[1])
    with os.scandir(folder) as it:
        names = [e.name for e in it if is_photo_name(e.name) and e.is_file()]
    keys = {key: name for name, key in assign_keys(names).items()}
    _LAST_SCAN[stamp[0]] = (stamp[1], keys)
    return dict(keys)


@dataclass(frozen=True)
class UploadState:
    ready: bool
    reason: str


def _complete_tail(path: Path, size: int) -> bool:
    """JPEG and PNG announce their end; a file cut off mid-upload lacks the end marker."""
    suffix = path.suffix.lower()
    if suffix not in (".jpg", ".jpeg", ".jpe", ".png") or size < 8:
        return size > 0
    with open(path, "rb") as fh:
        fh.seek(max(0, size - _TAIL))
        tail = fh.read()
    if suffix == ".png":
        return tail.endswith(_PNG_END)
    return _JPEG_END in tail


def upload_state(path: Path, settle_seconds: float, now: float | None = None) -> UploadState:
    """Whether ``path`` looks completely written: untouched for ``settle_seconds`` and, for JPEG
    and PNG, ending in the format's end marker."""
    try:
        st = path.stat()
        complete = _complete_tail(path, st.st_size)
    except OSError as exc:
        return UploadState(False, f"unreadable: {exc.strerror or exc}")
    age = (time.time() if now is None else now) - st.st_mtime
    if age < settle_seconds:
        return UploadState(False, f"modified {age:.0f} s ago (waiting {settle_seconds:.0f} s for the upload to settle)")
    if not complete:
        return UploadState(False, "incomplete file (no end-of-image marker): still uploading or truncated")
    return UploadState(True, "ready")
