"""The catalog export stage: true size from products.csv / config / default, the three files validated, the QA
checks on them, and the viewer page a person can turn in a browser."""

from __future__ import annotations

import base64
import io
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from morpheus_core.export.gltf import decode_glb, encode_glb
from morpheus_core.export.gltf_validator import validator_available
from morpheus_core.export.web_glb import SizeBudgetError
from morpheus_core.geometry.textured_mesh import BakedTexture
from ops.engine.viewer_page import ViewerPage, vendor_viewer, write_viewer
from ops.intake.products import ProductsFileError
from ops.reporting.gallery import gallery_html
from ops.stages import stage_checks
from ops.stages.bake import ASSET_GLB
from ops.stages.export import MODEL_GLB, MODEL_USDZ, MODEL_WEB_GLB, ExportStageConfig, export_asset, product_size
from ops.stages.qa import QAConfig
from tests.browser import missing_browser_parts


def smooth_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    low = rng.random((size // 16, size // 16, 3))
    img = Image.fromarray((low * 255).astype(np.uint8)).resize((size, size), Image.BICUBIC)
    return np.asarray(img)


def random_box_asset(rng: np.random.Generator, size: int = 256) -> BakedTexture:
    """A box of random proportions in the method's frame (per-face split vertices, random UVs in [0, 1])."""
    half = rng.uniform(0.2, 0.9, size=3)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) * half
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    verts, faces = [], []
    for q in quads:
        base = len(verts)
        verts.extend(corners[list(q)])
        faces.extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])
    v = np.asarray(verts, np.float32) + rng.uniform(-0.1, 0.1, size=3).astype(np.float32)
    normals = v / np.linalg.norm(v, axis=1, keepdims=True)
    return BakedTexture(v, np.asarray(faces), rng.random((len(v), 2)).astype(np.float32), normals,
                        smooth_texture(rng, size), 0.5, len(faces))


def bake_dir(tmp_path: Path, asset: BakedTexture) -> Path:
    d = tmp_path / "bake"
    d.mkdir()
    (d / ASSET_GLB).write_bytes(encode_glb(asset))
    return d


def photo_folder(tmp_path: Path, csv: str | None) -> Path:
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "mug.jpg").write_bytes(b"\xff\xd8 not decoded here \xff\xd9")
    if csv is not None:
        (folder / "products.csv").write_text(csv, encoding="utf-8")
    return folder / "mug.jpg"


def extent_mm(path: Path) -> np.ndarray:
    v = decode_glb(path.read_bytes()).vertices
    return (v.max(axis=0) - v.min(axis=0)) * 1000


@pytest.mark.parametrize("column", ["height_mm", "width_mm", "depth_mm"])
def test_each_column_sizes_the_exported_files(tmp_path, column):
    rng = np.random.default_rng()
    asset = random_box_asset(rng)
    mm = round(float(rng.uniform(40, 600)), 1)
    photo = photo_folder(tmp_path, f"photo,sku,height_mm,width_mm,depth_mm\nmug.jpg,SKU-{mm},"
                                   + ",".join(str(mm) if c == column else "" for c in
                                              ("height_mm", "width_mm", "depth_mm")) + "\n")
    cfg = ExportStageConfig()
    size = product_size(photo, cfg)
    out = tmp_path / "out"
    out.mkdir()
    result = export_asset(bake_dir(tmp_path, asset), out, cfg, size, "mug")
    m = result.metrics
    axis = {"width_mm": 0, "height_mm": 1, "depth_mm": 2}[column]
    assert extent_mm(out / MODEL_GLB)[axis] == pytest.approx(mm, rel=0.01)  # true to size within 1 %
    assert m[column] == pytest.approx(mm, rel=1e-4) and m["scale_source"] == "products.csv:2"
    assert m["sku"] == f"SKU-{mm}" and m["scaled_by"] == column.removesuffix("_mm")
    bottom = decode_glb((out / MODEL_GLB).read_bytes()).vertices
    assert bottom[:, 1].min() == pytest.approx(0.0, abs=1e-6)  # standing on the floor
    assert m["web_glb_bytes"] == (out / MODEL_WEB_GLB).stat().st_size <= cfg.web_budget_bytes
    assert m["usdz_bytes"] == (out / MODEL_USDZ).stat().st_size > 0
    assert m["usdz_errors"] == 0, m["usdz_messages"]
    if validator_available() is None:
        assert m["glb_errors"] == 0 and m["web_glb_errors"] == 0, (m["glb_messages"], m["web_glb_messages"])
    checks = {c.name: c for c in stage_checks("export", m, QAConfig())}
    assert checks["true_size"].passed
    assert checks["formats_valid"].passed == (validator_available() is None)


