"""Compaction of the run catalog: merging each past day's files into one ``compact-`` file, deleting the files
it replaces once their retention is over (the protocol is in ``assets_store.catalog``'s docstring).
``Catalog.compact`` calls ``compact_days`` with its root and day folders."""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import json
import os
import re
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow.parquet as pq

from assets_store.atomic import atomic_write
from assets_store.catalog_files import (
    COMPACT_PREFIX,
    READ_THREADS,
    REPLACES_KEY,
    CatalogError,
    compact_names,
    list_data_files,
    new_file_name,
    open_file,
    read_or_error,
    replaced_names,
    unify_tables,
)
from assets_store.fsutil import fsync_dir

LOCK_FILE = ".compact.lock"

_TMP_FILE = re.compile(r"\..+\.\d+\.tmp")
_STALE_TMP_S = 24 * 3600.0  # a temporary this old belongs to a killed writer (an append takes milliseconds)


@dataclass
class CompactResult:
    """What ``Catalog.compact`` did. ``busy``: another compaction held the lock, nothing was done."""

    days: list[str] = field(default_factory=list)
    files_merged: int = 0
    rows: int = 0
    files_deleted: int = 0
    skipped: list[tuple[Path, str]] = field(default_factory=list)
    busy: bool = False


@contextlib.contextmanager
def _compaction_lock(root: Path) -> Iterator[bool]:
    root.mkdir(parents=True, exist_ok=True)
    fd = os.open(root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            # Two compactions of one day would each publish a merged file of the same rows; readers would
            # then read both. flock dies with its process, so a killed compaction never wedges the next.
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        yield True
    finally:
        os.close(fd)


def compact_days(
    root: Path, days: Callable[[], list[dt.date]], day_dir: Callable[[dt.date], Path],
    before: dt.date | None = None, min_files: int = 2, retention_s: float = 600.0,
) -> CompactResult:
    """Merge each past day's files of the catalog at ``root`` (``days()`` lists them, listed under the lock;
    ``day_dir(day)`` is a day's folder) into one ``compact-`` file; return what was done.

    ``before``: only days strictly before it (default: today, UTC — today still gets appends; a late
    append to a past day is a new part, merged by the next compaction). ``min_files``: a day with fewer
    live files is left alone. ``retention_s``: replaced files are deleted by the first compaction at least
    this long after the merged file was published, so readers that listed them meanwhile can still read
    them (0: at once; readers then re-read a day whose file vanished). Unreadable files are never merged
    or deleted. No row is dropped: the merged file's row count is checked against its inputs before
    anything is deleted.
    """
    if min_files < 1:
        raise ValueError("min_files must be at least 1")
    before = before or dt.datetime.now(dt.timezone.utc).date()
    result = CompactResult()
    with _compaction_lock(root) as locked:
        if not locked:
            result.busy = True
            return result
        with ThreadPoolExecutor(READ_THREADS) as pool:
            for day in days():
                if day < before:
                    _compact_day(day, day_dir(day), min_files, retention_s, result, pool)
    return result


def _compact_day(
    day: dt.date, directory: Path, min_files: int, retention_s: float, result: CompactResult,
    pool: ThreadPoolExecutor,
) -> None:
    now = time.time()
    _remove_stale_temporaries(directory, now)
    names = list_data_files(directory)  # under the lock only appends add files: this list is complete
    replaced: dict[str, float] = {}  # replaced name -> publication time of its merged file
    for name in sorted(compact_names(names)):
        try:
            with open_file(directory / name) as pf:
                covered = replaced_names(pf)
            published = (directory / name).stat().st_mtime
            for old in covered:
                replaced[old] = max(replaced.get(old, 0.0), published)
        except Exception as exc:
            # Which files this merged file replaces is unknown: deleting or merging anything here could
            # lose or duplicate rows, so the day is left as it is.
            result.skipped.append((directory / name, f"unreadable, day not compacted: {exc}"))
            return
    deleted = 0
    for old, published in replaced.items():
        if old in names and now - published >= retention_s:
            (directory / old).unlink(missing_ok=True)
            names.discard(old)
            deleted += 1
    live = sorted(names - replaced.keys())
    if len(live) >= max(min_files, 2):  # one file is already as merged as it gets
        tables = []
        paths = [directory / name for name in live]
        for path, res in zip(paths, pool.map(read_or_error, paths), strict=True):
            if isinstance(res, BaseException):
                result.skipped.append((path, f"unreadable, left in place: {res}"))
            else:
                tables.append((path, res))
        merged, inputs, conflicts = unify_tables(tables)
        result.skipped.extend((p, f"{why}; left in place") for p, why in conflicts)
        if merged is not None and len(inputs) >= min_files:
            merged_paths = set(inputs)
            expected = sum(t.num_rows for p, t in tables if p in merged_paths)
            # Every name still on disk that some merged file replaces stays replaced by the new one too,
            # so a reader skips it whichever merged file it looks at; names already deleted never return
            # (names are unique), so they need not be listed.
            covers = {p.name for p in inputs} | (replaced.keys() & names)
            merged = merged.replace_schema_metadata({REPLACES_KEY: json.dumps(sorted(covers)).encode()})
            path = directory / new_file_name(COMPACT_PREFIX)
            atomic_write(path, lambda tmp: pq.write_table(merged, str(tmp)))
            with open_file(path) as pf:
                written = pf.metadata.num_rows
            if written != expected:
                path.unlink()
                raise CatalogError(f"{path}: merged {written} rows, expected {expected}; nothing deleted")
            fsync_dir(directory)
            result.days.append(day.isoformat())
            result.files_merged += len(inputs)
            result.rows += written
            if retention_s <= 0:
                for name in covers:
                    (directory / name).unlink(missing_ok=True)
                    deleted += 1
    if deleted:
        fsync_dir(directory)
    result.files_deleted += deleted


def _remove_stale_temporaries(directory: Path, now: float) -> None:
    with os.scandir(directory) as it:
        for entry in it:
            if _TMP_FILE.fullmatch(entry.name):
                with contextlib.suppress(FileNotFoundError):
                    if now - entry.stat().st_mtime > _STALE_TMP_S:
                        os.unlink(entry.path)
