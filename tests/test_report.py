"""``morpheus3d report``: a self-contained HTML page over the run catalog, checked in headless Chromium.

A store with a catalog of 12 synthetic rows (random metrics, 2 failed rows, real PNG previews, real Parquet run
logs written by ``assets_store.runlog.write_runlog``; one log and one preview missing on purpose) is reported by
the CLI; Chromium opens the page from a ``file://`` URL: every section is there, every image decodes, the
failure reasons are shown, the worst-asset list is in order and catalog text is escaped. Also: an empty
catalog renders, and bad arguments exit 2.

Skips only when Chromium, chromedriver or selenium are missing (``make browser`` installs them).
"""

from __future__ import annotations

import datetime as dt
import io
import math
import random
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from assets_store.catalog import Catalog
from assets_store.runlog import write_runlog
from assets_store.store import Store
from ops.cli import main
from ops.reporting.asset_metrics import HISTOGRAM_MIN_ASSETS
from ops.reporting.report import SECTIONS
from ops.reporting.report_sections import worst_order
from ops.stages import STAGE_IDS
from tests.browser import chromium, needs_browser
from tests.catalog_rows import LOGGED_STAGES, synthetic_row
from tests.report_page import totals

T0 = dt.datetime(2026, 5, 4, 9, 0, tzinfo=dt.timezone.utc)
HOSTILE = "<script>alert('x')</script> & \"quotes\""


@pytest.fixture(scope="module")
def browser() -> Iterator:
    with chromium() as driver:
        yield driver


def _png(rng: np.random.Generator, width: int, height: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (height, width, 3), dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def _runlog(rng: random.Random, start_psnr: float, wall_s: float) -> list[dict]:
    """A loop's log over most of its stage's wall time (the rest is set-up and export)."""
    rows = []
    for step in range(0, 60, 3):
        row = {"step": step, "wall_s": 0.9 * wall_s * step / 57, "loss_rgb": rng.random(), "loss_mask": rng.random()}
        if step % 6 == 0:  # evaluated every other logged step, as the loops do
            row["ref_psnr"] = start_psnr + 8 * (1 - math.exp(-step / 20)) + rng.gauss(0, 0.2)
        rows.append(row)
    return rows


def build_store(store: Path) -> list[dict]:
    """12 rows of 11 photos (photo03 ran twice), 2 failed; previews and run logs under the store."""
    rng, nrng = random.Random(7), np.random.default_rng(7)
    rows = []
    for i in range(12):
        key = f"photo{min(i, 10):02d}" if i != 11 else "photo03"
        failed = {4: "dmtet", 8: "texture"}.get(i)
        paths = {"preview": f"{key}/run{i}/turntable.png", "glb": f"{key}/run{i}/asset.glb"}
        for stage in LOGGED_STAGES:
            paths[stage] = f"{key}/run{i}/{stage}_runlog.parquet"
        row = synthetic_row(rng, f"run{i:02d}", key, T0 + dt.timedelta(hours=5 * i), failed_at=failed, paths=paths)
        (store / paths["preview"]).parent.mkdir(parents=True, exist_ok=True)
        if not failed and i != 2:  # photo02's preview is missing: the page must say so, not show a broken image
            (store / paths["preview"]).write_bytes(_png(nrng, 8 * 48, 48))
        for stage in LOGGED_STAGES:
            # A failed run logged the stages it ran, up to the failing one. One log is missing: that curve has
            # a gap and the page a note.
            if row[f"runlog_{stage}"] and (i, stage) != (5, "dmtet"):
                write_runlog(store / paths[stage], _runlog(rng, 15 + 2 * LOGGED_STAGES.index(stage),
                                                           row[f"{stage}_wall_s"]))
        rows.append(row)
    rows[6]["verdict"] = "fail"
    rows[6]["reasons"] = HOSTILE  # catalog text must be escaped, never markup
    rows[9]["metric_ref_psnr"] = 12.5  # clearly the worst by PSNR
    rows[0]["metric_lpips"] = math.inf  # infinite values are counted, not drawn
    rows[1]["metric_ref_psnr"] = 30  # an int in a float column: promoted on read
    Catalog(Store(store).catalog_dir).append(rows[:6])
    Catalog(Store(store).catalog_dir).append(rows[6:])  # two part files
    return rows


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict], str]:
    store = tmp_path_factory.mktemp("store")
    rows = build_store(store)
    out = store.parent / "report.html"
    assert main(["report", "--store", str(store), "--out", str(out)]) == 0
    return out, rows, out.read_text(encoding="utf-8")


def test_the_page_is_self_contained_and_escaped(report: tuple[Path, list[dict], str]) -> None:
    _, _, page = report
    srcs = re.findall(r'\bsrc="([^"]*)"', page)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert not re.search(r"<(script|link)\b", page), "no scripts or external stylesheets"
    assert "http://" not in page and "https://" not in page
    assert "&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt;" in page
    for sid, _ in SECTIONS:
        assert f'<section id="{sid}">' in page


