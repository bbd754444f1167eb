"""The run catalog: concurrent appends by many processes lose and duplicate nothing; schema evolution, ``since``,
newest row per photo; killed writers, corrupt files and type conflicts are skipped and reported; compaction
keeps every row, including for a reader reading while it runs."""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import math
import multiprocessing as mp
import os
import random
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from assets_store.catalog import Catalog, CatalogWarning, rows_table
from assets_store.catalog_compaction import LOCK_FILE
from assets_store.catalog_files import REPLACES_KEY
from tests import catalog_workers
from tests.catalog_rows import synthetic_row

UTC = dt.timezone.utc
T0 = dt.datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _rows(n: int, start: dt.datetime = T0, step: dt.timedelta = dt.timedelta(hours=1), prefix: str = "r",
          photos: int = 5, seed: int = 0) -> list[dict]:
    rng = random.Random(seed)
    return [synthetic_row(rng, f"{prefix}{i}", f"photo{i % photos}", start + i * step) for i in range(n)]


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*.parquet") if not p.name.startswith("."))


def test_twenty_writer_processes_lose_and_duplicate_nothing(tmp_path: Path) -> None:
    workers, appends, per_append = 20, 4, 5
    ctx = mp.get_context("spawn")  # fork would copy this process's pyarrow/torch thread pools mid-state
    start = ctx.Event()
    procs = [ctx.Process(target=catalog_workers.writer, args=(str(tmp_path), w, appends, per_append, start))
             for w in range(workers)]
    for p in procs:
        p.start()
    start.set()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0, f"writer {p.pid} exited with {p.exitcode}"

    table = Catalog(tmp_path).read()
    ids = table["run_id"].to_pylist()
    expected = {f"w{w}-{a}-{r}" for w in range(workers) for a in range(appends) for r in range(per_append)}
    assert len(ids) == len(expected), "rows lost or duplicated"
    assert set(ids) == expected
    # Every append wrote one file per day it touched, each under its own name, all in Hive day folders.
    files = _files(tmp_path)
    assert len(files) >= workers * appends
    assert {p.parent.name for p in files} <= {"date=2026-03-01", "date=2026-03-02"}
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")], "temporaries left behind"
    # Each row sits in the folder of its own UTC day.
    for path in files:
        day = path.parent.name.removeprefix("date=")
        assert {t.date().isoformat() for t in pq.read_table(path)["created_at"].to_pylist()} == {day}


