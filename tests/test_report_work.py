"""The catalog counts work once: a cached re-run records that it happened without copying stage times, and the
report's totals, histograms and run counts equal one run's. The metrics section is a table per asset, with
histograms from ``HISTOGRAM_MIN_ASSETS`` assets up.

The re-runs go through the code that writes the rows (``MorpheusResource.record``, what the Dagster QA step
calls, and ``record_outcomes``, what ``morpheus3d run`` calls) over a store of committed stage outputs with
random wall times, so no stage has to run; ``test_report.py`` runs the real pipeline twice.
"""

from __future__ import annotations

import base64
import datetime as dt
import io
import json
import random
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from assets_store.catalog import Catalog
from assets_store.manifest import Fingerprint, Manifest
from assets_store.store import Store
from ops.engine.checks import QA_FILE
from ops.engine.store_layout import open_store
from ops.pipeline.photo_run import PhotoOutcome, StageOutcome
from ops.reporting.asset_metrics import HISTOGRAM_MIN_ASSETS
from ops.reporting.catalog_rows import photo_row, record_outcomes
from ops.reporting.report import build_report
from ops.stages import STAGE_IDS
from ops.stages.qa import QA_TURNTABLE_FILE
from orchestration.resources import MorpheusResource
from tests.catalog_rows import METRICS, synthetic_row
from tests.report_page import totals

T0 = dt.datetime(2026, 5, 4, 9, 0, tzinfo=dt.timezone.utc)


@pytest.fixture
def rng() -> random.Random:
    seed = random.randrange(2**32)
    print(f"seed {seed}")  # shown when a test fails: rerun with random.Random(seed)
    return random.Random(seed)


