"""The store layout and atomic stage commits.

Layout under the root::

    <root>/<photo-key>/<stage>/...                      finished output, manifest.json written last
    <root>/<photo-key>/.checkpoints/<stage>/            checkpoints of a running stage
    <root>/<photo-key>/.staging/<stage>.<pid>.<random>/ a stage being written (+ .lock: its writer lives)

A stage is written into a fresh staging folder and swapped into place only when complete, so a
reader (or a rerun after a crash) sees the previous finished output or the new one, never a mix.
Every path handed out is checked to resolve inside the root, so a crafted key or a symlinked photo
folder cannot make the store write elsewhere.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import secrets
import shutil
import stat
import time
from dataclasses import replace
from pathlib import Path
from types import TracebackType

from assets_store.atomic import atomic_write_text
from assets_store.fsutil import fsync_dir, lock_held, try_lock
from assets_store.hashing import file_sha256
from assets_store.keys import UnsafeKeyError, check_key, is_safe_key
from assets_store.manifest import MANIFEST_FILE, FileRecord, Fingerprint, Manifest

CHECKPOINTS_DIR = ".checkpoints"
STAGING_DIR = ".staging"
LOCK_SUFFIX = ".lock"  # <staging>/<folder>.lock: held by the folder's writer while it writes
CATALOG_DIR = ".catalog"

_STAGE_NAME = re.compile(r"[a-z0-9_]{1,64}")
_STAGING_NAME = re.compile(r"(?P<stage>[a-z0-9_]+)\.(?P<pid>\d+)\.(?P<token>[0-9a-f]+)(?P<old>\.old)?")
_CHUNK = 1 << 20
LOCKLESS_STALE_S = 24 * 3600.0  # a lockless staging folder this old has no writer (a stage writes within hours)
_SWAP_ATTEMPTS = 5


def check_stage(stage: str) -> str:
    """Return ``stage`` unchanged, or raise UnsafeKeyError: stage names are ``[a-z0-9_]+``."""
    if not isinstance(stage, str) or not _STAGE_NAME.fullmatch(stage):
        raise UnsafeKeyError(f"unsafe stage name {stage!r}: must match [a-z0-9_]+ (at most 64 characters)")
    return stage


def _hash_and_sync(path: Path) -> FileRecord:
    # One pass reads the file for its hash; the fsync makes sure what we hashed is on disk.
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            digest.update(chunk)
            size += len(chunk)
        os.fsync(fh.fileno())
    return FileRecord(sha256=digest.hexdigest(), size=size)


class Store:
    """Deterministic on-disk layout of every photo's stage outputs, checkpoints and staging folders."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        self._resolved_root: Path | None = None

    def _inside(self, path: Path) -> Path:
        if self._resolved_root is None or not self._resolved_root.exists():
            self._resolved_root = self.root.resolve()  # once: catalog-wide scans call this per stage
        root = self._resolved_root
        resolved = path.resolve()
        if resolved != root and not resolved.is_relative_to(root):
            raise UnsafeKeyError(f"{path} resolves to {resolved}, outside the store root {root}")
        return path

    def photo_dir(self, key: str) -> Path:
        """``<root>/<key>``: everything derived from one photo."""
        return self._inside(self.root / check_key(key))

    def stage_dir(self, key: str, stage: str) -> Path:
        """``<root>/<key>/<stage>``: a finished stage output."""
        return self._inside(self.photo_dir(key) / check_stage(stage))

    def checkpoint_dir(self, key: str, stage: str) -> Path:
        """``<root>/<key>/.checkpoints/<stage>``: checkpoints of a running stage."""
        return self._inside(self.photo_dir(key) / CHECKPOINTS_DIR / check_stage(stage))

    def staging_root(self, key: str) -> Path:
        """``<root>/<key>/.staging``: stage folders being written."""
        return self._inside(self.photo_dir(key) / STAGING_DIR)

    def read_manifest(self, key: str, stage: str) -> Manifest | None:
        """The stage's manifest, or None when missing, unparseable, for another key/stage, or when
        an output it lists is missing or has another size (sizes only: no re-hashing here)."""
        folder = self.stage_dir(key, stage)
        try:
            manifest = Manifest.from_json((folder / MANIFEST_FILE).read_text(encoding="utf-8"))
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if manifest.stage != stage or manifest.photo_key != key:
            return None
        for name, record in manifest.outputs.items():
            path = folder / name
            try:
                # A flat, plain name cannot leave the (already checked) stage folder, and lstat below
                # refuses a symlink; only nested names need the costlier full resolution.
                if "/" in name or "\\" in name or name in ("", ".", ".."):
                    self._inside(path)
                st = os.lstat(path)
                if not stat.S_ISREG(st.st_mode) or st.st_size != record.size:
                    return None
            except (OSError, UnsafeKeyError):
                return None
        return manifest

    def verify(self, key: str, stage: str) -> bool:
        """Full check: the manifest is valid and every output's sha256 matches (reads every byte)."""
        manifest = self.read_manifest(key, stage)
        if manifest is None:
            return False
        folder = self.stage_dir(key, stage)
        try:
            return all(file_sha256(folder / n) == r.sha256 for n, r in manifest.outputs.items())
        except OSError:
            return False

    def lookup(self, key: str, stage: str, *fingerprints: Fingerprint) -> Manifest | None:
        """The finished output's manifest when it is valid and was made from exactly one of ``fingerprints``."""
        manifest = self.read_manifest(key, stage)
        if manifest is None or manifest.fingerprint not in fingerprints:
            return None
        return manifest

    def stage_writer(self, key: str, stage: str) -> StageWriter:
        """A context manager giving a fresh staging folder; ``commit`` swaps it into place."""
        return StageWriter(self, check_key(key), check_stage(stage))

    def clear_checkpoints(self, key: str, stage: str) -> None:
        """Remove the stage's checkpoints (after its output is committed, or when they are stale)."""
        shutil.rmtree(self.checkpoint_dir(key, stage), ignore_errors=True)

    def cleanup_staging(self, key: str) -> list[Path]:
        """Remove staging folders whose writer is gone; returns what was removed.

        A writer holds an ``flock`` on ``<folder>.lock`` beside its folder while it writes, so
        liveness holds across hosts on shared storage (a process id means nothing on another
        host) and a killed writer's folder is free at once. A folder without a lock (written before
        these locks) is judged by age: gone once untouched for ``LOCKLESS_STALE_S``. A name that does
        not parse is left alone (not ours to judge).
        """
        staging = self.staging_root(key)
        removed: list[Path] = []
        if not staging.is_dir():
            return removed
        for entry in sorted(staging.iterdir()):
            if entry.name.endswith(LOCK_SUFFIX):
                continue
            match = _STAGING_NAME.fullmatch(entry.name)
            if match is None:
                continue
            lock = staging / (entry.name.removesuffix(".old") + LOCK_SUFFIX)
            alive = lock_held(lock) if lock.exists() else _recent(entry, LOCKLESS_STALE_S)
            if alive:
                continue
            if entry.is_symlink() or not entry.is_dir():
                entry.unlink(missing_ok=True)
            else:
                shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
        for lock in staging.glob(f"*{LOCK_SUFFIX}"):
            if not (staging / lock.name.removesuffix(LOCK_SUFFIX)).exists() and not lock_held(lock):
                lock.unlink(missing_ok=True)
        try:
            staging.rmdir()  # only succeeds when empty
        except OSError:
            pass
        return removed

    @property
    def catalog_dir(self) -> Path:
        """``<root>/.catalog``: the Parquet catalog (a row per photo per run); the leading dot keeps
        it apart from photo folders (a key never starts with a dot)."""
        return self.root / CATALOG_DIR

    def keys(self) -> list[str]:
        """Photo keys present under the root (folders whose names are safe keys), sorted."""
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and is_safe_key(p.name))