@needs_browser
def test_report_in_chromium(report: tuple[Path, list[dict], str], browser) -> None:
    from selenium.webdriver.common.by import By

    out, rows, _ = report
    browser.get(out.resolve().as_uri())
    for sid, title in SECTIONS:
        section = browser.find_element(By.ID, sid)
        assert section.find_element(By.TAG_NAME, "h2").text == title
    assert browser.execute_script("return document.scripts.length") == 0, "escaped text became a script"

    images = browser.execute_script(
        "return Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth, i.naturalHeight])")
    assert all(complete and w > 0 and h > 0 for _, complete, w, h in images), images
    alts = [alt for alt, *_ in images]
    # 9 assets (11 photos, photo04's and photo08's only runs failed): below the histograms' threshold, the metrics
    # are a table with a row per asset and its turntable thumbnail.
    assert not [a for a in alts if a.startswith("histogram of ")] and HISTOGRAM_MIN_ASSETS > 9
    assets = browser.find_elements(By.CSS_SELECTOR, "#metrics tr.asset")
    assert [a.get_attribute("data-photo-key") for a in assets] == [f"photo{i:02d}" for i in range(11)
                                                                    if i not in (4, 8)]
    thumbs = browser.find_elements(By.CSS_SELECTOR, "#metrics img.thumb")
    assert len(thumbs) == 8 and all(t.get_property("naturalHeight") == 48 for t in thumbs)  # photo02's is missing
    assert "preview unreadable" in assets[2].text
    assert "reference PSNR against wall time" in alts
    previews = browser.find_elements(By.CSS_SELECTOR, "#worst img.preview")
    assert previews and all(p.get_property("naturalWidth") == 8 * 48 for p in previews)

    summary = browser.find_element(By.ID, "summary").text
    assert "failed 2" in summary and "ok 10" in summary
    assert re.search(r"photos 11\b", summary) and re.search(r"runs that did work 12\b", summary)
    assert re.search(r"runs that found everything cached 0\b", summary)
    for stage in STAGE_IDS:
        assert stage in summary

    curves = browser.find_element(By.ID, "curves").text
    assert "photo05: dmtet log missing" in curves  # photo05's dmtet log was not written

    failures = browser.find_element(By.ID, "failures")
    failed = [r for r in rows if r["status"] == "failed"]
    cells = [td.text for td in failures.find_elements(By.CSS_SELECTOR, "td")]
    for row in failed:
        assert row["failure_reason"] in cells
        assert row["run_id"] in cells
    assert len(failures.find_elements(By.CSS_SELECTOR, "tbody tr")) == 2

    # The worst list: the newest finished run per photo, verdict fail first, then ascending PSNR.
    items = browser.find_elements(By.CSS_SELECTOR, "#worst li.worst-asset")
    got = [(li.get_attribute("data-verdict"), li.get_attribute("data-ref-psnr"), li.get_attribute("data-photo-key"))
           for li in items]
    newest: dict[str, dict] = {}
    for row in rows:
        if row["photo_key"] not in newest or row["created_at"] > newest[row["photo_key"]]["created_at"]:
            newest[row["photo_key"]] = row
    want = worst_order([r for r in newest.values() if r["status"] == "ok"])
    assert [k for _, _, k in got] == [r["photo_key"] for r in want]
    fails = [v == "fail" for v, _, _ in got]
    assert fails == sorted(fails, reverse=True), "verdict fail first"
    for group in (True, False):
        psnrs = [float(p) for (v, p, _), f in zip(got, fails, strict=True) if f == group]
        assert psnrs == sorted(psnrs), "ascending PSNR within the fail / not-fail groups"
    assert any(p == "12.5" for _, p, _ in got)
    photo02 = next(li for li in items if li.get_attribute("data-photo-key") == "photo02")
    assert "preview unreadable" in photo02.text  # missing preview: said, not a broken image
    assert HOSTILE in browser.find_element(By.ID, "worst").text  # shown as text


@needs_browser
def test_an_empty_catalog_renders_a_page_saying_so(tmp_path: Path, browser) -> None:
    from selenium.webdriver.common.by import By

    store = tmp_path / "store"
    store.mkdir()
    out = tmp_path / "empty.html"
    assert main(["report", "--store", str(store), "--since", "2026-01-01", "--out", str(out)]) == 0
    browser.get(out.resolve().as_uri())
    assert "holds no rows since 2026-01-01" in browser.find_element(By.ID, "summary").text
    for sid, _ in SECTIONS:
        assert browser.find_element(By.ID, sid)
    assert browser.execute_script("return document.images.length") == 0


