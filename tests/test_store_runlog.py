"""The run log round-trips mixed rows through Parquet, keeping inf/nan and explicit column types."""

from __future__ import annotations

import math
import random
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from assets_store.runlog import read_runlog, write_runlog


def test_round_trip_with_mixed_and_missing_columns(tmp_path: Path) -> None:
    rows = []
    for step in range(random.randint(5, 20)):
        row = {"step": step, "wall_s": random.uniform(0, 100), "loss": random.random(), "stage": "geometry"}
        if step % 3 == 0:
            row["psnr"] = random.uniform(10, 40)  # evaluated only every third step
        rows.append(row)
    rows[1]["loss"] = math.inf
    rows[2]["loss"] = math.nan
    rows[3]["loss"] = -math.inf
    rows.append({"note": "finished", "step": len(rows)})
    path = write_runlog(tmp_path / "run" / "runlog.parquet", rows)

    schema = pq.read_schema(path)
    assert schema.names == ["step", "wall_s", "loss", "stage", "psnr", "note"]  # first-seen order
    assert schema.field("step").type == pa.int64() and schema.field("loss").type == pa.float64()
    assert schema.field("stage").type == pa.string()

    back = read_runlog(path)
    assert len(back) == len(rows)
    for want, got in zip(rows, back, strict=True):
        for name in schema.names:
            value = want.get(name)
            if isinstance(value, float) and math.isnan(value):
                assert math.isnan(got[name])
            else:
                assert got[name] == value, name
    assert back[1]["loss"] == math.inf and back[3]["loss"] == -math.inf
    assert back[1]["psnr"] is None and back[-1]["loss"] is None
    assert [p.name for p in path.parent.iterdir()] == ["runlog.parquet"]  # no temporary left


def test_int_float_mix_becomes_float64(tmp_path: Path) -> None:
    path = write_runlog(tmp_path / "r.parquet", [{"lr": 1}, {"lr": 0.5}, {"lr": None}])
    assert pq.read_schema(path).field("lr").type == pa.float64()
    assert read_runlog(path) == [{"lr": 1.0}, {"lr": 0.5}, {"lr": None}]


def test_empty_log_and_bad_column(tmp_path: Path) -> None:
    assert read_runlog(write_runlog(tmp_path / "empty.parquet", [])) == []
    with pytest.raises(TypeError, match="'value'"):
        write_runlog(tmp_path / "bad.parquet", [{"value": 1}, {"value": "one"}])
    assert not (tmp_path / "bad.parquet").exists()


def test_rewrite_replaces_atomically(tmp_path: Path) -> None:
    path = tmp_path / "r.parquet"
    write_runlog(path, [{"step": 1}])
    write_runlog(path, [{"step": 2}, {"step": 3}])
    assert read_runlog(path) == [{"step": 2}, {"step": 3}]
