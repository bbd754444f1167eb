"""The run log: one row per measurement (error against run time), stored as one Parquet file.

Rows may differ in their keys (a metric logged only every n steps); the table's columns are the
union in first-seen order with nulls where a row lacks a key. Column types are fixed explicitly
rather than inferred per file, so logs of different runs concatenate: ints as int64, floats
(and int/float mixes) as float64 with inf/nan kept, strings as string.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from assets_store.atomic import atomic_write
from assets_store.columns import typed_table


def runlog_table(rows: Sequence[Mapping[str, Any]]) -> pa.Table:
    """The rows as a table with explicit column types (``assets_store.columns``)."""
    return typed_table(rows, "run log")


def write_runlog(path: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Write the rows as one Parquet file, atomically (a reader never sees a partial log)."""
    table = runlog_table(rows)
    return atomic_write(Path(path), lambda tmp: pq.write_table(table, str(tmp)))


def read_runlog(path: Path) -> list[dict[str, Any]]:
    """The rows of a run log, missing values as None."""
    return pq.read_table(str(path)).to_pylist()
