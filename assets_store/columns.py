"""Rows (dicts) → an Arrow table with explicit column types, shared by the run log and the catalog.

Columns are the union of the rows' keys in first-seen order, with nulls where a row lacks a key.
Types are fixed by rule rather than inferred per file, so files written at different times
concatenate: bools (Python or numpy), ints as int64, floats and int/float mixes as float64 (inf
and nan kept), strings, timezone-aware datetimes as UTC timestamps; an all-null column is null
(it unifies with any type on reading). Mixing kinds in one column is refused.
"""

from __future__ import annotations

import datetime as dt
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pyarrow as pa

TIMESTAMP = pa.timestamp("us", tz="UTC")


class ColumnTypeError(TypeError, ValueError):
    """A column whose values cannot share one type (or a naive datetime)."""


def _is_bool(value: Any) -> bool:
    return isinstance(value, (bool, np.bool_))


def _utc(value: dt.datetime, where: str) -> dt.datetime:
    if value.tzinfo is None or value.utcoffset() is None:
        raise ColumnTypeError(f"{where}: {value.isoformat()} has no timezone; give UTC explicitly")
    return value.astimezone(dt.timezone.utc)


def column_type(name: str, values: list[Any], what: str) -> pa.DataType | None:
    """The column's Arrow type by the module's rules; ``what`` names the table in errors."""
    present = [v for v in values if v is not None]
    if not present:
        return pa.null()
    if all(_is_bool(v) for v in present):
        return pa.bool_()
    if any(_is_bool(v) for v in present):
        raise ColumnTypeError(f"{what} column {name!r} mixes booleans with other values")
    if all(isinstance(v, numbers.Integral) for v in present):
        return pa.int64()
    if all(isinstance(v, numbers.Real) for v in present):
        return pa.float64()
    if all(isinstance(v, str) for v in present):
        return pa.string()
    if all(isinstance(v, dt.datetime) for v in present):
        for v in present:
            _utc(v, f"{what} column {name!r}")
        return TIMESTAMP
    if any(isinstance(v, (str, numbers.Real, dt.datetime)) for v in present):
        raise ColumnTypeError(f"{what} column {name!r} mixes strings, numbers, times or other values")
    return None  # nested values (lists, dicts): let pyarrow infer


def _convert(value: Any, dtype: pa.DataType | None) -> Any:
    if value is None:
        return None
    if dtype == pa.bool_():
        return bool(value)
    if dtype == pa.int64():
        return int(value)
    if dtype == pa.float64():
        return float(value)
    if dtype == TIMESTAMP:
        return value.astimezone(dt.timezone.utc)
    return value


def typed_table(rows: Sequence[Mapping[str, Any]], what: str) -> pa.Table:
    """The rows as one table with explicit column types."""
    names: dict[str, None] = {}  # an ordered set: columns in first-seen order
    for row in rows:
        names.update(dict.fromkeys(row))
    columns = {}
    for name in names:
        if not isinstance(name, str):
            raise ColumnTypeError(f"{what} column names must be strings, got {name!r}")
        values = [row.get(name) for row in rows]
        dtype = column_type(name, values, what)
        columns[name] = pa.array([_convert(v, dtype) for v in values], type=dtype)
    return pa.table(columns)
