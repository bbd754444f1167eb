"""The run log: one row per measurement (error against run time), stored as one Parquet file.

Rows may differ in their keys (a metric logged only every n steps); the table's columns are the
union in first-seen order with nulls where a row lacks a key. Column types are fixed explicitly
rather than inferred per file, so logs of different runs concatenate: ints as int64, floats
(and int/float mixes) as float64 with inf/nan kept, strings as string.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from assets_store.atomic import atomic_write


def _column_type(name: str, values: list[Any]) -> pa.DataType | None:
    present = [v for v in values if v is not None]
    if not present:
        return pa.null()
    if all(isinstance(v, bool) for v in present):
        return pa.bool_()
    if any(isinstance(v, bool) for v in present):
        raise TypeError(f"run log column {name!r} mixes booleans with other values")
    if all(isinstance(v, numbers.Integral) for v in present):
        return pa.int64()
    if all(isinstance(v, numbers.Real) for v in present):
        return pa.float64()
    if all(isinstance(v, str) for v in present):
        return pa.string()
    if any(isinstance(v, (str, numbers.Real)) for v in present):
        raise TypeError(f"run log column {name!r} mixes strings, numbers or other values")
    return None  # nested values (lists, dicts): let pyarrow infer


def _convert(value: Any, dtype: pa.DataType | None) -> Any:
    if value is None:
        return None
    if dtype == pa.int64():
        return int(value)
    if dtype == pa.float64():
        return float(value)
    return value


def runlog_table(rows: Sequence[Mapping[str, Any]]) -> pa.Table:
    """The rows as a table with explicit column types (see the module docstring)."""
    names: dict[str, None] = {}  # an ordered set: columns in first-seen order
    for row in rows:
        names.update(dict.fromkeys(row))
    columns = {}
    for name in names:
        values = [row.get(name) for row in rows]
        dtype = _column_type(name, values)
        columns[name] = pa.array([_convert(v, dtype) for v in values], type=dtype)
    return pa.table(columns)


def write_runlog(path: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Write the rows as one Parquet file, atomically (a reader never sees a partial log)."""
    table = runlog_table(rows)
    return atomic_write(Path(path), lambda tmp: pq.write_table(table, str(tmp)))


def read_runlog(path: Path) -> list[dict[str, Any]]:
    """The rows of a run log, missing values as None."""
    return pq.read_table(str(path)).to_pylist()
