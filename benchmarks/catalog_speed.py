"""How fast the run catalog appends and reads at 100,000 rows, and what compaction buys for many small files.

100,000 synthetic rows of the pipeline's convention (60 columns: ids, plan, six stages' wall time/device/status,
16 metrics, 8 checks, paths), spread evenly over 30 days and 20,000 photos, written twice with
``Catalog.append``: in 1,000 appends of 100 rows, and in 10,000 appends of 10 rows (the worst case: one file
per finished photo). For each layout, and again after ``compact`` (retention 0), ``read()``,
``read(since=<last 7 days>)``, ``read(columns=<3 columns>)`` and ``latest_per_photo()`` are timed (median of
``--repeats``; the files were just written, so they are in the page cache: a cold read is slower).

    python benchmarks/catalog_speed.py            # writes benchmarks/results/catalog_speed_cpu.{json,md}
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import random
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pyarrow as pa

from assets_store.atomic import atomic_write_text
from assets_store.catalog import Catalog
from tests.catalog_rows import synthetic_row

RESULTS = Path(__file__).parent / "results"
START = dt.datetime(2026, 10, 1, tzinfo=dt.timezone.utc)


def make_rows(n: int, days: int, photos: int) -> list[dict[str, Any]]:
    rng = random.Random(0)
    span = dt.timedelta(days=days) / n
    rows = []
    for i in range(n):
        failed = rng.choice(["dmtet", "texture"]) if rng.random() < 0.03 else None
        rows.append(synthetic_row(rng, f"run{i:07d}", f"photo{rng.randrange(photos):06d}", START + i * span,
                                  failed_at=failed))
    return rows


def _timed(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def _files(root: Path) -> tuple[int, int]:
    files = [p for p in root.rglob("*.parquet") if not p.name.startswith(".")]
    return len(files), sum(p.stat().st_size for p in files)


def measure_reads(catalog: Catalog, since: dt.datetime, repeats: int, expected_rows: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    read_s, table = _timed(catalog.read, repeats)
    if table.num_rows != expected_rows:
        raise AssertionError(f"read {table.num_rows} rows, expected {expected_rows}")
    out["read_s"] = round(read_s, 3)
    since_s, recent = _timed(lambda: catalog.read(since=since), repeats)
    out["read_since_s"], out["read_since_rows"] = round(since_s, 3), recent.num_rows
    cols_s, _ = _timed(lambda: catalog.read(columns=["photo_key", "created_at", "metric_ref_psnr"]), repeats)
    out["read_3_columns_s"] = round(cols_s, 3)
    latest_s, latest = _timed(catalog.latest_per_photo, repeats)
    out["latest_per_photo_s"], out["photos"] = round(latest_s, 3), latest.num_rows
    return out


def bench_layout(rows: list[dict[str, Any]], per_append: int, root: Path, since: dt.datetime, repeats: int,
                 compact_before: dt.date) -> dict[str, Any]:
    catalog = Catalog(root)
    start = time.perf_counter()
    for i in range(0, len(rows), per_append):
        catalog.append(rows[i:i + per_append])
    write_s = time.perf_counter() - start
    files, size = _files(root)
    result: dict[str, Any] = {
        "rows_per_append": per_append, "appends": len(rows) // per_append, "append_total_s": round(write_s, 1),
        "append_ms_each": round(1000 * write_s / (len(rows) / per_append), 2), "files": files,
        "mib_on_disk": round(size / 2**20, 1),
    }
    result["before_compaction"] = measure_reads(catalog, since, repeats, len(rows))
    start = time.perf_counter()
    done = catalog.compact(before=compact_before, retention_s=0)
    result["compact_s"] = round(time.perf_counter() - start, 2)
    files, size = _files(root)
    result["after_compaction"] = measure_reads(catalog, since, repeats, len(rows)) | {
        "files": files, "mib_on_disk": round(size / 2**20, 1), "days_compacted": len(done.days)}
    return result


def write_results(result: dict[str, Any], out: Path) -> None:
    atomic_write_text(out.with_suffix(".json"), json.dumps(result, indent=2) + "\n")
    lines = [
        f"# Run catalog speed ({result['date']}, {result['cpu_count']} CPU cores, {result['machine']}, "
        f"pyarrow {result['pyarrow']})",
        "",
        f"{result['rows']:,} rows × {result['columns']} columns over {result['days']} days and "
        f"{result['photos']:,} photos; reads are the median of {result['repeats']} (page cache warm). "
        f"`since` = the last 7 days ({result['layouts'][0]['before_compaction']['read_since_rows']:,} rows); "
        "3 columns = photo_key, created_at, metric_ref_psnr.",
        "",
        "| layout | files | MiB | append each | read() | read(since) | read(3 columns) | latest_per_photo() |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for lay in result["layouts"]:
        for phase in ("before_compaction", "after_compaction"):
            r = lay[phase]
            files = lay["files"] if phase == "before_compaction" else r["files"]
            mib = lay["mib_on_disk"] if phase == "before_compaction" else r["mib_on_disk"]
            name = f"{lay['appends']:,} appends of {lay['rows_per_append']}"
            name += "" if phase == "before_compaction" else f", compacted ({lay['compact_s']} s)"
            append = f"{lay['append_ms_each']} ms" if phase == "before_compaction" else "-"
            lines.append(f"| {name} | {files:,} | {mib} | {append} | {r['read_s']} s | {r['read_since_s']} s | "
                         f"{r['read_3_columns_s']} s | {r['latest_per_photo_s']} s |")
    lines += ["", f"Generating the rows (Python dicts): {result['generate_s']} s. Appends fsync the file and its "
              "folder (durable on return)."]
    atomic_write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=100_000)
    parser.add_argument("--days", type=int, default=30)
    parser.add_argument("--photos", type=int, default=20_000)
    parser.add_argument("--appends", type=int, nargs="+", default=[100, 10], help="rows per append, per layout")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS / "catalog_speed_cpu")
    parser.add_argument("--tmp", type=Path, default=None, help="where to write the catalogs (default: $TMPDIR)")
    args = parser.parse_args()

    start = time.perf_counter()
    rows = make_rows(args.rows, args.days, args.photos)
    generate_s = time.perf_counter() - start
    end = START + dt.timedelta(days=args.days)
    since = end - dt.timedelta(days=7)
    result: dict[str, Any] = {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "cpu_count": os.cpu_count(), "python": platform.python_version(), "pyarrow": pa.__version__,
        "rows": args.rows, "columns": len(rows[0]), "days": args.days, "photos": args.photos,
        "repeats": args.repeats, "generate_s": round(generate_s, 1), "layouts": [],
    }
    tmp = Path(tempfile.mkdtemp(prefix="catalog_speed_", dir=args.tmp))
    try:
        for per_append in args.appends:
            root = tmp / f"per{per_append}"
            print(f"{args.rows:,} rows in appends of {per_append} ...", flush=True)
            layout = bench_layout(rows, per_append, root, since, args.repeats, end.date() + dt.timedelta(days=1))
            print(json.dumps(layout, indent=2), flush=True)
            result["layouts"].append(layout)
            shutil.rmtree(root)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_results(result, args.out)
    print(f"wrote {args.out.with_suffix('.json')} and .md")


if __name__ == "__main__":
    main()