def test_since_limits_the_rows(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = tmp_path / "store"
    store.mkdir()
    rows = build_store(store)
    out = tmp_path / "recent.html"
    cut = T0 + dt.timedelta(hours=5 * 8)  # rows 8.. are on or after this day
    scans = []
    scan = Catalog.scan
    monkeypatch.setattr(Catalog, "scan", lambda self, *a, **k: scans.append(a) or scan(self, *a, **k))
    assert main(["report", "--catalog", str(Store(store).catalog_dir), "--store", str(store),
                 "--since", cut.date().isoformat(), "--out", str(out)]) == 0
    assert len(scans) == 1  # the report and the gallery read the catalog once
    expected = sum(1 for r in rows if r["created_at"].date() >= cut.date())
    page = out.read_text()
    assert re.search(rf"<td>rows \(a photo in a run\)</td><td>{expected}</td>", page)


@pytest.mark.parametrize("since", ["yesterday", "2026-13-01", "20260101", "2026-02-30"])
def test_a_bad_since_exits_2_with_a_message(tmp_path: Path, capsys: pytest.CaptureFixture[str], since: str) -> None:
    out = tmp_path / "r.html"
    assert main(["report", "--store", str(tmp_path), "--since", since, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--since" in err and repr(since) in err
    assert not out.exists()


def test_missing_store_or_catalog_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "r.html"
    assert main(["report", "--out", str(out)]) == 2
    assert main(["report", "--store", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert main(["report", "--catalog", str(tmp_path / "nope"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "give --store" in err and "no such folder" in err
    assert not out.exists()


@needs_browser
def test_qa_on_a_bundled_photo_then_the_report_in_chromium(tmp_path: Path, browser) -> None:
    """The real path: `morpheus3d run` on a bundled photo (tiny draft) writes the QA stage and a
    catalog row; `morpheus3d report` turns the store into a page that renders in Chromium."""
    import json

    from selenium.webdriver.common.by import By

    from ops.engine.checks import QA_FILE
    from ops.stages.qa import QA_TURNTABLE_GIF
    from tests.pipeline_helpers import PHOTOS, cli_overrides, tiny_config

    store = tmp_path / "store"
    assert main(["run", str(PHOTOS / "mug.jpg"), "--out", str(store), "--preset", "draft",
                 *cli_overrides(tiny_config())]) in (0, 1)
    qa = json.loads((Store(store).stage_dir("mug.jpg", "qa") / QA_FILE).read_text())
    for name in ("ref_psnr", "psnr_in", "ssim", "ssim_in", "mask_iou", "hf_ratio", "colour_deviation",
                 "watertight", "euler_number", "uv_coverage", "texel_density", "seam_leakage"):
        assert name in qa["metrics"], name
    assert all(w["status"] == "skipped" and w["detail"].startswith("skipped: weights missing (expected files ")
               for w in qa["weighted"].values()) and set(qa["weighted"]) == {"lpips", "clip_similarity",
                                                                             "clipiqa", "maniqa"}
    gif = Image.open(Store(store).stage_dir("mug.jpg", "qa") / QA_TURNTABLE_GIF)
    assert gif.n_frames == tiny_config().qa.turntable_views
    rows = Catalog(Store(store).catalog_dir).read().to_pylist()
    assert len(rows) == 1 and rows[0]["photo_key"] == "mug.jpg" and rows[0]["verdict"] == qa["verdict"]
    assert rows[0]["metric_ref_psnr"] == pytest.approx(qa["metrics"]["ref_psnr"])

    out = tmp_path / "report.html"
    assert main(["report", "--store", str(store), "--out", str(out)]) == 0
    browser.get(out.resolve().as_uri())
    for sid, title in SECTIONS:
        assert browser.find_element(By.ID, sid).find_element(By.TAG_NAME, "h2").text == title
    images = browser.execute_script("return Array.from(document.images).map(i => [i.alt, i.naturalWidth])")
    assert images and all(w > 0 for _, w in images), images
    assert "reference PSNR against wall time" in [alt for alt, _ in images]
    assert "mug.jpg" in browser.find_element(By.ID, "worst").text

    # Again, everything cached: a second row says so, and the report's totals are the first run's.
    first = totals(out.read_text(encoding="utf-8"))
    assert main(["run", str(PHOTOS / "mug.jpg"), "--out", str(store), "--preset", "draft",
                 *cli_overrides(tiny_config())]) in (0, 1)
    again = [r for r in Catalog(Store(store).catalog_dir).read().to_pylist() if r["run_id"] != rows[0]["run_id"]]
    assert len(again) == 1 and again[0]["status"] == "cached" and again[0]["work_s"] == 0
    assert all(again[0][f"{s}_wall_s"] == 0 for s in STAGE_IDS) and rows[0]["work_s"] > 0
    assert main(["report", "--store", str(store), "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")
    assert totals(page) == first and "<td>runs that found everything cached</td><td>1</td>" in page
