"""The run catalog: one Parquet dataset with a row per photo per run, appended to by many writers at once.

Layout under the root (``<store>/catalog/`` by convention)::

    <root>/date=YYYY-MM-DD/part-<utc time>-<pid>-<random>.parquet      one append's rows of that UTC day
    <root>/date=YYYY-MM-DD/compact-<utc time>-<pid>-<random>.parquet   many parts merged by ``compact``
    <root>/date=YYYY-MM-DD/.<name>.<host>.<pid>.tmp                      a file being written (readers ignore it)
    <root>/.compact.lock                                               held (flock) by a running compaction

Appends need no lock: every append writes its own new file under a name no other writer can pick (time, pid
and 48 random bits), first under a dot-prefixed temporary name, then renamed into place, so a reader lists
either nothing or the complete file, and a killed writer leaves only a temporary that readers never open.

Rows are plain dicts; the only required key is ``created_at`` (a timezone-aware datetime), which picks the
day partition. Column types are fixed per append as in the run log (bools, int64, float64 with inf/nan,
strings, UTC timestamps); files written at different times may differ in their columns and reading unifies
them: a column absent from a file reads as null there, int64 and float64 of one column promote to float64.

Reading never lets one bad file hide the catalog: an unreadable (corrupt, truncated) file, or one whose
column types cannot be unified with the others, is skipped, named in ``CatalogRead.skipped``, logged and
warned about (``CatalogWarning``).

Compaction (``compact``) merges the files of past days into one ``compact-`` file whose Parquet metadata
lists the names it replaces. Readers skip every listed name, so between publishing the merged file and
deleting the old ones a reader sees each row once. The old files are deleted only ``retention_s`` later (a
following compaction deletes them); a reader that still lost a file it had listed (it took longer than the
retention, or ``retention_s=0``) gets FileNotFoundError, and a reader whose listing raced a compaction sees
the set of ``compact-`` files change between its first and its second listing: in both cases it reads that
day again. So a reader sees either the old files or the new one, never both, never neither.

The files' naming, listing, reading and unifying are in ``assets_store.catalog_files``, the compaction in
``assets_store.catalog_compaction`` (``Catalog.compact``).
"""

from __future__ import annotations

import datetime as dt
import logging
import re
import warnings
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from assets_store.atomic import atomic_write
from assets_store.catalog_compaction import CompactResult, compact_days
from assets_store.catalog_files import (
    PART_PREFIX,
    READ_THREADS,
    CatalogError,
    compact_names,
    list_data_files,
    new_file_name,
    open_file,
    read_or_error,
    replaced_names,
    unify_tables,
)
from assets_store.columns import TIMESTAMP, typed_table
from assets_store.fsutil import fsync_dir

log = logging.getLogger(__name__)

CREATED_AT = "created_at"
PHOTO_KEY = "photo_key"

_PARTITION = re.compile(r"date=(\d{4}-\d{2}-\d{2})")
_READ_ATTEMPTS = 5  # re-reads of one day racing compactions before giving up


class CatalogWarning(UserWarning):
    """Some catalog files were skipped; the rows read are those of the other files."""


@dataclass
class CatalogRead:
    """What ``Catalog.scan`` read: the rows, the files they came from, and the files skipped (path, why)."""

    table: pa.Table
    files: list[Path] = field(default_factory=list)
    skipped: list[tuple[Path, str]] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------- rows -> table


def _utc(value: Any, where: str) -> dt.datetime:
    if not isinstance(value, dt.datetime):
        raise ValueError(f"{where}: {CREATED_AT} must be a timezone-aware datetime, got {type(value).__name__}")
    if value.tzinfo is None or value.utcoffset() is None:
        # A naive time is ambiguous (local? UTC?) and would put the row in the wrong day partition.
        raise ValueError(f"{where}: {CREATED_AT} {value.isoformat()} has no timezone; give UTC explicitly")
    return value.astimezone(dt.timezone.utc)


def rows_table(rows: Sequence[Mapping[str, Any]]) -> pa.Table:
    """The rows as a table: columns in first-seen order, nulls where a row lacks a key, explicit types."""
    return typed_table(rows, "catalog")


# ---------------------------------------------------------------------------------------------- the catalog