def test_schema_evolution_adds_null_columns_and_promotes_int_to_float(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    old = _rows(3, prefix="old")
    for row in old:
        row["metric_ref_psnr"] = 25  # an old writer logged whole dB values: an int64 column in that file
    catalog.append(old)
    new = _rows(2, start=T0 + dt.timedelta(days=1), prefix="new")
    for row in new:
        row["metric_x"] = 0.5
        row["metric_ref_psnr"] = 26.5
    catalog.append(new)
    assert pq.read_schema(_files(tmp_path)[0]).field("metric_ref_psnr").type == pa.int64()

    table = catalog.read()
    assert table.schema.field("metric_ref_psnr").type == pa.float64()
    assert table.schema.field("metric_x").type == pa.float64()
    got = {r["run_id"]: r for r in table.to_pylist()}
    assert [got[f"old{i}"]["metric_x"] for i in range(3)] == [None] * 3
    assert [got[f"new{i}"]["metric_x"] for i in range(2)] == [0.5, 0.5]
    assert got["old0"]["metric_ref_psnr"] == 25.0 and got["new0"]["metric_ref_psnr"] == 26.5
    # Asking for a column: files without it give nulls; a column nobody wrote is all null.
    picked = catalog.read(columns=["run_id", "metric_x", "metric_never"])
    assert picked.column_names == ["run_id", "metric_x", "metric_never"]
    assert picked["metric_never"].null_count == picked.num_rows == 5


def test_types_are_explicit_and_values_round_trip(tmp_path: Path) -> None:
    row = {"created_at": T0, "n": 3, "f": math.inf, "nan": math.nan, "b": True, "s": "x", "none": None}
    table = rows_table([row])
    assert [table.schema.field(c).type for c in table.column_names] == [
        pa.timestamp("us", tz="UTC"), pa.int64(), pa.float64(), pa.float64(), pa.bool_(), pa.string(), pa.null()]
    Catalog(tmp_path).append([row])
    back = Catalog(tmp_path).read().to_pylist()[0]
    assert back["created_at"] == T0 and back["n"] == 3 and back["f"] == math.inf and math.isnan(back["nan"])
    assert back["b"] is True and back["none"] is None


def test_since_reads_only_newer_rows_and_skips_older_day_folders(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    midnight = T0.replace(hour=0)
    rows = _rows(48, start=midnight, step=dt.timedelta(hours=2))
    catalog.append(rows)  # 4 days of 12 rows, one file per day
    assert len(catalog.days()) == 4 and len(_files(tmp_path)) == 4
    since = dt.datetime(2026, 3, 3, 7, 30, tzinfo=UTC)
    table = catalog.read(since=since)
    times = table["created_at"].to_pylist()
    assert times and min(times) >= since
    assert len(times) == sum(1 for r in rows if r["created_at"] >= since) == 12 + 8
    # A date means its UTC midnight; a timezone other than UTC is converted.
    assert catalog.read(since=dt.date(2026, 3, 3)).num_rows == 24
    plus_two = dt.timezone(dt.timedelta(hours=2))
    assert catalog.read(since=dt.datetime(2026, 3, 3, 9, 30, tzinfo=plus_two)).num_rows == table.num_rows
    # Older day folders are not even opened: corrupting one does not disturb a read since a later day.
    old = next(p for p in _files(tmp_path) if "2026-03-01" in str(p))
    old.write_bytes(b"not parquet")
    assert catalog.scan(since=since).skipped == []
    with pytest.raises(ValueError, match="no timezone"):
        catalog.read(since=dt.datetime(2026, 3, 3))


def test_latest_per_photo_is_the_newest_by_created_at_not_by_write_order(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    rows = _rows(12, photos=3, step=dt.timedelta(hours=5))
    random.Random(1).shuffle(rows)
    for i in range(0, 12, 4):  # written in shuffled order, over several files
        catalog.append(rows[i:i + 4])
    # A rerun with the very same created_at as photo0's newest row: the later write wins the tie.
    newest0 = max((r for r in rows if r["photo_key"] == "photo0"), key=lambda r: r["created_at"])
    catalog.append([dict(newest0, run_id="rerun")])
    catalog.append([dict(rows[0], photo_key=None, run_id="keyless")])  # no photo: in no photo's group
    latest = catalog.latest_per_photo(columns=["photo_key", "run_id", "created_at"])
    assert latest["photo_key"].to_pylist() == ["photo0", "photo1", "photo2"]
    want = {}
    for r in rows:
        if r["photo_key"] not in want or r["created_at"] > want[r["photo_key"]]["created_at"]:
            want[r["photo_key"]] = r
    assert latest["run_id"].to_pylist() == ["rerun", want["photo1"]["run_id"], want["photo2"]["run_id"]]
    assert Catalog(tmp_path / "empty").latest_per_photo().num_rows == 0


def test_a_killed_writer_leaves_only_a_temporary_that_readers_ignore(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    catalog.append(_rows(3))
    proc = mp.get_context("spawn").Process(target=catalog_workers.killed_writer, args=(str(tmp_path),))
    proc.start()
    proc.join(60)
    assert proc.exitcode == 9
    leftovers = [p for p in tmp_path.rglob("*.tmp")]
    assert len(leftovers) == 1 and leftovers[0].name.startswith(".part-"), leftovers
    read = catalog.scan()
    assert read.table.num_rows == 3 and read.skipped == []
    # Compaction removes temporaries old enough to be a dead writer's, and no younger ones.
    catalog.append(_rows(2, prefix="more"))
    catalog.compact(before=dt.date(2026, 3, 5), retention_s=0)
    assert leftovers[0].exists()
    os.utime(leftovers[0], (0, 0))
    catalog.compact(before=dt.date(2026, 3, 5), retention_s=0)
    assert not leftovers[0].exists()


def test_a_corrupt_file_is_skipped_and_reported_not_hiding_the_rest(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    catalog.append(_rows(4, prefix="a"))
    bad = catalog.append(_rows(2, prefix="b"))[0]
    catalog.append(_rows(3, prefix="c"))
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])  # truncated: a disk or copy problem
    with pytest.warns(CatalogWarning, match=bad.name):
        read = catalog.scan()
    assert sorted(read.table["run_id"].to_pylist()) == ["a0", "a1", "a2", "a3", "c0", "c1", "c2"]
    assert [p for p, _ in read.skipped] == [bad]
    assert "unreadable" in read.skipped[0][1]
    with pytest.warns(CatalogWarning):
        assert catalog.read().num_rows == 7


def test_a_file_with_conflicting_column_types_is_skipped_and_named(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    catalog.append(_rows(5, prefix="good"))
    stray = _rows(1, prefix="stray")
    stray[0]["metric_ref_psnr"] = "high"  # a producer bug: a string where every other file has a float
    bad = catalog.append(stray)[0]
    with pytest.warns(CatalogWarning, match="metric_ref_psnr"):
        read = catalog.scan()
    assert read.table.num_rows == 5 and read.table.schema.field("metric_ref_psnr").type == pa.float64()
    assert read.skipped[0][0] == bad and "conflict" in read.skipped[0][1]


def test_bad_rows_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    good = _rows(2)
    for bad_value, message in [(None, "timezone-aware datetime"), ("2026-03-01", "timezone-aware datetime"),
                               (dt.datetime(2026, 3, 1), "no timezone")]:
        with pytest.raises(ValueError, match=message):
            catalog.append([*good, dict(good[0], created_at=bad_value)])
    with pytest.raises(ValueError, match="mixes booleans"):
        catalog.append([dict(good[0], metric_a=True), dict(good[1], metric_a=1.0)])
    assert not tmp_path.exists() or not _files(tmp_path)
    assert catalog.append([]) == []
    assert catalog.read().num_rows == 0


def test_compaction_merges_past_days_and_keeps_every_row(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    for i in range(6):  # two days, three files each; a third day is "today" and must stay as it is
        catalog.append(_rows(4, start=T0 + dt.timedelta(hours=4 * i), step=dt.timedelta(minutes=5),
                             prefix=f"f{i}-"))
    catalog.append(_rows(4, start=T0 + dt.timedelta(days=2), prefix="today-"))
    evolved = _rows(1, start=T0 + dt.timedelta(hours=1), prefix="evolved-")
    evolved[0]["metric_new"] = 1.0
    catalog.append(evolved)
    before_rows = sorted(map(str, catalog.read().to_pylist()))
    day1, day2, today = (tmp_path / f"date=2026-03-0{d}" for d in (1, 2, 3))
    assert (len(_files(day1)), len(_files(day2))) == (4, 3)

    result = catalog.compact(before=dt.date(2026, 3, 3), retention_s=3600)
    assert result.days == ["2026-03-01", "2026-03-02"] and result.files_merged == 7 and result.rows == 25
    # Within the retention the old files stay (a reader may have listed them), yet are read once only.
    assert (len(_files(day1)), len(_files(day2))) == (5, 4)
    assert sorted(map(str, catalog.read().to_pylist())) == before_rows
    merged = next(p for p in _files(day1) if p.name.startswith("compact-"))
    assert len(json.loads(pq.read_schema(merged).metadata[REPLACES_KEY])) == 4

    # After the retention they are deleted; a late append to a past day is merged by the next compaction.
    catalog.append(_rows(2, start=T0 + dt.timedelta(hours=2), prefix="late-"))
    result = catalog.compact(before=dt.date(2026, 3, 3), retention_s=0)
    assert result.days == ["2026-03-01"] and result.files_deleted == 3 + 5 + 1
    assert [p.name.split("-")[0] for p in _files(day1)] == ["compact"]
    assert [p.name.split("-")[0] for p in _files(day2)] == ["compact"]
    assert len(_files(today)) == 1
    after = catalog.read()
    assert sorted(map(str, after.filter(pc.invert(pc.starts_with(after["run_id"], "late-"))).to_pylist())) == \
        before_rows
    assert after.num_rows == 31 and after["metric_new"].null_count == 30
    # Nothing left to merge: a third compaction changes nothing.
    assert catalog.compact(before=dt.date(2026, 3, 3), retention_s=0).days == []
    assert catalog.read().num_rows == 31


def test_compaction_skips_when_another_holds_the_lock_and_leaves_unreadable_files(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    for i in range(3):
        catalog.append(_rows(2, prefix=f"f{i}-"))
    with open(tmp_path / LOCK_FILE, "w") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        assert catalog.compact(before=dt.date(2026, 3, 5)).busy
    bad = _files(tmp_path)[0]
    bad.write_bytes(b"garbage")
    result = catalog.compact(before=dt.date(2026, 3, 5), retention_s=0)
    assert result.files_merged == 2 and [p for p, _ in result.skipped] == [bad]
    assert bad.exists(), "an unreadable file is evidence: never deleted"
    with pytest.warns(CatalogWarning):
        assert catalog.read().num_rows == 4


def test_a_reader_during_repeated_compactions_sees_every_row_exactly_once(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    for i in range(10):
        catalog.append(_rows(5, start=T0 + dt.timedelta(minutes=i), step=dt.timedelta(seconds=1),
                             prefix=f"init{i}-"))
    ctx = mp.get_context("spawn")
    ready, stop, out = ctx.Event(), ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=catalog_workers.reader, args=(str(tmp_path), ready, stop, out))
    proc.start()
    try:
        assert ready.wait(60), "the reader did not start"
        rounds = 0
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline or rounds < 10:
            # New parts, then an immediate merge that deletes the old files at once (retention 0): the
            # hardest case for a reader, whose listed files may vanish under it.
            catalog.append(_rows(3, start=T0 + dt.timedelta(hours=1), prefix=f"round{rounds}-"))
            catalog.append(_rows(2, start=T0 + dt.timedelta(hours=2), prefix=f"round{rounds}b-"))
            assert catalog.compact(before=dt.date(2026, 3, 2), retention_s=0).files_merged >= 2
            rounds += 1
    finally:
        stop.set()
        reads, problems = out.get(timeout=60)
        proc.join(60)
    assert problems == []
    assert reads >= 10, f"the reader only read {reads} times: the test proved little"
    assert catalog.read().num_rows == 50 + 5 * rounds
    assert len(_files(tmp_path)) == 1


def test_a_listing_that_raced_a_compaction_is_detected_and_the_day_read_again(tmp_path: Path, monkeypatch) -> None:
    """readdir during a rename and an unlink may return neither the new merged file nor the deleted part; the
    reader must notice (its second listing shows a merged file its first did not) instead of losing rows."""
    import assets_store.catalog as catalog_module

    catalog = Catalog(tmp_path)
    parts = [catalog.append(_rows(3, prefix=f"p{i}-"))[0] for i in range(4)]
    catalog.compact(before=dt.date(2026, 3, 2), retention_s=3600)
    parts[0].unlink()  # as a retention-0 compaction would, right after publishing the merged file
    stale = {p.name for p in parts[1:]}  # the listing that missed both the merged file and the deletion
    real = catalog_module.list_data_files
    calls = []

    def racing_listing(day_dir: Path) -> set[str]:
        calls.append(day_dir)
        return set(stale) if len(calls) == 1 else real(day_dir)

    monkeypatch.setattr(catalog_module, "list_data_files", racing_listing)
    ids = catalog.read()["run_id"].to_pylist()
    assert sorted(ids) == sorted(f"p{i}-{j}" for i in range(4) for j in range(3))
    assert len(calls) >= 3, "the day was not listed again"