def _png(rng: random.Random, width: int, height: int) -> bytes:
    buf = io.BytesIO()
    pixels = np.random.default_rng(rng.randrange(2**32)).integers(0, 255, (height, width, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


def finished_photo(store: Store, key: str, rng: random.Random, stages: tuple[str, ...] = STAGE_IDS) -> None:
    """Commit ``stages`` of ``key`` (random wall times, a QA report with random metrics, a turntable strip)."""
    for i, stage in enumerate(stages):
        with store.stage_writer(key, stage) as w:
            if stage == "qa":
                metrics = {"ref_psnr": rng.gauss(24, 3), "ssim_in": rng.uniform(0.6, 1), "watertight": True}
                (w.path / QA_FILE).write_text(json.dumps({"verdict": rng.choice(["pass", "warn"]), "reasons": [],
                                                          "checks": {"qa": []}, "metrics": metrics}))
                (w.path / QA_TURNTABLE_FILE).write_bytes(_png(rng, 8 * 40, 40))
            made = T0 + dt.timedelta(minutes=i, seconds=rng.randrange(60))
            w.commit(Manifest(stage=stage, photo_key=key, fingerprint=Fingerprint({"photo": "ab" * 32}, "c", "1"),
                              wall_time_s=round(rng.uniform(1, 900), 3), device="cpu", preset="draft",
                              created_at=made.isoformat(timespec="seconds")))


def _report(store: Store) -> str:
    return build_report(Catalog(store.catalog_dir), base_dir=store.root)


def _rows(store: Store, run_id: str) -> list[dict]:
    return [r for r in Catalog(store.catalog_dir).read().to_pylist() if r["run_id"] == run_id]


@pytest.mark.parametrize("photos", [3, HISTOGRAM_MIN_ASSETS])
def test_a_cached_dagster_rerun_is_recorded_without_its_work(tmp_path: Path, rng: random.Random,
                                                             photos: int) -> None:
    store = open_store(tmp_path / "store")
    keys = [f"p{i:02d}-{rng.randrange(10**6)}.jpg" for i in range(photos)]
    for key in keys:
        finished_photo(store, key, rng)
    morpheus = MorpheusResource(photo_dir=str(tmp_path / "photos"), store_root=str(store.root))
    for key in keys:  # the QA step of the first run knows only its own stage: the other stages are looked up
        morpheus.record(key, "run-1", {"qa": "ran"})
    first = totals(_report(store))
    for key in keys:
        morpheus.record(key, "run-2", {"qa": "cached"})
    page = _report(store)
    assert totals(page) == first
    assert first["photos"] == photos and first["runs"] == 1
    assert len(first["histograms"]) == (3 if photos >= HISTOGRAM_MIN_ASSETS else 0)  # ref_psnr, ssim_in, watertight
    assert "<td>runs that found everything cached</td><td>1</td>" in page

    built = {k: {s: store.read_manifest(k, s) for s in STAGE_IDS} for k in keys}
    for row in _rows(store, "run-1"):
        assert row["status"] == "ok"
        assert row["work_s"] == pytest.approx(sum(m.wall_time_s for m in built[row["photo_key"]].values()))
    for row in _rows(store, "run-2"):  # the run happened, found everything made, and did no work
        assert row["status"] == "cached" and row["work_s"] == 0
        for stage in STAGE_IDS:
            assert row[f"{stage}_status"] == "cached" and row[f"{stage}_wall_s"] == 0
            assert row[f"{stage}_built_at"].isoformat() == built[row["photo_key"]][stage].created_at
        assert row["metric_ref_psnr"] is not None  # still says what the asset is
    assert len(_rows(store, "run-2")) == photos


def test_a_cached_cli_rerun_and_a_retry_after_a_failure_count_each_stage_once(tmp_path: Path,
                                                                              rng: random.Random) -> None:
    store = open_store(tmp_path / "store")
    key = f"mug-{rng.randrange(10**6)}.jpg"
    finished_photo(store, key, rng, STAGE_IDS[:2])
    morpheus = MorpheusResource(photo_dir=str(tmp_path / "photos"), store_root=str(store.root))
    morpheus.record(key, "run-1", {"dmtet": "failed"}, "dmtet: FloatingPointError: NaN")  # after reference, nerf
    finished_photo(store, key, rng, STAGE_IDS[2:])  # the retry makes the rest
    morpheus.record(key, "run-2", {"qa": "ran"})
    (failed,) = _rows(store, "run-1")
    (retry,) = _rows(store, "run-2")
    walls = {s: store.read_manifest(key, s).wall_time_s for s in STAGE_IDS}
    assert failed["status"] == "failed" and failed["dmtet_wall_s"] is None
    assert [failed[f"{s}_wall_s"] for s in STAGE_IDS[:2]] == [walls[s] for s in STAGE_IDS[:2]]
    assert [retry[f"{s}_status"] for s in STAGE_IDS[:2]] == ["cached", "cached"]  # the failed run's work
    assert retry["work_s"] == pytest.approx(sum(walls[s] for s in STAGE_IDS[2:]))
    first = totals(_report(store))

    photo = Path(tmp_path / "photos" / key)
    outcome = PhotoOutcome(photo, key, [StageOutcome(s, "cached", 0.0, store.read_manifest(key, s))
                                        for s in STAGE_IDS])
    record_outcomes(store, [outcome], "cli-again")
    assert totals(_report(store)) == first
    (again,) = _rows(store, "cli-again")
    assert again["status"] == "cached" and again["work_s"] == 0
    assert re.search(r"<td>all stages \(per row with work\)</td><td>2</td>", _report(store))


def test_old_rows_that_copied_the_stage_times_are_read_as_one_run_and_recognised(tmp_path: Path,
                                                                                 rng: random.Random) -> None:
    """Catalogs written before rows said ``cached``: a re-run's row copied every stage time and said ``ok``.
    Reading counts that work once; a new re-run over such rows matches them by wall time."""
    store = open_store(tmp_path / "store")
    key = f"tin-{rng.randrange(10**6)}.jpg"
    finished_photo(store, key, rng)
    old = []
    for run in ("old-1", "old-2"):
        row = photo_row(store, key, run, dict.fromkeys(STAGE_IDS, "ran"))
        for stage in STAGE_IDS:
            del row[f"{stage}_built_at"]
            row[f"{stage}_status"] = "present"
        del row["work_s"]
        old.append(row)
    Catalog(store.catalog_dir).append(old[:1])
    first = totals(_report(store))
    Catalog(store.catalog_dir).append(old[1:])
    page = _report(store)
    assert totals(page) == first
    assert "<td>runs that found everything cached</td><td>1</td>" in page
    assert re.search(r"<td>cached</td><td>1</td>", page) and re.search(r"<td>ok</td><td>1</td>", page)

    MorpheusResource(photo_dir=str(tmp_path), store_root=str(store.root)).record(key, "new", {"qa": "cached"})
    (row,) = _rows(store, "new")
    assert row["status"] == "cached" and row["work_s"] == 0
    assert totals(_report(store)) == first


@pytest.mark.parametrize("assets", [HISTOGRAM_MIN_ASSETS - 1, HISTOGRAM_MIN_ASSETS])
def test_metrics_are_a_table_per_asset_with_histograms_from_the_threshold(tmp_path: Path, rng: random.Random,
                                                                          assets: int) -> None:
    store = Store(tmp_path / "store")
    rows = []
    for i in range(assets):
        key = f"photo{i:02d}"
        preview = f"{key}/qa/turntable.png"
        (store.root / preview).parent.mkdir(parents=True)
        (store.root / preview).write_bytes(_png(rng, 8 * 96, 96))
        created = T0 + dt.timedelta(minutes=rng.randrange(10**4))
        rows.append(synthetic_row(rng, f"run{i}", key, created, paths={"preview": preview}))
        if rng.random() < 0.3:  # an older failed run of the same photo: not an asset of its own
            rows.append(synthetic_row(rng, f"old{i}", key, created - dt.timedelta(days=1), failed_at="nerf"))
    rows.append(synthetic_row(rng, "lost", "gone", T0, failed_at="reference"))  # never finished: no asset
    Catalog(store.catalog_dir).append(rows)
    page = _report(store)
    histograms = re.findall(r'alt="histogram of ([^"]+)"', page)
    assert histograms == ([f"metric_{m}" for m in METRICS] if assets >= HISTOGRAM_MIN_ASSETS else [])
    table = re.search(r'<table class="assets">.*?</table>', page, re.S).group(0)
    keys = re.findall(r'<tr class="asset" data-photo-key="([^"]+)">', table)
    assert keys == [f"photo{i:02d}" for i in range(assets)]
    assert len(re.findall(r'<img class="thumb" alt="turntable of ', table)) == assets
    thumb = re.search(r'<img class="thumb"[^>]*src="data:image/png;base64,([^"]+)"', table).group(1)
    assert Image.open(io.BytesIO(base64.b64decode(thumb))).size == (8 * 64, 64)  # scaled to the thumbnail height
    psnr = {r["photo_key"]: r["metric_ref_psnr"] for r in rows if r["status"] == "ok"}
    for key, value in psnr.items():
        cells = re.search(rf'data-photo-key="{key}">(.*?)</tr>', table).group(1)
        assert f"<td>{value:.4g}</td>" in cells