class StageWriter:
    """Writes one stage output into a staging folder and commits it atomically.

    Use as ``with store.stage_writer(key, stage) as w: ...write under w.path...; w.commit(manifest)``.
    Leaving the block by an exception, or without a commit, removes the staging folder and leaves any
    previous finished output untouched.
    """

    def __init__(self, store: Store, key: str, stage: str) -> None:
        self.store = store
        self.key = key
        self.stage = stage
        self._path: Path | None = None
        self._manifest: Manifest | None = None
        self._lock: int | None = None

    @property
    def path(self) -> Path:
        """The staging folder to write the stage's files into."""
        if self._path is None:
            raise RuntimeError("StageWriter.path is only available inside its with block")
        return self._path

    @property
    def manifest(self) -> Manifest | None:
        """The committed manifest, once ``commit`` has run."""
        return self._manifest

    def __enter__(self) -> StageWriter:
        staging = self.store.staging_root(self.key)
        staging.mkdir(parents=True, exist_ok=True)
        name = f"{self.stage}.{os.getpid()}.{secrets.token_hex(8)}"
        path = self.store._inside(staging / name)
        # The lock exists before the folder: cleanup never sees this folder without its live lock.
        self._lock = try_lock(staging / (name + LOCK_SUFFIX))
        path.mkdir()
        self._path = path
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._manifest is None and self._path is not None:
            shutil.rmtree(self._path, ignore_errors=True)
        if self._path is not None and self._lock is not None:
            (self._path.parent / (self._path.name + LOCK_SUFFIX)).unlink(missing_ok=True)
            os.close(self._lock)
        self._path, self._lock = None, None

    def _records(self) -> dict[str, FileRecord]:
        root = self.path
        records: dict[str, FileRecord] = {}
        for dirpath, dirnames, filenames in os.walk(root):
            here = Path(dirpath)
            for name in sorted(dirnames + filenames):
                path = here / name
                # A symlink would become an "output" that points anywhere, maybe outside the store.
                if path.is_symlink():
                    raise ValueError(f"stage output {path.relative_to(root)} is a symlink; write real files")
                if name in dirnames:
                    continue
                if not path.is_file():
                    raise ValueError(f"stage output {path.relative_to(root)} is not a regular file")
                rel = path.relative_to(root).as_posix()
                if rel != MANIFEST_FILE:
                    records[rel] = _hash_and_sync(path)
            fsync_dir(here)
        return records

    def commit(self, manifest: Manifest) -> Manifest:
        """Record every file under ``path``, write the manifest last, and swap the folder into place.

        ``manifest.outputs`` is replaced by the files actually present. Returns the final manifest.
        """
        if self._manifest is not None:
            raise RuntimeError("this stage writer has already committed")
        if manifest.stage != self.stage or manifest.photo_key != self.key:
            raise ValueError(
                f"manifest is for {manifest.photo_key}/{manifest.stage}, writer for {self.key}/{self.stage}"
            )
        final = replace(manifest, outputs=self._records())
        atomic_write_text(self.path / MANIFEST_FILE, final.to_json())
        fsync_dir(self.path)
        self._swap()
        self._manifest = final
        return final

    def _swap(self) -> None:
        target = self.store.stage_dir(self.key, self.stage)
        parent = target.parent
        aside = self.path.with_name(self.path.name + ".old")
        for _ in range(_SWAP_ATTEMPTS):
            moved_aside = False
            if target.exists() or target.is_symlink():
                os.replace(target, aside)
                moved_aside = True
            try:
                os.replace(self.path, target)
            except OSError as exc:
                # Another writer of the same stage got its folder in between: move that aside and retry.
                raced = exc.errno in (errno.ENOTEMPTY, errno.EEXIST)
                if moved_aside and raced:
                    shutil.rmtree(aside, ignore_errors=True)  # superseded by the other writer's output
                elif moved_aside:
                    os.replace(aside, target)  # put the previous finished output back
                if raced:
                    continue
                raise
            if moved_aside:
                shutil.rmtree(aside, ignore_errors=True)
            fsync_dir(parent)
            return
        raise OSError(f"could not move the staging folder into {target}: another writer keeps replacing it")


def _recent(path: Path, seconds: float) -> bool:
    """Whether ``path`` was modified within the last ``seconds`` (False when it is gone)."""
    try:
        return time.time() - path.lstat().st_mtime < seconds
    except FileNotFoundError:
        return False