def test_default_size_config_override_and_disagreeing_dimensions(tmp_path):
    rng = np.random.default_rng()
    asset = random_box_asset(rng)
    bake = bake_dir(tmp_path, asset)
    extent = asset.vertices.max(axis=0) - asset.vertices.min(axis=0)
    photo = photo_folder(tmp_path, "photo,height_mm,width_mm\nmug.jpg,100,\n")
    # No row for another photo: the default height, said as such, and a QA warning.
    other = photo.with_name("other.jpg")
    cfg = ExportStageConfig(default_height_mm=float(rng.uniform(50, 400)))
    (tmp_path / "d").mkdir()
    m = export_asset(bake, tmp_path / "d", cfg, product_size(other, cfg), "other").metrics
    assert m["scale_source"] == "default" and m["height_mm"] == pytest.approx(cfg.default_height_mm, rel=1e-4)
    assert not {c.name: c for c in stage_checks("export", m, QAConfig())}["true_size"].passed
    # The run's config wins over products.csv; a width 50 % off the mesh's proportions is flagged.
    width = 200 * extent[0] / extent[1] * 1.5
    cfg = ExportStageConfig(height_mm=200, width_mm=float(width), validate=False)
    size = product_size(photo, cfg)
    assert size.source == "config"
    (tmp_path / "c").mkdir()
    result = export_asset(bake, tmp_path / "c", cfg, size, "mug")
    assert result.metrics["height_mm"] == pytest.approx(200, rel=1e-4)
    assert result.metrics["size_disagreement"] == pytest.approx(1 / 3, rel=1e-3)
    assert any("width" in n and "apart" in n for n in result.notes)
    check = {c.name: c for c in stage_checks("export", result.metrics, QAConfig())}
    assert not check["true_size"].passed and check["true_size"].severity == "warn"
    assert not check["formats_valid"].passed and check["formats_valid"].severity == "warn"  # not validated


def test_a_bad_row_fails_only_its_photo_and_a_missed_budget_writes_nothing(tmp_path):
    photo = photo_folder(tmp_path, "photo,height_mm\nmug.jpg,-3\n")
    with pytest.raises(ProductsFileError, match=r"products\.csv:2: height_mm '-3'"):
        product_size(photo, ExportStageConfig())
    assert product_size(photo.with_name("box.jpg"), ExportStageConfig()) is None  # another photo goes on
    rng = np.random.default_rng()
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(SizeBudgetError):
        export_asset(bake_dir(tmp_path, random_box_asset(rng)), out, ExportStageConfig(web_budget_bytes=200), None,
                     "mug")
    assert not (out / MODEL_WEB_GLB).exists() and not (out / MODEL_USDZ).exists()


def test_validator_errors_fail_qa():
    metrics = {"gltf_validator": "ran", "glb_errors": 0, "web_glb_errors": 2, "usdz_errors": 0,
               "web_glb_messages": ["ACCESSOR_INDEX_OOB: index out of bounds (/accessors/0)"]}
    check = {c.name: c for c in stage_checks("export", metrics, QAConfig())}["formats_valid"]
    assert not check.passed and check.severity == "error" and "ACCESSOR_INDEX_OOB" in check.message


def test_gallery_filters_by_verdict():
    rng = np.random.default_rng()
    verdicts = rng.choice(["pass", "warn", "fail"], size=7)
    page = gallery_html([{"key": f"p{i}.jpg", "verdict": v, "viewer_href": f"p{i}/qa/viewer.html",
                          "thumb_href": None, "size_mm": {"height": 100.0 + i}, "sku": ""}
                         for i, v in enumerate(verdicts)])
    for v in ("pass", "warn", "fail"):
        assert f'<label for="f-{v}">{v} ({int((verdicts == v).sum())})</label>' in page
        assert f"#f-{v}:checked~.grid .card:not(.{v}){{display:none}}" in page
    assert page.count('<a class="card') == 7 and 'href="p3/qa/viewer.html"' in page


@pytest.mark.slow
def test_viewer_page_turns_the_web_glb_in_chromium(tmp_path):
    """The page as the qa stage writes it, opened from the file system: the model loads and draws."""
    missing = missing_browser_parts()
    if missing:
        pytest.skip(f"headless Chromium unavailable ({', '.join(missing)}): `make browser`")
    store = tmp_path / "store"
    why = vendor_viewer(store)
    if why:
        pytest.skip(why)
    from tests.browser import chromium

    rng = np.random.default_rng()
    out = store / "p.jpg" / "export"
    out.mkdir(parents=True)
    export_asset(bake_dir(tmp_path, random_box_asset(rng)), out, ExportStageConfig(height_mm=300, validate=False),
                 None, "p")
    page_dir = store / "p.jpg" / "qa"
    write_viewer(page_dir / "viewer.html", ViewerPage(
        "p", (out / MODEL_WEB_GLB).read_bytes(), "../export/model.glb", None, None, "../../.viewer",
        {"height": 300.0}, "pass"))
    with chromium((900, 700)) as driver:
        driver.get((page_dir / "viewer.html").as_uri())
        deadline, state = time.monotonic() + 90, None
        while time.monotonic() < deadline:
            state = driver.execute_script("return window.viewerState || null")
            if state and (state["loaded"] or state["error"]):
                break
            time.sleep(0.25)
        assert state is not None and state["loaded"], state
        time.sleep(1.0)  # a frame after load
        uri = driver.execute_script("return document.querySelector('model-viewer').toDataURL('image/png')")
    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(uri.split(",", 1)[1]))).convert("RGB")).astype(int)
    drawn = (np.abs(img - img[2, 2]).sum(axis=-1) > 30).mean()
    assert drawn > 0.05, f"only {drawn:.1%} of the viewer's pixels differ from its background"
