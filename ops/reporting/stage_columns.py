"""Catalog columns as the report reads them.

Columns carry stage ids (``<stage>_wall_s``, ``<stage>_status``, ``runlog_<stage>``, ``check_<stage>_<name>``);
rows written before the ids were unified use the old ids (``nerf_fit_wall_s``, …). Reading maps those columns
onto the current ones, so a catalog that spans the renaming reads as one table.

Each piece of work counts once (``count_work_once``): a stage's output is named by the photo and
``<stage>_built_at``, or, in rows from before that column, by its wall time (those rows copied the wall time of
a cached output, so equal times are the same output). Only the first row reporting an output, and only when
its run made it (not ``cached``, not ``failed``), counts its time.
"""

from __future__ import annotations

import datetime as dt
import re
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from ops.migrations import RENAMED_STAGES
from ops.stages import STAGE_IDS

WORK_SUFFIX = "_work_s"  # per stage: the seconds of work this row counts (null: none, or counted elsewhere)
BUILD_SUFFIX = "_build_s"  # per stage: the seconds it took to make the output this row describes
NOT_WORK = frozenset({"cached", "failed", "missing"})  # stage statuses whose wall time is no work of the row's run

_OLD = re.compile(r"^(?P<head>runlog_|check_)?(?P<stage>" + "|".join(map(re.escape, RENAMED_STAGES))
                  + r")(?P<tail>_.*)?$")
_WALL = re.compile(r"(?P<stage>.+)_wall_s")


def current_column(name: str) -> str:
    """The column name with a stage id from before the renaming replaced by the current id."""
    m = _OLD.match(name)
    if m is None:
        return name
    return f"{m['head'] or ''}{RENAMED_STAGES[m['stage']]}{m['tail'] or ''}"


def current_stage_columns(table: pa.Table) -> pa.Table:
    """``table`` with old-id columns merged into the current ones (a row has one or the other)."""
    for name in [n for n in table.column_names if current_column(n) != n]:
        new, old = current_column(name), table[name]
        index = table.column_names.index(name)
        table = table.remove_column(index)
        if new not in table.column_names:
            table = table.add_column(index, new, old)
            continue
        current = table[new]
        if pa.types.is_null(current.type):
            merged = old
        elif pa.types.is_null(old.type):
            merged = current
        else:
            merged = pc.coalesce(current, old.cast(current.type))
        table = table.set_column(table.column_names.index(new), new, merged)
    return table


def float_column(table: pa.Table, name: str) -> np.ndarray:
    """A column as float64 with NaN for null (and for a missing column)."""
    if name not in table.column_names:
        return np.full(table.num_rows, np.nan)
    column = table[name]
    if pa.types.is_null(column.type):
        return np.full(table.num_rows, np.nan)
    return pc.cast(column, pa.float64()).to_numpy(zero_copy_only=False).astype(np.float64)


def string_column(table: pa.Table, name: str) -> list[str | None]:
    """A column as strings (None for null and for a missing column)."""
    if name not in table.column_names:
        return [None] * table.num_rows
    return [None if v is None else str(v) for v in table[name].to_pylist()]


def wall_stages(columns: list[str]) -> list[str]:
    """The stages with a ``<stage>_wall_s`` or ``runlog_<stage>`` column: pipeline order, then unknown ones."""
    found = {m.group("stage") for c in columns if (m := _WALL.fullmatch(c))}
    found |= {c.removeprefix("runlog_") for c in columns if c.startswith("runlog_")}
    known = [s for s in STAGE_IDS if s in found]
    return known + sorted(found - set(STAGE_IDS))


def _set(table: pa.Table, name: str, values: Any) -> pa.Table:
    if name in table.column_names:
        return table.set_column(table.column_names.index(name), name, values)
    return table.append_column(name, values)


def count_work_once(table: pa.Table) -> pa.Table:
    """``table`` with ``<stage>_work_s`` and ``<stage>_build_s`` per stage, ``work_s`` per row (the sum of its
    stages' work) and ``status`` ``cached`` for an ``ok`` row that counts no work but reports outputs (a
    re-run written before rows said so). See the module docstring for what counts."""
    n = table.num_rows
    stages = [s for s in wall_stages(table.column_names) if f"{s}_wall_s" in table.column_names]
    if n == 0 or not stages:
        return table
    oldest = dt.datetime.min.replace(tzinfo=dt.timezone.utc)
    created = table["created_at"].to_pylist() if "created_at" in table.column_names else [None] * n
    order = sorted(range(n), key=lambda i: (created[i] or oldest, i))  # on a tie, the later write is later
    photos = string_column(table, "photo_key")
    total = np.zeros(n)
    counted_any = np.zeros(n, dtype=bool)
    reports = np.zeros(n, dtype=bool)
    for stage in stages:
        wall = float_column(table, f"{stage}_wall_s")
        status = string_column(table, f"{stage}_status")
        made = table[f"{stage}_built_at"].to_pylist() if f"{stage}_built_at" in table.column_names else [None] * n
        work, build = np.full(n, np.nan), np.full(n, np.nan)
        first: dict[tuple[Any, ...], float] = {}  # an output -> the time it took, from the row that counted it
        undated: dict[str | None, float] = {}  # a photo -> the time of its newest output counted by an old row
        for i in order:
            does = status[i] not in NOT_WORK and np.isfinite(wall[i])
            own = wall[i] if does else np.nan
            if made[i] is not None:
                output: tuple[Any, ...] | None = (photos[i], "at", made[i])
            elif np.isfinite(wall[i]) and wall[i] > 0:
                output = (photos[i], "wall", float(wall[i]))
                if does:
                    undated[photos[i]] = own
            else:
                output = None
            if output is None:
                work[i] = build[i] = own
                continue
            reports[i] = True
            if output in first:
                build[i] = first[output]
            elif does:
                first[output] = work[i] = build[i] = own
            else:
                # Found cached and reported first by a dated row: the output an old (undated) row counted, which
                # is how the writer matched it (by wall time); its time is that row's.
                first[output] = build[i] = undated.get(photos[i], np.nan) if made[i] is not None else np.nan
        finite = np.isfinite(work)
        total += np.where(finite, work, 0.0)
        counted_any |= finite
        table = _set(table, f"{stage}{WORK_SUFFIX}", pa.array(work, from_pandas=True))
        table = _set(table, f"{stage}{BUILD_SUFFIX}", pa.array(build, from_pandas=True))
    table = _set(table, "work_s", pa.array(total))
    if "status" in table.column_names:
        status = string_column(table, "status")
        fixed = ["cached" if s == "ok" and reports[i] and not counted_any[i] else s for i, s in enumerate(status)]
        table = _set(table, "status", pa.array(fixed, pa.string()))
    return table
