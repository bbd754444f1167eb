"""Content hashes of source photos, remembered by (size, mtime, inode) like a version-control index.

The nightly catch-up and the photo observation compare every photo's content hash with what its
stages were made from; re-reading 100k photos each night would take hours, so a photo is hashed
again only when its size, modification time or inode changed. The cache lives in the store root;
writes are atomic, and a lost update between two writers only costs a re-hash.
"""

from __future__ import annotations

import json
from pathlib import Path

from assets_store.atomic import atomic_write_text
from assets_store.hashing import file_sha256

CACHE_FILE = ".photo_hashes.json"


class PhotoHashes:
    def __init__(self, store_root: Path | str) -> None:
        self.path = Path(store_root) / CACHE_FILE
        self._entries: dict[str, list] = {}
        self._dirty = False
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            if isinstance(data, dict):
                self._entries = data
        except (OSError, ValueError):
            pass  # missing or damaged: everything is hashed again

    def sha256(self, photo: Path) -> str:
        """The photo's content hash (re-hashed only when its size, mtime or inode changed)."""
        path = Path(photo).resolve()
        st = path.stat()
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        entry = self._entries.get(str(path))
        if entry is not None and entry[:3] == stamp:
            return entry[3]
        digest = file_sha256(path)
        self._entries[str(path)] = [*stamp, digest]
        self._dirty = True
        return digest

    def save(self) -> None:
        if self._dirty:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.path, json.dumps(self._entries, separators=(",", ":")))
            self._dirty = False
