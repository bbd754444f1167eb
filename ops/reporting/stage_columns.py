"""Catalog columns carry stage ids (``<stage>_wall_s``, ``<stage>_status``, ``runlog_<stage>``,
``check_<stage>_<name>``); rows written before the ids were unified use the old ids
(``nerf_fit_wall_s``, …). Reading maps those columns onto the current ones, so a catalog that spans
the renaming reads as one table."""

from __future__ import annotations

import re

import pyarrow as pa
import pyarrow.compute as pc

from ops.engine.stage_ids import RENAMED_STAGES

_OLD = re.compile(r"^(?P<head>runlog_|check_)?(?P<stage>" + "|".join(map(re.escape, RENAMED_STAGES))
                  + r")(?P<tail>_.*)?$")


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