class Catalog:
    """An append-only Parquet dataset partitioned by UTC day (see the module docstring)."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)

    # -- writing

    def day_dir(self, day: dt.date) -> Path:
        return self.root / f"date={day.isoformat()}"

    def append(self, rows: Sequence[Mapping[str, Any]]) -> list[Path]:
        """Write the rows as one new file per UTC day of their ``created_at``; return the files written.

        Every row is checked before anything is written, so a bad row leaves the catalog unchanged. Each
        file is atomic on its own; rows spanning several days are several files (a crash between them
        leaves the earlier days written).
        """
        if not rows:
            return []
        by_day: dict[dt.date, list[Mapping[str, Any]]] = {}
        for i, row in enumerate(rows):
            if not isinstance(row, Mapping):
                raise ValueError(f"row {i}: a catalog row is a mapping, got {type(row).__name__}")
            by_day.setdefault(_utc(row.get(CREATED_AT), f"row {i}").date(), []).append(row)
        tables = {day: rows_table(day_rows) for day, day_rows in by_day.items()}
        written = []
        for day in sorted(tables):
            table = tables[day]
            directory = self.day_dir(day)
            new_dir = not directory.is_dir()
            path = directory / new_file_name(PART_PREFIX)
            atomic_write(path, lambda tmp, table=table: pq.write_table(table, str(tmp)))
            # The rename is durable only once the directory entry is: a power cut must not undo an append
            # the caller was told succeeded.
            fsync_dir(directory)
            if new_dir:
                fsync_dir(self.root)
            written.append(path)
        return written

    # -- reading

    def days(self) -> list[dt.date]:
        """The day partitions present, oldest first (folders not named ``date=YYYY-MM-DD`` are ignored)."""
        if not self.root.is_dir():
            return []
        out = []
        for entry in self.root.iterdir():
            m = _PARTITION.fullmatch(entry.name)
            if m and entry.is_dir():
                try:
                    out.append(dt.date.fromisoformat(m.group(1)))
                except ValueError:
                    continue  # date=2024-13-45: not a partition this catalog wrote
        return sorted(out)

    def _plan_day(self, day_dir: Path) -> tuple[set[str], list[Path], list[tuple[Path, str]]]:
        """(compact names seen, live files to read, skipped) for one day; FileNotFoundError: list again."""
        names = list_data_files(day_dir)
        compacts = compact_names(names)
        replaced: set[str] = set()
        skipped = []
        for name in sorted(compacts):
            try:
                with open_file(day_dir / name) as pf:
                    replaced |= replaced_names(pf)
            except FileNotFoundError:
                raise
            except Exception as exc:  # a corrupt merged file: its rows are lost to readers, say so
                skipped.append((day_dir / name, f"unreadable: {exc}"))
                replaced.add(name)
        live = [day_dir / n for n in sorted(names - replaced)]
        return compacts, live, skipped

    def _read_day_files(
        self, days: list[dt.date], columns: Sequence[str] | None, pool: ThreadPoolExecutor
    ) -> tuple[list[tuple[Path, pa.Table]], list[tuple[Path, str]]]:
        """Read the live files of these days, re-reading a day whose files changed under us (compaction)."""
        tables: list[tuple[Path, pa.Table]] = []
        skipped: list[tuple[Path, str]] = []
        pending = list(days)
        for _attempt in range(_READ_ATTEMPTS):
            if not pending:
                break
            plans: dict[dt.date, tuple[set[str], list[Path], list[tuple[Path, str]]]] = {}
            retry: list[dt.date] = []
            for day in pending:
                try:
                    plans[day] = self._plan_day(self.day_dir(day))
                except FileNotFoundError:
                    retry.append(day)
            jobs = [(day, path) for day, plan in plans.items() for path in plan[1]]
            results = list(pool.map(lambda path: read_or_error(path, columns), [p for _, p in jobs]))
            by_day: dict[dt.date, list[tuple[Path, pa.Table | BaseException]]] = {d: [] for d in plans}
            for (day, path), res in zip(jobs, results, strict=True):
                by_day[day].append((path, res))
            for day, plan in plans.items():
                compacts_before = plan[0]
                got = by_day[day]
                lost = any(isinstance(r, FileNotFoundError) for _, r in got)
                # A compaction published between our listing and now: the files we read may overlap the
                # merged file, or miss one it replaced; either way read the day again.
                changed = compact_names(list_data_files(self.day_dir(day))) != compacts_before
                if lost or changed:
                    retry.append(day)
                    continue
                skipped.extend(plan[2])
                for path, res in got:
                    if isinstance(res, BaseException):
                        skipped.append((path, f"unreadable: {res}"))
                    else:
                        tables.append((path, res))
            pending = sorted(retry)
        if pending:
            raise CatalogError(f"{self.root}: days {[d.isoformat() for d in pending]} kept changing during "
                               f"{_READ_ATTEMPTS} reads (a compaction loop?)")
        return tables, skipped

    def scan(
        self, since: dt.datetime | dt.date | None = None, columns: Sequence[str] | None = None
    ) -> CatalogRead:
        """Read every row (``created_at >= since`` when given); see ``read``. Also reports skipped files."""
        since_ts = None
        days = self.days()
        if since is not None:
            if isinstance(since, dt.datetime):
                since_ts = _utc(since, "since")
            else:  # a date: from its start, UTC
                since_ts = dt.datetime.combine(since, dt.time(), tzinfo=dt.timezone.utc)
            # The partition says the day of every row in it: older days are not even opened.
            days = [d for d in days if d >= since_ts.date()]
        wanted = None if columns is None else list(dict.fromkeys(columns))
        read_cols = None
        if wanted is not None:
            read_cols = wanted + ([CREATED_AT] if since_ts is not None and CREATED_AT not in wanted else [])
        with ThreadPoolExecutor(READ_THREADS) as pool:
            tables, skipped = self._read_day_files(days, read_cols, pool)
        # Read order: day, then file name (write time), so equal timestamps resolve to the later write.
        tables.sort(key=lambda pt: (pt[0].parent.name, pt[0].name))
        table, files, conflicts = unify_tables(tables)
        skipped.extend(conflicts)
        if table is None:
            table = pa.table({})
        if since_ts is not None and table.num_rows:
            if CREATED_AT in table.column_names:
                table = table.filter(pc.greater_equal(table[CREATED_AT], pa.scalar(since_ts, TIMESTAMP)))
            else:
                table = table.slice(0, 0)
        if wanted is not None:
            for name in wanted:
                if name not in table.column_names:
                    table = table.append_column(name, pa.nulls(table.num_rows))
            table = table.select(wanted)
        if skipped:
            names = ", ".join(f"{p} ({why})" for p, why in skipped)
            log.warning("catalog %s: skipped %d file(s): %s", self.root, len(skipped), names)
            warnings.warn(f"catalog {self.root}: skipped {len(skipped)} file(s): {names}", CatalogWarning,
                          stacklevel=3)
        return CatalogRead(table=table, files=files, skipped=skipped)

    def read(self, since: dt.datetime | dt.date | None = None, columns: Sequence[str] | None = None) -> pa.Table:
        """All rows as one table, oldest day first.

        ``since``: only rows with ``created_at >= since`` (an aware datetime, or a date meaning its UTC
        midnight); day partitions before it are never opened. ``columns``: only these, in this order; a
        column no file has reads as all null. Unreadable files are skipped with a ``CatalogWarning``.
        """
        return self.scan(since, columns).table

    def latest_per_photo(
        self, since: dt.datetime | dt.date | None = None, columns: Sequence[str] | None = None
    ) -> pa.Table:
        """The newest row (largest ``created_at``; on a tie the later write) of every ``photo_key``.

        Rows without a ``photo_key`` are left out. Sorted by ``photo_key``.
        """
        wanted = None if columns is None else list(dict.fromkeys(columns))
        read_cols = None if wanted is None else list(dict.fromkeys([*wanted, PHOTO_KEY, CREATED_AT]))
        table = self.read(since, read_cols)
        return latest_rows(table, wanted)

    # -- compaction (``assets_store.catalog_compaction``)

    def compact(self, before: dt.date | None = None, min_files: int = 2, retention_s: float = 600.0) -> CompactResult:
        """Merge each past day's files into one ``compact-`` file; return what was done (``compact_days``: which
        days, when replaced files go, what is never touched)."""
        return compact_days(self.root, self.days, self.day_dir, before, min_files, retention_s)


def latest_rows(table: pa.Table, columns: Sequence[str] | None = None) -> pa.Table:
    """Of each ``photo_key``, the row with the largest ``created_at``; on a tie the later row in ``table``.

    Rows without a ``photo_key`` are left out; the result is sorted by ``photo_key``.
    """
    if table.num_rows == 0:
        return table if columns is None else table.select([c for c in columns if c in table.column_names])
    for needed in (PHOTO_KEY, CREATED_AT):
        if needed not in table.column_names:
            raise CatalogError(f"the catalog rows have no {needed!r} column")
    # Sort only the keys, then take the winners from the full table: a catalog read from many small files has
    # one chunk per file, and sorting (taking every row of) all its columns across thousands of chunks is what
    # made this 2-3x slower than the read itself.
    keys = pa.table({"k": table[PHOTO_KEY].combine_chunks(), "t": table[CREATED_AT].combine_chunks(),
                     "o": pa.array(np.arange(table.num_rows, dtype=np.int64))})
    order = pc.sort_indices(keys, [("k", "ascending"), ("t", "descending"), ("o", "descending")])
    sorted_keys = pc.take(keys["k"], order)
    first = np.ones(len(sorted_keys), dtype=bool)  # the first row of each run of equal keys is that photo's newest
    if len(sorted_keys) > 1:
        differs = pc.not_equal(sorted_keys.slice(1), sorted_keys.slice(0, len(sorted_keys) - 1))
        first[1:] = pc.fill_null(differs, True).to_numpy(zero_copy_only=False)
    first &= pc.is_valid(sorted_keys).to_numpy(zero_copy_only=False)
    out = table.take(pc.filter(order, pa.array(first)))
    return out if columns is None else out.select(list(columns))
