"""Process entry points for the catalog tests. A module of its own, importing only the catalog, so that spawned
children start fast (importing the test module would pull in pytest, and conftest torch)."""

from __future__ import annotations

import datetime as dt
import os
import random
import time
from pathlib import Path
from typing import Any

from assets_store.catalog import Catalog
from tests.catalog_rows import synthetic_row

BASE = dt.datetime(2026, 3, 1, 22, 0, tzinfo=dt.timezone.utc)


def writer(root: str, worker: int, appends: int, rows_per_append: int, start: Any) -> None:
    """Append ``appends`` batches of rows with ids ``w<worker>-<append>-<row>``, once every writer is ready."""
    rng = random.Random(worker)
    catalog = Catalog(Path(root))
    start.wait()  # all writers append at the same moment, into the same day folders
    for a in range(appends):
        rows = []
        for r in range(rows_per_append):
            # Two hours around midnight: most appends hit the same two day folders, some span both.
            created = BASE + dt.timedelta(minutes=rng.uniform(0, 240))
            rows.append(synthetic_row(rng, f"w{worker}-{a}-{r}", f"photo{rng.randrange(50)}", created))
        catalog.append(rows)


def killed_writer(root: str) -> None:
    """Die (as with SIGKILL: no cleanup runs) halfway through writing a part file."""
    import pyarrow.parquet as pq

    def half_write(table: Any, where: str, **_: Any) -> None:
        with open(where, "wb") as fh:
            fh.write(b"PAR1" + b"\0" * 100)  # a Parquet header and no footer: what a killed write leaves
            fh.flush()
        os._exit(9)

    pq.write_table = half_write
    Catalog(Path(root)).append([synthetic_row(random.Random(0), "killed", "photo0", BASE)])


def reader(root: str, ready: Any, stop: Any, out: Any) -> None:
    """Read the catalog in a loop until ``stop``, checking each read: no id twice, and every id of the previous
    read still there (rows are only ever added). Puts (reads, problems) at the end."""
    catalog = Catalog(Path(root))
    previous: set[str] = set()
    reads, problems = 0, []
    while not stop.is_set():
        ids = catalog.read(columns=["run_id"])["run_id"].to_pylist()
        reads += 1
        if len(ids) != len(set(ids)):
            problems.append(f"read {reads}: {len(ids) - len(set(ids))} duplicate rows")
        if not previous <= set(ids):
            problems.append(f"read {reads}: {len(previous - set(ids))} rows vanished")
        previous = set(ids)
        ready.set()
        time.sleep(0.0005)
    out.put((reads, problems))
