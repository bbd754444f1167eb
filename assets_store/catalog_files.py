"""The run catalog's files (the layout and protocol are in ``assets_store.catalog``'s docstring): their names,
listing a day's data files, opening and reading them (a ``compact-`` file's list of the names it replaces), and
unifying the tables read; and ``CatalogError``, raised by the reading and the compaction alike.

This is the file-level interface that ``Catalog``'s reading (``assets_store.catalog``) and its compaction
(``assets_store.catalog_compaction``) share; neither reaches into the files any other way."""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import secrets
from collections.abc import Sequence
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

PART_PREFIX = "part"
COMPACT_PREFIX = "compact"
REPLACES_KEY = b"morpheus.catalog.replaces"  # Parquet key-value metadata of a compact file: JSON list of names

_DATA_FILE = re.compile(r"(part|compact)-\d{8}T\d{12}Z-\d+-[0-9a-f]+\.parquet")
# Catalog files are small: a read is mostly per-file overhead (open, footer, Python), ~1 ms. Two threads per core
# overlap the I/O waits; pyarrow's own per-read threads are off (use_threads=False) because with many files in
# flight they only contend (measured on 2 cores: 1,000 files in 1.06 s this way, 2-3 s with both pools on).
READ_THREADS = min(8, 2 * (os.cpu_count() or 1))
"""Threads of the pool that reads a catalog's files (the reading and the compaction alike)."""


class CatalogError(RuntimeError):
    """The catalog cannot answer (e.g. a day kept changing under the reader)."""


# ---------------------------------------------------------------------------------------------- file naming


def new_file_name(prefix: str) -> str:
    """A fresh data file name, ``<prefix>-<utc time>-<pid>-<random>.parquet``, that no other writer picks."""
    now = dt.datetime.now(dt.timezone.utc)
    # The time first so names sort by write time (parts of a day are read in write order); pid + 48 random
    # bits make a clash between writers in the same microsecond practically impossible, with no lock.
    return f"{prefix}-{now:%Y%m%dT%H%M%S%f}Z-{os.getpid()}-{secrets.token_hex(6)}.parquet"


def list_data_files(day_dir: Path) -> set[str]:
    """The names of the data files (parts and compacts, no temporaries) in a day folder; none if it is absent."""
    try:
        with os.scandir(day_dir) as it:
            return {e.name for e in it if _DATA_FILE.fullmatch(e.name) and e.is_file()}
    except FileNotFoundError:
        return set()


def compact_names(names: set[str]) -> set[str]:
    """The ``compact-`` files among these names."""
    return {n for n in names if n.startswith(COMPACT_PREFIX + "-")}


def replaced_names(pf: pq.ParquetFile) -> set[str]:
    """The names of the files a ``compact-`` file replaces (its metadata); none for a part file."""
    meta = pf.schema_arrow.metadata or {}
    raw = meta.get(REPLACES_KEY)
    return set(json.loads(raw)) if raw else set()


def open_file(path: Path) -> pq.ParquetFile:
    """Open a catalog data file for its metadata or rows (a context manager)."""
    # FileNotFoundError propagates (a compaction removed the file: the caller reads the day again); every
    # other failure means the file itself is bad.
    return pq.ParquetFile(str(path))


def _read_file(path: Path, columns: Sequence[str] | None) -> pa.Table:
    with open_file(path) as pf:
        if columns is None:
            return pf.read(use_threads=False)
        present = set(pf.schema_arrow.names)
        return pf.read(columns=[c for c in columns if c in present], use_threads=False)


def read_or_error(path: Path, columns: Sequence[str] | None = None) -> pa.Table | Exception:
    """One data file's table (those of ``columns`` it has, all when None), or the exception reading it raised.

    The failure is returned instead of raised: one bad file must not stop a pool map.
    """
    try:
        return _read_file(path, columns)
    except Exception as exc:
        return exc


# ---------------------------------------------------------------------------------------------- unify


def unify_tables(
    tables: list[tuple[Path, pa.Table]],
) -> tuple[pa.Table | None, list[Path], list[tuple[Path, str]]]:
    """Concatenate tables with schema unification; a table whose types cannot be unified is left out.

    Larger tables are unified first so the types of the many rows win over those of a stray file.
    """
    order = sorted(range(len(tables)), key=lambda i: -tables[i][1].num_rows)
    schema: pa.Schema | None = None
    kept: set[int] = set()
    skipped: list[tuple[Path, str]] = []
    for i in order:
        path, table = tables[i]
        try:
            schema = table.schema if schema is None else pa.unify_schemas(
                [schema, table.schema], promote_options="permissive")
        except (pa.ArrowTypeError, pa.ArrowInvalid) as exc:
            skipped.append((path, f"column types conflict with the rest of the catalog: {exc}"))
            continue
        kept.add(i)
    chosen = [tables[i] for i in sorted(kept)]  # back to read order
    if not chosen:
        return None, [], skipped
    combined = pa.concat_tables([t.replace_schema_metadata(None) for _, t in chosen], promote_options="permissive")
    return combined, [p for p, _ in chosen], skipped
